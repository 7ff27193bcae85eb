"""DrQ-v2's exploration-noise schedules, in agent steps (``num_timesteps``, not frames): ``"linear(1.0,0.1,100000)"``
decays linearly from 1.0 to 0.1 over the first 100,000 agent steps, then stays at 0.1."""

from __future__ import annotations

import math
import re
from collections.abc import Callable

import numpy as np

ScheduleSpec = float | int | str | Callable[[int], float]

_FORM = re.compile(r"^\s*(linear|step_linear)\((.*)\)\s*$")
_ARGUMENTS = {"linear": 3, "step_linear": 5}
_FORMS = (
    "a number such as 0.2, 'linear(init,final,duration)', "
    "'step_linear(init,final1,duration1,final2,duration2)' (durations in agent steps), "
    "or a callable taking the agent step and returning a float"
)


def linear_schedule(init: float, final: float, duration: float, step: int) -> float:
    """:return: ``init`` to ``final`` linearly over ``duration`` agent steps, then ``final``, at agent ``step``"""
    mix = float(np.clip(step / duration, 0.0, 1.0))
    return (1.0 - mix) * init + mix * final


def step_linear_schedule(
    init: float, final1: float, duration1: float, final2: float, duration2: float, step: int
) -> float:
    """:return: DrQ-v2's ``step_linear``: ``init -> final1`` over ``duration1`` agent steps, then ``final1 ->
    final2`` over ``duration2``, at agent ``step``"""
    if step <= duration1:
        return linear_schedule(init, final1, duration1, step)
    return linear_schedule(final1, final2, duration2, step - duration1)


class StddevSchedule:
    """
    The exploration standard deviation as a function of the agent step (``num_timesteps``).

    :param spec: a constant, ``"linear(init,final,duration)"``, ``"step_linear(init,final1,duration1,final2,
        duration2)"`` (durations in agent steps) or a callable ``step -> std``; a malformed one raises ``ValueError``
    """

    def __init__(self, spec: ScheduleSpec) -> None:
        self.spec = spec
        self._fn = self._parse(spec)
        value = self(0)  # a callable that fails or returns garbage fails now
        if not isinstance(value, (int, float, np.floating)) or not math.isfinite(value) or value < 0:
            raise ValueError(
                f"The stddev schedule {spec!r} gave {value!r} at agent step 0: a standard deviation must be a finite "
                "float >= 0."
            )

    @staticmethod
    def _parse(spec: ScheduleSpec) -> Callable[[int], float]:
        if isinstance(spec, StddevSchedule):
            return spec._fn
        if isinstance(spec, bool) or not isinstance(spec, (int, float, str)) and not callable(spec):
            raise ValueError(f"Invalid stddev schedule {spec!r} of type {type(spec).__name__}: expected {_FORMS}.")
        if callable(spec):
            return spec
        try:
            value = float(spec)
            return lambda step: value
        except ValueError:
            pass
        match = _FORM.match(spec)  # type: ignore[arg-type]
        try:
            args = [float(arg) for arg in match.group(2).split(",")] if match else []
        except ValueError as error:
            raise ValueError(f"Invalid stddev schedule string {spec!r}: {error}. Expected {_FORMS}.") from None
        if not match or len(args) != _ARGUMENTS[match.group(1)]:
            raise ValueError(f"Invalid stddev schedule string {spec!r}: expected {_FORMS}.")
        if not all(map(math.isfinite, args)) or not all(duration > 0 for duration in args[2::2]):
            raise ValueError(f"Invalid stddev schedule string {spec!r}: finite numbers, durations > 0 agent steps.")
        schedule = linear_schedule if match.group(1) == "linear" else step_linear_schedule
        return lambda step: schedule(*args, step)  # type: ignore[operator]

    @property
    def end_step(self) -> int | None:
        """The agent step at which the std reaches its final value and stays there: a ``linear`` schedule's duration,
        the sum of ``step_linear``'s two; ``None`` for a constant or a callable (no decay to read)."""
        match = _FORM.match(self.spec) if isinstance(self.spec, str) else None
        if match is None:
            return None
        return math.ceil(sum(float(arg) for arg in match.group(2).split(",")[2::2]))

    def __call__(self, step: int) -> float:
        """:return: the exploration standard deviation at agent ``step``"""
        return float(self._fn(step))

    def __repr__(self) -> str:
        return f"StddevSchedule({self.spec!r})"

    def __getstate__(self) -> dict:
        return {"spec": self.spec}  # the lambdas of _parse do not pickle: parsed again

    def __setstate__(self, state: dict) -> None:
        self.spec = state["spec"]
        self._fn = self._parse(self.spec)
