"""The replay buffer ``DrQv2`` picks and its memory: a warning when the full buffer would not fit in RAM, a
``MemoryError`` that suggests a size when it cannot be reserved."""

from __future__ import annotations

import contextlib
import os
import warnings
from collections.abc import Iterator
from typing import Any

import numpy as np
from gymnasium import spaces
from stable_baselines3.common.buffers import DictReplayBuffer, NStepReplayBuffer, ReplayBuffer

from sb3_collapse.drqv2.encoders import PixelEncoder
from sb3_collapse.drqv2.policies import CnnPolicy
from sb3_collapse.drqv2.replay_buffer import (
    DEFAULT_MIN_EPISODE_LENGTH,
    FrameStackReplayBuffer,
    frame_stack_storage_bytes,
)
from sb3_collapse.drqv2.sb3_compat import DictNStepReplayBuffer


def default_replay_buffer(
    replay_buffer_class: type[ReplayBuffer] | None,
    replay_buffer_kwargs: dict[str, Any],
    pixel_policy: bool,
    observation_space: spaces.Space,
    env_config: dict[str, Any] | None,
    n_steps: int,
    gamma: float,
) -> type[ReplayBuffer] | None:
    """The replay buffer class unless one was given (``FrameStackReplayBuffer`` for a ``pixel_policy`` on a
    frame-stacked env, SB3's dict buffers for dict observations); fills in ``replay_buffer_kwargs``' defaults."""
    config = env_config or {}
    frame_stack = config.get("frame_stack")
    if replay_buffer_class is None and isinstance(observation_space, spaces.Dict):
        replay_buffer_class = DictNStepReplayBuffer if n_steps > 1 else DictReplayBuffer
    stacked = isinstance(frame_stack, (int, np.integer)) and frame_stack > 1
    if replay_buffer_class is None and pixel_policy and config.get("obs_type") in (None, "pixels") and stacked:
        replay_buffer_class = FrameStackReplayBuffer
    n_step_buffers = (FrameStackReplayBuffer, NStepReplayBuffer, DictNStepReplayBuffer)
    if replay_buffer_class is not None and issubclass(replay_buffer_class, n_step_buffers):
        replay_buffer_kwargs.setdefault("n_steps", n_steps)
        replay_buffer_kwargs.setdefault("gamma", gamma)
        if uses_frame_stack_buffer(replay_buffer_class) and frame_stack is not None:
            replay_buffer_kwargs.setdefault("frame_stack", frame_stack)
    return replay_buffer_class


def uses_frame_stack_buffer(replay_buffer_class: type[ReplayBuffer] | None) -> bool:
    return replay_buffer_class is not None and issubclass(replay_buffer_class, FrameStackReplayBuffer)


def bytes_per_transition(
    replay_buffer_class: type[ReplayBuffer] | None,
    replay_buffer_kwargs: dict[str, Any],
    buffer_size: int,
    observation_space: spaces.Space,
    action_space: spaces.Space,
    n_envs: int,
) -> float:
    """:return: bytes per transition of the replay buffer (SB3's stores obs and next_obs)"""
    if uses_frame_stack_buffer(replay_buffer_class) and replay_buffer_kwargs.get("frame_stack") is not None:
        total = frame_stack_storage_bytes(
            buffer_size, observation_space, action_space, replay_buffer_kwargs["frame_stack"], n_envs,  # type: ignore[arg-type]
            replay_buffer_kwargs.get("min_episode_length", DEFAULT_MIN_EPISODE_LENGTH),
        )  # fmt: skip
        return total / buffer_size
    subspaces = observation_space.spaces.values() if isinstance(observation_space, spaces.Dict) else [observation_space]
    obs_bytes = sum(
        int(np.prod(space.shape or (1,))) * np.dtype(space.dtype or np.float32).itemsize for space in subspaces
    )
    return 2 * obs_bytes + int(np.prod(action_space.shape or (1,))) * 4 + 12


def memory_advice(replay_buffer_class: type[ReplayBuffer] | None, buffer_size: int, per_transition: float) -> str:
    """:return: what the buffer takes and which ``buffer_size`` would fit in 70% of this machine's RAM"""
    ram = physical_memory_bytes()
    fitting = int(0.7 * ram / per_transition)
    storage = "SB3's buffer stores obs and next_obs separately"
    if uses_frame_stack_buffer(replay_buffer_class):
        storage = "FrameStackReplayBuffer stores each frame once"
    return (
        f"{storage}: {per_transition / 1e3:,.0f} KB per transition, "
        f"{buffer_size * per_transition / 1e9:,.1f} GB in all, and this machine has "
        f"{ram / 1e9:,.1f} GB of RAM. Pass a smaller buffer_size, e.g. "
        f"buffer_size={fitting:_} (70% of the RAM), or the number of agent steps of your run if smaller."
    )


