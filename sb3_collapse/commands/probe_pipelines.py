"""The probe's folder pipelines (``python -m sb3_collapse.probe run|record|sweep|film|health``): each reads
checkpoints or a sweep folder, computes with :mod:`sb3_collapse.probe`, draws with :mod:`sb3_collapse.report` and
writes its output folder (staged: all files or none)."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import torch as th
from stable_baselines3.common.utils import get_device

from sb3_collapse.common.progress import progress_bar
from sb3_collapse.drqv2.checks import check_device
from sb3_collapse.errors import InputError
from sb3_collapse.paper import PAPER
from sb3_collapse.probe import probing
from sb3_collapse.probe.checkpoints import checkpoint_labels, load_checkpoint
from sb3_collapse.probe.film import FILM_FRAMES, FILM_SIZE, film_episode
from sb3_collapse.probe.health import HEALTH_COLUMNS, HealthSettings, checkpoint_health, health_checkpoint_paths
from sb3_collapse.probe.pipeline import (
    ROLLOUTS_NAME,
    RecordOptions,
    check_checkpoint_files,
    record,
    record_agents,
    summary_head,
)
from sb3_collapse.probe.probing import ProbeSettings
from sb3_collapse.probe.rollouts import Rollouts, resolve_env_config
from sb3_collapse.protocol import (
    FIGURE2_PNG,
    FINAL_MODEL,
    PROBE_SUMMARY_JSON,
    SNAPSHOTS_DIR,
    SWEEP_PROBE_DIR,
    TABLES_1_6_CSV,
    snapshot_files,
    write_json_atomically,
)
from sb3_collapse.report import figure2, probe_outputs
from sb3_collapse.report.collapse_figure import agent_class
from sb3_collapse.report.film import STRIP_EVERY_FRAMES, plot_filmstrip, write_actions_csv, write_gif
from sb3_collapse.report.health import plot_health
from sb3_collapse.report.loading import Sweep, Trial, load_sweep
from sb3_collapse.report.statistics import budget_frames
from sb3_collapse.report.tables import write_csv
from sb3_collapse.staged_outputs import StagedOutputs

CSV_NAME = "probe.csv"
SUMMARY_NAME = PROBE_SUMMARY_JSON
BY_LAYER_PLOT = "mse_by_layer.png"
OVER_TRAINING_PLOT = "mse_over_training.png"
PROBE_FILES = (CSV_NAME, SUMMARY_NAME, BY_LAYER_PLOT, OVER_TRAINING_PLOT)
"""The files a probe run writes (``summary.json`` last: its presence marks a complete run)."""
TABLES_MD = "tables_1_6.md"
SWEEP_FILES = (FIGURE2_PNG, TABLES_1_6_CSV, TABLES_MD, CSV_NAME, ROLLOUTS_NAME, SUMMARY_NAME)
"""Every file ``probe sweep`` writes (``summary.json`` last)."""
FILMSTRIP_PNG = "filmstrip.png"
ACTIONS_CSV = "actions.csv"
FILM_FILES = (FILMSTRIP_PNG, "*.gif", ACTIONS_CSV)
"""What ``film`` writes (``actions.csv`` last)."""
HEALTH_CSV = "health.csv"
HEALTH_JSON = "health.json"
HEALTH_PNG = "health_{network}.png"
HEALTH_FILES = (HEALTH_CSV, "health_*.png", HEALTH_JSON)
"""What ``health`` writes (``health.json`` last: its presence marks a complete run)."""


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
    :raises InputError: for bad input
    """
    out = Path(out)
    if out.is_dir():
        raise InputError(f"out {out} is a folder; give the path of the .npz file to write.", parameter="out")
    if out.exists() and not overwrite:
        raise InputError(f"{out} exists: pass `overwrite=True` or another `out`.", parameter="out")
    options.check()
    check_device(device)
    checkpoint = load_checkpoint(checkpoint_path, device=get_device(device))
    rollouts = record(checkpoint, options, progress)
    path, task = rollouts.save(out), rollouts.env_config["task_id"]
    print(f"Saved {len(rollouts)} agent steps of {rollouts.n_episodes} episodes of {task} to {path}")
    return path


