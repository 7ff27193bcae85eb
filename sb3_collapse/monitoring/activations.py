"""
Named activations of an actor: ``cnn0`` .. ``cnn4``, ``mlp0`` .. ``mlp2`` and ``action``, read with forward hooks,
on DrQv2 and SB3's TD3, DDPG and SAC, at the modules that :func:`sb3_collapse.common.layers.layer_taps` names (the
mapping for SB3's policies: docs/monitoring.md).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import TypeAlias

import numpy as np
import torch as th
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.policies import BasePolicy

from sb3_collapse.common.layers import LayerTap, layer_taps, policy_of

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
    policy = policy_of(model)
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
