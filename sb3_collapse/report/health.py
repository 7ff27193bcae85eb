"""``python -m sb3_collapse.probe health``: the network health of saved models (computed by
:mod:`sb3_collapse.probe.health`), a PNG per network; docs/probe.md#network-health."""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.lines import Line2D

from sb3_collapse.report.collapse_figure import BOUNDED_METRICS
from sb3_collapse.report.plots import panels
from sb3_collapse.report.style import LAYER_COLORS, OKABE_ITO, TOL_MUTED, frames_axis

FRACTION_METRICS = (*BOUNDED_METRICS, "active_fraction", "persistent_dormant_fraction", "action_saturation")
"""Metrics in [0, 1], drawn on that range (the dormant ratios too: their names start with ``dormant_ratio``)."""


def _network_head(layer: str) -> str:
    """:return: the Q network of a critic layer (``q1.mlp0`` -> ``q1``), ``""`` for the actor's layers"""
    head = layer.partition(".")[0]
    return head if head[:1] == "q" and head[1:].isdigit() else ""


def layer_line_style(layer: str) -> dict[str, Any]:
    """:return: ``plot`` keywords of ``layer`` of either network: the actor's colours of
    :data:`~sb3_collapse.report.style.LAYER_COLORS` (solid CNN, dashed MLP); a critic layer ``q<k>.mlp<i>`` coloured
    by ``i`` (``q<k>`` itself black), solid for ``q1``, dashed for ``q2``"""
    head, rest = _network_head(layer), layer.partition(".")[2]
    if head:
        palette = (*TOL_MUTED, *OKABE_ITO)
        color = "#000000" if not rest else palette[int(rest.removeprefix("mlp") or 0) % len(palette)]
        return {"color": color, "linestyle": "-" if head == "q1" else "--"}
    return {"color": LAYER_COLORS.get(layer, "#777777"), "linestyle": "--" if layer.startswith("mlp") else "-"}


def _unique(values: Sequence[Any]) -> list[Any]:
    return list(dict.fromkeys(values))


def _is_fraction(metric: str) -> bool:
    return metric in FRACTION_METRICS or metric.startswith("dormant_ratio")


def plot_health(rows: Sequence[dict[str, Any]], network: str, path: Path, series: bool, title: str) -> None:
    """
    The health of one network to the PNG ``path``: a panel per metric. Over a time series (``series``), as the
    paper's Figure 4: a line per layer against training frames; otherwise the value of each layer (x), a line per
    checkpoint.

    :param rows: rows of :data:`~sb3_collapse.probe.health.HEALTH_COLUMNS` (the network's are drawn)
    :param network: ``"actor"`` or ``"critic"``
    :param path: the PNG to write
    :param series: whether the checkpoints are a time series (in training order in ``rows``)
    :param title: the figure's title
    """
    rows = [row for row in rows if row["network"] == network]
    metrics, layers, checkpoints = (_unique([row[key] for row in rows]) for key in ("metric", "layer", "checkpoint"))
    layers = sorted(layers, key=_network_head)  # each Q network's layers together, its value last (stable sort)
    value = {(row["checkpoint"], row["layer"], row["metric"]): row["value"] for row in rows}
    frames = {row["checkpoint"]: row["frames"] for row in rows}
    columns = 5
    fig, axes = panels(len(metrics), columns, (3.0, 2.3))
    for ax, metric in zip(axes.flat, metrics):
        drawn = [layer for layer in layers if any((c, layer, metric) in value for c in checkpoints)]
        if series:
            xs = [frames[c] for c in checkpoints]
            for layer in drawn:
                ys = [value.get((c, layer, metric), np.nan) for c in checkpoints]
                ax.plot(xs, ys, marker="o", ms=2.5, lw=1.2, **layer_line_style(layer))
            pad = 0.04 * (max(xs) - min(xs))  # one x range in every panel, a first NaN (no previous) included
            ax.set_xlim(min(xs) - pad, max(xs) + pad)
            frames_axis(ax)
            ax.xaxis.label.set_size(7)
        else:
            for k, checkpoint in enumerate(checkpoints):  # a line through each network's layers (q1's, q2's apart)
                for _, run in itertools.groupby(enumerate(drawn), key=lambda item: _network_head(item[1])):
                    xs, run_layers = zip(*run)
                    ys = [value.get((checkpoint, layer, metric), np.nan) for layer in run_layers]
                    ax.plot(xs, ys, marker="o", ms=3, lw=1.0, color=OKABE_ITO[k % len(OKABE_ITO)])
            ax.set_xticks(range(len(drawn)), drawn, rotation=60, fontsize=6)
        if _is_fraction(metric):
            ax.set_ylim(-0.02, 1.02)
        ax.set_title(metric.replace("_", " "), fontsize=8)
        ax.tick_params(labelsize=6)
        ax.grid(alpha=0.3)
    if series:
        handles = [Line2D([], [], lw=1.2, **layer_line_style(layer)) for layer in layers]
        labels = layers
    else:
        handles = [Line2D([], [], color=OKABE_ITO[k % len(OKABE_ITO)], marker="o") for k in range(len(checkpoints))]
        labels = checkpoints
    fig.suptitle(title, fontsize=9)
    per_row = 10  # legend entries per row: every layer of the actor (cnn0..action) in one
    fig.tight_layout(rect=(0, 0.04 + 0.02 * ((len(labels) - 1) // per_row), 1, 0.97))
    fig.legend(handles, labels, loc="lower center", ncol=min(len(labels), per_row), fontsize=7, frameon=False)
    fig.savefig(path, dpi=100)
    plt.close(fig)
