"""
The collapse metrics of Figures 4, 8, 9 on one fixed observation set, after training.

Section 5.1 of the paper computes the numerical rank "of the matrix of MLP activations H, as defined in Figure
1", and the correlation and zeros of the same activations; Figure 1's H holds the activations of the probing
samples ("All the samples in three sets are collected from well-performing agents", Section 4.1). So every snapshot
(encoder and actor at each evaluation, :func:`~sb3_collapse.protocol.snapshot_files`) of the picked agents is run
on the same observations: by default one set per task, the rollouts that ``python -m sb3_collapse.probe sweep``
recorded from the well-performing agent of the highest final return of the baseline variant
(:attr:`FixedInputSettings.rollouts_variant`, ``drqv2``: ``<sweep>/probe/<task>_drqv2/rollouts.npz``), for every
variant of the task, or a rollouts file given by the user; agents of every variant are then compared on the same
inputs. (``rollouts_variant=None`` reads each variant's own rollouts instead: another set per variant.) A seeded
subset of :attr:`FixedInputSettings.fixed_samples` observations keeps the cost bounded (all of them with
``fixed_samples=None``).
"""

from __future__ import annotations

import csv
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch as th
from stable_baselines3.common.utils import get_device
from tqdm.auto import tqdm

from sb3_collapse.drqv2.checks import check_device
from sb3_collapse.errors import ParameterError, ProbeError, ReportError
from sb3_collapse.monitoring import collect_activations, layer_metrics, unit_count
from sb3_collapse.paper import PAPER, metric_tag
from sb3_collapse.probe.checkpoints import load_checkpoint
from sb3_collapse.probe.pipeline import ROLLOUTS_NAME
from sb3_collapse.probe.rollouts import Rollouts
from sb3_collapse.protocol import LEGACY_SNAPSHOTS_DIR, SNAPSHOTS_DIR, SWEEP_PROBE_DIR, snapshot_files
from sb3_collapse.report.collapse_figure import (
    FIGURE4_LAYERS,
    AgentMetrics,
    AgentPick,
    agent_metrics,
)
from sb3_collapse.report.headline import BASELINE_VARIANT
from sb3_collapse.report.loading import Trial

FIXED_SAMPLES = 2048
"""Observations of the fixed set by default: more than the 1024 units of ``mlp1`` and ``mlp2``, so that their
numerical rank is not bounded by the number of inputs (the online batch of 512 bounds it at 512)."""


@dataclass
class FixedInputSettings:
    """
    How Figures 4, 8, 9 are computed on the fixed observation set, and how their agents are picked.

    :param pick_seed: seed of the random pick of the three agents
        (:func:`~sb3_collapse.report.collapse_figure.pick_paper_agents`)
    :param failure_return: a final return below it is poorly performing (``PAPER.failure_return``; the
        well-performing bound is the report's ``success_return``)
    :param rollouts: the rollouts file of the observations, for the tasks it was recorded on (``None``: those of
        ``rollouts_variant``)
    :param rollouts_variant: the variant whose rollouts (``<sweep>/probe/<task>_<variant>/rollouts.npz``, written
        by ``python -m sb3_collapse.probe sweep`` from its well-performing seed of the highest final return) are the
        fixed set of every variant of the task (the baseline, ``drqv2``); ``None``: each variant's own rollouts
    :param fixed_samples: observations drawn from the rollouts (without replacement, with ``sample_seed``;
        ``None``: all)
    :param sample_seed: seed of that draw
    :param device: where the checkpoints run (``"auto"``: CUDA when available)
    :param batch_size: observations per forward pass
    :param layers: the layers measured and drawn
    """

    pick_seed: int = 0
    failure_return: float = PAPER.failure_return
    rollouts: str | Path | None = None
    rollouts_variant: str | None = BASELINE_VARIANT
    fixed_samples: int | None = FIXED_SAMPLES
    sample_seed: int = 0
    device: str = "auto"
    batch_size: int = 256
    layers: tuple[str, ...] = FIGURE4_LAYERS

    def validate(self) -> None:
        """:raises ReportError: on a setting out of range, or a rollouts file that does not exist"""
        if self.fixed_samples is not None and self.fixed_samples < 2:
            raise ReportError(
                f"fixed_samples must be >= 2 observations, got {self.fixed_samples}.", parameter="fixed_samples"
            )
        if self.batch_size < 1:
            raise ReportError(f"batch_size must be >= 1, got {self.batch_size}.", parameter="batch_size")
        if self.rollouts is not None and not Path(self.rollouts).is_file():
            raise ReportError(
                f"rollouts {self.rollouts} is not a file; give the rollouts.npz of python -m sb3_collapse.probe sweep "
                "(or of probe record).",
                parameter="rollouts",
            )
        try:
            check_device(self.device)
        except ParameterError as error:
            raise ReportError(str(error), parameter="device") from error


