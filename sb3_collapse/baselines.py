"""SB3's TD3, SAC and DDPG with the package's model interface, and :func:`build_baseline`: SB3's TD3 or SAC on
DeepMind Control pixels, sized like DrQ-v2 (docs/interventions.md#sb3s-td3-and-sac-on-pixels)."""

from __future__ import annotations

__all__ = ["BASELINES", "DDPG", "SAC", "TD3", "build_baseline"]

from typing import Any, TypeVar

import numpy as np
import stable_baselines3 as sb3
import torch as th
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.noise import NormalActionNoise
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback

from sb3_collapse.common.grad_norms import GradNormRecorder
from sb3_collapse.common.layers import layer_parameters
from sb3_collapse.common.model import CollapseModel, CollapseModelBase
from sb3_collapse.errors import LayerMappingError

ModelT = TypeVar("ModelT", bound=BaseAlgorithm)


class SB3Model(CollapseModelBase):
    """:class:`~sb3_collapse.common.model.CollapseModel` for SB3's TD3, DDPG and SAC (mixed in before them)."""

    def _setup_model(self) -> None:
        super()._setup_model()  # type: ignore[misc]
        self._record_grad_norms()

    def _record_grad_norms(self) -> None:
        if self.grad_norm_recorder is not None:
            self.grad_norm_recorder.remove()
        try:
            layers = layer_parameters(self)  # type: ignore[arg-type]
        except LayerMappingError:
            self.grad_norm_recorder = None
            return
        policy = self.policy  # type: ignore[attr-defined]
        self.grad_norm_recorder = GradNormRecorder(layers, [policy.actor.optimizer, policy.critic.optimizer])

    def reset_from_scratch(self) -> None:
        """The paper's rule: SB3's ``_setup_model()`` again (not re-seeded), the buffer emptied, the warm-up again."""
        model: Any = self
        warmup = model.learning_starts - self.reset_step
        was_training = model.policy.training
        seed, model.seed = model.seed, None  # _setup_model seeds the generators with it: new weights need new draws
        try:
            model._setup_model()  # the replay buffer, which exists, is kept
        finally:
            model.seed = seed
        model.policy.set_training_mode(was_training)
        model.replay_buffer.reset()
        if model.action_noise is not None:
            model.action_noise.reset()
        self.reset_step = self.num_timesteps
        model.learning_starts = self.num_timesteps + warmup

    def _setup_learn(
        self,
        total_timesteps: int,
        callback: MaybeCallback = None,
        reset_num_timesteps: bool = True,
        tb_log_name: str = "run",
        progress_bar: bool = False,
    ) -> tuple[int, BaseCallback]:
        if reset_num_timesteps and self.reset_step:  # a new run from step 0: the warm-up gets its length back
            self.learning_starts -= self.reset_step  # type: ignore[attr-defined]
            self.reset_step = 0
        return super()._setup_learn(total_timesteps, callback, reset_num_timesteps, tb_log_name, progress_bar)  # type: ignore[misc]

    def _excluded_save_params(self) -> list[str]:
        return [*super()._excluded_save_params(), "grad_norm_recorder"]  # type: ignore[misc]


class TD3(SB3Model, sb3.TD3):
    """SB3's ``TD3`` with the :class:`SB3Model` interface."""


class SAC(SB3Model, sb3.SAC):
    """SB3's ``SAC`` with the :class:`SB3Model` interface."""


class DDPG(SB3Model, sb3.DDPG):
    """SB3's ``DDPG`` with the :class:`SB3Model` interface."""


_WRAPPERS: dict[type, type] = {sb3.TD3: TD3, sb3.SAC: SAC, sb3.DDPG: DDPG}


def collapse_model(model: ModelT) -> ModelT:
    """:return: ``model`` itself, its class made the wrapper's when it is an SB3 ``TD3``, ``DDPG`` or ``SAC`` (or a
    subclass), attributes, optimizers and buffer kept; any other model as it is"""
    cls = type(model)
    if isinstance(model, CollapseModel) or not any(base in _WRAPPERS for base in cls.__mro__):
        return model
    if cls not in _WRAPPERS:  # a user's subclass: the class with SB3Model mixed in
        _WRAPPERS[cls] = type(cls.__name__, (SB3Model, cls), {"__module__": cls.__module__, "__doc__": cls.__doc__})
    model.__class__ = _WRAPPERS[cls]
    model._record_grad_norms()  # type: ignore[attr-defined]
    return model


