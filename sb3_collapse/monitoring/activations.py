"""Named activations of an actor (``cnn0`` .. ``action``) read with forward hooks at :func:`layer_taps`' modules, and
of its critic's Q networks (``q1.mlp0`` .. ``q1``) at :func:`critic_layer_taps`'."""

from __future__ import annotations

import contextlib
from collections.abc import Iterable, Iterator, Mapping
from typing import TypeAlias

import numpy as np
import torch as th
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.policies import BasePolicy

from sb3_collapse.common.layers import LayerTap, critic_layer_taps, layer_taps, policy_of

Observations: TypeAlias = np.ndarray | th.Tensor | Mapping[str, np.ndarray | th.Tensor]
"""A batch of observations: an array or tensor ``(n, ...)``, or a dict of them (``spaces.Dict``), ``n`` per key."""


def _batch_length(observations: Observations) -> int:
    """The number ``n`` of observations; a ``ValueError`` for a dict whose keys hold different numbers, or none."""
    if not isinstance(observations, Mapping):
        return len(observations)
    lengths = {key: len(value) for key, value in observations.items()}
    if len(set(lengths.values())) != 1:
        raise ValueError(f"observations must hold the same number of observations under every key, got {lengths}.")
    return next(iter(lengths.values()))


def _batch_slice(observations: Observations, start: int, stop: int, device: th.device | str) -> th.Tensor | dict:
    """Observations ``start:stop`` as a tensor on ``device``, or a dict of them (each key sliced)."""
    if isinstance(observations, Mapping):
        return {key: th.as_tensor(value[start:stop], device=device) for key, value in observations.items()}
    return th.as_tensor(observations[start:stop], device=device)


def collect_activations(
    model: BaseAlgorithm | BasePolicy,
    observations: Observations,
    layers: Iterable[str] | None = None,
    batch_size: int = 256,
    device: th.device | str = "cpu",
    critic_layers: Iterable[str] = (),
) -> dict[str, th.Tensor]:
    """
    The named activations of the actor on ``observations``, and with ``critic_layers`` those of the critic on the
    actor's deterministic actions ``Q(s, mu(s))``, in eval mode without gradient (then restored).

    :param model: a DrQv2, TD3, DDPG or SAC model, or its policy
    :param observations: a batch as stored by the env (e.g. uint8 ``(n, 9, 84, 84)``), or a dict of them, one per key
    :param layers: the names to return, ``None`` for all of :func:`layer_taps`
    :param batch_size: observations per forward pass
    :param device: where the returned activations live
    :param critic_layers: names of :func:`critic_layer_taps` to return too (``q1.mlp0``, ``q1.mlp1``, ``q1``...)
    :return: name -> float32 tensor of shape ``(n, *activation_shape)``, in the order of :func:`layer_taps`, then
        of :func:`critic_layer_taps`
    :raises KeyError: for a layer name the model does not have
    """
    policy = policy_of(model)
    taps = layer_taps(policy)
    wanted = list(taps) if layers is None else list(layers)
    critic_wanted = list(critic_layers)
    critic_taps = critic_layer_taps(policy) if critic_wanted else {}
    unknown = [name for name in wanted if name not in taps] + [n for n in critic_wanted if n not in critic_taps]
    if unknown:
        raise KeyError(f"Unknown layer(s) {unknown}; this model has {list(taps) + list(critic_taps)}.")
    n = _batch_length(observations)
    actions = []
    with reading(policy, {name: tap for name, tap in taps.items() if name in wanted}, device) as outputs:
        for start in range(0, n, batch_size):
            chunk = _batch_slice(observations, start, start + batch_size, policy.device)
            actions.append(policy._predict(chunk, deterministic=True))
    if critic_wanted:  # a second pass, so that the actor's hooks (on a shared encoder too) read each input once
        chosen = {name: tap for name, tap in critic_taps.items() if name in critic_wanted}
        with reading(policy, chosen, device) as critic_outputs:
            for start, action in zip(range(0, n, batch_size), actions, strict=True):
                _critic_forward(policy, _batch_slice(observations, start, start + batch_size, policy.device), action)
        outputs = {**outputs, **critic_outputs}
    return {
        name: th.cat(chunks) if chunks else th.empty(0, device=device, dtype=th.float32)
        for name, chunks in outputs.items()
    }


def _critic_forward(policy: BasePolicy, observations: th.Tensor | dict, actions: th.Tensor) -> None:
    """Run the critic's Q networks on ``observations`` and ``actions`` in [-1, 1] (DrQv2's critic reads features)."""
    if callable(getattr(policy, "named_layers", None)):  # DrQv2Policy: Critic(features, action), its one encoder
        policy.critic(policy.extract_features(observations), actions)  # type: ignore[operator]
    else:  # SB3's ContinuousCritic(obs, actions) extracts its own features
        policy.critic(observations, actions)  # type: ignore[operator]


@contextlib.contextmanager
def reading(
    policy: BasePolicy, taps: Mapping[str, LayerTap], device: th.device | str | None
) -> Iterator[dict[str, list[th.Tensor]]]:
    """
    Name -> the float32 activations read at ``taps`` in each forward pass of the block, on ``device`` (``None``: where
    made); the block runs in eval mode without gradient (restored after, even on error).
    """
    outputs: dict[str, list[th.Tensor]] = {name: [] for name in taps}
    handles = [_register(tap, outputs[name], device) for name, tap in taps.items()]
    was_training = policy.training
    policy.set_training_mode(False)
    try:
        with th.no_grad():
            yield outputs
    finally:
        for handle in handles:
            handle.remove()
        policy.set_training_mode(was_training)


def _register(tap: LayerTap, sink: list[th.Tensor], device: th.device | str | None) -> th.utils.hooks.RemovableHandle:
    def store(value: th.Tensor) -> None:
        if tap.transform is not None:
            value = tap.transform(value)
        sink.append(value.detach().to(device=device, dtype=th.float32, memory_format=th.contiguous_format))

    if tap.source == "input":
        return tap.module.register_forward_pre_hook(lambda _module, args: store(args[0]))
    return tap.module.register_forward_hook(lambda _module, _args, output: store(output))
