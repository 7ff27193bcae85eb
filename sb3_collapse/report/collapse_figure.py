"""
The paper's Figure 4 (walker-walk) and its appendix versions, Figures 8 (hopper-stand) and 9 (finger-spin): the
collapse metrics of a well-performing, a middle and a poorly performing agent over training, next to the
evaluation return, from each trial's collapse metrics and evaluation files (``protocol.COLLAPSE_METRICS_CSV``,
``protocol.EVAL_CSV``).

The paper picks "a randomly picked well-performing agent", "a middle agent between goodness and badness" and "a
randomly picked poorly performing agent"; here they are the seeds of the highest, the median and the lowest final
return (named in the title, so the choice is reproducible).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.lines import Line2D
from matplotlib.ticker import LogLocator, NullLocator

from sb3_collapse.protocol import COLLAPSE_EVENTS_CSV, COLLAPSE_METRICS_CSV, CONFIG_JSON, EVAL_CSV, metric_tag
from sb3_collapse.report.errors import ReportError
from sb3_collapse.report.loading import Trial, load_trial, read_collapse_events, read_collapse_metrics, read_json
from sb3_collapse.report.style import ESCAPE_COLOR, RESET_COLOR, RETURN_COLOR, frames_axis, layer_style

FIGURE4_METRICS: tuple[tuple[str, str], ...] = (
    ("numerical_rank", "numerical rank"),
    ("correlation", "correlation"),
    ("zero_fraction", "zero activations (fraction)"),
    ("grad_norm", "gradient norm"),
)
"""The metric columns of Figure 4, in order: collapse metric (``collapse/<layer>/<metric>``) -> axis label."""
FIGURE4_LAYERS = ("mlp1", "mlp2")
"""The layers of Figure 4 ("we only visualize the metrics of mlp1 and mlp2"; ``mlp0`` on request)."""
BOUNDED_METRICS = ("correlation", "zero_fraction")
"""Metrics in [0, 1], drawn on that range."""
ROLES = ("best", "middle", "worst")
"""The rows of Figure 4: highest, median and lowest final return."""


@dataclass
class AgentMetrics:
    """
    One row of Figure 4.

    :param trial: the trial (evaluation curve, result)
    :param role: ``"best"``, ``"middle"`` or ``"worst"`` (or ``"run"`` for a single run folder)
    :param metrics: tag -> ``(frames, values)`` of its collapse metrics file (empty without one)
    :param resets: frames of the reset rule's interventions
    :param escapes: frames of its escapes
    """

    trial: Trial
    role: str
    metrics: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    resets: list[int] = field(default_factory=list)
    escapes: list[int] = field(default_factory=list)

    @property
    def final_return(self) -> float:
        """The return of the last evaluation."""
        return float(self.trial.returns[-1])


def final_return(trial: Trial) -> float:
    """:return: the return of the trial's last evaluation (nan without one)"""
    return float(trial.returns[-1]) if len(trial.returns) else float("nan")


