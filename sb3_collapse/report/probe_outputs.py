"""``python -m sb3_collapse.probe``'s plots and tables of the probe's rows: MSE by layer, MSE over training."""

from __future__ import annotations

import sys
from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from sb3_collapse.report.plots import panels


def group_means(rows: list[dict[str, Any]], key: str = "test_mse") -> dict[tuple[str, str, str], float]:
    """:return: ``(checkpoint, layer, group)`` -> mean of the column ``key`` of ``rows`` over the group's components"""
    values: dict[tuple[str, str, str], list[float]] = defaultdict(list)
    for row in rows:
        values[(row["checkpoint"], row["layer"], row["group"])].append(row[key])
    return {k: float(np.mean(v)) for k, v in values.items()}


def _unique(values: list[Any]) -> list[Any]:
    return list(dict.fromkeys(values))


def _checkpoint_colors(checkpoints: list[str]) -> list[Any]:
    if len(checkpoints) <= 10:
        return [f"C{i}" for i in range(len(checkpoints))]
    return list(plt.cm.viridis(np.linspace(0, 1, len(checkpoints))))


def warned(warnings: Sequence[dict[str, Any]], key: str) -> set[str]:
    """:return: the ``targets`` or ``layers`` (``key``) that :func:`~sb3_collapse.probe.probing.probe_warnings` names"""
    return {name for warning in warnings for name in warning.get(key, ())}


def report_warnings(warnings: Sequence[dict[str, Any]]) -> None:
    """Print each warning's message to stderr."""
    for warning in warnings:
        print(f"Warning: {warning['message']}", file=sys.stderr, flush=True)


def plot_mse_by_layer(rows: list[dict[str, Any]], path: Path, warnings: Sequence[dict[str, Any]] = ()) -> None:
    """Write to ``path`` a panel per component: test MSE by layer, a line per checkpoint (a colour map beyond 10);
    the targets and layers that ``warnings`` name are marked in red."""
    targets, few = warned(warnings, "targets"), warned(warnings, "layers")
    layers = _unique([r["layer"] for r in rows])
    components = _unique([r["component"] for r in rows])
    checkpoints = _unique([r["checkpoint"] for r in rows])
    mse = {(r["checkpoint"], r["component"], r["layer"]): r["test_mse"] for r in rows}
    fig, axes = panels(len(components), 6, (3.2, 2.6))
    colors = _checkpoint_colors(checkpoints)
    for ax, component in zip(axes.flat, components):
        for checkpoint, color in zip(checkpoints, colors):
            ys = [mse.get((checkpoint, component, layer), np.nan) for layer in layers]
            ax.plot(range(len(layers)), ys, marker="o", ms=3, color=color, label=checkpoint)
        flat = component in targets
        ax.set_title(component + (" (barely varies)" if flat else ""), fontsize=9, color="red" if flat else "black")
        ax.set_xticks(range(len(layers)), [layer + "*" * (layer in few) for layer in layers], rotation=45, fontsize=7)
        for label in ax.get_xticklabels():
            label.set_color("red" if label.get_text().endswith("*") else "black")
        ax.set_ylim(bottom=0)
        ax.tick_params(axis="y", labelsize=7)
        ax.grid(alpha=0.3)
    axes.flat[0].set_ylabel("test MSE (standardized)", fontsize=8)
    marks = "; red: the warnings of summary.json (*: fewer test samples than max_tau)" if warnings else ""
    fig.suptitle("OMP probing: test MSE by layer" + marks, fontsize=11)
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
    """:return: the checkpoints by training step when there are 2 or more with distinct steps, else ``None``"""
    steps = {r["checkpoint"]: r["num_timesteps"] for r in rows}
    if len(steps) < 2 or len(set(steps.values())) != len(steps):
        return None
    return sorted(steps, key=steps.__getitem__)


def plot_mse_over_training(rows: list[dict[str, Any]], path: Path) -> bool:
    """Write to ``path`` a panel per state component group: mean test MSE over training frames, a line per layer;
    return False (nothing written) unless the checkpoints are ordered by training step (:func:`training_order`)."""
    order = training_order(rows)
    if order is None:
        return False
    frames = {r["checkpoint"]: r["frames"] for r in rows}
    layers = _unique([r["layer"] for r in rows])
    groups = _unique([r["group"] for r in rows])
    means = group_means(rows)
    fig, axes = panels(len(groups), 4, (3.2, 2.6))
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
