"""
Layer names, and the layer structure that the DrQ-v2 policy and the interventions both read.

The names (:data:`LAYER_NAMES`) are the vocabulary shared by the callbacks, the probe and the plots: ``cnn0`` the
normalized pixels (``obs / 255 - 0.5``), ``cnn1``..``cnn4`` after each conv + ReLU, ``mlp0`` the actor trunk
(Linear to 50, LayerNorm, Tanh), ``mlp1`` and ``mlp2`` after each 1024-unit Linear + ReLU, ``action`` the
deterministic action (Linear + Tanh); per algorithm: docs/monitoring.md. :class:`LayerParts` describes a hidden
layer whose units ReDo may recycle; :func:`sequential_hidden_parts` finds them in a flat list of modules, and
:func:`reinitialize` draws new initial values for a module's parameters.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import NamedTuple

import torch as th
from torch import nn

LAYER_NAMES = ("cnn0", "cnn1", "cnn2", "cnn3", "cnn4", "mlp0", "mlp1", "mlp2", "action")
"""Every named layer, input to output."""


class LayerParts(NamedTuple):
    """
    The parts of a hidden layer, ``activation(linear(x))`` read by the ``consumers``: a unit is an output feature of
    a Linear, or an output channel of a convolution.

    :param name: ``mlp1``, ``mlp2`` (actor), ``q1.mlp1``... (critic's Q networks), ``cnn1``..``cnn4`` (encoder)
    :param linear: the layer's Linear or Conv2d (incoming weights: its rows, or output channels, and bias)
    :param activation: the module whose output is the layer's activation
    :param consumers: every Linear or Conv2d that reads it, in every network, target networks included (outgoing
        weights: their input columns or channels); ReDo zeroes these alone, so a missing one changes that network's
        output at recycling
    :param positions: spatial positions per channel in the consumers' flattened input (a last convolution read by
        Linear layers: ``height x width``); 1 otherwise
    :param channels_last: the consumers' flattened input is in (height, width, channel) order, else (channel,
        height, width)
    """

    name: str
    linear: nn.Linear | nn.Conv2d
    activation: nn.Module
    consumers: tuple[nn.Linear | nn.Conv2d, ...]
    positions: int = 1
    channels_last: bool = False

    @property
    def units(self) -> int:
        """Output features or channels."""
        return int(self.linear.weight.shape[0])

    def consumer_columns(self, index: th.Tensor) -> th.Tensor:
        """
        :param index: ``(k,)`` indices of units
        :return: the indices of the consumers' weight columns (dim 1) that read them, on ``index``'s device
        """
        if self.positions == 1:
            return index
        where = th.arange(self.positions, device=index.device)
        if self.channels_last:  # column of (position p, channel c): p * channels + c
            return (where[:, None] * self.units + index[None, :]).flatten()
        return (index[:, None] * self.positions + where[None, :]).flatten()  # c * positions + p


def sequential_hidden_parts(
    prefix: str, modules: Sequence[nn.Module], tail: tuple[nn.Linear, ...] = (), first: int = 1
) -> list[LayerParts]:
    """
    The hidden layers of a flat list of modules run one after the other: ``Linear, activation`` pairs, each one's
    consumer the next Linear of the list, or ``tail`` for the last. A Linear followed by a module with parameters
    (LayerNorm) or by nothing, and the output Linear (no consumer), are not hidden layers.

    :param prefix: put before each name (``"q1."``)
    :param modules: the modules, in the order of the forward pass
    :param tail: the consumers of the last Linear's activation (modules outside the list)
    :param first: the number in the name of the list's first Linear: names are ``<prefix>mlp<k>``
    :return: the hidden layers, input to output
    """
    modules = list(modules)
    linears = [i for i, module in enumerate(modules) if isinstance(module, nn.Linear)]
    hidden = []
    for k, i in enumerate(linears):
        following = [modules[j] for j in linears if j > i]
        consumers = (following[0],) if following else tail
        if i + 1 < len(modules) and next(modules[i + 1].parameters(), None) is None and consumers:
            hidden.append(LayerParts(f"{prefix}mlp{k + first}", modules[i], modules[i + 1], consumers))  # type: ignore[arg-type]
    return hidden


def reinitialize(module: nn.Module, initializer: Callable[[nn.Module], None] | None = None) -> None:
    """
    Draw new initial values for every parameter of ``module``, in place, submodule by submodule (in the order of
    ``module.modules()``, from torch's global generator): ``initializer`` on each Linear and Conv2d when given,
    ``reset_parameters()`` (PyTorch's default) on the others and on all without ``initializer``.

    :param module: the module to initialize
    :param initializer: an in-place initializer of one Linear or Conv2d (e.g. DrQ-v2's ``weight_init``)
    :raises TypeError: for a submodule with parameters that has no known initializer
    """
    for sub in module.modules():
        if next(sub.parameters(recurse=False), None) is None:
            continue
        if initializer is not None and isinstance(sub, (nn.Linear, nn.Conv2d)):
            initializer(sub)
        elif callable(getattr(sub, "reset_parameters", None)):
            sub.reset_parameters()  # type: ignore[operator]
        else:
            raise TypeError(f"Cannot draw new initial values for the parameters of {type(sub).__name__}.")