SELF_RECORDED_NOTE = (
    "the rollouts were recorded by the first probed checkpoint itself; the paper's protocol (Section 4.1) records "
    "them once from a well-performing agent (final return >= {success:g}) and probes every checkpoint on them: "
    "record with `python -m sb3_collapse.probe record GOOD.zip --out rollouts.npz` and pass `--rollouts "
    "rollouts.npz` (library: `rollouts_path`), or use `python -m sb3_collapse.probe sweep` on a sweep folder"
)
"""What the probe says when it records its rollouts from the checkpoint it probes."""


def staged_output(out: str | Path, overwrite: bool = False) -> StagedOutputs:
    """:return: the probe's staged output folder ``out`` (moved in on success, ``summary.json`` last)"""
    return StagedOutputs(out, PROBE_FILES, SUMMARY_NAME, overwrite=overwrite, error=InputError)


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
        split = probing.split_by_episode(rollouts.episode_ids, settings.fractions, settings.split_seed)
        results = _probe_checkpoints(checkpoint_paths, labels, device, rollouts, split, settings)
        rows = [row for result in results for row in result.rows]
        warnings = probing.probe_warnings(rollouts, split, rows, settings)
        probe_outputs.report_warnings(warnings)
        write_csv(rows, list(rows[0]), staged.path(CSV_NAME))
        probe_outputs.plot_mse_by_layer(rows, staged.path(BY_LAYER_PLOT), warnings)
        over_training = probe_outputs.plot_mse_over_training(rows, staged.path(OVER_TRAINING_PLOT))
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
    if record_options.episodes < probing.MIN_EPISODES:  # the split needs them
        raise InputError(
            f"episodes must be >= {probing.MIN_EPISODES} to split them into training, validation and test episodes, "
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
    split: probing.EpisodeSplit,
    settings: ProbeSettings,
) -> list[probing.CheckpointProbe]:
    """Probe each checkpoint in turn on ``rollouts``, printing its table; the networks are freed after each."""
    results: list[probing.CheckpointProbe] = []
    reuse: dict = {}  # cnn0 (the normalized pixels) is probed once for checkpoints that normalize alike
    for path, label in zip(checkpoint_paths, labels):
        checkpoint = load_checkpoint(path, device=device)
        checkpoint.label = label
        print(
            f"Probing {checkpoint.path} ({checkpoint.algorithm}, {checkpoint.num_timesteps:,} agent steps)", flush=True
        )
        result = probing.probe_checkpoint(checkpoint, rollouts, split, settings, reuse)
        result.checkpoint.model = None  # type: ignore[assignment]  # free the networks
        results.append(result)
        print(probe_outputs.format_table(result.rows), flush=True)
    return results


def _summary(
    results: list[probing.CheckpointProbe],
    rows: list[dict[str, Any]],
    rollouts: Rollouts,
    rollouts_path: str | Path,
    split: probing.EpisodeSplit,
    settings: ProbeSettings,
    over_training: bool,
    command: Sequence[str] | None,
) -> dict[str, Any]:
    means = probe_outputs.group_means(rows)
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


def split_agents(
    trials: Sequence[Trial], success_return: float = PAPER.success_return, failure_return: float = PAPER.failure_return
) -> tuple[list[Trial], list[Trial]]:
    """:return: ``(well, poor)`` finished trials (:func:`agent_class`), each by decreasing final return"""
    ranked = sorted((t for t in trials if t.finished and len(t.returns)), key=lambda t: (-t.final_return, t.seed))
    classes = [agent_class(t.final_return, success_return, failure_return) for t in ranked]
    well, poor = figure2.ROWS
    return [t for t, c in zip(ranked, classes) if c == well], [t for t, c in zip(ranked, classes) if c == poor]


