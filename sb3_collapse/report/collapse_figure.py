"""The paper's Figures 4, 8 and 9: the collapse metrics of three agents over training, beside the evaluation return.
The readings: docs/figures.md#figures-4-8-9-collapse-metrics-of-three-agents."""

from __future__ import annotations

import textwrap
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.lines import Line2D
from matplotlib.ticker import LogLocator, NullLocator

from sb3_collapse.errors import InputError
from sb3_collapse.monitoring import CORRELATION_READINGS, FIGURE_CORRELATION
from sb3_collapse.paper import PAPER, metric_tag
from sb3_collapse.protocol import (
    COLLAPSE_EVENTS_CSV,
    COLLAPSE_METRICS_CSV,
    CONFIG_JSON,
    EVAL_CSV,
)
from sb3_collapse.report.loading import Trial, load_trial
from sb3_collapse.report.style import ESCAPE_COLOR, RESET_COLOR, RETURN_COLOR, frames_axis, layer_style
from sb3_collapse.runfolder import read_collapse_events, read_collapse_metrics, read_json

CORRELATION_LABELS = {
    "input_correlation": "correlation (between inputs)",
    "unit_correlation": "correlation (between units)",
    "unit_abs_correlation": "|correlation| (between units)",
}
"""The axis label of each reading of the paper's correlation (``CORRELATION_READINGS``)."""


def figure4_metrics(correlation: str = FIGURE_CORRELATION) -> tuple[tuple[str, str], ...]:
    """
    Figure 4's metric columns, metric -> axis label (the paper's "zeros", "the number of zero activations, also
    called dead neurons", are the dead units).

    :param correlation: the reading of the correlation column, one of ``CORRELATION_READINGS``
    """
    if correlation not in CORRELATION_LABELS:
        raise InputError(
            f"correlation must be one of {list(CORRELATION_READINGS)}, got {correlation!r}.", parameter="correlation"
        )
    return (
        ("numerical_rank", "numerical rank"),
        (correlation, CORRELATION_LABELS[correlation]),
        ("dead_units", "dead units"),
        ("grad_norm", "gradient norm"),
    )


FIGURE4_LAYERS = ("mlp1", "mlp2")
"""The layers of Figure 4 ("we only visualize the metrics of mlp1 and mlp2"; ``mlp0`` on request)."""
BOUNDED_METRICS = (*CORRELATION_READINGS, "zero_fraction", "dead_fraction")
"""Metrics in [0, 1], drawn on that range (a signed correlation below 0 extends it)."""
GRAD_NORM_FLOOR = 1e-12
"""The floor of the gradient-norm column (a log axis): a norm at or below it, such as the exact 0 of a collapsed
actor (Section 5.1: "the gradient norm is always around zero when an agent gets stuck"), is drawn on it, where the
log axis would leave it out; the axis label says so."""
THRESHOLD_STYLE = {"color": "0.45", "ls": "--", "lw": 0.8}
"""The line of the rule's threshold (``PAPER.threshold``) on the gradient-norm column."""
_CENTRED = {"ha": "center", "va": "center", "fontsize": 8}
_EVENTS = (("resets", "reset", RESET_COLOR, "-.", 0.8), ("escapes", "escape (reset rule)", ESCAPE_COLOR, ":", 0.9))
"""The vertical lines of Figure 4: :class:`AgentMetrics` field, legend label, colour, line style, alpha."""
ROLES = ("best", "middle", "worst")
"""The rows of :func:`pick_agents`."""
PAPER_ROLES = ("well-performing", "middle", "poorly performing")
"""The rows of Figures 4, 8, 9 (:func:`pick_paper_agents`)."""


@dataclass
class AgentMetrics:
    """One row of Figure 4: a trial's (``None``: ``absent`` says why) metrics, tag -> ``(frames, values)``, the frames
    of its resets and escapes, and layer -> width in units where known (``role``: ``"run"`` for one run folder);
    ``correlation``: the reading of its correlation column (``CORRELATION_READINGS``)."""

    trial: Trial | None
    role: str
    metrics: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    resets: list[int] = field(default_factory=list)
    escapes: list[int] = field(default_factory=list)
    absent: str = ""
    widths: dict[str, int] = field(default_factory=dict)
    correlation: str = FIGURE_CORRELATION

    @property
    def final_return(self) -> float:
        """The trial's final return (nan for a row without an agent)."""
        return float("nan") if self.trial is None else self.trial.final_return


