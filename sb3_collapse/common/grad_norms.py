"""The gradient norm of each named layer at each update, recorded when its optimizer steps: no extra backward pass,
no host transfer per update. See docs/interventions.md#the-health-value-gradient-norms-recorded-at-each-update."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any

import torch as th
from torch import nn


class GradNormRecorder:
    """Records the L2 gradient norm of the named ``layers`` (name -> parameters, input to output) each time the first
    of the ``optimizers`` (``None`` skipped) that holds their parameters steps."""

    def __init__(
        self, layers: Mapping[str, Sequence[nn.Parameter]], optimizers: Iterable[th.optim.Optimizer | None]
    ) -> None:
        self.names = list(layers)
        self.optimizers = tuple(optimizer for optimizer in optimizers if optimizer is not None)
        params = [list(layer) for layer in layers.values()]
        self.device = params[0][0].device if params and params[0] else th.device("cpu")
        self._norms: th.Tensor | None = None
        self._recorded: set[int] = set()
        self._handles: list[th.utils.hooks.RemovableHandle] = []
        assigned: set[int] = set()
        for optimizer in self.optimizers:
            owned = {id(parameter) for group in optimizer.param_groups for parameter in group["params"]}
            slots = [i for i, layer in enumerate(params) if layer and id(layer[0]) in owned and i not in assigned]
            if slots:
                assigned.update(slots)
                self._handles.append(optimizer.register_step_pre_hook(self._hook([params[i] for i in slots], slots)))

    @classmethod
    def of_modules(
        cls, modules: Mapping[str, nn.Module], optimizers: Iterable[th.optim.Optimizer | None]
    ) -> GradNormRecorder:
        """:return: a recorder of ``modules`` (layer name -> module; those without parameters left out)"""
        layers = {name: list(module.parameters()) for name, module in modules.items()}
        return cls({name: params for name, params in layers.items() if params}, optimizers)

    def _hook(self, layers: list[list[nn.Parameter]], slots: list[int]) -> Callable[..., None]:
        params = [parameter for layer in layers for parameter in layer]
        segment = th.tensor([slot for slot, layer in zip(slots, layers) for _ in layer], device=self.device)
        index = th.tensor(slots, device=self.device)

        def record(_optimizer: th.optim.Optimizer, _args: tuple, _kwargs: dict) -> None:
            self._record(params, segment, index)
            self._recorded.update(slots)

        return record

    def _record(self, params: list[nn.Parameter], segment: th.Tensor, index: th.Tensor) -> None:
        """Each layer's ``sqrt(sum over its parameters of ||g||^2)`` (no gradient: 0), without host sync; ``segment``
        ``(len(params),)``: each parameter's slot in :attr:`names`; ``index`` ``(layers,)``: the layers' slots."""
        grads = [param.grad if param.grad is not None else param.new_zeros(()) for param in params]
        squares = th.stack(th._foreach_norm(grads)).detach().float().square()
        per_slot = squares.new_zeros(len(self.names)).index_add_(0, segment, squares)
        norms = per_slot.index_select(0, index).sqrt()
        base = self._norms if self._norms is not None else squares.new_zeros(len(self.names))
        self._norms = base.index_copy(0, index, norms)  # a new tensor: earlier reads are not modified

    @property
    def norms(self) -> th.Tensor | None:
        """``(len(names),)``: the last norm of every layer (0 before its first), on the device; ``None`` before any."""
        return self._norms

    def last(self) -> dict[str, float]:
        """:return: layer name -> norm at its optimizer's last step, for the layers recorded since :meth:`clear`"""
        if self._norms is None:
            return {}
        values = self._norms.tolist()
        return {name: values[i] for i, name in enumerate(self.names) if i in self._recorded}

    def state_dict(self) -> dict[str, Any]:
        """:return: the recorded norms (on the CPU) and which layers were recorded"""
        return {
            "names": list(self.names),
            "norms": None if self._norms is None else self._norms.detach().cpu().clone(),
            "recorded": sorted(self._recorded),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """:param state: a :meth:`state_dict` of a recorder of the same layers (``ValueError`` for others)"""
        if list(state["names"]) != self.names:
            raise ValueError(f"GradNormRecorder: saved norms of {state['names']}, this one records {self.names}.")
        self._norms = None if state["norms"] is None else state["norms"].to(self.device)
        self._recorded = set(state["recorded"])

    def clear(self) -> None:
        """Forget the recorded norms (e.g. after the networks were re-initialized)."""
        self._norms = None
        self._recorded = set()

    def watches(self, optimizers: Iterable[th.optim.Optimizer | None]) -> bool:
        """:return: whether this recorder is hooked on exactly these optimizers (the same objects)"""
        current = tuple(optimizer for optimizer in optimizers if optimizer is not None)
        return len(current) == len(self.optimizers) and all(a is b for a, b in zip(current, self.optimizers))

    def remove(self) -> None:
        """Remove the hooks: nothing more is recorded."""
        for handle in self._handles:
            handle.remove()
        self._handles = []
