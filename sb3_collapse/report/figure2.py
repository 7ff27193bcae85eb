"""The paper's Figure 2 and Tables 1-6 of a sweep's task and variant (``python -m sb3_collapse.probe sweep``): "we
plot the probing MSE for three environment state components: torso velocity, joint orientation, and torso height".
The columns and readings: docs/figures.md#figure-2-and-tables-1-6-probing-over-training."""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.lines import Line2D

from sb3_collapse.protocol import REWARD_PREFIX
from sb3_collapse.report.collapse_figure import PAPER_ROLES
from sb3_collapse.report.statistics import across_seed_std, stage_indices, stages_caption
from sb3_collapse.report.style import frames_axis, layer_style
from sb3_collapse.report.tables import markdown_table

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
"""Domain -> the columns of Figure 2: title and the probe targets it averages."""
ROWS = (PAPER_ROLES[0], PAPER_ROLES[2])
"""The rows of Figure 2: well-performing and poorly performing agents (:func:`agent_class`)."""


def figure2_columns(task: str, components: Sequence[str], groups: Sequence[str]) -> list[tuple[str, tuple[str, ...]]]:
    """:return: Figure 2's columns of ``task`` whose probe targets all exist (another domain than
    :data:`FIGURE2_COLUMNS`': one per reward input, then per state component of ``groups``)"""
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
    """One line of Figure 2, a layer in the panel of a row of :data:`ROWS` and a column: ``(agents, frames)`` each
    agent's mean test MSE over the column's targets, on the training frames every agent of the row has."""

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
    """:return: a curve per (row, column, layer) with an agent, from probe ``rows`` (``agents``: label -> its row)"""
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
                matrix = [[np.mean([values[(a, layer, int(f), n)] for n in names]) for f in frames] for a in members]
                matrix = np.array(matrix, dtype=np.float64).reshape(len(members), len(frames))
                curves.append(PanelCurve(row, title, layer, frames, matrix, members))
    return curves


def plot_figure2(
    curves: Sequence[PanelCurve],
    path: Path,
    title: str,
    flat_columns: Collection[str] = (),
    few_layers: Collection[str] = (),
) -> None:
    """The paper's Figure 2 to ``path``: a row per class of agents, a column per state column, a line per layer;
    in red the columns of a barely varying target (``flat_columns``) and the layers of ``few_layers`` (fewer test
    samples than max_tau, marked ``*``)."""
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
        flat = " (barely varies)" if curve.column in flat_columns else ""
        ax.set_title(
            f"{curve.row} ({len(curve.agents)}): {curve.column}{flat}", fontsize=9, color="red" if flat else "black"
        )
    for ax in axes.flat:
        ax.grid(alpha=0.3)
        ax.set_ylim(bottom=0)
        ax.tick_params(labelsize=7)
    for row in axes:
        row[0].set_ylabel("test MSE (standardized)", fontsize=8)
    for ax in axes[-1]:
        frames_axis(ax, "training frames")
    handles = [Line2D([], [], lw=1.3, **layer_style(layer)) for layer in layers]
    legend = fig.legend(
        handles,
        [layer + "*" * (layer in few_layers) for layer in layers],
        loc="lower center",
        ncol=len(layers),
        fontsize=8,
        frameon=False,
    )
    for text in legend.get_texts():
        text.set_color("red" if text.get_text().endswith("*") else "black")
    marks = (
        "\nred: the warnings of summary.json (*: fewer test samples than max_tau)" if flat_columns or few_layers else ""
    )
    fig.suptitle(title + marks, fontsize=10)
    fig.savefig(path, dpi=90)
    plt.close(fig)


TABLE_NUMBERS = {(row, column): 1 + 2 * column + row for row in range(2) for column in range(3)}
"""(row, column of :data:`PAPER_COLUMNS`) of Figure 2 -> its table in the paper (Table 1: subplot (1, 1))."""


TABLE_COLUMNS = ("table", "row", "column", "layer", "agents", "stage", "frame", "std")
"""The columns of ``tables_1_6.csv``."""


def stage_table_rows(curves: Sequence[PanelCurve], budget_frames: int | None = None) -> list[dict]:
    """:return: Tables 1-6 (:data:`TABLE_COLUMNS`): per panel, layer and stage of ``budget_frames`` (``None``: the
    paper's), the std across the row's agents"""
    table_rows = []
    for curve in curves:
        in_paper = curve.row in ROWS and curve.column in PAPER_COLUMNS
        number = TABLE_NUMBERS[(ROWS.index(curve.row), PAPER_COLUMNS.index(curve.column))] if in_paper else ""
        stages = stage_indices(curve.frames, budget_frames) if len(curve.frames) else []
        stds = across_seed_std(curve.values[:, stages], axis=0) if stages else []
        for stage, (index, std) in enumerate(zip(stages, stds)):
            values = (number, curve.row, curve.column, curve.layer, len(curve.agents), stage, int(curve.frames[index]))
            table_rows.append(dict(zip(TABLE_COLUMNS, (*values, float(std)))))
    return table_rows


def stage_panels(table_rows: Sequence[Mapping[str, Any]]) -> list[tuple[str, list[str], list[list[Any]]]]:
    """:return: Tables 1-6 of :func:`stage_table_rows` (or its CSV), numbered first: ``(title, header, rows)``, a row
    per layer with its std per stage"""
    panels: dict[tuple[str, str, str], list[Mapping[str, Any]]] = defaultdict(list)
    for r in table_rows:
        panels[(str(r["table"]), r["row"], r["column"])].append(r)
    tables = []
    numbered_first = sorted(panels.items(), key=lambda item: (not item[0][0], item[0][0].zfill(3)))
    for (number, row, column), entries in numbered_first:
        frames = list(dict.fromkeys(int(e["frame"]) for e in entries))
        stds: dict[str, dict[int, float]] = defaultdict(dict)
        for e in entries:
            stds[e["layer"]][int(e["frame"])] = float(e["std"] or "nan")
        title = f"Table {number}".rstrip() + f": {row} agents ({entries[0]['agents']}), {column}"
        header = ["layer", *(f"std at {f:,} frames" for f in frames)]
        tables.append((title, header, [[layer, *(by.get(f, math.nan) for f in frames)] for layer, by in stds.items()]))
    return tables


def stage_tables_markdown(table_rows: Sequence[Mapping[str, Any]]) -> str:
    """:return: Tables 1-6 as Markdown (:func:`stage_panels`)"""
    lines = ["# Tables 1-6: std of the probe's test MSE across agents at four training stages", ""]
    for title, header, rows in stage_panels(table_rows):
        body = [[row[0], *("-" if math.isnan(v) else f"{v:.3f}" for v in row[1:])] for row in rows]
        lines += [f"## {title}", "", *markdown_table(header, body), ""]
    lines.append(stages_caption("shared snapshots") + " Std across agents, ddof=1 (- with one agent).")
    return "\n".join(lines) + "\n"
