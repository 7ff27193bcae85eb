"""
Named activations of an actor: ``cnn0`` .. ``cnn4``, ``mlp0`` .. ``mlp2`` and ``action``, read with forward hooks,
on DrQv2 and SB3's TD3, DDPG and SAC. Each name maps to the module that produces the activation
(:func:`layer_taps`) and to the parameters of the layer that computes it (:func:`layer_parameters`). The names:
:mod:`sb3_collapse.common.layers`; the mapping for SB3's policies: docs/monitoring.md.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import TypeAlias

import numpy as np
import torch as th
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.torch_layers import FlattenExtractor, NatureCNN
from torch import nn

from sb3_collapse.errors import LayerMappingError


@dataclass(frozen=True)
class LayerTap:
    """
    Where a named activation is read.

    :param module: the module whose forward call produces (or, for ``source="input"``, receives) it
    :param parameters: the parameters of the layer that computes it (empty for ``cnn0``)
    :param source: ``"output"``: the module's output; ``"input"``: its first positional input
    :param transform: applied to what is read (e.g. ``tanh`` for SAC's action), ``None`` for none
    """

    module: nn.Module
    parameters: tuple[nn.Parameter, ...]
    source: str = "output"
    transform: Callable[[th.Tensor], th.Tensor] | None = None


def _policy_of(model: BaseAlgorithm | BasePolicy) -> BasePolicy:
    policy = model.policy if isinstance(model, BaseAlgorithm) else model
    if not isinstance(policy, BasePolicy):
        raise LayerMappingError(f"Expected an SB3 algorithm or policy, got {type(model).__name__}.")
    return policy


def layer_taps(model: BaseAlgorithm | BasePolicy) -> dict[str, LayerTap]:
    """
    The named layers of a DrQv2, TD3, DDPG or SAC actor, input to output (the mapping: docs/monitoring.md).

    :param model: an algorithm or its policy
    :return: ordered mapping name -> :class:`LayerTap`
    :raises LayerMappingError: for a policy whose modules do not follow a known layout
    """
    policy = _policy_of(model)
    named_layers = getattr(policy, "named_layers", None)
    if callable(named_layers):  # DrQv2Policy names its own layers
        return {name: LayerTap(module, tuple(module.parameters())) for name, module in named_layers().items()}
    actor = getattr(policy, "actor", None)
    if actor is None or not hasattr(actor, "features_extractor"):
        raise LayerMappingError(
            f"Cannot map the layers of {type(policy).__name__}: named layers are defined for DrQv2 and for "
            "SB3's TD3, DDPG and SAC policies (an `actor` with a features extractor)."
        )
    taps = _extractor_taps(actor.features_extractor)
    if hasattr(actor, "latent_pi"):  # SAC: latent_pi = hidden layers, mu = mean action before the tanh squash
        if getattr(actor, "use_sde", False):
            raise LayerMappingError("SAC with gSDE (use_sde=True) has no deterministic tanh(mu) action to name.")
        taps.update(_hidden_taps(actor.latent_pi))
        taps["action"] = LayerTap(actor.mu, tuple(actor.mu.parameters()), transform=th.tanh)
    elif isinstance(getattr(actor, "mu", None), nn.Sequential):  # TD3 / DDPG: mu = hidden layers, Linear, Tanh
        linears = [i for i, m in enumerate(actor.mu) if isinstance(m, nn.Linear)]
        if not linears or linears[-1] + 1 >= len(actor.mu):
            raise LayerMappingError(
                f"Cannot map the layers of {type(policy).__name__}: unexpected actor.mu {actor.mu}."
            )
        last = linears[-1]
        taps.update(_hidden_taps(actor.mu[:last]))
        taps["action"] = LayerTap(actor.mu[last + 1], tuple(actor.mu[last].parameters()))
    else:
        raise LayerMappingError(f"Cannot map the layers of {type(policy).__name__}: its actor has no `mu` network.")
    return taps


def _extractor_taps(extractor: nn.Module) -> dict[str, LayerTap]:
    """``cnn0``..``cnnK`` and ``mlp0`` of SB3's ``NatureCNN`` or ``FlattenExtractor``."""
    if isinstance(extractor, NatureCNN):
        taps = {"cnn0": LayerTap(extractor.cnn, (), source="input")}
        modules = list(extractor.cnn)
        for k, index in enumerate((i for i, m in enumerate(modules) if isinstance(m, nn.Conv2d)), start=1):
            if index + 1 >= len(modules) or isinstance(modules[index + 1], (nn.Conv2d, nn.Flatten)):
                raise LayerMappingError(f"NatureCNN conv {k} has no activation after it.")
            taps[f"cnn{k}"] = LayerTap(modules[index + 1], tuple(modules[index].parameters()))
        taps["mlp0"] = LayerTap(extractor.linear, tuple(extractor.linear.parameters()))
        return taps
    if isinstance(extractor, FlattenExtractor):
        return {"mlp0": LayerTap(extractor, ())}
    raise LayerMappingError(
        f"Cannot map the layers of the features extractor {type(extractor).__name__}: "
        "NatureCNN (CnnPolicy) and FlattenExtractor (MlpPolicy) are supported."
    )


def _hidden_taps(layers: Iterable[nn.Module]) -> dict[str, LayerTap]:
    """``mlp1``..``mlpK`` of a ``Linear, activation, Linear, activation, ...`` sequence."""
    modules = list(layers)
    taps: dict[str, LayerTap] = {}
    for k, index in enumerate((i for i, m in enumerate(modules) if isinstance(m, nn.Linear)), start=1):
        if index + 1 >= len(modules) or isinstance(modules[index + 1], nn.Linear):
            raise LayerMappingError(f"Hidden layer {k} of the actor has no activation after it.")
        taps[f"mlp{k}"] = LayerTap(modules[index + 1], tuple(modules[index].parameters()))
    return taps


def layer_parameters(model: BaseAlgorithm | BasePolicy) -> dict[str, tuple[nn.Parameter, ...]]:
    """
    The parameters of the layer that computes each named activation (``cnn0`` excluded: it has none).

    :param model: an algorithm or its policy
    :return: ordered mapping name -> parameters
    """
    return {name: tap.parameters for name, tap in layer_taps(model).items() if tap.parameters}


Observations: TypeAlias = np.ndarray | th.Tensor | Mapping[str, np.ndarray | th.Tensor]
"""A batch of observations: an array or tensor ``(n, ...)``, or a dict of them (``spaces.Dict``), ``n`` per key."""


def _batch_length(observations: Observations) -> int:
    """
    :param observations: a batch of observations, an array or tensor, or a dict of them (``MultiInputPolicy``)
    :return: the number ``n`` of observations
    :raises ValueError: for a dict whose keys hold different numbers of observations, or no key
    """
    if not isinstance(observations, Mapping):
        return len(observations)
    lengths = {key: len(value) for key, value in observations.items()}
    if len(set(lengths.values())) != 1:
        raise ValueError(f"observations must hold the same number of observations under every key, got {lengths}.")
    return next(iter(lengths.values()))


def _batch_slice(
    observations: Observations, start: int, stop: int, device: th.device | str
) -> th.Tensor | dict[str, th.Tensor]:
    """
    :param observations: a batch of observations, an array or tensor, or a dict of them (``MultiInputPolicy``)
    :param start: first observation
    :param stop: one past the last observation
    :param device: where the returned tensors live
    :return: observations ``start:stop`` as a tensor, or a dict of tensors (each key sliced) for a dict
    """
    if isinstance(observations, Mapping):
        return {key: th.as_tensor(value[start:stop], device=device) for key, value in observations.items()}
    return th.as_tensor(observations[start:stop], device=device)


def collect_activations(
    model: BaseAlgorithm | BasePolicy,
    observations: Observations,
    layers: Iterable[str] | None = None,
    batch_size: int = 256,
    device: th.device | str = "cpu",
) -> dict[str, th.Tensor]:
    """
    Run observations through the actor and return the named activations, without changing training state.

    The forward passes run under ``torch.no_grad()`` in eval mode; the policy's previous mode is restored and
    the hooks are removed afterwards, even on error.

    :param model: a DrQv2, TD3, DDPG or SAC model, or its policy
    :param observations: a batch of observations as stored by the env (e.g. uint8 ``(n, 9, 84, 84)``), or a dict
        of such batches, one per key, for dict observation spaces (``MultiInputPolicy``)
    :param layers: the names to return, ``None`` for all of :func:`layer_taps`
    :param batch_size: observations per forward pass
    :param device: where the returned activations live
    :return: name -> float32 tensor of shape ``(n, *activation_shape)``, in the order of :func:`layer_taps`
    :raises KeyError: for a layer name the model does not have
    """
    policy = _policy_of(model)
    taps = layer_taps(policy)
    wanted = list(taps) if layers is None else list(layers)
    unknown = [name for name in wanted if name not in taps]
    if unknown:
        raise KeyError(f"Unknown layer(s) {unknown}; this model has {list(taps)}.")
    outputs: dict[str, list[th.Tensor]] = {name: [] for name in taps if name in wanted}
    handles = [_register(taps[name], sink, device) for name, sink in outputs.items()]
    was_training = policy.training
    policy.set_training_mode(False)
    try:
        with th.no_grad():
            for start in range(0, _batch_length(observations), batch_size):
                policy._predict(
                    _batch_slice(observations, start, start + batch_size, policy.device), deterministic=True
                )
    finally:
        for handle in handles:
            handle.remove()
        policy.set_training_mode(was_training)
    return {
        name: th.cat(chunks) if chunks else th.empty(0, device=device, dtype=th.float32)
        for name, chunks in outputs.items()
    }


def _register(tap: LayerTap, sink: list[th.Tensor], device: th.device | str) -> th.utils.hooks.RemovableHandle:
    def store(value: th.Tensor) -> None:
        if tap.transform is not None:
            value = tap.transform(value)
        sink.append(value.detach().to(device=device, dtype=th.float32, memory_format=th.contiguous_format))

    if tap.source == "input":
        return tap.module.register_forward_pre_hook(lambda _module, args: store(args[0]))
    return tap.module.register_forward_hook(lambda _module, _args, output: store(output))
