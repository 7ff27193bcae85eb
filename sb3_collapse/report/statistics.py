"""The report's numbers from loaded trials: aligned curves, percentile bands, the table and the transplant grid.
See docs/sweeps.md#reports-python--m-sb3_collapsereport-runssweep."""

from __future__ import annotations

import functools
import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from sb3_collapse.errors import InputError
from sb3_collapse.monitoring.reset import first_escape
from sb3_collapse.paper import PAPER
from sb3_collapse.protocol import COLLAPSE_METRICS_CSV
from sb3_collapse.report.loading import Sweep, Trial
from sb3_collapse.run.config import RUN, check_declared, declared, setting
from sb3_collapse.run.variants import TRANSPLANT_SOURCES, transplant_sources


@declared
@dataclass
class ReportSettings:
    """The definitions of the report's numbers (defaults: the paper's, :data:`sb3_collapse.paper.PAPER`), each
    declared once: ``python -m sb3_collapse.report``'s flags and range checks are generated from them."""

    collapse_tag: str = setting(
        PAPER.collapse_tag, cli=RUN, help=f"{COLLAPSE_METRICS_CSV} tag that decides 'stuck in action collapse'"
    )
    collapse_threshold: float = setting(PAPER.threshold, cli=RUN)
    """the reset rule's threshold: a seed escapes at `collapse_checks` values in a row above it,
    and is stuck at the end when the median of its last `collapse_checks` values is <= this"""
    collapse_checks: int = setting(PAPER.patience, cli=RUN, minimum=1)
    """the consecutive checks of an escape, and the number of last collapse checks whose median is tested"""
    last_evals: int = setting(PAPER.last_evals, cli=RUN, unit="evaluations", minimum=1)
    """the across-seed std is averaged over this many last evaluations"""
    success_return: float = setting(PAPER.success_return, cli=RUN)
    """transplant grid: a seed succeeds when its final return is >= this"""
    percentiles: tuple[float, float] = setting(
        PAPER.percentiles, cli=RUN, unit="percent", nargs=2, metavar=("LOW", "HIGH"), minimum=0, maximum=100
    )
    """Figure 5's band"""

    def validate(self) -> None:
        """:raises InputError: on a setting out of its declared range (the message names it), a threshold that is not
        finite or a band whose low end is not below its high end"""
        check_declared(self)
        if not math.isfinite(self.collapse_threshold):
            raise InputError(f"collapse_threshold must be a finite number, got {self.collapse_threshold}.")
        low, high = self.percentiles
        if not low < high:
            raise InputError(f"percentiles must satisfy 0 <= low < high <= 100, got {low} and {high}.")


def aligned_returns(trials: Sequence[Trial]) -> tuple[np.ndarray, np.ndarray]:
    """:return: ``(frames, returns)``, frames all trials share; ``returns[i, j]``: ``trials[i]`` at ``frames[j]``"""
    frames = functools.reduce(np.intersect1d, [t.frames for t in trials]) if trials else np.zeros(0)
    frames = np.unique(frames).astype(np.int64)
    returns = np.array([trial.returns[np.searchsorted(trial.frames, frames)] for trial in trials], dtype=np.float64)
    return frames, returns.reshape(len(trials), len(frames))


@dataclass
class BandCurve:
    """A curve of Figure 5 (a variant, or the reference): mean return and percentile band across seeds per frame."""

    name: str
    frames: np.ndarray
    mean: np.ndarray
    low: np.ndarray
    high: np.ndarray
    seeds: int


def band_curve(
    name: str, frames: np.ndarray, returns: np.ndarray, percentiles: tuple[float, float] = (5.0, 95.0)
) -> BandCurve:
    """:return: the curve of ``(seeds, frames)`` aligned ``returns``: mean and ``percentiles`` band across seeds"""
    low, high = np.percentile(returns, percentiles, axis=0)
    return BandCurve(name, frames, returns.mean(axis=0), low, high, returns.shape[0])


def across_seed_std(values: np.ndarray, axis: int = 0) -> np.ndarray | float:
    """:return: the std across the seeds on ``axis`` of ``values`` (``ddof=1``; nan with < 2 seeds), a float for 1-d"""
    values = np.asarray(values, dtype=np.float64)
    if values.shape[axis] < 2:
        shape = values.shape[:axis] + values.shape[axis + 1 :]
        return float("nan") if not shape else np.full(shape, np.nan)
    std = np.std(values, axis=axis, ddof=1)
    return float(std) if np.ndim(std) == 0 else std


def last_evals_std_mean(returns: np.ndarray, last_evals: int = 10) -> float:
    """
    The paper's "average standard deviation over the last ten evaluations": the across-seed std at each of the last
    ``last_evals`` frames, averaged.

    :param returns: ``(seeds, frames)`` aligned returns
    :param last_evals: how many last frames
    :return: the mean std (nan with fewer than 2 seeds or no frame)
    """
    if returns.shape[0] < 2 or returns.shape[1] == 0:
        return float("nan")
    return float(np.mean(across_seed_std(returns[:, -last_evals:], axis=0)))