def warn_if_too_large(replay_buffer_class: type[ReplayBuffer] | None, buffer_size: int, per_transition: float) -> None:
    """Warn when the full replay buffer (SB3's or ``FrameStackReplayBuffer``) cannot fit in RAM."""
    sb3 = replay_buffer_class in (None, ReplayBuffer, NStepReplayBuffer)
    known = sb3 or uses_frame_stack_buffer(replay_buffer_class)
    if known and buffer_size * per_transition > physical_memory_bytes():
        warnings.warn(
            f"The replay buffer of {buffer_size:,} transitions will not fit in memory once full. "
            + memory_advice(replay_buffer_class, buffer_size, per_transition),
            stacklevel=5,  # the user's DrQv2(...) call
        )


def physical_memory_bytes() -> int:
    """Total RAM of this machine, in bytes."""
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def check_optimize_memory_usage(
    optimize_memory_usage: bool, replay_buffer_class: type[ReplayBuffer] | None, frame_stack_buffer: bool, n_steps: int
) -> bool:
    """:return: ``optimize_memory_usage`` where SB3's plain ``ReplayBuffer`` (``None`` and ``n_steps=1``) takes it,
    else ``False`` with a warning that says why"""
    plain = replay_buffer_class is ReplayBuffer or (replay_buffer_class is None and n_steps == 1)
    if not optimize_memory_usage or plain:
        return bool(optimize_memory_usage)
    if frame_stack_buffer:
        reason = "FrameStackReplayBuffer already stores each frame once (less memory than SB3's option)"
    else:
        name = "NStepReplayBuffer" if replay_buffer_class is None else replay_buffer_class.__name__
        reason = f"the replay buffer ({name}) does not support it; n_steps=1 uses SB3's ReplayBuffer, which does"
    warnings.warn(f"DrQv2: optimize_memory_usage=True is ignored: {reason}.", stacklevel=4)
    return False


def warn_not_ready(num_timesteps: int) -> None:
    """Say why the updates wait: DrQ-v2's sampling takes finished episodes only, and none it can sample has ended."""
    warnings.warn(
        f"DrQv2: no update at transition {num_timesteps}: the replay buffer samples finished episodes only "
        "(replay_buffer_kwargs sampling='drqv2', DrQ-v2's rule) and no episode of at least n_steps transitions has "
        "finished in it yet (since the last reset, if any). Updates start when one ends. DrQ-v2 starts learning "
        "after 4,000 frames (several episodes); pass a larger learning_starts, or sampling='sb3' to sample the "
        "episode in progress too.",
        stacklevel=2,
    )


@contextlib.contextmanager
def replay_buffer_setup(model: Any) -> Iterator[None]:
    """Around SB3's ``_setup_model`` of a ``DrQv2``: choose the buffer, check ``optimize_memory_usage``, warn when
    it cannot fit in RAM; in the block, a ``MemoryError`` says what size would fit."""
    encoder_class = model.policy_kwargs.get("encoder_class", PixelEncoder)
    model.replay_buffer_class = default_replay_buffer(
        model.replay_buffer_class, model.replay_buffer_kwargs,
        pixel_policy=issubclass(model.policy_class, CnnPolicy) and issubclass(encoder_class, PixelEncoder),
        observation_space=model.observation_space, env_config=model.env_config, n_steps=model.n_steps,
        gamma=model.gamma,
    )  # fmt: skip
    per_transition = bytes_per_transition(
        model.replay_buffer_class, model.replay_buffer_kwargs, model.buffer_size, model.observation_space,
        model.action_space, model.n_envs,
    )  # fmt: skip
    model.optimize_memory_usage = check_optimize_memory_usage(
        model.optimize_memory_usage, model.replay_buffer_class, uses_frame_stack_buffer(model.replay_buffer_class),
        model.n_steps,
    )  # fmt: skip
    warn_if_too_large(model.replay_buffer_class, model.buffer_size, per_transition)
    try:
        with warnings.catch_warnings():
            if "n_steps" in model.replay_buffer_kwargs:  # a loaded model's n-step buffer: SB3's warning is wrong
                warnings.filterwarnings("ignore", message=r"`n_steps=\d+` is ignored")
            yield
    except MemoryError as error:
        raise MemoryError(
            f"Could not allocate a replay buffer of {model.buffer_size:,} transitions ({error}). "
            + memory_advice(model.replay_buffer_class, model.buffer_size, per_transition)
        ) from None
