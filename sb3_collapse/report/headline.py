"""The top of the report: the paper's headline numbers and Proposition 1 beside the sweep's, and Figure 5's curves.
The readings: docs/figures.md#figure-5-the-headline-numbers-and-proposition-1."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from statistics import NormalDist

import numpy as np

from sb3_collapse.errors import InputError
from sb3_collapse.paper import PAPER, PAPER_RESULTS, PROPOSITION_1, PaperResult
from sb3_collapse.presets import reset_window_frames
from sb3_collapse.protocol import CONFIG_JSON, RESULT_JSON
from sb3_collapse.report.loading import Sweep, Trial
from sb3_collapse.report.statistics import (
    BandCurve,
    ReportSettings,
    VariantSummary,
    aligned_returns,
    band_curve,
    last_evals_std_mean,
    transplant_sources,
)
from sb3_collapse.report.tables import markdown_table
from sb3_collapse.run.variants import BASELINE_VARIANT, RULE_VARIANT, split_variant
from sb3_collapse.runfolder import read_json

CONFIDENCE = 0.95
"""The confidence of every interval of the headline and of Proposition 1."""
BOOTSTRAP_RESAMPLES = 2000

Interval = tuple[float, float]


def wilson_interval(successes: int, trials: int, confidence: float = CONFIDENCE) -> Interval:
    """:return: the Wilson score interval ``(low, high)`` of ``successes`` of ``trials`` (nan without trials)"""
    if not 0 <= successes <= trials:
        raise ValueError(f"successes must be in [0, trials], got {successes} of {trials}.")
    if trials == 0:
        return (math.nan, math.nan)
    z = NormalDist().inv_cdf(0.5 + confidence / 2)
    proportion = successes / trials
    denominator = 1 + z * z / trials
    centre = (proportion + z * z / (2 * trials)) / denominator
    half = z * math.sqrt(proportion * (1 - proportion) / trials + z * z / (4 * trials * trials)) / denominator
    low = 0.0 if successes == 0 else max(0.0, centre - half)  # exact bounds there, free of rounding
    high = 1.0 if successes == trials else min(1.0, centre + half)
    return (low, high)


def escape_probability(stuck_probability: float, windows: int) -> float:
    """
    :param stuck_probability: p, the probability of getting stuck in action collapse (one window)
    :param windows: n, the windows of the budget
    :return: Proposition 1's escape probability ``1 - p^n``
    """
    return 1.0 - stuck_probability**windows


def escape_interval(p_interval: Interval, windows: int) -> Interval:
    """:return: the interval of ``1 - p^n`` from ``p_interval`` of p: ``(1 - high^n, 1 - low^n)``"""
    low, high = p_interval
    return (escape_probability(high, windows), escape_probability(low, windows))


def bootstrap_std_interval(
    returns: np.ndarray,
    last_evals: int = PAPER.last_evals,
    confidence: float = CONFIDENCE,
    resamples: int = BOOTSTRAP_RESAMPLES,
    seed: int = 0,
) -> Interval:
    """:return: the percentile bootstrap interval over seeds of :func:`last_evals_std_mean` of ``(seeds, frames)``
    aligned ``returns`` (nan with fewer than 2 seeds)"""
    seeds = returns.shape[0]
    if seeds < 2 or returns.shape[1] == 0:
        return (math.nan, math.nan)
    rng = np.random.default_rng(seed)
    values = np.array(
        [last_evals_std_mean(returns[rng.integers(0, seeds, seeds)], last_evals) for _ in range(resamples)]
    )
    alpha = (1 - confidence) / 2
    low, high = np.quantile(values, [alpha, 1 - alpha])
    return (float(low), float(high))


def figure5_curves(sweep: Sweep, task: str, percentiles: tuple[float, float] = PAPER.percentiles) -> list[BandCurve]:
    """Figure 5's curves of ``task`` ("The performance comparison ... between DrQ-v2 and DrQ-v2 plus our rule"): a
    curve per variant whose finished seeds share a frame, without the transplant cells (Figure 3's)."""
    curves = []
    for variant in sweep.variants(task):
        frames, returns = aligned_returns(sweep.select(task, variant))
        if len(frames) and transplant_sources(variant) is None:
            curves.append(band_curve(variant, frames, returns, percentiles))
    return curves


@dataclass
class Proportion:
    """``count`` seeds of ``total``, with the Wilson ``interval`` of the fraction."""

    count: int
    total: int
    interval: Interval

    @property
    def fraction(self) -> float:
        """``count / total`` (nan without seeds)."""
        return self.count / self.total if self.total else math.nan

    @classmethod
    def of(cls, count: int, total: int, confidence: float = CONFIDENCE) -> Proportion:
        return cls(count, total, wilson_interval(count, total, confidence))


@dataclass
class Estimate:
    """A value with its interval (nan when undefined)."""

    value: float
    interval: Interval


@dataclass
class HeadlineRow:
    """One task of the headline: the paper's numbers and the sweep's (``None``: not in the paper / the sweep); the
    cells' definitions: :func:`headline_definitions`. Both arms are counted by one test, the reset rule's own escape
    test over each seed's logged checks (:func:`~sb3_collapse.report.statistics.escaped_at`): ``never_escaped_*``
    is the paper's "seeds stuck in action collapse continuously" for DrQ-v2 and its "all 40 seeds of ours escape
    action collapse" for the rule; ``stuck_end_*`` the seeds stuck at the end of training, a column of its own."""

    task: str
    paper: PaperResult | None
    baseline: VariantSummary | None
    rule: VariantSummary | None
    never_escaped_baseline: Proportion | None
    never_escaped_rule: Proportion | None
    stuck_end_baseline: Proportion | None
    stuck_end_rule: Proportion | None
    std_baseline: Estimate | None
    std_rule: Estimate | None


def _never_escaped(row: VariantSummary | None, within_frames: int | None = None) -> Proportion | None:
    """:return: ``row``'s seeds that never passed the escape test (within the first ``within_frames`` frames, when
    given), of the seeds whose collapse state is known; ``None`` without seeds"""
    if row is None or row.seeds == 0:
        return None
    count = row.never_escaped if within_frames is None else row.stuck_after(within_frames)
    return Proportion.of(count, len(row.escape_frames))


def _stuck(row: VariantSummary | None) -> Proportion | None:
    if row is None or row.seeds == 0:
        return None
    return Proportion.of(row.stuck, row.seeds - row.collapse_unknown)


def _std(sweep: Sweep, row: VariantSummary | None, settings: ReportSettings) -> Estimate | None:
    if row is None or row.seeds == 0:
        return None
    _, returns = aligned_returns(sweep.select(row.task, row.variant))
    return Estimate(row.last_evals_std_mean, bootstrap_std_interval(returns, settings.last_evals))


def headline_rows(
    sweep: Sweep,
    rows: Sequence[VariantSummary],
    settings: ReportSettings,
    baseline: str = BASELINE_VARIANT,
    rule: str = RULE_VARIANT,
) -> list[HeadlineRow]:
    """The headline, a row per task (the paper's first, in its order): each arm's seeds that never escaped (one test
    for both), its seeds stuck at the end and "the average standard deviation over the last ten evaluations",
    beside the paper's."""
    by_key = {(row.task, row.variant): row for row in rows}
    papers = {result.task: result for result in PAPER_RESULTS}
    tasks = [task for task in papers if task in sweep.tasks()] + [t for t in sweep.tasks() if t not in papers]
    headline = []
    for task in tasks:
        base, ruled = by_key.get((task, baseline)), by_key.get((task, rule))
        if task not in papers and base is None and ruled is None:
            continue
        stds = _std(sweep, base, settings), _std(sweep, ruled, settings)
        counts = _never_escaped(base), _never_escaped(ruled), _stuck(base), _stuck(ruled)
        headline.append(HeadlineRow(task, papers.get(task), base, ruled, *counts, *stds))
    return headline


@dataclass
class Proposition1Row:
    """Proposition 1 for one task and ``rule`` variant: p the ``baseline``'s ``stuck`` fraction (its seeds with no
    escape within the first window of m frames, by the rule's escape test), n the rule's whole ``windows`` of m
    ``window_frames`` in the budget (``None``: unknown), the ``predicted`` ``1 - p^n``, and the rule's seeds that
    ``escaped`` by the same test."""

    task: str
    baseline: str
    rule: str
    stuck: Proportion
    windows: int | None
    predicted: Estimate | None
    escaped: Proportion
    window_frames: int | None = None


def rule_windows(trials: Sequence[Trial]) -> tuple[int | None, int | None]:
    """:return: Proposition 1's ``(n, m)`` from the settings of a rule variant's ``trials``: m the rule's window in
    frames (a settings file without it: :func:`~sb3_collapse.presets.reset_window_frames` of its task, schedule and
    action repeat, as the runner resolves it), n ``frames // m``; ``(None, None)`` when no settings file says, or
    they disagree"""
    found = set()
    for trial in trials:
        try:
            config = read_json(trial.path / CONFIG_JSON)
        except InputError:
            continue
        frames, window = config.get("frames"), config.get("reset_window_frames")
        if window is None:  # a settings file of a version that did not record it: the task's exploration end
            try:
                window = reset_window_frames(trial.task, config.get("stddev_schedule"), config.get("action_repeat"))
            except ValueError:
                continue
        if isinstance(frames, int) and isinstance(window, int) and window > 0:
            found.add((frames // window, window))
    return found.pop() if len(found) == 1 else (None, None)


def proposition1_rows(sweep: Sweep, rows: Sequence[VariantSummary]) -> list[Proposition1Row]:
    """
    Proposition 1 ("the probability of escaping action collapse when applying our proposed rule is 1 - p^n") per
    task and ``<algorithm>+<intervention>`` variant whose plain algorithm is in the sweep. One test counts both arms,
    the rule's own (:func:`~sb3_collapse.report.statistics.escaped_at`): p, "the probability of getting stuck in
    action collapse" in one window, is the fraction of the plain algorithm's seeds that did not escape within its
    first m frames (a window of the rule is such a start from scratch; all of its frames when m is unknown); the
    observed escape is the fraction of the rule's seeds that escaped.
    """
    by_key = {(row.task, row.variant): row for row in rows}
    result = []
    for row in rows:
        algorithm, suffix = split_variant(row.variant)
        base = by_key.get((row.task, algorithm))
        if suffix is None or base is None or base.seeds == 0 or row.reset_rule_seeds == 0:
            continue
        windows, window_frames = rule_windows(sweep.select(row.task, row.variant))
        stuck = _never_escaped(base, window_frames)
        predicted = None
        if windows is not None and stuck.total:
            predicted = Estimate(escape_probability(stuck.fraction, windows), escape_interval(stuck.interval, windows))
        known = len(row.escape_frames)
        escaped = Proportion.of(known - row.never_escaped, known)
        result.append(
            Proposition1Row(row.task, algorithm, row.variant, stuck, windows, predicted, escaped, window_frames)
        )
    return result


def _percent(value: float) -> str:
    return "-" if math.isnan(value) else f"{100 * value:.0f}%"


def _interval(interval: Interval, percent: bool = True) -> str:
    low, high = interval
    if math.isnan(low):
        return "-"
    return f"{_percent(low)}-{_percent(high)}" if percent else f"{low:.1f}-{high:.1f}"


def _proportion(value: Proportion | None) -> str:
    if value is None:
        return "not in this sweep"
    if value.total == 0:
        return f"{value.count}/0"
    return f"{value.count}/{value.total} ({_percent(value.fraction)}, CI {_interval(value.interval)})"


def _estimate(value: Estimate | None) -> str:
    if value is None:
        return "not in this sweep"
    if math.isnan(value.value):
        return "-"
    return f"{value.value:.1f} (CI {_interval(value.interval, percent=False)})"


HEADLINE_HEADER = (
    "task",
    "stuck continuously (never escaped), DrQ-v2: paper",
    "this sweep",
    "with the rule: paper",
    "this sweep",
    "stuck at the end, DrQ-v2: this sweep",
    "with the rule: this sweep",
    "std over last 10 evals, DrQ-v2: paper",
    "this sweep",
    "with the rule: paper",
    "this sweep",
)
PROPOSITION1_HEADER = (
    "task",
    "rule",
    "p: baseline not escaped within m",
    "n windows (m frames)",
    "predicted escape 1 - p^n",
    "observed escape",
)


def headline_table(headline: Sequence[HeadlineRow]) -> list[list[str]]:
    """:return: the headline's cells, one list per row (:data:`HEADLINE_HEADER`)"""
    table = []
    for row in headline:
        p = row.paper
        papers = ("-",) * 4 if p is None else (f"{p.stuck_baseline}/{p.seeds}", f"{p.never_escaped_rule}/{p.seeds}")
        papers += () if p is None else (f"{p.std_baseline:.1f}", f"{p.std_rule:.1f}")
        never = _proportion(row.never_escaped_baseline), _proportion(row.never_escaped_rule)
        stuck = _proportion(row.stuck_end_baseline), _proportion(row.stuck_end_rule)
        stds = _estimate(row.std_baseline), _estimate(row.std_rule)
        table.append(
            [row.task, papers[0], never[0], papers[1], never[1], *stuck, papers[2], stds[0], papers[3], stds[1]]
        )
    return table


def proposition1_table(rows: Sequence[Proposition1Row]) -> list[list[str]]:
    """:return: Proposition 1's cells, one list per row (:data:`PROPOSITION1_HEADER`)"""
    table = []
    for row in rows:
        predicted = row.predicted and f"{_percent(row.predicted.value)} (CI {_interval(row.predicted.interval)})"
        windows = "unknown" if row.windows is None else f"{row.windows} ({row.window_frames:,})"
        table.append([row.task, row.rule, _proportion(row.stuck), windows, predicted or "-", _proportion(row.escaped)])
    return table


def headline_definitions(settings: ReportSettings) -> str:
    """:return: what the headline's and Proposition 1's cells mean, one paragraph"""
    return (
        f"Paper: Section 5.2 (40 seeds per task and variant). This sweep: {BASELINE_VARIANT} and {RULE_VARIANT}, "
        "finished seeds whose collapse state is known. Both arms are counted by one test, the rule's own escape "
        f"test over each seed's logged checks ({settings.collapse_checks} consecutive {settings.collapse_tag} values "
        f"above {settings.collapse_threshold:g}, the streak starting again after each of the rule's resets). Stuck "
        'continuously (the paper: "seeds stuck in action collapse continuously", and for the rule "all 40 seeds of '
        'ours escape action collapse"): seeds that never passed it. Stuck at the end: seeds stuck at the end of '
        "training (see the summary's definitions); a seed that escaped and collapsed again counts there, not as "
        f"stuck continuously ({RESULT_JSON}'s escaped, the rule's own record, is in the summary table). "
        f"Std over last {settings.last_evals} evals: the across-seed std at each of the last "
        f"{settings.last_evals} scheduled evaluations, averaged. Intervals: {CONFIDENCE:.0%}, Wilson for counts, "
        f"percentile bootstrap over seeds ({BOOTSTRAP_RESAMPLES} resamples) for the std. Proposition 1: p is the "
        "fraction of the baseline's seeds that did not pass the test within the rule's window m (a window is such a "
        "start from scratch), n the rule's whole windows in the budget; p's Wilson interval [lo, hi] gives "
        "[1 - hi^n, 1 - lo^n]; observed escape: the rule's seeds that passed the test."
    )


def headline_markdown(
    headline: Sequence[HeadlineRow], proposition: Sequence[Proposition1Row], settings: ReportSettings
) -> str:
    """:return: the headline and Proposition 1 as Markdown, for the top of ``summary.md``"""
    lines = ["## The paper's headline beside this sweep's", ""]
    lines += markdown_table(HEADLINE_HEADER, headline_table(headline))
    lines += ["", "## Proposition 1", "", f"> {PROPOSITION_1}", ""]
    if proposition:
        lines += markdown_table(PROPOSITION1_HEADER, proposition1_table(proposition))
    else:
        lines.append("No rule variant with its baseline in this sweep.")
    lines += ["", headline_definitions(settings), ""]
    return "\n".join(lines) + "\n"
