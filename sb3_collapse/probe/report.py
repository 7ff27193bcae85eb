"""Outputs of the probe: ``probe.csv``, ``summary.json`` and PNG plots, written so that a failed run leaves none."""

from __future__ import annotations

import csv
import json
from collections import defaultdict
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from sb3_collapse.errors import ProbeError
from sb3_collapse.staged_outputs import StagedOutputs

CSV_NAME = "probe.csv"
SUMMARY_NAME = "summary.json"
BY_LAYER_PLOT = "mse_by_layer.png"
OVER_TRAINING_PLOT = "mse_over_training.png"
OUTPUT_FILES = (CSV_NAME, SUMMARY_NAME, BY_LAYER_PLOT, OVER_TRAINING_PLOT)
"""The files a probe run writes (``summary.json`` last: its presence marks a complete run)."""


def staged_output(out: str | Path, overwrite: bool = False) -> StagedOutputs:
    """
    The probe's output folder, staged (see :class:`~sb3_collapse.staged_outputs.StagedOutputs`): files are moved
    into ``out`` only when the whole run succeeded, ``summary.json`` last.

    :param out: the output folder (created if needed)
    :param overwrite: replace the outputs of a previous run; otherwise their presence is an error
    :raises ProbeError: when ``out`` is a file, or holds a previous run's outputs and ``overwrite`` is false
    """
    return StagedOutputs(out, OUTPUT_FILES, SUMMARY_NAME, overwrite=overwrite, error=ProbeError)


def write_csv(rows: list[dict[str, Any]], path: Path) -> None:
    """One row per (checkpoint, layer, component), columns in the order of the first row."""
    with path.open("w", newline="") as file:
        writer = csv.DictWriter(file, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


def write_json(data: dict[str, Any], path: Path) -> None:
    """Pretty-printed JSON."""
    path.write_text(json.dumps(data, indent=2) + "\n")


def group_means(rows: list[dict[str, Any]], key: str = "test_mse") -> dict[tuple[str, str, str], float]:
    """
    :param rows: probe rows
    :param key: the column averaged
    :return: ``(checkpoint, layer, group)`` -> mean of ``key`` over the group's components
    """
    values: dict[tuple[str, str, str], list[float]] = defaultdict(list)
    for row in rows:
        values[(row["checkpoint"], row["layer"], row["group"])].append(row[key])
    return {k: float(np.mean(v)) for k, v in values.items()}


def _unique(values: list[Any]) -> list[Any]:
    return list(dict.fromkeys(values))


def _grid(count: int, columns: int) -> tuple[plt.Figure, np.ndarray]:
    ncols = min(columns, count)
    nrows = -(-count // ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(3.2 * ncols, 2.6 * nrows), squeeze=False)
    for ax in axes.flat[count:]:
        ax.set_visible(False)
    return fig, axes


def _checkpoint_colors(checkpoints: list[str]) -> list[Any]:
    if len(checkpoints) <= 10:
        return [f"C{i}" for i in range(len(checkpoints))]
    return list(plt.cm.viridis(np.linspace(0, 1, len(checkpoints))))


def plot_mse_by_layer(rows: list[dict[str, Any]], path: Path) -> None:
    """
    One subplot per component: test MSE (standardized) by layer, one line per checkpoint (in the given order;
    a colour map from first to last when there are more than 10).
    """
    layers = _unique([r["layer"] for r in rows])
    components = _unique([r["component"] for r in rows])
    checkpoints = _unique([r["checkpoint"] for r in rows])
    mse = {(r["checkpoint"], r["component"], r["layer"]): r["test_mse"] for r in rows}
    fig, axes = _grid(len(components), 6)
    colors = _checkpoint_colors(checkpoints)
    for ax, component in zip(axes.flat, components):
        for checkpoint, color in zip(checkpoints, colors):
            ys = [mse.get((checkpoint, component, layer), np.nan) for layer in layers]
            ax.plot(range(len(layers)), ys, marker="o", ms=3, color=color, label=checkpoint)
        ax.set_title(component, fontsize=9)
        ax.set_xticks(range(len(layers)), layers, rotation=45, fontsize=7)
        ax.set_ylim(bottom=0)
        ax.tick_params(axis="y", labelsize=7)
        ax.grid(alpha=0.3)
    axes.flat[0].set_ylabel("test MSE (standardized)", fontsize=8)
    fig.suptitle("OMP probing: test MSE by layer", fontsize=11)
    fig.tight_layout()
    if len(checkpoints) <= 10:
        handles, labels = axes.flat[0].get_legend_handles_labels()
        fig.legend(
            handles, labels, loc="upper center", bbox_to_anchor=(0.5, 0.0), ncol=min(5, len(checkpoints)), fontsize=8
        )
    else:
        mappable = plt.cm.ScalarMappable(cmap="viridis", norm=plt.Normalize(0, len(checkpoints) - 1))
        fig.colorbar(mappable, ax=axes, label="checkpoint (given order)", shrink=0.6)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)


def training_order(rows: list[dict[str, Any]]) -> list[str] | None:
    """
    :return: the checkpoints sorted by training step when there are at least 2 and their steps are distinct,
        else ``None``
    """
    steps = {r["checkpoint"]: r["num_timesteps"] for r in rows}
    if len(steps) < 2 or len(set(steps.values())) != len(steps):
        return None
    return sorted(steps, key=steps.__getitem__)


def plot_mse_over_training(rows: list[dict[str, Any]], path: Path) -> bool:
    """
    The paper's Figure 2: one subplot per state component group, test MSE (standardized, mean over the group's
    components) against training frames, one line per layer.

    :return: False (nothing written) unless the checkpoints are ordered by training step
        (:func:`training_order`)
    """
    order = training_order(rows)
    if order is None:
        return False
    frames = {r["checkpoint"]: r["frames"] for r in rows}
    layers = _unique([r["layer"] for r in rows])
    groups = _unique([r["group"] for r in rows])
    means = group_means(rows)
    fig, axes = _grid(len(groups), 4)
    xs = [frames[c] for c in order]
    for ax, group in zip(axes.flat, groups):
        for i, layer in enumerate(layers):
            ys = [means.get((c, layer, group), np.nan) for c in order]
            ax.plot(
                xs, ys, marker="o", ms=3, color=f"C{i}", linestyle="--" if layer.startswith("mlp") else "-", label=layer
            )
        ax.set_title(group, fontsize=10)
        ax.set_xlabel("training frames", fontsize=8)
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.3)
    axes.flat[0].set_ylabel("test MSE (standardized)", fontsize=8)
    fig.suptitle("OMP probing over training: mean test MSE of each component group", fontsize=11)
    fig.tight_layout()
    handles, labels = axes.flat[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="upper center", bbox_to_anchor=(0.5, 0.0), ncol=len(layers), fontsize=8)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return True


def format_table(rows: list[dict[str, Any]]) -> str:
    """Text table of the mean test MSE (standardized) per checkpoint, layer and component group."""
    means = group_means(rows)
    groups = _unique([r["group"] for r in rows])
    width = max(12, *(len(group) + 2 for group in groups))
    lines = []
    for checkpoint in _unique([r["checkpoint"] for r in rows]):
        lines.append(f"{checkpoint}: mean test MSE (standardized) per component group")
        lines.append(f"  {'layer':<6}" + "".join(f"{group:>{width}}" for group in groups))
        for layer in _unique([r["layer"] for r in rows if r["checkpoint"] == checkpoint]):
            lines.append(
                f"  {layer:<6}" + "".join(f"{means[(checkpoint, layer, group)]:>{width}.4f}" for group in groups)
            )
    return "\n".join(lines)