def probe_sweep(
    sweep_dir: str | Path,
    task: str,
    variant: str = "drqv2",
    out: str | Path | None = None,
    settings: ProbeSettings | None = None,
    rollouts_path: str | Path | None = None,
    record_options: RecordOptions | None = None,
    success_return: float = PAPER.success_return,
    failure_return: float = PAPER.failure_return,
    overwrite: bool = False,
    command: Sequence[str] | None = None,
    jobs: int = 1,
) -> dict[str, Any]:
    """
    Figure 2 and Tables 1-6 of one task and variant of a sweep, written into ``out`` only when everything succeeded;
    a damaged trial is listed (``damaged``), not probed. The steps: docs/figures.md.

    :param sweep_dir: the sweep folder
    :param task: its task folder, e.g. ``"walker-walk"``
    :param variant: its variant folder
    :param out: the output folder (default ``<sweep>/probe/<task>_<variant>``)
    :param settings: the probe's settings
    :param rollouts_path: rollouts to probe on (``None``: record them from the best well-performing seed, or pool
        those of the ``record_options.pool_agents`` best)
    :param record_options: how to record
    :param success_return: final return of a well-performing agent, at least
    :param failure_return: final return of a poorly performing agent, below
    :param overwrite: replace a previous run's outputs in ``out``
    :param command: the command line, for the summary
    :param jobs: checkpoints probed at once
    :return: the summary (as written to ``summary.json``)
    :raises InputError: for bad input (nothing written then)
    """
    started = time.perf_counter()
    settings = settings or ProbeSettings()
    record_options = record_options or RecordOptions()
    sweep, agents, files = _sweep_agents(
        sweep_dir, task, variant, settings, rollouts_path, record_options, success_return, failure_return, jobs
    )
    out = Path(sweep_dir) / SWEEP_PROBE_DIR.format(task=task, variant=variant) if out is None else Path(out)
    with StagedOutputs(out, SWEEP_FILES, SUMMARY_NAME, overwrite=overwrite, error=InputError) as staged:
        rollouts, recorded_from = _sweep_rollouts(agents, files, rollouts_path, record_options, settings, staged)
        rows, warnings = _probe_agents(agents, files, rollouts, settings, jobs)
        probe_outputs.report_warnings(warnings)
        columns = _write_figure2(rows, rollouts, agents, task, variant, staged, warnings)
        summary = {
            "complete": True,
            "created": datetime.now(UTC).isoformat(timespec="seconds"),
            "command": list(command) if command is not None else None,
            "sweep": str(sweep_dir),
            "task": task,
            "variant": variant,
            "success_return": success_return,
            "failure_return": failure_return,
            "agents": [
                {"seed": t.seed, "row": which, "final_return": t.final_return, "checkpoints": len(files[t.seed])}
                for t, which in agents
            ],
            "not_probed": [
                {"seed": t.seed, "final_return": t.final_return} for t in sweep.finished if t.seed not in files
            ],
            "unfinished": [t.seed for t in sweep.unfinished],
            "damaged": [{"seed": t.seed, "reason": t.reason} for t in sweep.unfinished if t.reason],
            "rollouts": {"recorded_from": recorded_from, "samples": len(rollouts), "episodes": rollouts.n_episodes},
            "columns": {title: list(targets) for title, targets in columns},
            "settings": {k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(settings).items()},
            "jobs": jobs,
            "warnings": warnings,
            "total_seconds": round(time.perf_counter() - started, 1),
        }
        write_json_atomically(staged.path(SUMMARY_NAME), summary)
        written = staged.commit()
    for damaged in summary["damaged"]:
        print(f"Not probed: seed {damaged['seed']}: {damaged['reason']}")
    print("Wrote " + ", ".join(str(f) for f in written))
    return summary


