"""
The paper's Figure 2 and Tables 1-6 from the probe rows of many agents: rows well-performing / poorly performing
agents, columns torso velocity, joint orientations, torso height; in each panel, per layer, the mean over the
row's agents of the probe's test MSE (standardized) against training frames; the tables give the std across the
agents at four training stages.

The paper: "we plot the probing MSE for three environment state components: torso velocity, joint orientation, and
torso height ... We choose these three components because all of them are the input to the reward function." The
columns are therefore the quantities that the task's reward function reads (``reward:...`` targets, recorded by
``DMCEnv.reward_inputs``, see :data:`sb3_collapse.envs.dmc.REWARD_INPUTS`), followed by the state-vector readings of
the same names as extra columns (:data:`FIGURE2_COLUMNS`):

- **walker** (walker-walk's and walker-run's reward: ``stand = (3 tolerance(torso_height) + (1 + torso_upright) / 2)
  / 4`` times a term of ``horizontal_velocity``; walker-stand's is ``stand`` alone, so it has no torso velocity
  column): torso velocity = ``reward:horizontal_velocity`` (the centre of mass's horizontal
  velocity); orientation = ``reward:torso_upright`` (the torso's, the only orientation the reward reads; the paper
  calls the column "joint orientation"); torso height = ``reward:torso_height``. Extra columns: root velocities
  (state) = ``velocity_0..2`` (the root joints' velocities: torso vertical, horizontal and pitch velocity); leg
  orientations (state) = ``orientations_2..13`` (the x and z components of the orientation of the six leg bodies;
  ``orientations_0..1`` are the torso's). The state's ``height`` is ``torso_height`` itself, so it has no column of
  its own.
- **hopper** (hopper-hop's reward: ``tolerance(height)`` times a term of ``speed``; hopper-stand's:
  ``tolerance(height)`` times a term of the control, so it has no torso velocity column): torso velocity =
  ``reward:speed``, torso height = ``reward:height`` (torso above the foot); its reward reads no orientation. Extra
  columns: root velocities (state) = ``velocity_0..2``; rootz (state) = ``position_0``.
- any other domain: one column per reward input, then one per state component (the whole component averaged).

A column is shown when its targets exist: the rollouts hold the reward inputs of their own task only.

Rollouts recorded before the reward inputs were have only the state columns.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.lines import Line2D

from sb3_collapse.probe.rollouts import REWARD_PREFIX
from sb3_collapse.report.statistics import across_seed_std, stage_indices, stages_caption
from sb3_collapse.report.style import frames_axis, layer_style

ORIENTATION = "orientation (torso upright)"
"""The title of walker's second column: the paper's "joint orientation", read as the orientation the reward reads."""
PAPER_COLUMNS = ("torso velocity", ORIENTATION, "torso height")
"""The paper's three columns, in its order (Tables 1-6 are numbered by them)."""

FIGURE2_COLUMNS: dict[str, tuple[tuple[str, tuple[str, ...]], ...]] = {
    "walker": (
        ("torso velocity", ("reward:horizontal_velocity",)),
        (ORIENTATION, ("reward:torso_upright",)),
        ("torso height", ("reward:torso_height",)),
        ("root velocities (state)", tuple(f"velocity_{i}" for i in range(3))),
        ("leg orientations (state)", tuple(f"orientations_{i}" for i in range(2, 14))),
    ),
    "hopper": (
        ("torso velocity", ("reward:speed",)),
        ("torso height", ("reward:height",)),
        ("root velocities (state)", tuple(f"velocity_{i}" for i in range(3))),
        ("rootz (state)", ("position_0",)),
    ),
}
"""Domain -> the columns of Figure 2: title and the probe targets (``probe.csv`` ``component``) it averages."""
ROWS = ("well-performing", "poorly performing")
"""The rows of Figure 2."""


