"""The report's PNG figures: Figure 5 (curves with percentile bands) and the transplant-grid heatmap."""

from __future__ import annotations

from collections import Counter
from collections.abc import Mapping, Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.ticker import EngFormatter

from sb3_collapse.monitoring.interventions import INTERVENTION_LABELS
from sb3_collapse.paper import PAPER
from sb3_collapse.report.loading import Trial
from sb3_collapse.report.statistics import BandCurve, GridCell, TransplantCurves
from sb3_collapse.report.style import OKABE_ITO, TOL_MUTED, frames_axis
from sb3_collapse.run.variants import TRANSPLANT_SOURCES, split_variant

REFERENCE_COLOR = "0.15"


def variant_colors(variants: Sequence[str]) -> dict[str, tuple[float, ...] | str]:
    """:return: variant -> its colour in every panel (Okabe-Ito but black, then Paul Tol's muted, then ``tab20``)"""
    palette = [color for color in OKABE_ITO if color != "#000000"] + list(TOL_MUTED)
    if len(variants) <= len(palette):
        return {variant: palette[i] for i, variant in enumerate(variants)}
    cmap = plt.get_cmap("tab20")
    return {variant: cmap(i % cmap.N) for i, variant in enumerate(variants)}


def variant_label(variant: str) -> str:
    """:return: the legend name of ``variant``: ``<algorithm>+<intervention>`` gets the intervention's name"""
    _, suffix = split_variant(variant)
    label = INTERVENTION_LABELS.get(suffix) if suffix is not None else None
    return variant if label is None else f"{variant}: {label}"


def panels(count: int, columns: int = 3, size: tuple[float, float] = (5.0, 3.8)) -> tuple[plt.Figure, np.ndarray]:
    """
    :param count: the panels
    :param columns: panels per row
    :param size: inches per panel, width and height
    :return: the figure and its axes (spare ones hidden)
    """
    ncols = min(columns, max(count, 1))
    nrows = -(-max(count, 1) // ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(size[0] * ncols, size[1] * nrows), squeeze=False)
    for ax in axes.flat[count:]:
        ax.set_visible(False)
    return fig, axes


def _clip_reference(reference: BandCurve, last_frame: int | None) -> tuple[np.ndarray, ...]:
    """:return: ``frames, mean, low, high`` of ``reference`` up to ``last_frame`` (``None``: all), interpolated there"""
    frames = np.asarray(reference.frames, dtype=float)
    columns = [np.asarray(c, dtype=float) for c in (reference.mean, reference.low, reference.high)]
    if last_frame is None or frames[-1] <= last_frame:
        return (frames, *columns)
    keep = frames <= last_frame
    ends = [np.interp(last_frame, frames, c) for c in columns]
    return (np.append(frames[keep], last_frame), *(np.append(c[keep], end) for c, end in zip(columns, ends)))


def plot_figure5(
    curves: Mapping[str, Sequence[BandCurve]],
    path: Path,
    references: Mapping[str, BandCurve] | None = None,
    partial: Mapping[str, Sequence[Trial]] | None = None,
    percentiles: tuple[float, float] = (5.0, 95.0),
) -> None:
    """The paper's Figure 5 to ``path``: a panel per task; per variant the mean evaluation return (solid) and the
    percentile band; the published DrQ-v2 ``references`` dashed, hatched band; ``partial`` unfinished curves dotted."""
    references = references or {}
    partial = partial or {}
    tasks = list(curves)
    names = [c.name for task in tasks for c in curves[task]]
    names += [t.variant for task in tasks for t in partial.get(task, [])]
    colors = variant_colors(list(dict.fromkeys(names)))
    low, high = percentiles
    fig, axes = panels(len(tasks))
    for ax, task in zip(axes.flat, tasks):
        last_frame = max((int(c.frames[-1]) for c in curves[task]), default=None)
        reference = references.get(task)
        if reference is not None:
            frames, mean, low_band, high_band = _clip_reference(reference, last_frame)
            marker, label = "o" if len(frames) == 1 else None, f"{reference.name} (n={reference.seeds})"
            ax.plot(frames, mean, "--", marker=marker, color=REFERENCE_COLOR, lw=1.5, label=label)
            hatched = {"facecolor": "none", "edgecolor": REFERENCE_COLOR, "hatch": "///", "lw": 0.0, "alpha": 0.35}
            ax.fill_between(frames, low_band, high_band, **hatched)
        for curve in curves[task]:
            color = colors[curve.name]
            marker = "o" if len(curve.frames) == 1 else None  # a single evaluation is a point, not a line
            label = f"{variant_label(curve.name)} (n={curve.seeds})"
            ax.plot(curve.frames, curve.mean, color=color, lw=2.0, marker=marker, label=label)
            ax.fill_between(curve.frames, curve.low, curve.high, color=color, alpha=0.2, lw=0.0)
        drawn = [trial for trial in partial.get(task, []) if len(trial.frames)]
        counts = Counter(trial.variant for trial in drawn)  # popped: one legend entry per variant
        for trial in drawn:
            count = counts.pop(trial.variant, None)
            label = None if count is None else f"{variant_label(trial.variant)}, unfinished, partial (n={count})"
            ax.plot(trial.frames, trial.returns, ":", color=colors[trial.variant], lw=1.0, label=label)
        ax.set_title(task)
        ax.set_xlabel("frames")
        ax.set_ylabel("evaluation return")
        ax.xaxis.set_major_formatter(EngFormatter(sep=""))
        ax.grid(alpha=0.3)
        entries = len(ax.get_legend_handles_labels()[1])
        if entries == 0:
            ax.text(0.5, 0.5, "no finished seed yet", ha="center", va="center", transform=ax.transAxes)
        else:  # beside the panel: never over the curves or bands
            ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)
    fig.suptitle(f"Mean evaluation return, {low:g}th-{high:g}th percentile band across seeds", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)


