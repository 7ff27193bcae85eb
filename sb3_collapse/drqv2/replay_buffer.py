"""A replay buffer of frame-stacked pixels that stores each frame once (docs/algorithm.md, *Replay buffer*)."""

from __future__ import annotations

import math
import warnings
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.preprocessing import get_action_dim
from stable_baselines3.common.type_aliases import ReplayBufferSamples
from stable_baselines3.common.vec_env import VecNormalize

from sb3_collapse.errors import NonFiniteDataError, ParameterError

REPLAY_SAMPLINGS = ("sb3", "drqv2")
FALLBACK_ADVICE = (
    "If the observations are not stacked frames, pass replay_buffer_class=NStepReplayBuffer (n-step returns) "
    "or ReplayBuffer (from stable_baselines3.common.buffers), which store whole observations."
)
DEFAULT_MIN_EPISODE_LENGTH = 250  # agent steps
PER_TRANSITION_ARRAYS_BYTES = 8 + 4 + 4 + 4  # frame index (int64), reward, done, timeout (float32)


def frame_capacity(transitions: int, frame_stack: int, min_episode_length: int) -> int:
    """:return: frames one environment's column holds, ``transitions + frame_stack * (1 + ceil(transitions /
    min_episode_length))`` (docs/algorithm.md#inside-the-frame-store)"""
    return transitions + frame_stack * (1 + math.ceil(transitions / min_episode_length))