def figure2_columns(task: str, components: Sequence[str], groups: Sequence[str]) -> list[tuple[str, tuple[str, ...]]]:
    """
    :param task: the task, ``<domain>-<task>``
    :param components: the probe targets (``probe.csv`` ``component``)
    :param groups: the state component of each target
    :return: the columns whose targets all exist; for a domain without :data:`FIGURE2_COLUMNS`, one column per
        reward input (``reward:`` groups), then one per state component
    """
    domain = task.split("-")[0]
    available = set(components)
    if domain in FIGURE2_COLUMNS:
        return [(title, names) for title, names in FIGURE2_COLUMNS[domain] if set(names) <= available]
    by_group: dict[str, list[str]] = defaultdict(list)
    for component, group in zip(components, groups):
        by_group[group].append(component)
    columns = [(group, tuple(names)) for group, names in by_group.items()]
    return sorted(columns, key=lambda column: not column[0].startswith(REWARD_PREFIX))


@dataclass
class PanelCurve:
    """
    One line of Figure 2: a layer in one panel (row, column).

    :param row: ``"well-performing"`` or ``"poorly performing"``
    :param column: the column's title
    :param layer: the layer
    :param frames: the training frames shared by every agent of the row
    :param values: ``(agents, frames)`` each agent's mean test MSE over the column's targets
    :param agents: the agents' labels (e.g. ``seed 3``)
    """

    row: str
    column: str
    layer: str
    frames: np.ndarray
    values: np.ndarray
    agents: list[str]

    @property
    def mean(self) -> np.ndarray:
        """The mean across agents at each frame."""
        return self.values.mean(axis=0)


def panel_curves(
    rows: Sequence[Mapping[str, Any]], agents: Mapping[str, str], columns: Sequence[tuple[str, tuple[str, ...]]]
) -> list[PanelCurve]:
    """
    :param rows: probe rows with ``checkpoint``, ``frames``, ``layer``, ``component``, ``test_mse`` and ``agent``
    :param agents: agent label -> its row (:data:`ROWS`)
    :param columns: the panels' columns (:func:`figure2_columns`)
    :return: one curve per (row, column, layer) with at least one agent, on the frames every agent of the row has
    """
    values: dict[tuple[str, str, int, str], dict[str, float]] = defaultdict(dict)
    for r in rows:
        values[(r["agent"], r["layer"], int(r["frames"]), r["component"])] = r["test_mse"]  # type: ignore[index]
    layers = list(dict.fromkeys(r["layer"] for r in rows))
    curves = []
    for row in ROWS:
        members = [agent for agent, which in agents.items() if which == row]
        if not members:
            continue
        frame_sets = [{int(r["frames"]) for r in rows if r["agent"] == agent} for agent in members]
        frames = np.array(sorted(set.intersection(*frame_sets)), dtype=np.int64)
        for title, names in columns:
            for layer in layers:
                matrix = np.array(
                    [
                        [np.mean([values[(agent, layer, int(f), name)] for name in names]) for f in frames]
                        for agent in members
                    ],
                    dtype=np.float64,
                ).reshape(len(members), len(frames))
                curves.append(PanelCurve(row, title, layer, frames, matrix, members))
    return curves


def plot_figure2(curves: Sequence[PanelCurve], path: Path, title: str) -> None:
    """
    The paper's Figure 2: rows well / poorly performing agents, one column per state column, one line per layer
    (mean over the row's agents; colours and line styles of :mod:`sb3_collapse.report.style`), a shared legend
    under the panels.

    :param curves: :func:`panel_curves`
    :param path: the PNG file to write
    :param title: the figure's title (task, variant, agents)
    """
    rows = list(dict.fromkeys(c.row for c in curves))
    columns = list(dict.fromkeys(c.column for c in curves))
    layers = list(dict.fromkeys(c.layer for c in curves))
    height = 2.9 * len(rows) + 1.2
    fig, axes = plt.subplots(
        len(rows), len(columns), figsize=(4.3 * len(columns), height), squeeze=False, sharex=True, sharey="col"
    )
    fig.subplots_adjust(left=0.09, right=0.98, wspace=0.25, hspace=0.3, top=1 - 0.55 / height, bottom=0.95 / height)
    for curve in curves:
        ax = axes[rows.index(curve.row)][columns.index(curve.column)]
        ax.plot(curve.frames, curve.mean, marker="o", ms=2.5, lw=1.3, **layer_style(curve.layer))
        ax.set_title(f"{curve.row} ({len(curve.agents)}): {curve.column}", fontsize=9)
    for ax in axes.flat:
        ax.grid(alpha=0.3)
        ax.set_ylim(bottom=0)
        ax.tick_params(labelsize=7)
    for row in axes:
        row[0].set_ylabel("test MSE (standardized)", fontsize=8)
    for ax in axes[-1]:
        frames_axis(ax, "training frames")
    handles = [Line2D([], [], lw=1.3, **layer_style(layer)) for layer in layers]
    fig.legend(handles, layers, loc="lower center", ncol=len(layers), fontsize=8, frameon=False)
    fig.suptitle(title, fontsize=10)
    fig.savefig(path, dpi=90)
    plt.close(fig)


