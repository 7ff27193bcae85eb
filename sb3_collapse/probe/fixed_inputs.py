"""The collapse metrics of a run's snapshots on one fixed observation set, "the matrix of MLP activations H, as defined
in Figure 1" of Section 5.1 (Figures 4, 8, 9; the report draws them; the set: docs/figures.md)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch as th

from sb3_collapse.common.progress import progress_bar
from sb3_collapse.errors import InputError
from sb3_collapse.monitoring import collect_activations, layer_metrics, unit_count
from sb3_collapse.paper import metric_tag
from sb3_collapse.probe.checkpoints import load_checkpoint
from sb3_collapse.probe.probing import ProbeSettings, split_by_episode
from sb3_collapse.probe.rollouts import Rollouts
from sb3_collapse.protocol import SNAPSHOTS_DIR

FIXED_SAMPLES = 2048
"""Observations of the fixed set by default: more than the 1024 units of ``mlp1`` and ``mlp2``, so that the inputs
do not bound their numerical rank."""


@dataclass
class FixedInputs:
    """The fixed observation set: ``(n, *obs_shape)`` uint8 ``observations``, their increasing ``(n,)`` rows
    ``indices`` in the rollouts file ``source`` of ``total`` observations and ``episodes`` episodes, and what recorded
    that file (``None``: unknown); ``recorded_frames`` are the training frames of the checkpoint ``recorded_from``;
    ``train_episodes``: the episodes the set was drawn from when it is the probe's training episodes (Figure 1's H),
    ``None`` when drawn from every episode."""

    observations: np.ndarray
    indices: np.ndarray
    source: Path
    total: int
    episodes: int
    recorded_from: str | None = None
    task: str | None = None
    recorded_frames: int | None = None
    train_episodes: list[int] | None = None

    def fits(self, task: str) -> bool:
        """:return: whether the rollouts were recorded on ``task`` (or their task is unknown)"""
        return self.task is None or self.task.replace("_", "-") == task.replace("_", "-")

    def describe(self) -> str:
        """:return: what the metrics are computed on, for captions: the rollouts file and what recorded it"""
        source = f"{self.source.parent.name}/{self.source.name}"
        agent = ""
        if self.recorded_from is not None:
            checkpoint = Path(self.recorded_from)
            snapshot = checkpoint.parent.name == SNAPSHOTS_DIR  # one folder deeper
            agent = f", recorded from {'/'.join(checkpoint.parts[-4 - snapshot :])}"
            agent += "" if self.recorded_frames is None else f" at {self.recorded_frames:,} frames"
        if self.train_episodes is not None:
            return (
                f"the probe's training episodes ({len(self.indices)} observations of {len(self.train_episodes)} of "
                f"the {self.episodes} episodes of {source}{agent})"
            )
        subset = f"{len(self.indices)} of the {self.total}" if len(self.indices) < self.total else f"all {self.total}"
        return f"the fixed probing set ({subset} observations of {source}, {self.episodes} episodes{agent})"


def load_fixed_inputs(
    path: str | Path, samples: int | None = FIXED_SAMPLES, seed: int = 0, train_episodes: bool = False
) -> FixedInputs:
    """
    The fixed set of a rollouts file, kept in file order.

    :param path: the rollouts file
    :param samples: observations drawn without replacement by ``numpy.random.default_rng(seed)`` (``None``: all)
    :param seed: seed of that draw
    :param train_episodes: draw from the probe's training episodes only, the samples of Figure 1's H ("given n
        training samples, we collect all the l-th layer activation vectors H"): the episodes that
        :func:`~sb3_collapse.probe.probing.split_by_episode` gives to training at ``python -m sb3_collapse.probe``'s
        default split (``ProbeSettings().fractions`` and ``split_seed``)
    :return: the set
    :raises InputError: not a rollouts file; with ``train_episodes``, fewer than 3 episodes
    """
    rollouts = Rollouts.load(path)
    total = len(rollouts)
    rows, trained_on = np.arange(total), None
    if train_episodes:
        defaults = ProbeSettings()
        split = split_by_episode(rollouts.episode_ids, defaults.fractions, defaults.split_seed)
        rows, trained_on = np.sort(split.order[: split.n_train]), split.episodes["train"]
    if samples is not None and samples < len(rows):
        rows = rows[np.sort(np.random.default_rng(seed).choice(len(rows), size=samples, replace=False))]
    meta, env = rollouts.metadata, rollouts.env_config
    steps, repeat = meta.get("checkpoint_num_timesteps"), env.get("action_repeat")
    frames = int(steps) * int(repeat) if steps is not None and repeat is not None else None
    recorded = (meta.get("checkpoint"), env.get("task_id"), frames, trained_on)
    return FixedInputs(rollouts.observations[rows], rows, Path(path), total, rollouts.n_episodes, *recorded)


@dataclass
class FixedMetrics:
    """One trial's ``metrics`` on the fixed set, ``collapse/<layer>/<metric>`` -> ``(frames, values)`` of its
    ``checkpoints`` (in training order), and each layer's width in units."""

    metrics: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    widths: dict[str, int] = field(default_factory=dict)
    checkpoints: list[Path] = field(default_factory=list)


def fixed_metrics(
    paths: Sequence[Path],
    inputs: FixedInputs,
    layers: Sequence[str],
    device: th.device | str = "cpu",
    batch_size: int = 256,
    progress: bool = False,
    desc: str = "checkpoints",
) -> FixedMetrics:
    """:func:`~sb3_collapse.monitoring.metrics.layer_metrics` of the ``layers`` of each checkpoint (a trial's
    snapshots, in training order) on the fixed set, ``batch_size`` observations per forward pass (``progress``: a bar
    labelled ``desc``)."""
    columns: dict[str, tuple[list[int], list[float]]] = {}
    result = FixedMetrics(checkpoints=list(paths))
    for path in progress_bar(paths, desc, "checkpoint", progress):
        checkpoint = load_checkpoint(path, device=device)
        shape = tuple(checkpoint.model.observation_space.shape or ())
        if tuple(inputs.observations.shape[1:]) != shape:
            raise InputError(
                f"{inputs.source} holds observations of shape {tuple(inputs.observations.shape[1:])} but {path} "
                f"takes {shape}: give `rollouts` recorded with the checkpoints' image size and frame stack.",
                parameter="rollouts",
            )
        activations = collect_activations(checkpoint.model, inputs.observations, layers, batch_size, device=device)
        result.widths = {layer: unit_count(values) for layer, values in activations.items()}
        for layer, values in activations.items():
            for name, value in layer_metrics(values).items():
                frames, column = columns.setdefault(metric_tag(layer, name), ([], []))
                frames.append(checkpoint.frames)
                column.append(value)
        del checkpoint
    result.metrics = {
        tag: (np.asarray(frames, dtype=np.int64), np.asarray(values, dtype=np.float64))
        for tag, (frames, values) in columns.items()
    }
    return result