def stuck_in_collapse(
    values: np.ndarray, threshold: float = PAPER.threshold, checks: int = PAPER.patience
) -> bool | None:
    """
    Whether a seed ends stuck in action collapse: the median of its last ``checks`` values of the collapse metric
    is ``<= threshold`` (the reset rule's test at the end of the run).

    :param values: the metric's finite values of one seed, in frame order
    :param threshold: the value at or below which the metric means collapse
    :param checks: how many last values
    :return: ``True`` (stuck), ``False`` or ``None`` (no value logged)
    """
    if len(values) == 0:
        return None
    return bool(np.median(np.asarray(values[-checks:], dtype=np.float64)) <= threshold)


def escaped_at(trial: Trial, settings: ReportSettings) -> int | None:
    """
    The reset rule's own escape test (:func:`~sb3_collapse.monitoring.reset.first_escape`: ``collapse_checks``
    consecutive values of the collapse metric above ``collapse_threshold``) over a seed's logged checks, the same
    test for every variant, with or without the rule: the paper counts "the number of seeds stuck in action collapse
    continuously. There are 13, 8, and 7 seeds out of 40 respectively for DrQ-v2. In comparison, all 40 seeds of ours
    escape action collapse" (Section 5.2). The streak starts again after each of the rule's resets (``reset_frames``
    of the result file: a new window, a new network).

    :param trial: a finished trial with its collapse metric (``collapse_frames``, ``collapse_values``)
    :param settings: the test's metric, threshold and consecutive checks
    :return: the frame of the check that completes the first escape, ``None`` when the seed never escaped
    """
    threshold, checks = settings.collapse_threshold, settings.collapse_checks
    return first_escape(trial.collapse_frames, trial.collapse_values, threshold, checks, trial.reset_frames)


@dataclass
class VariantSummary:
    """One row of the table (its columns: docs/sweeps.md); ``dropped_frames``: evaluation frames of some but not all
    finished seeds; ``finals``: each finished seed's final return, of ``seed_ids``; ``escape_frames``: the escape
    test's frame (:func:`escaped_at`; ``None``: never escaped) of each seed whose collapse state is known."""

    task: str
    variant: str
    seeds: int
    unfinished: int
    final_frame: int | None = None
    final_mean: float = float("nan")
    final_std: float = float("nan")
    stuck: int = 0
    collapse_unknown: int = 0
    resets_total: int = 0
    seeds_reset: int = 0
    escaped: int = 0
    reset_rule_seeds: int = 0
    last_evals: int = 0
    last_evals_std_mean: float = float("nan")
    dropped_frames: int = 0
    finals: list[float] = field(default_factory=list)
    seed_ids: list[int] = field(default_factory=list)
    escape_frames: list[int | None] = field(default_factory=list)

    @property
    def never_escaped(self) -> int:
        """The seeds whose logged checks never passed the escape test (:func:`escaped_at`), of ``escape_frames``."""
        return sum(frame is None for frame in self.escape_frames)

    def stuck_after(self, frames: int) -> int:
        """:return: the seeds of ``escape_frames`` with no escape at or before ``frames``"""
        return sum(frame is None or frame > frames for frame in self.escape_frames)


def summarize_variant(
    task: str, variant: str, finished: Sequence[Trial], unfinished: int, settings: ReportSettings
) -> VariantSummary:
    """:return: the table's row of ``finished`` trials and ``unfinished`` others (statistics nan / 0 without any)"""
    row = VariantSummary(task=task, variant=variant, seeds=len(finished), unfinished=unfinished)
    if not finished:
        return row
    frames, returns = aligned_returns(finished)
    row.dropped_frames = len(set().union(*(set(t.frames.tolist()) for t in finished))) - len(frames)
    row.seed_ids = [t.seed for t in finished]
    if len(frames):
        finals = returns[:, -1]
        row.final_frame = int(frames[-1])
        row.finals = [float(v) for v in finals]
        row.final_mean = float(np.mean(finals))
        row.final_std = float(across_seed_std(finals))
        row.last_evals = min(settings.last_evals, len(frames))
        row.last_evals_std_mean = last_evals_std_mean(returns, settings.last_evals)
    states = [
        stuck_in_collapse(t.collapse_values, settings.collapse_threshold, settings.collapse_checks) for t in finished
    ]
    row.stuck = sum(state is True for state in states)
    row.collapse_unknown = sum(state is None for state in states)
    row.escape_frames = [escaped_at(t, settings) for t, state in zip(finished, states) if state is not None]
    row.resets_total = sum(t.resets for t in finished)
    row.seeds_reset = sum(t.resets >= 1 for t in finished)
    row.escaped = sum(t.escaped is True for t in finished)
    row.reset_rule_seeds = sum(t.escaped is not None for t in finished)
    return row