def _sweep_rollouts(
    agents: list[tuple[Trial, str]],
    files: dict[int, list[Path]],
    rollouts_path: str | Path | None,
    record_options: RecordOptions,
    settings: ProbeSettings,
    staged: StagedOutputs,
) -> tuple[Rollouts, str]:
    """:return: the rollouts to probe on (``rollouts_path``, or recorded from the final model or last checkpoint of
    the best agent, or of the ``record_options.pool_agents`` best, pooled), and where they come from"""
    if rollouts_path is not None:
        return Rollouts.load(rollouts_path), str(rollouts_path)
    wells = [trial for trial, which in agents if which == figure2.ROWS[0]][: record_options.pool_agents]
    sources = [t.path / FINAL_MODEL if (t.path / FINAL_MODEL).exists() else files[t.seed][-1] for t in wells]
    rollouts = record_rollouts(sources, get_device(settings.device), record_options, settings, staged)
    return rollouts, ", ".join(map(str, sources))


def _probe_agents(
    agents: list[tuple[Trial, str]],
    files: dict[int, list[Path]],
    rollouts: Rollouts,
    settings: ProbeSettings,
    jobs: int,
) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """:return: the probe's rows of every checkpoint of every agent, with its agent, row and final return, and the
    probe's warnings (of each distinct split, :func:`~sb3_collapse.probe.probing.agent_split`)"""
    splits = {trial.seed: probing.agent_split(rollouts.episode_ids, settings, trial.seed) for trial, _ in agents}
    work = [(trial, which, path) for trial, which in agents for path in files[trial.seed]]
    labels = [f"seed_{trial.seed}/{path.stem}" for trial, _, path in work]
    paths, work_splits = [path for _, _, path in work], [splits[trial.seed] for trial, _, _ in work]
    per_checkpoint = probing.probe_each_checkpoint(paths, labels, rollouts, work_splits, settings, jobs)
    for (trial, which, _), result_rows in zip(work, per_checkpoint):
        for row in result_rows:
            row.update(agent=f"seed {trial.seed}", agent_row=which, final_return=trial.final_return)
    rows = [row for result_rows in per_checkpoint for row in result_rows]
    if not settings.split_per_agent:  # one split for every agent
        return rows, probing.probe_warnings(rollouts, work_splits[0], rows, settings)
    warnings: list[dict[str, Any]] = []
    for seed, split in splits.items():  # each agent's split: the warnings of the rows probed on it, once each
        for warning in probing.probe_warnings(
            rollouts, split, [r for r in rows if r["agent"] == f"seed {seed}"], settings
        ):
            if warning not in warnings:
                warnings.append(warning)
    return rows, warnings


def _sweep_agents(
    sweep_dir: str | Path,
    task: str,
    variant: str,
    settings: ProbeSettings,
    rollouts_path: str | Path | None,
    record_options: RecordOptions,
    success_return: float,
    failure_return: float,
    jobs: int,
) -> tuple[Sweep, list[tuple[Trial, str]], dict[int, list[Path]]]:
    """:return: the sweep, its agents with their row of Figure 2 (the well-performing first) and seed -> snapshots,
    :func:`probe_sweep`'s arguments checked before any work (:raises InputError: naming the bad one)"""
    settings.validate()
    if isinstance(jobs, bool) or not isinstance(jobs, int) or jobs < 1:
        raise InputError(f"jobs must be an integer >= 1, got {jobs!r}.", parameter="jobs")
    if not failure_return <= success_return:
        raise InputError(
            f"failure_return must be <= success_return, got {failure_return:g} and {success_return:g}.",
            parameter="failure_return",
        )
    try:
        sweep = load_sweep(sweep_dir, tasks=[task], variants=[variant], progress=False)
    except InputError as error:
        raise InputError(
            str(error), parameter=error.parameter if error.parameter != "sweep" else "sweep_dir"
        ) from error
    well, poor = split_agents(sweep.finished, success_return, failure_return)
    if not well and not poor:
        finals = ", ".join(f"seed {t.seed}: {t.final_return:.0f}" for t in sweep.finished) or "no finished trial"
        raise InputError(
            f"{task} / {variant} has no well-performing (final return >= {success_return:g}) nor poorly performing "
            f"(< {failure_return:g}) finished trial ({finals}); lower success_return or raise failure_return.",
            parameter="success_return",
        )
    agents = [(trial, figure2.ROWS[0]) for trial in well] + [(trial, figure2.ROWS[1]) for trial in poor]
    files = {trial.seed: snapshot_files(trial.path) for trial, _ in agents}
    lacking = [t for t, _ in agents if not files[t.seed]]
    if lacking:
        raise InputError(
            f"no {SNAPSHOTS_DIR}/*.zip in {', '.join(str(t.path) for t in lacking)}: train the trials with "
            "--snapshots (TrainConfig.snapshots) to probe them over training."
        )
    if rollouts_path is None:
        if not well:
            raise InputError(
                f"{task} / {variant} has no well-performing trial (final return >= {success_return:g}) to record "
                "rollouts from: pass rollouts_path (python -m sb3_collapse.probe record GOOD.zip).",
                parameter="rollouts_path",
            )
        checked_record_options(record_options, pooled=True)
        if record_options.pool_agents > len(well):
            raise InputError(
                f"pool_agents={record_options.pool_agents} but {task} / {variant} has {len(well)} well-performing "
                f"trial(s) (final return >= {success_return:g}) to record from: pass at most {len(well)}.",
                parameter="pool_agents",
            )
    return sweep, agents, files