@dataclass
class FixedInputs:
    """
    The fixed observation set.

    :param observations: ``(n, *obs_shape)`` observations as the env gives them (uint8)
    :param indices: ``(n,)`` their rows in the rollouts file, increasing
    :param source: the rollouts file
    :param total: observations in the file
    :param episodes: episodes in the file
    :param recorded_from: the checkpoint the rollouts were recorded from (their metadata), ``None`` if unknown
    :param task: the task the rollouts were recorded on (``env_config["task_id"]``), ``None`` if unknown
    :param recorded_frames: the training frames of that checkpoint (its agent steps x the action repeat), ``None``
        if unknown
    """

    observations: np.ndarray
    indices: np.ndarray
    source: Path
    total: int
    episodes: int
    recorded_from: str | None = None
    task: str | None = None
    recorded_frames: int | None = None

    def fits(self, task: str) -> bool:
        """:return: whether the rollouts were recorded on ``task`` (or their task is unknown)"""
        return self.task is None or self.task.replace("_", "-") == task.replace("_", "-")

    def describe(self) -> str:
        """
        :return: what the metrics are computed on, for titles and captions: the rollouts file (its folder and name)
            and the trial (``<task>/<variant>/seed_<k>`` of a sweep), checkpoint and frame they were recorded from
        """
        subset = f"{len(self.indices)} of the {self.total}" if len(self.indices) < self.total else f"all {self.total}"
        agent = ""
        if self.recorded_from is not None:
            checkpoint = Path(self.recorded_from)
            snapshot = checkpoint.parent.name in (SNAPSHOTS_DIR, LEGACY_SNAPSHOTS_DIR)  # one folder deeper
            agent = f", recorded from {'/'.join(checkpoint.parts[-4 - snapshot :])}"
            agent += "" if self.recorded_frames is None else f" at {self.recorded_frames:,} frames"
        source = f"{self.source.parent.name}/{self.source.name}"
        return f"the fixed probing set ({subset} observations of {source}, {self.episodes} episodes{agent})"


def default_rollouts(sweep_dir: str | Path, task: str, variant: str) -> Path:
    """:return: the rollouts file of ``probe sweep`` for a task and variant of a sweep (the fixed set of every variant
    of the task when ``variant`` is :attr:`FixedInputSettings.rollouts_variant`)"""
    return Path(sweep_dir) / SWEEP_PROBE_DIR.format(task=task, variant=variant) / ROLLOUTS_NAME


def load_fixed_inputs(path: str | Path, samples: int | None = FIXED_SAMPLES, seed: int = 0) -> FixedInputs:
    """
    Read the fixed observation set: ``samples`` observations of a rollouts file drawn without replacement by
    ``numpy.random.default_rng(seed)`` (kept in file order), or all of them.

    :param path: a rollouts file (:class:`~sb3_collapse.probe.rollouts.Rollouts`)
    :param samples: how many (``None`` or more than the file holds: all)
    :param seed: seed of the draw
    :return: the set
    :raises ReportError: for a file that is missing or not a rollouts file
    """
    path = Path(path)
    try:
        rollouts = Rollouts.load(path)
    except ProbeError as error:
        raise ReportError(str(error), parameter="rollouts") from error
    total = len(rollouts)
    if samples is None or samples >= total:
        indices = np.arange(total)
    else:
        indices = np.sort(np.random.default_rng(seed).choice(total, size=samples, replace=False))
    recorded_from = rollouts.metadata.get("checkpoint")
    task = rollouts.env_config.get("task_id")
    steps, repeat = rollouts.metadata.get("checkpoint_num_timesteps"), rollouts.env_config.get("action_repeat")
    frames = int(steps) * int(repeat) if steps is not None and repeat is not None else None
    return FixedInputs(
        rollouts.observations[indices], indices, path, total, rollouts.n_episodes, recorded_from, task, frames
    )


def snapshot_metrics(
    model: object,
    observations: np.ndarray,
    layers: Sequence[str] = FIGURE4_LAYERS,
    device: th.device | str = "cpu",
    batch_size: int = 256,
) -> tuple[dict[str, dict[str, float]], dict[str, int]]:
    """
    :func:`~sb3_collapse.monitoring.metrics.layer_metrics` of a snapshot's activations of the observations.

    :param model: a loaded DrQv2 (or TD3, DDPG, SAC) model
    :param observations: ``(n, *obs_shape)`` observations
    :param layers: the named layers
    :param device: where the activations are gathered (float64 metrics are computed there)
    :param batch_size: observations per forward pass
    :return: layer -> metric -> value, and layer -> width in units
    """
    activations = collect_activations(model, observations, layers, batch_size=batch_size, device=device)
    return (
        {layer: layer_metrics(values) for layer, values in activations.items()},
        {layer: unit_count(values) for layer, values in activations.items()},
    )


@dataclass
class FixedMetrics:
    """
    The metrics of one trial's snapshots on the fixed set.

    :param metrics: ``collapse/<layer>/<metric>`` -> ``(frames, values)``, one value per checkpoint
    :param widths: layer -> units
    :param checkpoints: the checkpoints read, in training order
    """

    metrics: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    widths: dict[str, int] = field(default_factory=dict)
    checkpoints: list[Path] = field(default_factory=list)


