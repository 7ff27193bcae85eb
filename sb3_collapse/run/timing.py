"""Where the wall-clock time of ``learn()`` goes: waiting for the environments, updating, and the rest
(docs/throughput.md#where-the-time-goes-learntimer-resultjson)."""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch as th
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.vec_env import VecEnv, VecEnvWrapper
from stable_baselines3.common.vec_env.base_vec_env import VecEnvStepReturn


@dataclass
class PhaseTime:
    """Rounds, transitions (agent steps x ``n_envs``), updates and seconds of one phase of ``learn()``, each field as
    docs/throughput.md#where-the-time-goes-learntimer-resultjson says."""

    rounds: int = 0
    transitions: int = 0
    updates: int = 0
    env_s: float = 0.0
    update_s: float = 0.0
    total_s: float = 0.0

    @property
    def overhead_s(self) -> float:
        """Seconds neither waiting for the environments nor updating: ``total_s - env_s - update_s``."""
        return self.total_s - self.env_s - self.update_s

    def add(self, other: PhaseTime) -> None:
        """Add ``other``'s counts and seconds to this phase's."""
        for item in dataclasses.fields(self):
            setattr(self, item.name, getattr(self, item.name) + getattr(other, item.name))


@dataclass
class LearnTimings:
    """Time split of one ``learn()`` call (``LearnTimer.timings``): the ``warmup`` rounds (random actions, no updates),
    the ``learning`` ones, and the first round of updates (seconds, one-time costs included; updates)."""

    warmup: PhaseTime = field(default_factory=PhaseTime)
    learning: PhaseTime = field(default_factory=PhaseTime)
    first_round_s: float | None = None
    first_round_updates: int = 0

    def steady_learning_s(self) -> float:
        """Seconds of the ``learning`` phase with its first round of updates counted at the mean time of the later
        updates (without one-time costs); ``learning.total_s`` before the second round of updates."""
        phase = self.learning
        if self.first_round_s is None or phase.updates <= self.first_round_updates:
            return phase.total_s
        later_mean = (phase.update_s - self.first_round_s) / (phase.updates - self.first_round_updates)
        return phase.total_s - self.first_round_s + later_mean * self.first_round_updates

    def as_dict(self) -> dict[str, Any]:
        """The timings as plain JSON types, with ``overhead_s`` of each phase."""
        timings = dataclasses.asdict(self)
        for name in ("warmup", "learning"):
            timings[name]["overhead_s"] = getattr(self, name).overhead_s
        return {**timings, "steady_learning_s": self.steady_learning_s()}


class UpdateClock:
    """The device time of the rounds of updates on CUDA (nothing on other devices), from two events per round on the
    device's current stream: :meth:`start` before the updates, :meth:`stop` after, :meth:`collect` now and then."""

    def __init__(self) -> None:
        self._pending: list[tuple[Any, Any, PhaseTime, float]] = []

    @staticmethod
    def _record(device: th.device) -> Any:
        with th.cuda.device(device):  # that device's events, though another one is current
            event = th.cuda.Event(enable_timing=True)
            event.record(th.cuda.current_stream(device))
        return event

    def start(self, device: th.device) -> tuple[th.device, Any] | None:
        """:return: ``device`` and a CUDA event recorded on its current stream, ``None`` off CUDA"""
        return (device, self._record(device)) if device.type == "cuda" else None

    def stop(self, start: tuple[th.device, Any] | None, phase: PhaseTime, host_s: float) -> None:
        """Record the end of the round begun at ``start`` (of :meth:`start`; ``None``: nothing), added to ``phase``
        with ``host_s`` of ``update_s`` measured on the host."""
        if start is not None:
            self._pending.append((start[1], self._record(start[0]), phase, host_s))

    def collect(self, wait: bool = False) -> None:
        """Add the device time beyond the host time of each completed round to its phase's ``update_s`` (``wait``: for
        the rounds still running too, a synchronization for the end of ``learn()``)."""
        pending = []
        for start, end, phase, host_s in self._pending:
            if wait:
                end.synchronize()
            elif not end.query():
                pending.append((start, end, phase, host_s))
                continue
            phase.update_s += max(0.0, start.elapsed_time(end) / 1000.0 - host_s)
        self._pending = pending