def pick_agents(trials: Sequence[Trial]) -> list[tuple[str, Trial]]:
    """
    The other reading of Figure 4's agents: the highest, the (upper) median and the lowest final return, ties to
    the smaller seed, each trial once.

    :param trials: the trials of one task and variant
    :return: ``(role, trial)`` pairs
    """
    ranked = sorted((t for t in trials if t.finished and len(t.returns)), key=lambda t: (-t.final_return, t.seed))
    if not ranked:
        return []
    picks = {"best": ranked[0], "middle": ranked[(len(ranked) - 1) // 2], "worst": ranked[-1]}
    return [(role, picks[role]) for i, role in enumerate(ROLES) if picks[role] not in [picks[r] for r in ROLES[:i]]]


@dataclass
class AgentPick:
    """One row of Figures 4, 8, 9 (:func:`pick_paper_agents`): the trial of class ``role`` (``None``: none) picked
    with ``pick_seed`` among the ``candidates`` seeds of the class, of ``seeds`` finished seeds."""

    role: str
    trial: Trial | None
    candidates: list[int]
    seeds: int
    pick_seed: int

    @property
    def absent(self) -> str:
        """What the row says without an agent: ``"no middle agent among 20 seeds"``."""
        return f"no {self.role} agent among {self.seeds} seeds"


def agent_class(
    final: float, success_return: float = PAPER.success_return, failure_return: float = PAPER.failure_return
) -> str:
    """
    The class of an agent, one of :data:`PAPER_ROLES` (Section 4.1: "well-performing agents achieving more than
    [success_return] rewards or poorly performing agents achieving less than [failure_return] rewards").
    """
    if final >= success_return:
        return PAPER_ROLES[0]
    if final < failure_return:
        return PAPER_ROLES[2]
    return PAPER_ROLES[1]


def pick_paper_agents(
    trials: Sequence[Trial],
    pick_seed: int = 0,
    success_return: float = PAPER.success_return,
    failure_return: float = PAPER.failure_return,
) -> list[AgentPick]:
    """
    The agents of Figures 4, 8, 9 (Figure 4's caption: "a randomly picked well-performing agent", "a middle agent
    between goodness and badness", "a randomly picked poorly performing agent"): one finished trial per
    :func:`agent_class`, picked with ``numpy.random.default_rng([pick_seed, k])`` for the k-th class.

    :param trials: the trials of one task and variant
    :param pick_seed: seed of the random picks
    :param success_return: well-performing at least
    :param failure_return: poorly performing below
    :return: one :class:`AgentPick` per class of :data:`PAPER_ROLES` (``trial`` ``None`` for an empty class)
    """
    if not failure_return <= success_return:
        raise ValueError(f"failure_return must be <= success_return, got {failure_return:g} and {success_return:g}.")
    finished = sorted((t for t in trials if t.finished and len(t.returns)), key=lambda t: t.seed)
    picks = []
    for k, role in enumerate(PAPER_ROLES):
        members = [t for t in finished if agent_class(t.final_return, success_return, failure_return) == role]
        trial = None
        if members:
            trial = members[int(np.random.default_rng([pick_seed, k]).integers(len(members)))]
        picks.append(AgentPick(role, trial, [t.seed for t in members], len(finished), pick_seed))
    return picks


def online_agent_rows(
    picks: Sequence[AgentPick], layers: Sequence[str] = FIGURE4_LAYERS, correlation: str = FIGURE_CORRELATION
) -> list[AgentMetrics]:
    """:return: one row of the online figure per pick (:func:`agent_metrics` of its trial)"""
    return [
        AgentMetrics(None, p.role, absent=p.absent, correlation=correlation)
        if p.trial is None
        else agent_metrics(p.trial, p.role, layers, correlation)
        for p in picks
    ]


def agent_metrics(
    trial: Trial, role: str, layers: Sequence[str] = FIGURE4_LAYERS, correlation: str = FIGURE_CORRELATION
) -> AgentMetrics:
    """:return: the row of ``trial``: its collapse metrics of ``layers`` (``correlation``: the reading of the
    correlation column) and events (InputError: a malformed file)"""
    tags = [metric_tag(layer, metric) for metric, _ in figure4_metrics(correlation) for layer in layers]
    config = read_json(trial.path / CONFIG_JSON) if (trial.path / CONFIG_JSON).is_file() else {}
    sizes = {"mlp0": config.get("feature_dim"), "mlp1": config.get("hidden_dim"), "mlp2": config.get("hidden_dim")}
    widths = {layer: int(sizes[layer]) for layer in layers if isinstance(sizes.get(layer), int)}
    agent = AgentMetrics(trial, role, widths=widths, correlation=correlation)
    metrics_path = trial.path / COLLAPSE_METRICS_CSV
    if metrics_path.exists():
        agent.metrics = read_collapse_metrics(metrics_path, tags)
    events_path = trial.path / COLLAPSE_EVENTS_CSV
    if events_path.exists():
        events = read_collapse_events(events_path)
        agent.resets = [frame for frame, event in events if event == "reset"]
        agent.escapes = [frame for frame, event in events if event == "escape"]
    return agent


def _row_label(agent: AgentMetrics) -> str:
    if agent.trial is None:
        return agent.role
    role = "" if agent.role == "run" else f"{agent.role}: "
    final = "none yet" if np.isnan(agent.final_return) else f"{agent.final_return:.0f}"
    return f"{role}seed {agent.trial.seed}\nfinal return {final}"


def dead_units_label(widths: dict[str, int], layers: Sequence[str]) -> str:
    """:return: the dead units' axis label: ``"dead units (of 1024)"``, ``"dead units (mlp0 of 50, mlp1 of 1024)"``"""
    known = {layer: widths[layer] for layer in layers if layer in widths}
    if not known:
        return "dead units"
    if len(set(known.values())) == 1 and len(known) == len(layers):
        return f"dead units (of {next(iter(known.values()))})"
    return "dead units (" + ", ".join(f"{layer} of {width}" for layer, width in known.items()) + ")"


def plot_collapse_metrics(
    agents: Sequence[AgentMetrics],
    path: Path,
    title: str,
    layers: Sequence[str] = FIGURE4_LAYERS,
    source: str = COLLAPSE_METRICS_CSV,
) -> None:
    """The paper's Figure 4 to the PNG ``path``: a row per agent; its evaluation return, then a panel per metric of
    :func:`figure4_metrics` (the agents' reading of the correlation), a line per layer; resets and escapes as
    vertical lines (``source``: where a missing metric other than the gradient norm would come from)."""
    if not agents:
        raise ValueError("agents must hold at least one agent to plot.")
    readings = {agent.correlation for agent in agents}
    if len(readings) != 1:
        raise ValueError(f"agents must share one reading of the correlation, got {sorted(readings)}.")
    metrics = figure4_metrics(readings.pop())
    columns, rows = 1 + len(metrics), len(agents)
    # the title wrapped to the figure's width (about 13 characters of its 9-point font per inch), 0.15 inch a line
    title = "\n".join(textwrap.fill(line, int(13 * 3.2 * columns)) for line in title.split("\n"))
    title_inches = 0.3 + 0.15 * (title.count("\n") + 1)
    height = 2.4 * rows + 0.5 + title_inches
    widths: dict[str, int] = {}
    for agent in agents:
        widths.update(agent.widths)
    shared_width = {widths.get(layer) for layer in layers}
    full_scale = shared_width.pop() if len(shared_width) == 1 else None
    # Shared x, and shared y per column: the rows compare at a glance.
    fig, axes = plt.subplots(rows, columns, figsize=(3.2 * columns, height), squeeze=False, sharex=True, sharey="col")
    # A fixed layout (inches from the edges): tight_layout would double the drawing time.
    fig.subplots_adjust(
        left=0.075, right=0.99, wspace=0.42, hspace=0.18, top=1 - title_inches / height, bottom=0.75 / height
    )
    threshold_drawn = False
    for row, agent in zip(axes, agents):
        ax = row[0]
        ax.set_ylabel(f"{_row_label(agent)}\n\nevaluation return", fontsize=8)
        if agent.trial is None:
            ax.text(0.5, 0.5, agent.absent, transform=ax.transAxes, wrap=True, **_CENTRED)
        else:
            ax.plot(agent.trial.frames, agent.trial.returns, color=RETURN_COLOR, lw=1.4)
            ax.set_ylim(bottom=min(0.0, float(np.min(agent.trial.returns))))
        for ax, (metric, label) in zip(row[1:], metrics):
            drawn, lowest = False, 0.0
            for layer in layers:
                frames, values = agent.metrics.get(metric_tag(layer, metric), (np.zeros(0), np.zeros(0)))
                if metric == "grad_norm":
                    values = np.maximum(values, GRAD_NORM_FLOOR)  # NaN stays NaN: a gap
                if len(frames):
                    ax.plot(frames, values, lw=1.2, **layer_style(layer))
                    drawn = True
                    lowest = min(lowest, float(np.nanmin(values, initial=0.0)))
            if metric == "grad_norm" and drawn:
                ax.axhline(PAPER.threshold, **THRESHOLD_STYLE)
                threshold_drawn = True
                label = f"{label} ({GRAD_NORM_FLOOR:g} and below\ndrawn at {GRAD_NORM_FLOOR:g})"
                ax.set_yscale("log")
                # a few major ticks and no minor ones: a log axis' minor ticks cost most of the drawing time
                ax.yaxis.set_major_locator(LogLocator(numticks=5))
                ax.yaxis.set_minor_locator(NullLocator())
            if metric in BOUNDED_METRICS:
                ax.set_ylim(lowest - 0.02, 1.02)
            if metric == "dead_units":
                label = dead_units_label(widths, layers)
                if full_scale is not None:
                    ax.set_ylim(-0.02 * full_scale, 1.02 * full_scale)
            if not drawn and agent.trial is not None:
                where = COLLAPSE_METRICS_CSV if metric == "grad_norm" else source  # gradient norms: training time
                ax.text(0.5, 0.5, f"no {metric} in\n{where}", transform=ax.transAxes, color="0.4", **_CENTRED)
            ax.set_ylabel(label, fontsize=8)
        for ax in row:
            for events, _, color, style, alpha in _EVENTS:
                for frame in getattr(agent, events):
                    ax.axvline(frame, color=color, lw=1.0, ls=style, alpha=alpha)
            ax.grid(alpha=0.3)
            ax.tick_params(labelsize=7)
    for ax in axes[-1]:
        frames_axis(ax)
    handles = [Line2D([], [], lw=1.2, **layer_style(layer)) for layer in layers]
    labels = list(layers)
    if threshold_drawn:
        handles.append(Line2D([], [], **THRESHOLD_STYLE))
        labels.append(f"the rule's threshold ({PAPER.threshold:g})")
    for events, label, color, style, _ in _EVENTS:
        if any(getattr(agent, events) for agent in agents):
            handles.append(Line2D([], [], color=color, ls=style, lw=1.0))
            labels.append(label)
    fig.suptitle(title, fontsize=9)
    fig.legend(handles, labels, loc="lower center", ncol=len(labels), fontsize=8, frameon=False)
    fig.savefig(path, dpi=90)
    plt.close(fig)


ONLINE_INPUTS = "each agent's own replay batch at training time (online metrics)"
"""What the online figure's metrics are computed on."""


def paper_figure_title(task: str, variant: str, picks: Sequence[AgentPick], inputs: str) -> str:
    """:return: the two-line title of Figures 4, 8, 9: each row's seed and final return, pick seed, ``inputs``"""
    rows = "; ".join(
        pick.absent if pick.trial is None else f"{pick.role}: seed {pick.trial.seed} ({pick.trial.final_return:.0f})"
        for pick in picks
    )
    pick_seed = picks[0].pick_seed if picks else 0
    return (
        f"{task} / {variant}: {rows} (final return; picked at random, pick seed {pick_seed})\n"
        f"rank, correlation, dead units on {inputs}; gradient norms at training time"
    )


def run_folder_trial(run_dir: str | Path) -> Trial:
    """:return: a run folder of the train CLI as a trial (a partial curve when unfinished; InputError: no run files)"""
    run_dir = Path(run_dir)
    if not is_run_folder(run_dir):
        raise InputError(
            f"{run_dir} is not a run folder of python -m sb3_collapse.train: it needs {CONFIG_JSON} and {EVAL_CSV}.",
            parameter="sweep",
        )
    config = read_json(run_dir / CONFIG_JSON)
    task = str(config.get("env", run_dir.name))
    variant = str(config.get("variant") or config.get("algorithm") or "drqv2")
    trial = load_trial(task, variant, int(config.get("seed", 0)), run_dir, partial=True)
    if not len(trial.frames):
        raise InputError(f"{run_dir / EVAL_CSV} has no evaluation yet; nothing to plot.", parameter="sweep")
    return trial


def is_run_folder(path: str | Path) -> bool:
    """:return: whether ``path`` is a single run folder (its own settings and evaluation files), not a sweep"""
    path = Path(path)
    return (path / CONFIG_JSON).is_file() and (path / EVAL_CSV).is_file()
