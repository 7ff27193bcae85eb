"""
The one rule of every periodic event of a run (an evaluation, a collapse check, a checkpoint), used online by the
callbacks that decide when each is due (``monitoring.callbacks.FrameScheduleCallback``) and offline by what counts
them in advance (``paper.evaluation_schedule``, the sweep's plan): an event is due at the first step whose count
(frames, or updates) reaches the next multiple of its period, once for a step that crosses several.
"""

from __future__ import annotations


def next_due(count: int, period: int) -> int:
    """
    :param count: the count (frames, or updates) of an event that just happened (``-1``: none yet, so that one is due
        at 0)
    :param period: counts between two events (> 0)
    :return: the count at which the next one is due: the first multiple of ``period`` above ``count``
    """
    return (count // period + 1) * period


def due_counts(total: int, period: int, per_step: int, at_start: bool = False) -> list[int]:
    """
    The counts at which :func:`next_due` makes an event happen over a run of ``total`` counts made in steps of
    ``per_step``, as the callbacks see them.

    :param total: the run's budget (frames), a multiple of ``per_step`` as a run's frames are
    :param period: counts between two events (> 0)
    :param per_step: counts a step adds (frames: action repeat x environments)
    :param at_start: the evaluations' form: one at count 0, none at the budget's last step (after which the final model
        is evaluated apart); otherwise the first is due at ``period`` and the last step may have one
    :return: the counts, increasing, each a step's (a multiple of ``per_step``)
    """
    if period <= 0 or per_step <= 0:
        raise ValueError(f"period and per_step must be > 0, got {period} and {per_step}.")
    counts = []
    due = next_due(-1, period) if at_start else next_due(0, period)
    while True:
        count = -(-due // per_step) * per_step  # the first step at or after the due count
        if count > total or (at_start and count == total):
            return counts
        counts.append(count)
        due = next_due(count, period)