class TimedVecEnv(VecEnvWrapper):
    """A ``VecEnv`` wrapper adding the seconds spent in ``venv``'s ``step_async`` and ``step_wait`` to ``env_s``."""

    def __init__(self, venv: VecEnv) -> None:
        super().__init__(venv)
        self.env_s = 0.0

    def reset(self) -> Any:
        return self.venv.reset()

    def step_async(self, actions: np.ndarray) -> None:
        start = time.perf_counter()
        self.venv.step_async(actions)
        self.env_s += time.perf_counter() - start

    def step_wait(self) -> VecEnvStepReturn:
        start = time.perf_counter()
        try:
            return self.venv.step_wait()
        finally:
            self.env_s += time.perf_counter() - start


class LearnTimer(BaseCallback):
    """
    Fills :attr:`timings` during each ``learn()`` of a model whose loop runs in rounds (``DrQv2``): a round's
    environment steps run from ``on_rollout_start`` to ``on_rollout_end``, its updates until the next round. Give it
    last in the callback list, so that the other callbacks' hooks count as overhead.

    :param env: the model's environments wrapped in a :class:`TimedVecEnv`, for ``env_s``; ``None``: ``env_s`` is 0
    """

    def __init__(self, env: TimedVecEnv | None = None) -> None:
        super().__init__()
        self.env = env
        self._on_training_start()  # timings: the time split of the current (or last) learn() call
        self._used_policy, self._updates_at_steps_end = False, 0
        self._start = self._steps_end = self._env_start = 0.0
        self._device_start: Any = None

    def _on_training_start(self) -> None:
        self.timings, self.clock = LearnTimings(), UpdateClock()
        self._round: PhaseTime | None = None

    def _on_rollout_start(self) -> None:
        self._close_round()
        self.clock.collect()  # the device time of earlier rounds that has completed
        self._round, self._used_policy = PhaseTime(rounds=1, transitions=-self.model.num_timesteps), False
        self._start, self._env_start, self._steps_end = time.perf_counter(), self._env_s(), 0.0

    def _on_step(self) -> bool:
        # The step's actions were chosen before it: from the policy unless the model was in its warm-up then.
        n_envs = self.training_env.num_envs
        before = self.model.num_timesteps - n_envs - self.model.reset_step
        self._used_policy |= before >= self.model.learning_starts
        return True

    def _on_rollout_end(self) -> None:
        self._end_steps()
        self._device_start = self.clock.start(self.model.device)

    def _end_steps(self) -> None:
        """End the environment steps of the round in progress."""
        assert self._round is not None
        self._steps_end = time.perf_counter()
        self._round.transitions += self.model.num_timesteps
        self._round.env_s = self._env_s() - self._env_start
        self._updates_at_steps_end = self.model.n_updates

    def _on_training_end(self) -> None:
        self._close_round()
        self.clock.collect(wait=True)

    def _close_round(self) -> None:
        """Add the round in progress to its phase (a round stopped by a callback before its updates included)."""
        if self._round is None:
            return
        if self._steps_end == 0.0:  # stopped during its environment steps
            self._end_steps()
            self._device_start = None
        round_, self._round, now = self._round, None, time.perf_counter()
        round_.updates = self.model.n_updates - self._updates_at_steps_end
        round_.update_s = now - self._steps_end if round_.updates > 0 else 0.0
        round_.total_s = now - self._start
        if self.timings.first_round_s is None and round_.updates > 0:
            self.timings.first_round_s, self.timings.first_round_updates = round_.update_s, round_.updates
        phase = self.timings.learning if self._used_policy or round_.updates > 0 else self.timings.warmup
        phase.add(round_)
        self.clock.stop(self._device_start if round_.updates > 0 else None, phase, round_.update_s)

    def _env_s(self) -> float:
        return 0.0 if self.env is None else self.env.env_s