def frame_stack_storage_bytes(
    buffer_size: int,
    observation_space: spaces.Box,
    action_space: spaces.Space,
    frame_stack: int,
    n_envs: int = 1,
    min_episode_length: int = DEFAULT_MIN_EPISODE_LENGTH,
) -> int:
    """:return: bytes of the arrays of a :class:`FrameStackReplayBuffer` built with these arguments"""
    transitions = max(buffer_size // n_envs, 1)
    frame_bytes = int(np.prod(observation_space.shape)) // frame_stack * np.dtype(observation_space.dtype).itemsize
    action_dtype = ReplayBuffer._maybe_cast_dtype(action_space.dtype)
    action_bytes = get_action_dim(action_space) * np.dtype(action_dtype).itemsize
    frames = frame_capacity(transitions, frame_stack, min_episode_length) * n_envs * frame_bytes
    return frames + transitions * n_envs * (action_bytes + PER_TRANSITION_ARRAYS_BYTES)


class FrameStackReplayBuffer(ReplayBuffer):
    """
    N-step replay buffer of channel-first stacks of ``frame_stack`` frames, oldest first, storing each frame once;
    it samples what SB3's ``NStepReplayBuffer`` samples, with the same ``np.random`` calls (docs/algorithm.md).

    :param buffer_size: capacity in transitions (all environments together, as in SB3)
    :param observation_space: ``Box`` of shape ``(channels * frame_stack, height, width)``
    :param action_space: the action space
    :param device: PyTorch device of the sampled tensors
    :param n_envs: number of parallel environments
    :param optimize_memory_usage: must be ``False`` (frames are already stored once)
    :param handle_timeout_termination: bootstrap at time limits (``infos[i]["TimeLimit.truncated"]``), as in SB3
    :param n_steps: length of the n-step returns, in agent steps (1: one-step returns, with ``discounts``)
    :param gamma: discount factor of the n-step returns
    :param frame_stack: frames per observation (``make_dmc_env``'s ``frame_stack``; DrQv2 reads it from the env)
    :param min_episode_length: shortest episode, in agent steps, for which all transitions stay sampleable
    :param sampling: ``"sb3"`` or ``"drqv2"`` (finished episodes only, as DrQ-v2's reference)
    """

    frames: np.ndarray
    frame_starts: np.ndarray
    frame_heads: np.ndarray

    def __init__(
        self,
        buffer_size: int,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        device: th.device | str = "auto",
        n_envs: int = 1,
        optimize_memory_usage: bool = False,
        handle_timeout_termination: bool = True,
        n_steps: int = 3,
        gamma: float = 0.99,
        frame_stack: int | None = None,
        min_episode_length: int = DEFAULT_MIN_EPISODE_LENGTH,
        sampling: str = "sb3",
    ) -> None:
        if sampling not in REPLAY_SAMPLINGS:
            raise ParameterError(
                "sampling", f"sampling must be one of {', '.join(map(repr, REPLAY_SAMPLINGS))}, got {sampling!r}."
            )
        if optimize_memory_usage:
            raise ValueError("FrameStackReplayBuffer stores each frame once already: pass optimize_memory_usage=False.")
        self.frame_stack = _check_layout(observation_space, frame_stack)
        if n_steps < 1:
            raise ValueError(f"n_steps must be >= 1 agent step, got {n_steps}.")
        if min_episode_length < 1:
            raise ValueError(f"min_episode_length must be >= 1 agent step, got {min_episode_length}.")
        super(ReplayBuffer, self).__init__(buffer_size, observation_space, action_space, device, n_envs=n_envs)
        self.buffer_size = max(buffer_size // n_envs, 1)
        if n_steps > self.buffer_size:
            raise ValueError(f"n_steps={n_steps} exceeds the capacity per environment ({self.buffer_size}).")
        self.optimize_memory_usage = False
        self.handle_timeout_termination = handle_timeout_termination
        self.n_steps = n_steps
        self.gamma = gamma
        self.min_episode_length = min_episode_length
        self.sampling = sampling

        channels, height, width = self.obs_shape
        self.frame_shape = (channels // self.frame_stack, height, width)
        self.frame_capacity = frame_capacity(self.buffer_size, self.frame_stack, min_episode_length)
        self.frames = np.zeros((self.frame_capacity, n_envs, *self.frame_shape), dtype=observation_space.dtype)
        self.frame_starts = np.zeros((self.buffer_size, n_envs), dtype=np.int64)
        self.frame_heads = np.zeros(n_envs, dtype=np.int64)  # frames written per env, since the last reset
        action_dtype = self._maybe_cast_dtype(action_space.dtype)
        self.actions = np.zeros((self.buffer_size, n_envs, self.action_dim), dtype=action_dtype)
        self.rewards, self.dones, self.timeouts = (np.zeros((self.buffer_size, n_envs), np.float32) for _ in range(3))
        self.steps_since_done = np.zeros(n_envs, dtype=np.int64)  # transitions of each env's episode in progress
        self.episodes_done = np.zeros(n_envs, dtype=np.int64)  # episodes ended per env, since the last reset
        self.transitions_added = 0  # add() calls (transitions per env) since the last reset
        self.resets = 0  # reset() calls since construction
        self._sampleable_checked: tuple[int, int, int, bool] | None = None  # ready_to_sample's last pass
        self._frame_offsets = np.arange(self.frame_stack)
        _warn_if_larger_than_available_memory(self.nbytes)

    @property
    def storage_arrays(self) -> dict[str, np.ndarray]:
        """The arrays holding the data, by name."""
        names = ("frames", "frame_starts", "actions", "rewards", "dones", "timeouts")
        return {name: getattr(self, name) for name in names}

    @property
    def nbytes(self) -> int:
        """Bytes of the storage arrays once filled (``np.zeros`` reserves them lazily)."""
        return sum(array.nbytes for array in self.storage_arrays.values())

    def reset(self) -> None:
        """Empty the buffer: no transition and no frame remain sampleable (the arrays are not zeroed)."""
        super().reset()
        for counts in (self.frame_heads, self.steps_since_done, self.episodes_done):
            counts[:] = 0
        self.transitions_added = 0
        self.resets += 1

    def add(
        self,
        obs: np.ndarray,
        next_obs: np.ndarray,
        action: np.ndarray,
        reward: np.ndarray,
        done: np.ndarray,
        infos: list[dict[str, Any]],
    ) -> None:
        """SB3's ``add``, ``obs`` ``(n_envs, channels * frame_stack, height, width)``; a ``next_obs`` that is not its
        ``obs`` shifted by one frame raises ``ValueError``, a non-finite ``reward`` or (float frames) ``next_obs``
        ``NonFiniteDataError`` (nothing stored)."""
        refuse_non_finite(reward, self.n_envs, "reward")
        if self.frames.dtype.kind == "f":  # pixels (integers) cannot hold a NaN
            refuse_non_finite(next_obs, self.n_envs, "observation")
            refuse_non_finite(obs, self.n_envs, "observation")  # an episode's first
        k, frame_shape = self.frame_stack, self.frame_shape
        obs_frames = np.asarray(obs).reshape(self.n_envs, k, *frame_shape)
        next_frames = np.asarray(next_obs).reshape(self.n_envs, k, *frame_shape)
        for env_index in range(self.n_envs):
            if not np.array_equal(next_frames[env_index, :-1], obs_frames[env_index, 1:]):
                raise ValueError(
                    f"FrameStackReplayBuffer stores each frame once, so it needs next_obs to be obs shifted by one "
                    f"frame of {frame_shape[0]} channels, the new frame last (frame_stack={k}); the transition of "
                    f"env {env_index} at position {self.pos} is not. Check frame_stack, or: {FALLBACK_ADVICE}"
                )
        for env_index in range(self.n_envs):
            head = int(self.frame_heads[env_index])
            if not self._continues(env_index, head, obs_frames[env_index]):
                self.frames[(head + self._frame_offsets) % self.frame_capacity, env_index] = obs_frames[env_index]
                head += k
            self.frame_starts[self.pos, env_index] = head - k
            self.frames[head % self.frame_capacity, env_index] = next_frames[env_index, -1]
            self.frame_heads[env_index] = head + 1

        self.actions[self.pos] = np.asarray(action).reshape(self.n_envs, self.action_dim)
        self.rewards[self.pos] = np.asarray(reward)
        self.dones[self.pos] = np.asarray(done)
        if self.handle_timeout_termination:
            self.timeouts[self.pos] = [info.get("TimeLimit.truncated", False) for info in infos]
        ended = np.asarray(done, dtype=bool).reshape(self.n_envs)
        self.steps_since_done = np.where(ended, 0, self.steps_since_done + 1)
        self.episodes_done += ended
        self.transitions_added += 1
        self.pos += 1
        if self.pos == self.buffer_size:
            self.full = True
            self.pos = 0

    def _continues(self, env_index: int, head: int, obs_frames: np.ndarray) -> bool:
        """Whether ``obs_frames`` are the last ``frame_stack`` frames written for this env (its last next_obs)."""
        if head < self.frame_stack:
            return False
        last = self.frames[(head - self.frame_stack + self._frame_offsets) % self.frame_capacity, env_index]
        return bool(np.array_equal(last, obs_frames))

    @property
    def ready_to_sample(self) -> bool:
        """Whether :meth:`sample` has a transition to draw (``"drqv2"``: of a finished episode with at least
        ``n_steps`` transitions; the buffer scanned only when that may have changed)."""
        if self.sampling != "drqv2":
            return self.size() > 0
        episodes = int(self.episodes_done.sum())
        if episodes == 0:
            return False
        laps = self.transitions_added // self.buffer_size
        checked = self._sampleable_checked
        if checked is not None and checked[:2] == (self.resets, laps) and (checked[3] or checked[2] == episodes):
            return checked[3]  # more finished episodes only add sampleable transitions until the ring wraps
        ready = self._any_sampleable(self.buffer_size if self.full else self.pos)
        self._sampleable_checked = (self.resets, laps, episodes, ready)
        return ready

    def frames_stored(self, batch_inds: np.ndarray, env_indices: np.ndarray) -> np.ndarray:
        """:return: for each ``(pos, env)``, whether all frames of its ``obs`` and ``next_obs`` are still stored"""
        starts = self.frame_starts[batch_inds, env_indices]
        return starts >= self.frame_heads[env_indices] - self.frame_capacity

    def is_sampleable(self, batch_inds: np.ndarray, env_indices: np.ndarray) -> np.ndarray:
        """:return: for each ``(pos, env)``, whether :meth:`sample` may draw it: its frames stored and, with
        ``sampling="drqv2"``, its episode finished with at least ``n_steps`` transitions from it on"""
        sampleable = self.frames_stored(batch_inds, env_indices)
        if self.sampling == "drqv2":
            newest = (self.pos - 1) % self.buffer_size
            age = (newest - batch_inds) % self.buffer_size  # 0 for the newest transition
            finished = age >= self.steps_since_done[env_indices]
            window = (batch_inds[:, None] + np.arange(self.n_steps - 1)) % self.buffer_size  # [batch, n_steps - 1]
            room = ~(self.dones[window, env_indices[:, None]] != 0).any(axis=1)
            sampleable &= finished & room
        return sampleable

    def sample(self, batch_size: int, env: VecNormalize | None = None) -> ReplayBufferSamples:
        """SB3's ``sample``, uniform among the sampleable transitions (:meth:`sample_indices`)."""
        batch_inds, env_indices = self.sample_indices(batch_size)
        return self._get_samples(batch_inds, env=env, env_indices=env_indices)

    def sample_indices(self, batch_size: int) -> tuple[np.ndarray, np.ndarray]:
        """:return: the positions and environments, each ``(batch_size,)``, that :meth:`sample` draws as SB3 does,
        drawing again those not sampleable (``ValueError`` when none is)"""
        upper_bound = self.buffer_size if self.full else self.pos
        if upper_bound == 0:
            raise ValueError("The replay buffer is empty: add transitions before sampling.")
        batch_inds = np.random.randint(0, upper_bound, size=batch_size)
        env_indices = np.random.randint(0, self.n_envs, size=batch_inds.shape)
        redraw = ~self.is_sampleable(batch_inds, env_indices)
        rounds = 0
        while redraw.any():  # not sampleable (overwritten frames, or drqv2's rule): draw those again
            rounds += 1
            if rounds % 100 == 0 and not self._any_sampleable(upper_bound):
                raise ValueError(
                    f"No transition of the replay buffer can be sampled: with sampling={self.sampling!r} only "
                    f"finished episodes of at least n_steps={self.n_steps} transitions are. Sample after the first "
                    "episode ends (DrQ-v2 starts learning after 4,000 frames, several episodes), or use "
                    "sampling='sb3'."
                )
            count = int(redraw.sum())
            batch_inds[redraw] = np.random.randint(0, upper_bound, size=count)
            env_indices[redraw] = np.random.randint(0, self.n_envs, size=count)
            redraw[redraw] = ~self.is_sampleable(batch_inds[redraw], env_indices[redraw])
        return batch_inds, env_indices

    def _any_sampleable(self, upper_bound: int) -> bool:
        """Whether any stored ``(pos, env)`` is sampleable (a pass over the whole buffer)."""
        positions = np.repeat(np.arange(upper_bound), self.n_envs)
        envs = np.tile(np.arange(self.n_envs), upper_bound)
        return bool(self.is_sampleable(positions, envs).any())

    def _get_samples(  # type: ignore[override]
        self, batch_inds: np.ndarray, env: VecNormalize | None = None, env_indices: np.ndarray | None = None
    ) -> ReplayBufferSamples:
        """SB3's ``_get_samples`` (:meth:`sample_arrays` as tensors); ``env_indices=None`` draws them as SB3 does."""
        if env_indices is None:
            env_indices = np.random.randint(0, self.n_envs, size=batch_inds.shape)
        arrays = self.sample_arrays(batch_inds, env_indices, env=env)  # the stacks are new arrays: not copied again
        stacks = ("observations", "next_observations")
        return ReplayBufferSamples(**{name: self.to_torch(a, copy=name not in stacks) for name, a in arrays.items()})

    def sample_arrays(
        self,
        batch_inds: np.ndarray,
        env_indices: np.ndarray,
        env: VecNormalize | None = None,
        frames_out: np.ndarray | None = None,
    ) -> dict[str, np.ndarray]:
        """:return: the fields of ``ReplayBufferSamples`` by name, host arrays of the n-step transitions at
        ``(batch_inds, env_indices)``, normalized by ``env`` or gathered into ``frames_out`` (``(2, batch, *obs)``)"""
        if not self.frames_stored(batch_inds, env_indices).all():
            raise ValueError(
                "Some requested transitions have had their frames overwritten by newer episodes: sample them "
                "only where frames_stored(batch_inds, env_indices) is True."
            )
        if frames_out is not None and env is not None:
            raise ValueError("sample_arrays: frames_out takes the stored frames, not normalized ones: pass env=None.")
        returns, discounts, dones, last = n_step_returns(self, batch_inds, env_indices, env)
        out = (None, None) if frames_out is None else (frames_out[0], frames_out[1])
        obs = self._stacks(self.frame_starts[batch_inds, env_indices], env_indices, out=out[0])
        next_obs = self._stacks(self.frame_starts[last, env_indices] + 1, env_indices, out=out[1])
        return {
            "observations": self._normalize_obs(obs, env),  # type: ignore[dict-item]
            "actions": self.actions[batch_inds, env_indices],
            "next_observations": self._normalize_obs(next_obs, env),  # type: ignore[dict-item]
            "dones": dones,
            "rewards": returns,
            "discounts": discounts,
        }

    def _stacks(self, first_frames: np.ndarray, env_indices: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """:return: the ``(batch, *obs_shape)`` stacks whose oldest frames are ``first_frames`` (into ``out``)"""
        slots = (first_frames[:, None] + self._frame_offsets) % self.frame_capacity  # [batch, frame_stack]
        flat_frames = self.frames.reshape(self.frame_capacity * self.n_envs, -1)
        rows = (slots * self.n_envs + env_indices[:, None]).ravel()
        if out is None:
            stacked = np.take(flat_frames, rows, axis=0)
            return stacked.reshape(len(first_frames), *self.obs_shape)
        expected = (len(first_frames), *self.obs_shape)
        if out.shape != expected or out.dtype != self.frames.dtype or not out.flags.c_contiguous:
            raise ValueError(
                f"frames_out must be C-contiguous {self.frames.dtype} of shape (2, *{expected}), got "
                f"{out.dtype} {out.shape}."
            )
        # mode="clip" writes straight into out (the default mode="raise" buffers it); every row is in range.
        np.take(flat_frames, rows, axis=0, out=out.reshape(len(rows), -1), mode="clip")
        return out


def n_step_returns(
    buffer: ReplayBuffer, batch_inds: np.ndarray, env_indices: np.ndarray, env: VecNormalize | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """SB3's ``NStepReplayBuffer`` rule on ``buffer``'s arrays. :return: the returns, their discounts
    ``gamma ** k`` and the dones, each ``(batch, 1)``, and the positions ``(batch,)`` of the last transitions summed"""
    n_steps, gamma, size = buffer.n_steps, buffer.gamma, buffer.buffer_size  # type: ignore[attr-defined]
    steps = np.arange(n_steps)
    window = (batch_inds[:, None] + steps) % size  # [batch, n_steps]
    envs = env_indices[:, None]
    newest = (buffer.pos - 1) % size
    ends = (buffer.dones[window, envs] != 0) | (buffer.timeouts[window, envs] != 0) | (window == newest)
    used = np.where(ends.any(axis=1), ends.argmax(axis=1), n_steps - 1)  # index of the last step summed
    mask = steps[None, :] <= used[:, None]
    rewards = buffer._normalize_reward(buffer.rewards[window, envs], env)
    powers = gamma ** np.arange(n_steps, dtype=np.float32)
    returns = (rewards * powers[None, :] * mask).sum(axis=1, keepdims=True)
    discounts = gamma ** mask.sum(axis=1, keepdims=True).astype(np.float32)
    last = (batch_inds + used) % size
    dones = (buffer.dones[last, env_indices] * (1.0 - buffer.timeouts[last, env_indices]))[:, None]
    return returns, discounts, dones.astype(np.float32), last


def refuse_non_finite(values: np.ndarray, n_envs: int, what: str) -> None:
    """:raises NonFiniteDataError: naming the first env whose ``values`` (a ``what`` per env, ``(n_envs, ...)``) are
    not all finite"""
    rows = np.asarray(values).reshape(n_envs, -1)
    bad = ~np.isfinite(rows)
    if bad.any():
        env = int(bad.any(axis=1).argmax())
        raise NonFiniteDataError(
            f"env {env} returned {'an' if what[0] in 'aeiou' else 'a'} {what} that is not finite "
            f"({rows[env][bad[env]][0]}), refused before it was stored: bad data from the environment, not a "
            "divergence of the training."
        )


def _check_layout(observation_space: spaces.Space, frame_stack: int | None) -> int:
    """:return: ``frame_stack``, checked against the ``(channels * frame_stack, height, width)`` Box"""
    if frame_stack is None:
        raise ValueError(
            "FrameStackReplayBuffer needs frame_stack, the number of frames per observation: pass "
            "replay_buffer_kwargs=dict(frame_stack=...) (DrQv2 reads it from make_dmc_env environments)."
        )
    if isinstance(frame_stack, bool) or not isinstance(frame_stack, (int, np.integer)) or frame_stack < 1:
        raise ValueError(f"frame_stack must be an integer >= 1, got {frame_stack!r}.")
    shape = getattr(observation_space, "shape", None)
    if not isinstance(observation_space, spaces.Box) or len(shape) != 3 or shape[0] % frame_stack != 0:
        raise ValueError(
            f"FrameStackReplayBuffer needs channel-first stacks of frame_stack={frame_stack} frames, a Box of "
            f"shape (channels * {frame_stack}, height, width), got {observation_space}. {FALLBACK_ADVICE}"
        )
    return int(frame_stack)


def _warn_if_larger_than_available_memory(nbytes: int) -> None:
    """Warn, as SB3's buffers do, when the filled buffer would exceed the memory available now."""
    try:
        with open("/proc/meminfo") as meminfo:
            fields = dict(line.split(":", 1) for line in meminfo)
        available = int(fields["MemAvailable"].split()[0]) * 1024
    except (OSError, KeyError, ValueError):
        return
    if nbytes > available:
        warnings.warn(
            f"This system does not have apparently enough memory to store the complete replay buffer "
            f"{nbytes / 1e9:.2f}GB > {available / 1e9:.2f}GB",
            stacklevel=3,
        )