def pick_agents(trials: Sequence[Trial]) -> list[tuple[str, Trial]]:
    """
    The agents of Figure 4 among finished trials with an evaluation: the highest final return, the median one
    (the upper median of an even count), the lowest; ties go to the smaller seed. With fewer than three trials
    the rows that would repeat a trial are left out.

    :param trials: the trials of one task and variant
    :return: ``(role, trial)`` for ``best``, ``middle``, ``worst``, each trial once
    """
    ranked = sorted((t for t in trials if t.finished and len(t.returns)), key=lambda t: (-final_return(t), t.seed))
    if not ranked:
        return []
    picks = {"best": ranked[0], "middle": ranked[(len(ranked) - 1) // 2], "worst": ranked[-1]}
    chosen, seen = [], set()
    for role in ROLES:
        trial = picks[role]
        if id(trial) not in seen:
            chosen.append((role, trial))
            seen.add(id(trial))
    return chosen


def agent_metrics(trial: Trial, role: str, layers: Sequence[str] = FIGURE4_LAYERS) -> AgentMetrics:
    """
    Read the collapse metrics and events of a trial.

    :param trial: the trial
    :param role: its row's name
    :param layers: the layers whose Figure 4 metrics are read
    :return: its row
    :raises ReportError: on a malformed file
    """
    tags = [metric_tag(layer, metric) for metric, _ in FIGURE4_METRICS for layer in layers]
    agent = AgentMetrics(trial, role)
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
    role = "" if agent.role == "run" else f"{agent.role}: "
    return f"{role}seed {agent.trial.seed}\nfinal return {agent.final_return:.0f}"


def _mark_events(ax: plt.Axes, agent: AgentMetrics) -> None:
    for frame in agent.resets:
        ax.axvline(frame, color=RESET_COLOR, lw=1.0, ls="-.", alpha=0.8)
    for frame in agent.escapes:
        ax.axvline(frame, color=ESCAPE_COLOR, lw=1.0, ls=":", alpha=0.9)


def plot_collapse_metrics(
    agents: Sequence[AgentMetrics], path: Path, title: str, layers: Sequence[str] = FIGURE4_LAYERS
) -> None:
    """
    The paper's Figure 4: one row per agent, columns evaluation return, then each metric of
    :data:`FIGURE4_METRICS` with one line per layer (gradient norm on a log axis), the reset rule's resets and
    escapes as vertical lines. A figure-wide legend under the panels names the layers and the event lines.

    :param agents: the rows
    :param path: the PNG file to write
    :param title: the figure's title (task, variant and which seeds)
    :param layers: the layers drawn
    """
    if not agents:
        raise ValueError("agents must hold at least one agent to plot.")
    columns, rows = 1 + len(FIGURE4_METRICS), len(agents)
    height = 2.4 * rows + 1.1
    # Shared x, and shared y per column: the rows compare at a glance.
    fig, axes = plt.subplots(rows, columns, figsize=(3.2 * columns, height), squeeze=False, sharex=True, sharey="col")
    # A fixed layout (inches from the edges): tight_layout would double the drawing time.
    fig.subplots_adjust(
        left=0.075, right=0.99, wspace=0.42, hspace=0.18, top=1 - 0.45 / height, bottom=0.75 / height
    )
    for row, agent in zip(axes, agents):
        ax = row[0]
        ax.plot(agent.trial.frames, agent.trial.returns, color=RETURN_COLOR, lw=1.4)
        ax.set_ylabel(f"{_row_label(agent)}\n\nevaluation return", fontsize=8)
        ax.set_ylim(bottom=min(0.0, float(np.min(agent.trial.returns))))
        for ax, (metric, label) in zip(row[1:], FIGURE4_METRICS):
            drawn = False
            for layer in layers:
                frames, values = agent.metrics.get(metric_tag(layer, metric), (np.zeros(0), np.zeros(0)))
                if len(frames):
                    ax.plot(frames, values, lw=1.2, **layer_style(layer))
                    drawn = True
            if metric == "grad_norm" and drawn:
                ax.set_yscale("log")
                # a few major ticks and no minor ones: a log axis' minor ticks cost most of the drawing time
                ax.yaxis.set_major_locator(LogLocator(numticks=5))
                ax.yaxis.set_minor_locator(NullLocator())
            if metric in BOUNDED_METRICS:
                ax.set_ylim(-0.02, 1.02)
            if not drawn:
                ax.text(0.5, 0.5, f"no {metric} in\n{COLLAPSE_METRICS_CSV}", ha="center", va="center",
                        transform=ax.transAxes, fontsize=8, color="0.4")
            ax.set_ylabel(label, fontsize=8)
        for ax in row:
            _mark_events(ax, agent)
            ax.grid(alpha=0.3)
            ax.tick_params(labelsize=7)
    for ax in axes[-1]:
        frames_axis(ax)
    handles = [Line2D([], [], lw=1.2, **layer_style(layer)) for layer in layers]
    labels = list(layers)
    if any(a.resets for a in agents):
        handles.append(Line2D([], [], color=RESET_COLOR, ls="-.", lw=1.0))
        labels.append("reset")
    if any(a.escapes for a in agents):
        handles.append(Line2D([], [], color=ESCAPE_COLOR, ls=":", lw=1.0))
        labels.append("escape (reset rule)")
    fig.suptitle(title, fontsize=10)
    fig.legend(handles, labels, loc="lower center", ncol=len(labels), fontsize=8, frameon=False)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def figure_title(task: str, variant: str, agents: Sequence[AgentMetrics]) -> str:
    """The title of a Figure 4: task, variant and the seeds of each row with their final return."""
    rows = ", ".join(f"{a.role} seed {a.trial.seed} ({a.final_return:.0f})" for a in agents)
    return f"{task} / {variant}: collapse metrics over training, {rows} (final return)"


def run_folder_trial(run_dir: str | Path) -> Trial:
    """
    Read a single run folder of ``python -m sb3_collapse.train`` (``runs/walker-walk_s0``) as a trial: task,
    variant and seed from its settings file.

    :param run_dir: the run folder
    :return: the trial (finished or not; an unfinished run's partial evaluation curve is read)
    :raises ReportError: when the folder lacks the settings or the evaluation file
    """
    run_dir = Path(run_dir)
    config_path = run_dir / CONFIG_JSON
    if not (run_dir / EVAL_CSV).exists() or not config_path.exists():
        raise ReportError(
            f"{run_dir} is not a run folder of python -m sb3_collapse.train: it needs {CONFIG_JSON} and {EVAL_CSV}.",
            parameter="sweep",
        )
    config = read_json(config_path)
    task = str(config.get("env", run_dir.name))
    variant = str(config.get("variant") or config.get("algorithm") or "drqv2")
    trial = load_trial(task, variant, int(config.get("seed", 0)), run_dir, partial=True)
    if not len(trial.frames):
        raise ReportError(f"{run_dir / EVAL_CSV} has no evaluation yet; nothing to plot.", parameter="sweep")
    return trial


def is_run_folder(path: str | Path) -> bool:
    """:return: whether ``path`` is a single run folder (its own settings and evaluation files), not a sweep"""
    path = Path(path)
    return (path / CONFIG_JSON).is_file() and (path / EVAL_CSV).is_file()


def run_title(trial: Trial) -> str:
    """The title of a single run's Figure 4."""
    return f"{trial.task} / {trial.variant} / seed {trial.seed}: collapse metrics over training ({trial.status})"

