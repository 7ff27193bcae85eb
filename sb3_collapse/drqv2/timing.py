"""Where the wall-clock time of ``DrQv2.learn()`` goes: waiting for the environments, updating, and the rest.

``DrQv2`` fills a :class:`LearnTimings` during every ``learn()`` call (``model.timings``, reset at the start of the
call). Each round of ``learn()``'s loop (the environment steps up to the next update, then that round of updates)
is counted in one of two phases:

- ``warmup``: rounds whose actions were all uniformly random and that made no update (the first
  ``learning_starts`` transitions, and again after each ``reset_from_scratch``): the environments alone;
- ``learning``: every other round (actions of the policy, updates).

In each phase, ``env_s`` is the time spent waiting for the environments (``VecEnv.step``, or ``step_wait`` for a
step sent before the updates, see ``DrQv2``'s ``step_envs_during_updates``), ``update_s`` the time in
``DrQv2.train`` (replay sampling included), ``total_s`` the wall-clock time of the phase's rounds, and
``overhead_s`` the rest: action selection, storing transitions, callbacks (evaluations and collapse checks run in
callbacks: they count here), logging.

On CUDA the kernels of an update are still running when ``train`` returns; whatever needs their result next (the next
action's copy to the host) waits for them. :class:`UpdateClock` times each round's updates on the device as well,
with a pair of CUDA events, and counts the update as ``max(host time, device time)``: the device time beyond the host
time moves from ``overhead_s`` (where the wait fell) to ``update_s``. The events are read when they have completed
(``Event.query``, no synchronization) and, for the last ones, once at the end of ``learn()``.

The first round of updates of a ``learn()`` call also includes one-time costs: ``torch.compile``'s compilation
(``compile_update``), cuDNN's autotuning, the allocators' first requests. ``first_round_s`` and
``first_round_updates`` record it, so that :meth:`PhaseTime.steady_total_s` can leave it out.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

import torch as th


@dataclass
class PhaseTime:
    """
    Seconds and counts of one phase of ``learn()`` (see the module docstring).

    :param rounds: rounds of the loop (environment steps up to an update, then the updates)
    :param transitions: transitions collected, summed over the environments (agent steps x ``n_envs``)
    :param updates: gradient updates
    :param env_s: seconds waiting for the environments
    :param update_s: seconds in ``DrQv2.train``
    :param total_s: wall-clock seconds of the phase's rounds
    """

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
    """
    Time split of one ``learn()`` call (``DrQv2.timings``).

    :param warmup: rounds of uniformly random actions without updates
    :param learning: the other rounds
    :param first_round_s: seconds of the first round of updates of the call (one-time costs included); ``None``
        before any update
    :param first_round_updates: updates in that round
    """

    warmup: PhaseTime = field(default_factory=PhaseTime)
    learning: PhaseTime = field(default_factory=PhaseTime)
    first_round_s: float | None = None
    first_round_updates: int = 0

    def steady_learning_s(self) -> float:
        """
        Seconds of the ``learning`` phase with the first round of updates replaced by the mean time of the same
        number of later updates: the phase's duration without the one-time costs (compilation, autotuning).
        Equal to ``learning.total_s`` before the second round of updates.
        """
        phase = self.learning
        if self.first_round_s is None or phase.updates <= self.first_round_updates:
            return phase.total_s
        later_mean = (phase.update_s - self.first_round_s) / (phase.updates - self.first_round_updates)
        return phase.total_s - self.first_round_s + later_mean * self.first_round_updates

    def as_dict(self) -> dict[str, Any]:
        """The timings as plain JSON types, with ``overhead_s`` of each phase."""
        phases = {
            name: {**dataclasses.asdict(getattr(self, name)), "overhead_s": getattr(self, name).overhead_s}
            for name in ("warmup", "learning")
        }
        return {
            **phases,
            "first_round_s": self.first_round_s,
            "first_round_updates": self.first_round_updates,
            "steady_learning_s": self.steady_learning_s(),
        }


class UpdateClock:
    """
    The device time of the rounds of updates on CUDA (see the module docstring); nothing on other devices.

    Use: ``start = clock.start(device)`` before ``train``, ``clock.stop(start, phase, host_s)`` once the round is added
    to ``phase``, :meth:`collect` now and then, ``collect(wait=True)`` at the end.
    """

    def __init__(self) -> None:
        self._pending: list[tuple[Any, Any, PhaseTime, float]] = []

    def start(self, device: th.device) -> Any:
        """:return: a recorded CUDA event on ``device``'s current stream, ``None`` off CUDA"""
        if device.type != "cuda":
            return None
        event = th.cuda.Event(enable_timing=True)
        event.record(th.cuda.current_stream(device))
        return event

    def stop(self, start: Any, phase: PhaseTime, host_s: float) -> None:
        """
        :param start: what :meth:`start` returned (nothing happens for ``None``)
        :param phase: the phase the round was added to
        :param host_s: the round's ``update_s`` measured on the host, already in ``phase``
        """
        if start is None:
            return
        end = th.cuda.Event(enable_timing=True)
        end.record()
        self._pending.append((start, end, phase, host_s))

    def collect(self, wait: bool = False) -> None:
        """
        Add the device time beyond the host time of each completed round to its phase's ``update_s``.

        :param wait: wait for the rounds still running (a synchronization; for the end of ``learn()``)
        """
        pending = []
        for start, end, phase, host_s in self._pending:
            if wait:
                end.synchronize()
            elif not end.query():
                pending.append((start, end, phase, host_s))
                continue
            phase.update_s += max(0.0, start.elapsed_time(end) / 1000.0 - host_s)
        self._pending = pending