def _write_figure2(
    rows: list[dict[str, Any]],
    rollouts: Rollouts,
    agents: Sequence[tuple[Trial, str]],
    task: str,
    variant: str,
    staged: StagedOutputs,
    warnings: Sequence[dict[str, Any]] = (),
) -> list[tuple[str, tuple[str, ...]]]:
    """Write Figure 2 (marking what ``warnings`` name), Tables 1-6 and ``probe.csv`` into ``staged``; :return: Figure
    2's columns"""
    names, groups, _ = rollouts.targets()
    columns = figure2.figure2_columns(task, names, groups)
    curves = figure2.panel_curves(rows, {f"seed {t.seed}": which for t, which in agents}, columns)
    well = sum(which == figure2.ROWS[0] for _, which in agents)
    described = f"well-performing: {well}, poorly performing: {len(agents) - well}"
    flat = [title for title, targets in columns if probe_outputs.warned(warnings, "targets") & set(targets)]
    title = f"{task} / {variant}: OMP probing over training ({described})"
    figure2.plot_figure2(curves, staged.path(FIGURE2_PNG), title, flat, probe_outputs.warned(warnings, "layers"))
    table_rows = figure2.stage_table_rows(curves, budget_frames([trial for trial, _ in agents]))
    if table_rows:
        write_csv(table_rows, list(table_rows[0]), staged.path(TABLES_1_6_CSV))
    staged.path(TABLES_MD).write_text(figure2.stage_tables_markdown(table_rows))
    write_csv(rows, list(rows[0]), staged.path(CSV_NAME))
    return columns


