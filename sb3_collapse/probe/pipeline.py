"""The probe's two commands as library functions: record rollouts, and probe checkpoints into an output folder."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from stable_baselines3.common.utils import get_device

from sb3_collapse.drqv2.checks import check_device
from sb3_collapse.errors import ProbeError
from sb3_collapse.paper import PAPER
from sb3_collapse.probe.checkpoints import (
    Checkpoint,
    checkpoint_labels,
    identify_algorithm,
    load_checkpoint,
    read_saved_data,
)
from sb3_collapse.probe.probing import (
    MIN_EPISODES,
    CheckpointProbe,
    ProbeSettings,
    probe_checkpoint,
    split_by_episode,
)
from sb3_collapse.probe.report import (
    BY_LAYER_PLOT,
    CSV_NAME,
    OVER_TRAINING_PLOT,
    SUMMARY_NAME,
    format_table,
    group_means,
    plot_mse_by_layer,
    plot_mse_over_training,
    staged_output,
    write_csv,
    write_json,
)
from sb3_collapse.probe.rollouts import Rollouts, check_record_arguments, record_rollouts, resolve_env_config

ROLLOUTS_NAME = "rollouts.npz"
SELF_RECORDED_NOTE = (
    "the rollouts were recorded by the first probed checkpoint itself; the paper's protocol (Section 4.1) records "
    "them once from a well-performing agent (final return >= {success:g}) and probes every checkpoint on them: "
    "record with `python -m sb3_collapse.probe record GOOD.zip --out rollouts.npz` and pass `--rollouts "
    "rollouts.npz` (library: `rollouts_path`), or use `python -m sb3_collapse.probe sweep` on a sweep folder"
)
"""What the probe says when it records its rollouts from the checkpoint it probes (today's default)."""


@dataclass
class RecordOptions:
    """
    How to record rollouts (``None`` settings come from the checkpoint, else ``make_dmc_env``'s defaults).

    :param env: dm_control task, e.g. ``"walker-walk"``
    :param episodes: episodes to record
    :param max_steps: cap on agent steps per episode (``None``: the task's time limit)
    :param seed: seed of the env and of the action noise
    :param deterministic: the policy's deterministic action (else its own exploration)
    :param noise_std: std of Gaussian noise added to the actions
    :param action_repeat: frames per agent step
    :param frame_stack: stacked frames per observation
    :param size: image size in pixels
    :param camera_id: camera of the renders
    """

    env: str | None = None
    episodes: int = 20
    max_steps: int | None = None
    seed: int = 0
    deterministic: bool = True
    noise_std: float = 0.0
    action_repeat: int | None = None
    frame_stack: int | None = None
    size: int | None = None
    camera_id: int | None = None

    def check(self) -> None:
        """:raises ProbeError: for a bad option, before anything is loaded or recorded"""
        check_record_arguments(self.episodes, self.max_steps, self.noise_std)


def record(checkpoint: Checkpoint, options: RecordOptions, progress: bool = True) -> Rollouts:
    """
    Record rollouts of a checkpoint's agent.

    :param checkpoint: the agent
    :param options: what to record
    :param progress: show a progress bar
    :return: the rollouts
    """
    env_config = resolve_env_config(
        checkpoint.env_config,
        task_id=options.env,
        action_repeat=options.action_repeat,
        frame_stack=options.frame_stack,
        size=options.size,
        camera_id=options.camera_id,
    )
    return record_rollouts(
        checkpoint.model,
        env_config,
        episodes=options.episodes,
        seed=options.seed,
        deterministic=options.deterministic,
        noise_std=options.noise_std,
        max_steps=options.max_steps,
        progress=progress,
        metadata={"checkpoint": str(checkpoint.path), "checkpoint_num_timesteps": checkpoint.num_timesteps},
    )


def record_to_file(
    checkpoint_path: str | Path,
    out: str | Path,
    options: RecordOptions,
    overwrite: bool = False,
    device: str = "auto",
    progress: bool = True,
) -> Path:
    """
    ``python -m sb3_collapse.probe record``: record rollouts and save them (atomically).

    :param checkpoint_path: the agent's checkpoint
    :param out: the ``.npz`` to write
    :param options: what to record
    :param overwrite: replace an existing file
    :param device: where the networks run
    :param progress: show a progress bar
    :return: the file written
    :raises ProbeError: for bad input
    """
    out = Path(out)
    if out.is_dir():
        raise ProbeError(f"out {out} is a folder; give the path of the .npz file to write.", parameter="out")
    if out.exists() and not overwrite:
        raise ProbeError(f"{out} exists: pass `overwrite=True` or another `out`.", parameter="out")
    options.check()
    check_device(device)
    checkpoint = load_checkpoint(checkpoint_path, device=get_device(device))
    rollouts = record(checkpoint, options, progress)
    path = rollouts.save(out)
    print(
        f"Saved {len(rollouts)} agent steps of {rollouts.n_episodes} episodes of {rollouts.env_config['task_id']} "
        f"to {path}"
    )
    return path


def check_checkpoint_files(paths: Sequence[str | Path], same_observations: bool = True) -> None:
    """
    Check, before any long work, that every path is an SB3 checkpoint of a probe-able algorithm, and that they all
    take observations of one shape (the same rollouts feed them all: another image size or frame stack cannot be
    probed with them).

    :param paths: the checkpoints
    :param same_observations: check that they all take observations of one shape
    :raises ProbeError: naming the first bad file, or two checkpoints whose observations differ
    """
    if not paths:
        raise ProbeError("Give at least one checkpoint (.zip).")
    shapes: dict[tuple, str | Path] = {}
    for path in paths:
        data = read_saved_data(path)
        identify_algorithm(data, path)
        shape = (data.get("observation_space") or {}).get("_shape")
        if shape is not None:
            shapes.setdefault(tuple(shape), path)
    if same_observations and len(shapes) > 1:
        (first, first_path), (other, other_path) = list(shapes.items())[:2]
        raise ProbeError(
            f"{first_path} takes observations of shape {first} and {other_path} of shape {other}: the probe feeds "
            "every checkpoint the same rollouts, so probe checkpoints of another image size or frame stack in a run "
            "of their own.",
            parameter="checkpoints",
        )


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
    ``python -m sb3_collapse.probe``: probe checkpoints and write ``probe.csv``, ``summary.json`` and the plots
    into ``out`` (only when every checkpoint succeeded; see :func:`~sb3_collapse.probe.report.staged_output`).

    Without ``rollouts_path``, rollouts of the first checkpoint are recorded first (``record_options``) and
    saved to ``<out>/rollouts.npz`` for reuse.

    :param checkpoint_paths: the checkpoints
    :param out: the output folder
    :param settings: the probe's settings
    :param rollouts_path: recorded rollouts, or ``None`` to record them
    :param record_options: how to record (when ``rollouts_path`` is ``None``)
    :param overwrite: replace a previous run's outputs in ``out``
    :param command: the command line, stored in the summary
    :return: the summary (as written to ``summary.json``)
    :raises ProbeError: for bad input
    """
    started = time.perf_counter()
    settings.validate()
    check_checkpoint_files(checkpoint_paths)
    labels = checkpoint_labels(list(checkpoint_paths))
    device = get_device(settings.device)
    out = Path(out)
    if rollouts_path is None:
        record_options = record_options or RecordOptions()
        record_options.check()
        if record_options.episodes < MIN_EPISODES:  # checked before recording: the split needs them
            raise ProbeError(
                f"episodes must be >= {MIN_EPISODES} to split them into training, validation and test episodes, "
                f"got {record_options.episodes}.",
                parameter="episodes",
            )
        if (out / ROLLOUTS_NAME).exists() and not overwrite:
            raise ProbeError(
                f"{out / ROLLOUTS_NAME} exists: reuse it with `rollouts`, or pass `overwrite=True`.", parameter="out"
            )
    self_recorded = rollouts_path is None
    with staged_output(out, overwrite=overwrite) as staged:
        if rollouts_path is None:
            first = load_checkpoint(checkpoint_paths[0], device=device)
            rollouts = record(first, record_options, settings.progress)
            rollouts.save(staged.path(ROLLOUTS_NAME))  # moved into out with the other files, only on success
            rollouts_path = out / ROLLOUTS_NAME
            print(
                f"Recorded {len(rollouts)} agent steps of {rollouts.n_episodes} episodes to {rollouts_path}", flush=True
            )
            print(f"Note: {SELF_RECORDED_NOTE.format(success=PAPER.success_return)}.", flush=True)
            del first
        else:
            rollouts = Rollouts.load(rollouts_path)
        split = split_by_episode(rollouts.episode_ids, settings.fractions, settings.split_seed)
        results: list[CheckpointProbe] = []
        reuse: dict = {}  # cnn0 (the normalized pixels) is probed once for checkpoints that normalize alike
        for path, label in zip(checkpoint_paths, labels):
            checkpoint = load_checkpoint(path, device=device)
            checkpoint.label = label
            print(
                f"Probing {checkpoint.path} ({checkpoint.algorithm}, {checkpoint.num_timesteps:,} agent steps)",
                flush=True,
            )
            result = probe_checkpoint(checkpoint, rollouts, split, settings, reuse)
            result.checkpoint.model = None  # type: ignore[assignment]  # free the networks
            results.append(result)
            print(format_table(result.rows), flush=True)

        rows = [row for result in results for row in result.rows]
        write_csv(rows, staged.path(CSV_NAME))
        plot_mse_by_layer(rows, staged.path(BY_LAYER_PLOT))
        over_training = plot_mse_over_training(rows, staged.path(OVER_TRAINING_PLOT))
        summary = _summary(results, rows, rollouts, rollouts_path, split, settings, over_training, command)
        if self_recorded:
            summary["rollouts"]["note"] = SELF_RECORDED_NOTE.format(success=PAPER.success_return)
        summary["total_seconds"] = round(time.perf_counter() - started, 1)
        write_json(summary, staged.path(SUMMARY_NAME))
        files = staged.commit()
    print("Wrote " + ", ".join(str(f) for f in files))
    return summary


def _summary(
    results: list[CheckpointProbe],
    rows: list[dict[str, Any]],
    rollouts: Rollouts,
    rollouts_path: str | Path,
    split: Any,
    settings: ProbeSettings,
    over_training: bool,
    command: Sequence[str] | None,
) -> dict[str, Any]:
    means = group_means(rows)
    names, groups, _ = rollouts.targets()
    files = [CSV_NAME, BY_LAYER_PLOT] + ([OVER_TRAINING_PLOT] if over_training else []) + [SUMMARY_NAME]
    return {
        "complete": True,
        "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "command": list(command) if command is not None else None,
        "settings": {k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(settings).items()},
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
        "split": {
            "n_train": split.n_train,
            "n_validation": split.n_validation,
            "n_test": split.n_test,
            "episodes": split.episodes,
        },
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
        "mse_over_training": "written"
        if over_training
        else "skipped: needs >= 2 checkpoints with distinct training steps",
        "files": files,
    }
