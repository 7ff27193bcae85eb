"""``python -m sb3_collapse.probe``: probe checkpoints and write ``probe.csv``, ``summary.json`` and PNG plots (all or
none)."""

from __future__ import annotations

import sys
import time
from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import torch as th
from stable_baselines3.common.utils import get_device

from sb3_collapse.errors import InputError
from sb3_collapse.paper import PAPER
from sb3_collapse.probe.checkpoints import checkpoint_labels, load_checkpoint
from sb3_collapse.probe.pipeline import (
    ROLLOUTS_NAME,
    RecordOptions,
    check_checkpoint_files,
    record_agents,
    summary_head,
)
from sb3_collapse.probe.probing import (
    MIN_EPISODES,
    CheckpointProbe,
    EpisodeSplit,
    ProbeSettings,
    probe_checkpoint,
    probe_warnings,
    split_by_episode,
)
from sb3_collapse.probe.rollouts import Rollouts
from sb3_collapse.protocol import PROBE_SUMMARY_JSON, write_json_atomically
from sb3_collapse.report.plots import panels
from sb3_collapse.report.tables import write_csv
from sb3_collapse.staged_outputs import StagedOutputs

CSV_NAME = "probe.csv"
SUMMARY_NAME = PROBE_SUMMARY_JSON
BY_LAYER_PLOT = "mse_by_layer.png"
OVER_TRAINING_PLOT = "mse_over_training.png"
OUTPUT_FILES = (CSV_NAME, SUMMARY_NAME, BY_LAYER_PLOT, OVER_TRAINING_PLOT)
"""The files a probe run writes (``summary.json`` last: its presence marks a complete run)."""
SELF_RECORDED_NOTE = (
    "the rollouts were recorded by the first probed checkpoint itself; the paper's protocol (Section 4.1) records "
    "them once from a well-performing agent (final return >= {success:g}) and probes every checkpoint on them: "
    "record with `python -m sb3_collapse.probe record GOOD.zip --out rollouts.npz` and pass `--rollouts "
    "rollouts.npz` (library: `rollouts_path`), or use `python -m sb3_collapse.probe sweep` on a sweep folder"
)
"""What the probe says when it records its rollouts from the checkpoint it probes."""


def staged_output(out: str | Path, overwrite: bool = False) -> StagedOutputs:
    """:return: the probe's staged output folder ``out`` (moved in on success, ``summary.json`` last)"""
    return StagedOutputs(out, OUTPUT_FILES, SUMMARY_NAME, overwrite=overwrite, error=InputError)


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


def probe_to_folder(
    checkpoint_paths: Sequence[str | Path],
    out: str | Path,
    settings: ProbeSettings,
    rollouts_path: str | Path | None = None,
    record_options: RecordOptions | None = None,
    overwrite: bool = False,
    command: Sequence[str] | None = None,
) -> dict[str, Any]:
    """
    ``python -m sb3_collapse.probe``: probe checkpoints and write ``probe.csv``, ``summary.json`` and the plots into
    ``out`` when every checkpoint succeeded. Without ``rollouts_path``, the first checkpoint's are recorded first.

    :param checkpoint_paths: the checkpoints
    :param out: the output folder
    :param settings: the probe's settings
    :param rollouts_path: recorded rollouts, or ``None`` to record them
    :param record_options: how to record (when ``rollouts_path`` is ``None``)
    :param overwrite: replace a previous run's outputs in ``out``
    :param command: the command line, stored in the summary
    :return: the summary (as written to ``summary.json``)
    :raises InputError: for bad input
    """
    started = time.perf_counter()
    settings.validate()
    if settings.split_per_agent:
        message = "split_per_agent seeds each agent's split by its seed in a sweep (probe sweep); one split here."
        raise InputError(message, parameter="split_per_agent")
    check_checkpoint_files(checkpoint_paths)
    labels = checkpoint_labels(list(checkpoint_paths))
    device = get_device(settings.device)
    out = Path(out)
    if rollouts_path is None:
        record_options = checked_record_options(record_options)
        if (out / ROLLOUTS_NAME).exists() and not overwrite:
            raise InputError(
                f"{out / ROLLOUTS_NAME} exists: reuse it with `rollouts`, or pass `overwrite=True`.", parameter="out"
            )
    self_recorded = rollouts_path is None
    with staged_output(out, overwrite=overwrite) as staged:
        if rollouts_path is None:
            rollouts = record_rollouts(checkpoint_paths[0], device, record_options, settings, staged)
            print(f"Recorded {len(rollouts)} agent steps of {rollouts.n_episodes} episodes to {out / ROLLOUTS_NAME}")
            print(f"Note: {SELF_RECORDED_NOTE.format(success=PAPER.success_return)}.", flush=True)
            rollouts_path = out / ROLLOUTS_NAME
        else:
            rollouts = Rollouts.load(rollouts_path)
        split = split_by_episode(rollouts.episode_ids, settings.fractions, settings.split_seed)
        results = _probe_checkpoints(checkpoint_paths, labels, device, rollouts, split, settings)
        rows = [row for result in results for row in result.rows]
        warnings = probe_warnings(rollouts, split, rows, settings)
        report_warnings(warnings)
        write_csv(rows, list(rows[0]), staged.path(CSV_NAME))
        plot_mse_by_layer(rows, staged.path(BY_LAYER_PLOT), warnings)
        over_training = plot_mse_over_training(rows, staged.path(OVER_TRAINING_PLOT))
        summary = _summary(results, rows, rollouts, rollouts_path, split, settings, over_training, command)
        summary["warnings"] = warnings
        if self_recorded:
            summary["rollouts"]["note"] = SELF_RECORDED_NOTE.format(success=PAPER.success_return)
        summary["total_seconds"] = round(time.perf_counter() - started, 1)
        write_json_atomically(staged.path(SUMMARY_NAME), summary)
        files = staged.commit()
    print("Wrote " + ", ".join(str(f) for f in files))
    return summary