TABLE_NUMBERS = {(row, column): 1 + 2 * column + row for row in range(2) for column in range(3)}
"""(row, column) of the paper's Figure 2 -> its table in the paper: Table 1 is subplot (1, 1), Table 2 (2, 1), Table 3
(1, 2)... Columns are those of :data:`PAPER_COLUMNS`; the other columns' tables have no number."""


def stage_table_rows(curves: Sequence[PanelCurve], budget_frames: int | None = None) -> list[dict]:
    """
    Tables 1-6: per panel and layer, the std across the row's agents (ddof=1; nan with one agent) at the four
    training stages (:func:`~sb3_collapse.report.statistics.stage_indices`).

    :param curves: :func:`panel_curves`
    :param budget_frames: the agents' budget, in frames (``None``: the paper's)
    :return: rows ``table, row, column, layer, agents, stage, frame, std``
    """
    table_rows = []
    for curve in curves:
        in_paper = curve.row in ROWS and curve.column in PAPER_COLUMNS
        number = TABLE_NUMBERS[(ROWS.index(curve.row), PAPER_COLUMNS.index(curve.column))] if in_paper else ""
        stages = stage_indices(curve.frames, budget_frames) if len(curve.frames) else []
        stds = across_seed_std(curve.values[:, stages], axis=0) if stages else []
        for stage, (index, std) in enumerate(zip(stages, stds)):
            table_rows.append(
                {
                    "table": number,
                    "row": curve.row,
                    "column": curve.column,
                    "layer": curve.layer,
                    "agents": len(curve.agents),
                    "stage": stage,
                    "frame": int(curve.frames[index]),
                    "std": float(std),
                }
            )
    return table_rows


def stage_tables_markdown(table_rows: Sequence[Mapping[str, Any]]) -> str:
    """Tables 1-6 as Markdown: one table per panel, a row per layer, a column per stage."""
    lines = ["# Tables 1-6: std of the probe's test MSE across agents at four training stages", ""]
    panels: dict[tuple, list[Mapping[str, Any]]] = defaultdict(list)
    for r in table_rows:
        panels[(r["table"], r["row"], r["column"])].append(r)
    numbered_first = sorted(panels.items(), key=lambda item: (item[0][0] == "", str(item[0][0]).zfill(3)))
    for (number, row, column), entries in numbered_first:
        frames = list(dict.fromkeys(e["frame"] for e in entries))
        label = f"Table {number}" if number != "" else "Table"
        agents = entries[0]["agents"]
        lines += [f"## {label}: {row} agents ({agents}), {column}", ""]
        lines.append("| layer | " + " | ".join(f"{f:,} frames" for f in frames) + " |")
        lines.append("|---|" + "---|" * len(frames))
        by_layer: dict[str, dict[int, float]] = defaultdict(dict)
        for e in entries:
            by_layer[e["layer"]][e["frame"]] = e["std"]
        for layer, stds in by_layer.items():
            cells = ["-" if np.isnan(stds[f]) else f"{stds[f]:.3f}" for f in frames]
            lines.append(f"| {layer} | " + " | ".join(cells) + " |")
        lines.append("")
    lines.append(stages_caption("shared snapshots") + " Std across agents, ddof=1 (- with one agent).")
    return "\n".join(lines) + "\n"
