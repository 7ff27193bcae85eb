"""
The trials of a sweep: one per (task, variant, seed), each in its own folder ``<out>/<task>/<variant>/seed_<k>``.
The variants (``drqv2``, ``td3+reset``, ``drqv2-leaky+redo_periodic``, ``cnn-good_mlp-bad``...): docs/sweeps.md.
"""

from __future__ import annotations

import contextlib
from collections.abc import Collection, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sb3_collapse.drqv2.transplant import resolve_source_path
from sb3_collapse.envs import parse_task
from sb3_collapse.errors import InputError
from sb3_collapse.protocol import trial_path
from sb3_collapse.run.config import TrainConfig
from sb3_collapse.run.variants import BLANK_SOURCE, transplant_of, variant_settings


def donor_key(source: str, part: str) -> str:
    """The key of a donor's checkpoints, ``source`` good/bad, ``part`` cnn/mlp: ``"good_cnn"`` (flag ``--good-cnn``)."""
    return f"{source}_{part}"


@dataclass(frozen=True, order=True)
class Trial:
    """
    One training run of a sweep.

    :param task: the task, ``<domain>-<task>`` (``"walker-walk"``)
    :param variant: the variant name (docs/sweeps.md)
    :param seed: the random seed
    """

    task: str
    variant: str
    seed: int

    def __str__(self) -> str:
        return f"{self.task}/{self.variant}/seed_{self.seed}"


def canonical_task(name: str) -> str:
    """The ``<domain>-<task>`` form of a task name (``"walker_walk"``: ``"walker-walk"``); ``InputError`` if unknown."""
    try:
        domain, task = parse_task(name)
    except ValueError as error:
        raise InputError(str(error)) from None
    return f"{domain}-{task}"


def expand_trials(tasks: Iterable[str], variants: Iterable[str], seeds: Iterable[int]) -> list[Trial]:
    """
    Every (task, variant, seed) combination, in that nesting order; an ``InputError`` for an unknown task or variant,
    a negative seed, an empty list or a value listed twice.

    :param tasks: task names (any form of :func:`canonical_task`)
    :param variants: variant names
    :param seeds: seeds (>= 0)
    """
    tasks = [canonical_task(task) for task in tasks]
    variants, seeds = list(variants), [int(seed) for seed in seeds]
    for name, values in (("tasks", tasks), ("variants", variants), ("seeds", seeds)):
        repeated = sorted({str(value) for value in values if values.count(value) > 1})
        if repeated:
            raise InputError(
                f"{name} lists {', '.join(repeated)} more than once: each (task, variant, seed) is one trial.",
                parameter=name,
            )
    for variant in variants:
        transplant_of(variant)
    if any(seed < 0 for seed in seeds):
        raise InputError(f"Seeds must be >= 0, got {min(seeds)}.")
    if not (tasks and variants and seeds):
        raise InputError("A sweep needs at least one task, one variant and one seed.")
    return [Trial(task, variant, seed) for task in tasks for variant in variants for seed in seeds]


def trial_dir(out: str | Path, trial: Trial) -> Path:
    """:return: the folder of ``trial`` in the sweep folder ``out``: ``<out>/<task>/<variant>/seed_<seed>``"""
    return trial_path(out, trial.task, trial.variant, trial.seed)


def parse_checkpoint_specs(specs: Sequence[str] | None, tasks: Sequence[str], flag: str) -> dict[str, str]:
    """
    Checkpoints of one donor per task, from ``PATH`` (every task) and ``TASK=PATH`` items (that task); ``.zip`` may be
    left out. An ``InputError`` for two plain paths, a task not in the sweep, or a path that is not a file.

    :param specs: the items, ``None`` for none
    :param tasks: the sweep's tasks, ``<domain>-<task>``
    :param flag: the command-line flag, for the messages (``"--good-cnn"``)
    :return: task -> absolute checkpoint path, for the tasks that have one
    """
    default: str | None = None
    by_task: dict[str, str] = {}
    for item in specs or []:
        name, separator, path = item.partition("=")
        task = None
        if separator:
            with contextlib.suppress(InputError):  # not a task name: the whole item is a path
                task = canonical_task(name)
        if task is None:
            if default is not None:
                raise InputError(f"{flag}: two checkpoints for every task ({default}, {item}); use TASK=PATH per task.")
            default = item
        elif task not in tasks:
            raise InputError(f"{flag} {item}: {task} is not a task of this sweep ({', '.join(tasks)}).")
        else:
            by_task[task] = path
    resolved = {}
    for task in tasks:
        path = by_task.get(task, default)
        if path is None:
            continue
        try:
            resolved[task] = str(resolve_source_path(flag, path))
        except FileNotFoundError:
            raise InputError(
                f"{flag}: {path} (for {task}) is not a file; give a checkpoint saved by DrQv2.save."
            ) from None
    return resolved


def trial_config(
    trial: Trial,
    out: str | Path,
    training: Mapping[str, Any],
    checkpoints: Mapping[str, Mapping[str, str]] | None = None,
    device: str = "cpu",
    torch_threads: int | None = None,
    snapshot_variants: Collection[str] | None = None,
) -> TrainConfig:
    """
    The resolved ``TrainConfig`` of one trial: the sweep's settings, its task, seed, folder, variant and donors; the
    settings left at ``None`` come from the task's preset.

    :param trial: the trial
    :param out: the sweep folder
    :param training: :class:`~sb3_collapse.run.config.TrainConfig` fields shared by all trials
    :param checkpoints: :func:`donor_key` (``"good_cnn"``...) -> task -> checkpoint path, for transplant-grid cells
    :param device: the torch device of the trial
    :param torch_threads: threads of torch's CPU operations in the trial
    :param snapshot_variants: the variants whose trials save snapshots (``TrainConfig.snapshots``, the disk of
        docs/sweeps.md's plan); ``None``: ``training``'s ``snapshots`` for every trial
    """
    transplant = transplant_of(trial.variant)
    per_trial: dict[str, Any] = {
        "env": trial.task, "seed": trial.seed, "run_dir": str(trial_dir(out, trial)), **variant_settings(trial.variant),
        "variant": trial.variant, "transplant": transplant, "device": device, "torch_threads": torch_threads,
        "progress_bar": False,
    }  # fmt: skip
    if snapshot_variants is not None:
        per_trial["snapshots"] = trial.variant in snapshot_variants
    for part, source in (transplant or {}).items():
        if source != BLANK_SOURCE:
            per_trial[f"init_{part}"] = (checkpoints or {})[donor_key(source, part)][trial.task]
    return TrainConfig(**{**training, **per_trial}).resolve()