def checked_record_options(record_options: RecordOptions | None, pooled: bool = False) -> RecordOptions:
    """:return: ``record_options`` (``None``: the defaults), checked (InputError: naming the bad option; ``pooled``:
    the caller records from ``pool_agents`` agents)"""
    record_options = record_options or RecordOptions()
    record_options.check(pooled)
    if record_options.episodes < MIN_EPISODES:  # the split needs them
        raise InputError(
            f"episodes must be >= {MIN_EPISODES} to split them into training, validation and test episodes, "
            f"got {record_options.episodes}.",
            parameter="episodes",
        )
    return record_options


def record_rollouts(
    source: str | Path | Sequence[str | Path],
    device: th.device,
    record_options: RecordOptions,
    settings: ProbeSettings,
    staged: StagedOutputs,
) -> Rollouts:
    """:return: the rollouts recorded by the checkpoint ``source`` (or pooled from several: :func:`record_agents`),
    saved into ``staged`` (moved in on success)"""
    sources = [source] if isinstance(source, (str, Path)) else list(source)
    rollouts = record_agents(sources, record_options, device, settings.progress)
    rollouts.save(staged.path(ROLLOUTS_NAME))
    return rollouts


def _probe_checkpoints(
    checkpoint_paths: Sequence[str | Path],
    labels: Sequence[str],
    device: th.device,
    rollouts: Rollouts,
    split: EpisodeSplit,
    settings: ProbeSettings,
) -> list[CheckpointProbe]:
    """Probe each checkpoint in turn on ``rollouts``, printing its table; the networks are freed after each."""
    results: list[CheckpointProbe] = []
    reuse: dict = {}  # cnn0 (the normalized pixels) is probed once for checkpoints that normalize alike
    for path, label in zip(checkpoint_paths, labels):
        checkpoint = load_checkpoint(path, device=device)
        checkpoint.label = label
        print(
            f"Probing {checkpoint.path} ({checkpoint.algorithm}, {checkpoint.num_timesteps:,} agent steps)", flush=True
        )
        result = probe_checkpoint(checkpoint, rollouts, split, settings, reuse)
        result.checkpoint.model = None  # type: ignore[assignment]  # free the networks
        results.append(result)
        print(format_table(result.rows), flush=True)
    return results


def _summary(
    results: list[CheckpointProbe],
    rows: list[dict[str, Any]],
    rollouts: Rollouts,
    rollouts_path: str | Path,
    split: EpisodeSplit,
    settings: ProbeSettings,
    over_training: bool,
    command: Sequence[str] | None,
) -> dict[str, Any]:
    means = group_means(rows)
    names, groups, _ = rollouts.targets()
    files = [CSV_NAME, BY_LAYER_PLOT] + ([OVER_TRAINING_PLOT] if over_training else []) + [SUMMARY_NAME]
    return {
        **summary_head(command, settings),
        "method": "OMP per (layer, component) on features standardized with train statistics (constant columns "
        "dropped) and standardized targets, no intercept; tau = argmin validation MSE over 1..max_tau; "
        "MSE in standardized units (columns *_mse) and in state units squared (*_mse_raw).",
        "rollouts": {
            "path": str(rollouts_path),
            "samples": len(rollouts),
            "episodes": rollouts.n_episodes,
            "observation_shape": list(rollouts.observations.shape[1:]),
            "env_config": rollouts.env_config,
            "metadata": rollouts.metadata,
        },
        "split": {key: getattr(split, key) for key in ("n_train", "n_validation", "n_test", "episodes")},
        "targets": {"names": names, "groups": groups},
        "checkpoints": [
            {
                "name": r.checkpoint.name,
                "path": str(r.checkpoint.path),
                "algorithm": r.checkpoint.algorithm,
                "num_timesteps": r.checkpoint.num_timesteps,
                "frames": r.checkpoint.frames,
                "extract_seconds": round(r.extract_seconds, 2),
                "layers": {
                    layer.layer: {
                        "n_features": layer.n_features,
                        "n_features_kept": layer.n_features_kept,
                        "max_tau": layer.max_tau,
                        "fit_seconds": round(layer.fit_seconds, 2),
                        "reused_from_an_earlier_checkpoint": layer.reused,
                        "mean_test_mse": {
                            group: means[(r.checkpoint.name, layer.layer, group)] for group in dict.fromkeys(groups)
                        },
                    }
                    for layer in r.layers
                },
            }
            for r in results
        ],
        "mse_over_training": "written" if over_training else "skipped: needs >= 2 checkpoints with distinct steps",
        "files": files,
    }
