"""What makes code written for SB3's TD3 run with ``DrQv2`` in its place: the constructor's callbacks (saved and
loaded) and n-step returns on dict observations (docs/algorithm.md, *SB3's keywords*)."""

from __future__ import annotations

import io
import pathlib
from collections.abc import Callable, Iterable
from typing import Any, ClassVar, TypeVar

import numpy as np
import torch as th
from stable_baselines3.common.buffers import DictReplayBuffer
from stable_baselines3.common.callbacks import BaseCallback, CallbackList, ConvertCallback
from stable_baselines3.common.type_aliases import DictReplayBufferSamples, GymEnv, MaybeCallback
from stable_baselines3.common.vec_env import VecNormalize

from sb3_collapse.common.saved_callbacks import restore_callbacks, saved_callbacks
from sb3_collapse.drqv2.checks import check_load_arguments
from sb3_collapse.drqv2.divergence import check_finite_weights
from sb3_collapse.drqv2.replay_buffer import n_step_returns

SelfConstructorCallbacks = TypeVar("SelfConstructorCallbacks", bound="ConstructorCallbacks")


def _as_callback(item: BaseCallback | Callable[[dict[str, Any], dict[str, Any]], bool]) -> BaseCallback:
    """SB3's conversion of one callback: a ``BaseCallback`` as is, a function ``(locals, globals) -> bool`` wrapped."""
    if isinstance(item, BaseCallback):
        return item
    if callable(item):
        return ConvertCallback(item)
    raise TypeError(
        f"A callback must be an SB3 BaseCallback, a function (locals, globals) -> bool, a list of them or None, "
        f"got {item!r}."
    )


def combine_callbacks(*callbacks: MaybeCallback) -> BaseCallback | None:
    """:return: ``callbacks`` (each what SB3's ``learn(callback=...)`` takes) as one callback, in order, or ``None``"""
    items = [one for item in callbacks if item is not None for one in (item if isinstance(item, list) else [item])]
    flat = [_as_callback(item) for item in items]  # type: ignore[arg-type]
    return None if not flat else flat[0] if len(flat) == 1 else CallbackList(flat)


class ConstructorCallbacks:
    """SB3's ``save`` and ``load`` with the constructor's ``callback=`` (a mixin before an SB3 algorithm): those that
    can be built again are saved with their state (``sb3_collapse.common.saved_callbacks``)."""

    callback: MaybeCallback = None
    load_parsers: ClassVar[dict[str, Callable[[Any], Any]]] = {}  # load(**kwargs) entries -> their parser

    @classmethod
    def load(  # type: ignore[misc]
        cls: type[SelfConstructorCallbacks],
        path: str | pathlib.Path | io.BufferedIOBase,
        env: GymEnv | None = None,
        device: th.device | str = "auto",
        custom_objects: dict[str, Any] | None = None,
        print_system_info: bool = False,
        force_reset: bool = True,
        **kwargs: Any,
    ) -> SelfConstructorCallbacks:
        """SB3's ``load`` (``kwargs``: saved attributes to override), the constructor's callbacks built again unless
        ``callback=`` is given; checked first by :func:`~sb3_collapse.drqv2.checks.check_load_arguments`."""
        check_load_arguments(path, kwargs, f"{cls.__name__}.load")
        kwargs = {name: cls.load_parsers.get(name, lambda value: value)(value) for name, value in kwargs.items()}
        model = super().load(path, env, device, custom_objects, print_system_info, force_reset, **kwargs)  # type: ignore[misc]
        where = path if isinstance(path, (str, pathlib.Path)) else f"the {type(path).__name__} file object"
        check_finite_weights(model.policy.state_dict(), f"{cls.__name__}.load: {where}")  # before any use of them
        saved = model.__dict__.pop("constructor_callbacks", None)
        if "callback" not in kwargs and saved is not None and saved["specs"]:
            model.callback = restore_callbacks(saved, f"{cls.__name__}.load")
        return model

    def save(
        self,
        path: str | pathlib.Path | io.BufferedIOBase,
        exclude: Iterable[str] | None = None,
        include: Iterable[str] | None = None,
    ) -> None:
        """SB3's ``save``, with the constructor's callbacks (``sb3_collapse.common.saved_callbacks``)."""
        self.constructor_callbacks = saved_callbacks(self.callback)  # type: ignore[arg-type]
        try:
            super().save(path, exclude=exclude, include=include)  # type: ignore[misc]
        finally:
            del self.constructor_callbacks

    def _excluded_save_params(self) -> list[str]:
        return [*super()._excluded_save_params(), "callback"]  # type: ignore[misc]


class DictNStepReplayBuffer(DictReplayBuffer):
    """SB3's ``DictReplayBuffer`` with the n-step returns of SB3's ``NStepReplayBuffer`` (``n_steps``, ``gamma``)."""

    def __init__(self, *args: Any, n_steps: int = 3, gamma: float = 0.99, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.n_steps = n_steps
        self.gamma = gamma

    def _get_samples(  # type: ignore[override]
        self, batch_inds: np.ndarray, env: VecNormalize | None = None
    ) -> DictReplayBufferSamples:
        env_indices = np.random.randint(0, self.n_envs, size=batch_inds.shape)
        returns, discounts, dones, last_indices = n_step_returns(self, batch_inds, env_indices, env)
        obs = self._normalize_obs(
            {key: value[batch_inds, env_indices] for key, value in self.observations.items()}, env
        )
        next_obs = self._normalize_obs(
            {key: value[last_indices, env_indices] for key, value in self.next_observations.items()}, env
        )
        assert isinstance(obs, dict) and isinstance(next_obs, dict)
        return DictReplayBufferSamples(
            observations={key: self.to_torch(value) for key, value in obs.items()},
            actions=self.to_torch(self.actions[batch_inds, env_indices]),
            next_observations={key: self.to_torch(value) for key, value in next_obs.items()},
            dones=self.to_torch(dones),
            rewards=self.to_torch(returns.astype(np.float32)),
            discounts=self.to_torch(discounts),
        )