def trial_fixed_metrics(
    trial: Trial, inputs: FixedInputs, settings: FixedInputSettings, progress: bool = False
) -> FixedMetrics:
    """
    Every snapshot of a trial run on the fixed set (:func:`snapshot_metrics`).

    :param trial: the trial (its snapshots, :func:`~sb3_collapse.protocol.snapshot_files`)
    :param inputs: the fixed set
    :param settings: device, batch size, layers
    :param progress: a progress bar over the checkpoints
    :return: the metrics (empty without snapshots)
    :raises ReportError: for a checkpoint that cannot be loaded or whose observations differ from the set's
    """
    device = get_device(settings.device)
    paths = snapshot_files(trial.path)
    columns: dict[str, tuple[list[int], list[float]]] = {}
    result = FixedMetrics(checkpoints=paths)
    for path in tqdm(paths, desc=f"seed {trial.seed} checkpoints", unit="checkpoint", disable=not progress):
        try:
            checkpoint = load_checkpoint(path, device=device)
        except ProbeError as error:
            raise ReportError(str(error)) from error
        shape = tuple(checkpoint.model.observation_space.shape or ())
        if tuple(inputs.observations.shape[1:]) != shape:
            raise ReportError(
                f"{inputs.source} holds observations of shape {tuple(inputs.observations.shape[1:])} but {path} "
                f"takes {shape}: give rollouts (--rollouts) recorded with the sweep's image size and frame stack.",
                parameter="rollouts",
            )
        values, result.widths = snapshot_metrics(
            checkpoint.model, inputs.observations, settings.layers, device, settings.batch_size
        )
        for layer, metrics in values.items():
            for name, value in metrics.items():
                frames, column = columns.setdefault(metric_tag(layer, name), ([], []))
                frames.append(checkpoint.frames)
                column.append(value)
        del checkpoint
    result.metrics = {
        tag: (np.asarray(frames, dtype=np.int64), np.asarray(values, dtype=np.float64))
        for tag, (frames, values) in columns.items()
    }
    return result


FIXED_METRICS = ("numerical_rank", "correlation", "dead_units")
"""The columns of Figure 4 taken from the fixed set (the gradient norm stays the training-time one)."""


def fixed_agent_rows(
    picks: Sequence[AgentPick], inputs: FixedInputs, settings: FixedInputSettings, progress: bool = False
) -> tuple[list[AgentMetrics], dict[int, FixedMetrics]]:
    """
    The rows of Figures 4, 8, 9: for each picked agent, rank, correlation and dead units of its snapshots
    on the fixed set, its training-time gradient norms, return curve, resets and escapes; a row that says so for
    an empty class.

    :param picks: :func:`~sb3_collapse.report.collapse_figure.pick_paper_agents`' picks
    :param inputs: the fixed set
    :param settings: how to compute
    :param progress: progress bars over the checkpoints
    :return: the rows, and seed -> its fixed-set metrics (every metric of :func:`layer_metrics`)
    """
    rows, computed = [], {}
    for pick in picks:
        if pick.trial is None:
            rows.append(AgentMetrics(None, pick.role, absent=pick.absent))
            continue
        online = agent_metrics(pick.trial, pick.role, settings.layers)
        fixed = trial_fixed_metrics(pick.trial, inputs, settings, progress)
        computed[pick.trial.seed] = fixed
        online.metrics = {tag: value for tag, value in online.metrics.items() if tag.endswith("/grad_norm")} | {
            metric_tag(layer, metric): fixed.metrics[metric_tag(layer, metric)]
            for layer in settings.layers
            for metric in FIXED_METRICS
            if metric_tag(layer, metric) in fixed.metrics
        }
        online.widths = fixed.widths or online.widths
        rows.append(online)
    return rows, computed


FIXED_CSV_COLUMNS = ("role", "seed", "final_return", "checkpoint", "frame", "tag", "value")


def write_fixed_metrics_csv(path: Path, picks: Sequence[AgentPick], computed: dict[int, FixedMetrics]) -> None:
    """
    Write every fixed-set metric of the picked agents, long format: role, seed, final return, checkpoint file,
    frame, tag, value.

    :param path: the CSV file
    :param picks: the picks
    :param computed: seed -> its metrics (:func:`fixed_agent_rows`)
    """
    with path.open("w", newline="") as file:
        writer = csv.writer(file)
        writer.writerow(FIXED_CSV_COLUMNS)
        for pick in picks:
            if pick.trial is None or pick.trial.seed not in computed:
                continue
            fixed = computed[pick.trial.seed]
            final = float(pick.trial.returns[-1])
            for tag, (frames, values) in fixed.metrics.items():
                for checkpoint, frame, value in zip(fixed.checkpoints, frames, values):
                    writer.writerow(
                        [pick.role, pick.trial.seed, repr(final), checkpoint.name, int(frame), tag, repr(float(value))]
                    )