def film_to_folder(
    checkpoint_paths: Sequence[str | Path],
    out: str | Path,
    frames: int = FILM_FRAMES,
    size: int = FILM_SIZE,
    every_frames: int = STRIP_EVERY_FRAMES,
    seeds: Sequence[int] = (0,),
    env: str | None = None,
    device: str = "auto",
    overwrite: bool = False,
    progress: bool = True,
) -> list[Path]:
    """
    ``python -m sb3_collapse.probe film``: film every checkpoint from each episode seed into ``out`` (all or nothing).

    :param checkpoint_paths: the agents (full models or snapshots)
    :param out: the output folder
    :param frames: environment frames per film
    :param size: render size of the film, in pixels
    :param every_frames: frames between two pictures of the strip
    :param seeds: episode seeds (one row per checkpoint and seed)
    :param env: the task, when a checkpoint does not say
    :param device: where the networks run
    :param overwrite: replace a previous film in ``out``
    :param progress: show a progress bar
    :return: the written files
    :raises InputError: for bad input
    """
    for name, value, low in (("frames", frames, 1), ("size", size, 16), ("every_frames", every_frames, 1)):
        if value < low:
            raise InputError(f"{name} must be >= {low}, got {value}.", parameter=name)
    if not seeds:
        raise InputError("seeds must hold at least one episode seed.", parameter="seeds")
    check_checkpoint_files(checkpoint_paths, same_observations=False)  # each films in its own env
    check_device(device)
    labels = checkpoint_labels(list(checkpoint_paths))
    films = []
    with StagedOutputs(out, FILM_FILES, ACTIONS_CSV, overwrite=overwrite, error=InputError) as staged:
        for path, label in progress_bar(zip(checkpoint_paths, labels), "filming", "checkpoint", progress):
            checkpoint = load_checkpoint(path, device=get_device(device))
            env_config = resolve_env_config(checkpoint.env_config, task_id=env)
            for seed in seeds:
                name = f"{label} ({checkpoint.frames:,} training frames), episode seed {seed}"
                films.append(film_episode(checkpoint.model, env_config, name, frames, size, seed))
                write_gif(films[-1], staged.path(f"{label.replace('/', '_')}_seed{seed}.gif"))
        task = films[0].task
        plot_filmstrip(
            films,
            staged.path(FILMSTRIP_PNG),
            every_frames,
            f"{task}: frames 0-{frames} of an episode (every {every_frames}th), and the actions taken",
        )
        write_actions_csv(films, staged.path(ACTIONS_CSV))
        written = staged.commit()
    print("Wrote " + ", ".join(str(f) for f in written))
    return written


def health_to_folder(
    checkpoint_paths: Sequence[str | Path],
    out: str | Path,
    settings: HealthSettings | None = None,
    rollouts_path: str | Path | None = None,
    record_options: RecordOptions | None = None,
    overwrite: bool = False,
    command: Sequence[str] | None = None,
) -> list[Path]:
    """
    ``python -m sb3_collapse.probe health``: the health metrics of checkpoints (a run folder: its snapshots) on one
    observation set, written into ``out`` only when every checkpoint was measured: ``health.csv`` (long format,
    :data:`~sb3_collapse.probe.health.HEALTH_COLUMNS`), ``health_<network>.png`` per network and ``health.json``.

    :param checkpoint_paths: SB3 zips of DrQv2, TD3, DDPG or SAC, DrQv2 snapshots, or run folders with snapshots
    :param out: the output folder
    :param settings: the metrics, networks, observations and device (``None``: the defaults)
    :param rollouts_path: a rollouts file, or ``None``: the first checkpoint's own rollouts, recorded
    :param record_options: how to record them
    :param overwrite: replace a previous run's outputs in ``out``
    :param command: the command line, stored in ``health.json``
    :return: the written files
    :raises InputError: for bad input (nothing written)
    """
    started = time.perf_counter()
    settings = settings or HealthSettings()
    paths = health_checkpoint_paths(checkpoint_paths)
    if not paths:
        raise InputError("Give at least one checkpoint (.zip) or a run folder with snapshots.", parameter="checkpoints")
    labels = checkpoint_labels(list(paths))
    with StagedOutputs(out, HEALTH_FILES, HEALTH_JSON, overwrite=overwrite, error=InputError) as staged:
        rows, measured = checkpoint_health(paths, settings, rollouts_path, record_options, labels)
        write_csv(rows, list(HEALTH_COLUMNS), staged.path(HEALTH_CSV))
        count = len(measured["checkpoints"])
        what = (
            f"{count} checkpoints over training"
            if measured["series"]
            else ", ".join(c["checkpoint"] for c in measured["checkpoints"])
        )
        for network in measured["networks"]:
            title = f"{network} health of {what}\non {measured['inputs']}"
            plot_health(rows, network, staged.path(HEALTH_PNG.format(network=network)), measured["series"], title)
        summary = {
            "complete": True,
            "created": datetime.now(UTC).isoformat(timespec="seconds"),
            "command": list(command) if command is not None else None,
            **measured,
            "seconds": round(time.perf_counter() - started, 1),
        }
        write_json_atomically(staged.path(HEALTH_JSON), summary)
        written = staged.commit()
    print("Wrote " + ", ".join(str(path) for path in written))
    return written