def plot_transplant_grid(
    grid: Mapping[str, Sequence[GridCell]], path: Path, success_return: float = PAPER.success_return
) -> None:
    """The paper's Figure 3(a) to ``path``: a heatmap per task, CNN (rows) x MLP source, of the successful seeds."""
    tasks = list(grid)
    fig, axes = panels(len(tasks))
    cmap = plt.get_cmap("viridis").with_extremes(bad="0.85")
    size = len(TRANSPLANT_SOURCES)
    for ax, task in zip(axes.flat, tasks):
        lookup = {(c.cnn, c.mlp): c for c in grid[task]}
        fraction = np.full((size, size), np.nan)
        for i, cnn in enumerate(TRANSPLANT_SOURCES):
            for j, mlp in enumerate(TRANSPLANT_SOURCES):
                cell = lookup[(cnn, mlp)]
                if cell.seeds:
                    fraction[i, j] = cell.successes / cell.seeds
                text = f"{cell.successes}/{cell.seeds}" if cell.seeds else "-"
                dark = cell.seeds and fraction[i, j] < 0.6
                ax.text(j, i, text, ha="center", va="center", fontsize=12, color="white" if dark else "black")
        image = ax.imshow(np.ma.masked_invalid(fraction), cmap=cmap, vmin=0.0, vmax=1.0)
        ax.set_xticks(range(size), [f"{s} MLP" for s in TRANSPLANT_SOURCES])
        ax.set_yticks(range(size), [f"{s} CNN" for s in TRANSPLANT_SOURCES])
        ax.set_title(task)
        fig.colorbar(image, ax=ax, fraction=0.046, pad=0.04, label="fraction successful")
    fig.suptitle(f"Successful seeds (final return >= {success_return:g}) / finished seeds", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


SOURCE_COLORS = dict(zip(TRANSPLANT_SOURCES, (OKABE_ITO[3], OKABE_ITO[2], OKABE_ITO[4])))
"""Figure 3(b): the CNN's source -> colour (blank blue, good green, bad vermillion)."""
SOURCE_LINESTYLES = dict(zip(TRANSPLANT_SOURCES, (":", "-", "--")))
"""Figure 3(b): the MLP's source -> line style (blank dotted, good solid, bad dashed)."""


def plot_figure3b(
    curves: Mapping[str, Sequence[TransplantCurves]], path: Path, success_return: float = PAPER.success_return
) -> None:
    """The paper's Figure 3(b) to ``path``: per task, the mean return (+- one std) of each cell's successful seeds,
    colour by the CNN's source, line style by the MLP's."""
    tasks = list(curves)
    fig, axes = panels(len(tasks), columns=2)
    for ax, task in zip(axes.flat, tasks):
        for cell in curves[task]:
            mean = cell.returns.mean(axis=0)
            color, style = SOURCE_COLORS[cell.cnn], SOURCE_LINESTYLES[cell.mlp]
            ax.plot(cell.frames, mean, color=color, ls=style, lw=1.6, label=f"{cell.label} (n={len(cell.returns)})")
            if len(cell.returns) > 1:
                std = cell.returns.std(axis=0, ddof=1)
                ax.fill_between(cell.frames, mean - std, mean + std, color=color, alpha=0.12, lw=0)
        ax.set_title(f"{task}: successful seeds per transplant cell", fontsize=10)
        ax.set_ylabel("evaluation return")
        frames_axis(ax)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)
    fig.suptitle(f"Figure 3(b): mean +- std of the seeds with final return >= {success_return:g}", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=100, bbox_inches="tight")
    plt.close(fig)
