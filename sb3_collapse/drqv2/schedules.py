"""Exploration-noise schedules of DrQ-v2.

DrQ-v2 writes its exploration standard deviation as a string evaluated at the current *agent step*
(``num_timesteps`` in SB3, not frames): ``"linear(1.0,0.1,100000)"`` decays linearly from 1.0 to 0.1
over the first 100,000 agent steps (twice as many frames with action repeat 2), then stays at 0.1.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable

import numpy as np

ScheduleSpec = float | int | str | Callable[[int], float]

_NUMBER = r"\s*([-+0-9.eE]+)\s*"
_LINEAR = re.compile(rf"^\s*linear\({_NUMBER},{_NUMBER},{_NUMBER}\)\s*$")
_STEP_LINEAR = re.compile(rf"^\s*step_linear\({_NUMBER},{_NUMBER},{_NUMBER},{_NUMBER},{_NUMBER}\)\s*$")

_FORMS = (
    "a number such as 0.2, 'linear(init,final,duration)', "
    "'step_linear(init,final1,duration1,final2,duration2)' (durations in agent steps), "
    "or a callable taking the agent step and returning a float"
)


def linear_schedule(init: float, final: float, duration: float, step: int) -> float:
    """
    Linear interpolation from ``init`` to ``final`` over ``duration`` agent steps, constant afterwards.

    :param init: value at step 0
    :param final: value from ``duration`` onwards
    :param duration: length of the decay, in agent steps
    :param step: current agent step
    :return: the scheduled value
    """
    mix = float(np.clip(step / duration, 0.0, 1.0))
    return (1.0 - mix) * init + mix * final


def step_linear_schedule(
    init: float, final1: float, duration1: float, final2: float, duration2: float, step: int
) -> float:
    """
    Two linear pieces, as DrQ-v2's ``step_linear``: ``init -> final1`` over ``duration1`` agent steps,
    then ``final1 -> final2`` over the next ``duration2`` agent steps.

    :param init: value at step 0
    :param final1: value at ``duration1``
    :param duration1: length of the first piece, in agent steps
    :param final2: value from ``duration1 + duration2`` onwards
    :param duration2: length of the second piece, in agent steps
    :param step: current agent step
    :return: the scheduled value
    """
    if step <= duration1:
        return linear_schedule(init, final1, duration1, step)
    return linear_schedule(final1, final2, duration2, step - duration1)


class StddevSchedule:
    """
    The exploration standard deviation as a function of the agent step (``num_timesteps``).

    Accepts every form of the DrQ-v2 reference: a constant, ``"linear(init,final,duration)"``,
    ``"step_linear(init,final1,duration1,final2,duration2)"``, or any callable ``step -> std``.
    Durations are in agent steps. A malformed string raises ``ValueError`` at construction,
    not in the middle of a run.

    :param spec: the schedule, see above
    """

    def __init__(self, spec: ScheduleSpec) -> None:
        self.spec = spec
        self._fn = self._parse(spec)
        # Evaluate once so that a callable that fails or returns garbage fails now.
        self._check_value(self(0), step=0)

    @staticmethod
    def _parse(spec: ScheduleSpec) -> Callable[[int], float]:
        if isinstance(spec, StddevSchedule):
            return spec._fn
        if isinstance(spec, bool):
            raise ValueError(f"Invalid stddev schedule {spec!r}: expected {_FORMS}.")
        if isinstance(spec, (int, float)):
            value = float(spec)
            return lambda step: value
        if callable(spec):
            return spec
        if not isinstance(spec, str):
            raise ValueError(f"Invalid stddev schedule {spec!r} of type {type(spec).__name__}: expected {_FORMS}.")
        try:
            value = float(spec)
        except ValueError:
            pass
        else:
            return lambda step: value
        match = _LINEAR.match(spec)
        if match:
            init, final, duration = _floats(spec, match.groups())
            _check_duration(spec, duration)
            return lambda step: linear_schedule(init, final, duration, step)
        match = _STEP_LINEAR.match(spec)
        if match:
            init, final1, duration1, final2, duration2 = _floats(spec, match.groups())
            _check_duration(spec, duration1)
            _check_duration(spec, duration2)
            return lambda step: step_linear_schedule(init, final1, duration1, final2, duration2, step)
        raise ValueError(f"Invalid stddev schedule string {spec!r}: expected {_FORMS}.")

    def _check_value(self, value: float, step: int) -> None:
        if not isinstance(value, (int, float, np.floating)) or not math.isfinite(value) or value < 0:
            raise ValueError(
                f"The stddev schedule {self.spec!r} gave {value!r} at agent step {step}: "
                "a standard deviation must be a finite float >= 0."
            )

    def __call__(self, step: int) -> float:
        """
        :param step: current agent step (``num_timesteps``)
        :return: the exploration standard deviation at that step
        """
        return float(self._fn(step))

    def __repr__(self) -> str:
        return f"StddevSchedule({self.spec!r})"

    def __getstate__(self) -> dict:
        # Lambdas built by _parse are not picklable by the standard pickler: keep the spec and re-parse.
        return {"spec": self.spec}

    def __setstate__(self, state: dict) -> None:
        self.spec = state["spec"]
        self._fn = self._parse(self.spec)


def _floats(spec: str, groups: tuple[str, ...]) -> list[float]:
    try:
        return [float(group) for group in groups]
    except ValueError as error:
        raise ValueError(f"Invalid stddev schedule string {spec!r}: {error}. Expected {_FORMS}.") from None


def _check_duration(spec: str, duration: float) -> None:
    if not duration > 0:
        raise ValueError(f"Invalid stddev schedule string {spec!r}: durations must be > 0 agent steps.")