def summarize(sweep: Sweep, settings: ReportSettings) -> list[VariantSummary]:
    """:return: one row of the table per task and variant of ``sweep`` (:func:`summarize_variant`)"""
    return [
        summarize_variant(task, variant, sweep.select(task, variant), len(sweep.select(task, variant, False)), settings)
        for task in sweep.tasks()
        for variant in sweep.variants(task)
    ]


@dataclass
class GridCell:
    """One cell of the transplant grid: of ``seeds`` finished seeds, ``successes`` with final return >= success."""

    task: str
    cnn: str
    mlp: str
    successes: int
    seeds: int
    unfinished: int


def transplant_grid(
    rows: Sequence[VariantSummary], success_return: float = PAPER.success_return
) -> dict[str, list[GridCell]]:
    """
    The paper's Figure 3(a): per task with ``cnn-<src>_mlp-<src>`` variants, 9 cells (CNN x MLP source, row-major)
    counting the seeds whose final return is ``>= success_return``.

    :param rows: the table rows (:func:`summarize`)
    :param success_return: the success threshold
    :return: task -> 9 cells
    """
    by_task: dict[str, dict[tuple[str, str], VariantSummary]] = {}
    for row in rows:
        sources = transplant_sources(row.variant)
        if sources is not None:
            by_task.setdefault(row.task, {})[sources] = row
    grid = {}
    for task, cells in sorted(by_task.items()):
        grid[task] = []
        for cnn, mlp in itertools.product(TRANSPLANT_SOURCES, TRANSPLANT_SOURCES):
            row = cells.get((cnn, mlp)) or VariantSummary(task, "", 0, 0)
            grid[task].append(
                GridCell(task, cnn, mlp, sum(v >= success_return for v in row.finals), row.seeds, row.unfinished)
            )
    return grid


def stage_indices(frames: np.ndarray, budget_frames: int | None = None) -> list[int]:
    """
    The training stages of the paper's Tables 1-7 (``x = 0, 35, 70, 110``): per stage frame of ``budget_frames``
    (:meth:`~sb3_collapse.paper.PaperProtocol.stages`; ``None``: the paper's), clipped to the last evaluation, the
    index of the nearest of the increasing ``frames`` (the earlier on ties). See docs/figures.md.
    """
    frames = np.asarray(frames, dtype=np.float64)
    if len(frames) == 0:
        raise ValueError("frames must hold at least one evaluation frame.")
    stages = np.minimum(np.asarray(PAPER.stages(budget_frames), dtype=np.float64), frames[-1])
    return [int(np.argmin(np.abs(frames - stage))) for stage in stages]


def stages_caption(reading: str) -> str:
    """:return: the sentence that says which stages a table of Tables 1-7 reads, of ``reading`` (plural)"""
    frames = ", ".join(f"{frame:,}" for frame in PAPER.stages())
    return (
        f"Stages: the paper's x = 0, 35, 70, 110 (frames {frames} of its {PAPER.train_frames:,}; the same fractions "
        f"of another budget), each at the nearest of the {reading}, the last at most."
    )


def budget_frames(trials: Sequence[Trial]) -> int | None:
    """
    :param trials: finished trials
    :return: the frames they trained (the smallest of their result files'), ``None`` when none says
    """
    budgets = [int(t.result["frames"]) for t in trials if t.result is not None and t.result.get("frames")]
    return min(budgets) if budgets else None


@dataclass
class TransplantCurves:
    """A curve of Figure 3(b) and a row of Table 7: the ``(successes, frames)`` returns of one transplant cell's
    successful seeds, and their across-seed std at the frames of the four stages (:func:`stage_indices`)."""

    task: str
    cnn: str
    mlp: str
    frames: np.ndarray
    returns: np.ndarray
    stage_frames: list[int]
    stage_std: list[float]

    @property
    def label(self) -> str:
        """The row name of Table 7, e.g. ``good CNN x good MLP``."""
        return f"{self.cnn} CNN x {self.mlp} MLP"


def transplant_curves(sweep: Sweep, success_return: float = PAPER.success_return) -> dict[str, list[TransplantCurves]]:
    """The paper's Figure 3(b) and Table 7: task -> its transplant cells with a successful seed, in grid order."""
    curves: dict[str, list[TransplantCurves]] = {}
    for task, cnn, mlp in itertools.product(sweep.tasks(), TRANSPLANT_SOURCES, TRANSPLANT_SOURCES):
        finished = sweep.select(task, f"cnn-{cnn}_mlp-{mlp}")
        frames, returns = aligned_returns(finished)
        successful = returns[returns[:, -1] >= success_return] if len(frames) else returns[:0]
        if len(successful):
            stages = stage_indices(frames, budget_frames(finished))
            stds = [float(s) for s in across_seed_std(successful[:, stages], axis=0)]
            cell = TransplantCurves(task, cnn, mlp, frames, successful, [int(frames[i]) for i in stages], stds)
            curves.setdefault(task, []).append(cell)
    return curves