BASELINES: dict[str, type[TD3 | SAC]] = {"td3": TD3, "sac": SAC}
"""The algorithms :func:`build_baseline` builds, by name (the train command's ``--algorithm``)."""
DRQV2_ONLY_SETTINGS = (
    "n_steps", "stddev_schedule", "stddev_clip", "tau", "train_freq", "augmentation_pad", "replay_sampling"
)  # fmt: skip
"""Settings of ``TrainConfig`` that only DrQ-v2 uses: the baselines keep SB3's own values for them."""
NATURE_CNN_MIN_SIZE = 36  # smallest image side of NatureCNN (8x8 stride 4, 4x4 stride 2, 3x3 stride 1)
TD3_ACTION_NOISE = 0.1  # std of TD3's Gaussian exploration noise, on actions in [-1, 1]


def build_baseline(
    algorithm: str,
    env: GymEnv,
    *,
    learning_rate: float,
    buffer_size: int,
    learning_starts: int,
    batch_size: int,
    feature_dim: int = 50,
    hidden_dim: int = 1024,
    gamma: float = 0.99,
    frame_stack: int | None = None,
    seed: int | None = None,
    device: th.device | str = "auto",
    verbose: int = 0,
) -> TD3 | SAC:
    """
    SB3's TD3 or SAC from pixels, sized like DrQ-v2.

    :param algorithm: ``"td3"`` or ``"sac"``
    :param env: a pixel environment, e.g. ``make_dmc_env(...)`` (channel-first uint8 images)
    :param learning_rate: Adam learning rate of every network
    :param buffer_size: replay capacity, in transitions (agent steps)
    :param learning_starts: agent steps of uniformly random actions before the first update
    :param batch_size: minibatch size
    :param feature_dim: output size of the ``NatureCNN`` features extractors (``mlp0``)
    :param hidden_dim: units of each of the two hidden layers of the actor and of each Q network
    :param gamma: discount factor
    :param frame_stack: frames per observation: ``> 1`` stores each frame once (``FrameStackReplayBuffer``)
    :param seed: random seed
    :param device: ``"auto"``, ``"cpu"``, ``"cuda"``...
    :param verbose: SB3 verbosity
    :return: the model, ready to ``learn()``
    :raises ValueError: for an unknown algorithm, or images smaller than ``NatureCNN`` takes
    """
    if algorithm not in BASELINES:
        raise ValueError(f"algorithm must be one of {', '.join(BASELINES)}, got {algorithm!r}.")
    height, width = env.observation_space.shape[-2:]  # type: ignore[union-attr,index]
    if min(height, width) < NATURE_CNN_MIN_SIZE:
        raise ValueError(
            f"SB3's NatureCNN needs images of at least {NATURE_CNN_MIN_SIZE}x{NATURE_CNN_MIN_SIZE} pixels, got "
            f"{height}x{width}: render larger images (make_dmc_env(size=...))."
        )
    policy_kwargs = dict(net_arch=[hidden_dim, hidden_dim], features_extractor_kwargs=dict(features_dim=feature_dim))
    params: dict[str, Any] = dict(learning_rate=learning_rate, buffer_size=buffer_size, batch_size=batch_size)
    params.update(gamma=gamma, learning_starts=learning_starts, policy_kwargs=policy_kwargs, seed=seed, device=device)
    if frame_stack is not None and frame_stack > 1:
        from sb3_collapse.drqv2.replay_buffer import FrameStackReplayBuffer  # monitoring imports this module, not drqv2

        params["replay_buffer_class"] = FrameStackReplayBuffer
        params["replay_buffer_kwargs"] = dict(n_steps=1, gamma=gamma, frame_stack=frame_stack)
    if algorithm == "td3":
        action_dim = int(np.prod(env.action_space.shape))  # type: ignore[union-attr]
        params["action_noise"] = NormalActionNoise(np.zeros(action_dim), TD3_ACTION_NOISE * np.ones(action_dim))
    return BASELINES[algorithm]("CnnPolicy", env, verbose=verbose, **params)
