"""
The trials of a sweep: one per (task, variant, seed), each in its own folder ``<out>/<task>/<variant>/seed_<k>``.

Variants:

- ``drqv2``: plain DrQ-v2; ``td3``, ``sac``: SB3's TD3 or SAC from the same pixels, with DrQ-v2's network sizes
  (:mod:`sb3_collapse.baselines`);
- ``<algorithm>+<intervention>``: the algorithm with the paper's rule (:class:`~sb3_collapse.CollapseReset`) doing
  the intervention at the end of each window without escape: ``drqv2+reset`` (the paper's reset from scratch),
  ``drqv2+redo`` (ReDo once at each trigger), ``td3+reset``, ``sac+shrink_perturb``... (interventions:
  :mod:`sb3_collapse.monitoring.interventions`);
- ``<algorithm>+redo_periodic``: the algorithm with ReDo as Sokar et al. run it, every
  :data:`~sb3_collapse.monitoring.redo.REDO_EVERY_UPDATES` updates for the whole run, no rule
  (:class:`~sb3_collapse.monitoring.redo.PeriodicReDo`, DrQ-v2's convolution channels included);
- ``drqv2-leaky``, ``drqv2-leaky+<intervention>``, ``drqv2-leaky+redo_periodic``: the same with every ReLU of
  DrQ-v2's encoder, actor and critic replaced by a Leaky-ReLU (negative slope 0.01, the paper's footnote 1);
- ``cnn-<src>_mlp-<src>`` with ``<src>`` in ``blank``, ``good``, ``bad``: a cell of the paper's transplant grid
  (Study 2, Figure 3a), plain DrQ-v2 whose encoder (CNN) and actor (MLP) start from the weights of a "good" or a
  "bad" agent of the same task, or blank (the usual random initialization); the critic starts blank. The CNN and
  the MLP of a source come from two different agents (:mod:`sb3_collapse.sweep.donors`): the checkpoints are keyed
  by :func:`donor_key` (``good_cnn``, ``good_mlp``, ``bad_cnn``, ``bad_mlp``).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sb3_collapse.drqv2.transplant import resolve_source_path
from sb3_collapse.envs import parse_task
from sb3_collapse.errors import InputError
from sb3_collapse.monitoring.interventions import INTERVENTIONS
from sb3_collapse.monitoring.redo import REDO_EVERY_UPDATES
from sb3_collapse.protocol import trial_path
from sb3_collapse.run.config import ALGORITHMS, TrainConfig

LEAKY = "-leaky"
"""Suffix of the DrQ-v2 variants with Leaky-ReLU activations (``drqv2-leaky``)."""
PERIODIC_REDO = "redo_periodic"
"""``<algorithm>+redo_periodic``: ReDo every :data:`~sb3_collapse.monitoring.redo.REDO_EVERY_UPDATES` updates."""
BASE_VARIANTS = ("drqv2", f"drqv2{LEAKY}", *(algorithm for algorithm in ALGORITHMS if algorithm != "drqv2"))
"""The algorithms of the variants: ``drqv2``, ``drqv2-leaky``, ``td3``, ``sac``."""
PLAIN_VARIANTS = tuple(
    f"{base}{suffix}"
    for base in BASE_VARIANTS
    for suffix in ("", *(f"+{name}" for name in INTERVENTIONS), f"+{PERIODIC_REDO}")
)
"""``<algorithm>``, ``<algorithm>+<intervention>`` and ``<algorithm>+redo_periodic``: ``drqv2``, ``drqv2+reset``,
``drqv2+reset_actor``..., ``drqv2+redo_periodic``, ``drqv2-leaky``, ``drqv2-leaky+reset``..., ``td3``, ``td3+reset``...,
``sac``..."""
TRANSPLANT_SOURCES = ("blank", "good", "bad")
GRID_VARIANTS = tuple(f"cnn-{cnn}_mlp-{mlp}" for cnn in TRANSPLANT_SOURCES for mlp in TRANSPLANT_SOURCES)
"""The nine cells of the transplant grid, CNN source major: ``cnn-blank_mlp-blank``, ``cnn-blank_mlp-good``..."""


def donor_key(source: str, part: str) -> str:
    """
    :param source: ``"good"`` or ``"bad"``
    :param part: ``"cnn"`` or ``"mlp"``
    :return: the key of that donor's checkpoints in a sweep's checkpoints (``"good_cnn"``); the flag is
        ``--good-cnn``
    """
    return f"{source}_{part}"




@dataclass(frozen=True, order=True)
class Trial:
    """
    One training run of a sweep.

    :param task: the task, ``<domain>-<task>`` (``"walker-walk"``)
    :param variant: the variant name (see the module docstring)
    :param seed: the random seed
    """

    task: str
    variant: str
    seed: int

    def __str__(self) -> str:
        return f"{self.task}/{self.variant}/seed_{self.seed}"


def canonical_task(name: str) -> str:
    """
    :param name: a task name in any form :func:`~sb3_collapse.envs.parse_task` accepts (``"walker_walk"``)
    :return: its ``<domain>-<task>`` form (``"walker-walk"``)
    :raises InputError: for an unknown task, with close names
    """
    try:
        domain, task = parse_task(name)
    except ValueError as error:
        raise InputError(str(error)) from None
    return f"{domain}-{task}"


def transplant_of(variant: str) -> dict[str, str] | None:
    """
    :param variant: a variant name
    :return: ``{"cnn": src, "mlp": src}`` for a transplant-grid cell, ``None`` for a plain variant
    :raises InputError: for an unknown variant, listing the valid ones
    """
    if variant in PLAIN_VARIANTS:
        return None
    if variant in GRID_VARIANTS:
        cnn, mlp = variant.split("_")
        return {"cnn": cnn.removeprefix("cnn-"), "mlp": mlp.removeprefix("mlp-")}
    raise InputError(
        f"Unknown variant {variant!r}: use <algorithm> or <algorithm>+<intervention> with <algorithm> in "
        f"{', '.join(BASE_VARIANTS)} and <intervention> in {', '.join(INTERVENTIONS)} or {PERIODIC_REDO} (e.g. "
        "drqv2+reset, td3+redo, drqv2-leaky+redo_periodic), "
        f"or a transplant-grid cell cnn-<src>_mlp-<src> with <src> in {', '.join(TRANSPLANT_SOURCES)} "
        "(e.g. cnn-good_mlp-bad)."
    )


def variant_settings(variant: str) -> dict[str, Any]:
    """
    The :class:`~sb3_collapse.run.config.TrainConfig` settings a variant fixes.

    :param variant: a variant name
    :return: ``algorithm``, ``reset_rule``, ``intervention`` (``None`` without the rule), ``activation``
        (``"leaky_relu"`` for ``drqv2-leaky...``) and ``redo_every_updates`` (for ``+redo_periodic``, else 0);
        transplant-grid cells are plain DrQ-v2
    :raises InputError: for an unknown variant
    """
    settings: dict[str, Any] = {
        "algorithm": "drqv2", "reset_rule": False, "intervention": None, "activation": "relu", "redo_every_updates": 0
    }  # fmt: skip
    if transplant_of(variant) is not None:
        return settings
    base, _, suffix = variant.partition("+")
    settings["algorithm"] = base.removesuffix(LEAKY)
    if base.endswith(LEAKY):
        settings["activation"] = "leaky_relu"
    if suffix == PERIODIC_REDO:
        settings["redo_every_updates"] = REDO_EVERY_UPDATES
    elif suffix:
        settings.update(reset_rule=True, intervention=suffix)
    return settings


def expand_trials(tasks: Iterable[str], variants: Iterable[str], seeds: Iterable[int]) -> list[Trial]:
    """
    Every (task, variant, seed) combination, in that nesting order.

    :param tasks: task names (any form of :func:`canonical_task`)
    :param variants: variant names
    :param seeds: seeds (>= 0)
    :return: the trials
    :raises InputError: for an unknown task or variant, a negative seed, an empty list or a value listed twice
        (``walker-walk`` and ``walker_walk`` are the same task)
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
    """
    :param out: the sweep folder
    :param trial: a trial
    :return: its folder, ``<out>/<task>/<variant>/seed_<seed>``
    """
    return trial_path(out, trial.task, trial.variant, trial.seed)


def parse_checkpoint_specs(specs: Sequence[str] | None, tasks: Sequence[str], flag: str) -> dict[str, str]:
    """
    Checkpoints of one source (good or bad) per task, from ``PATH`` (every task) and ``TASK=PATH`` items (that
    task; it overrides a plain ``PATH``). An item is ``TASK=PATH`` when the text before its first ``=`` is a task
    name; otherwise the whole item is a path. As in ``DrQv2.load``, ``.zip`` may be left out. Paths are made
    absolute (trials may run in another folder).

    :param specs: the items, ``None`` for none
    :param tasks: the sweep's tasks, ``<domain>-<task>``
    :param flag: the command-line flag, for the messages (``"--good-cnn"``)
    :return: task -> absolute checkpoint path, for the tasks that have one
    :raises InputError: for two plain paths, a task that is not in the sweep, or a path that is not a file
    """
    default: str | None = None
    by_task: dict[str, str] = {}
    for item in specs or []:
        name, separator, path = item.partition("=")
        task = None
        if separator:
            try:
                task = canonical_task(name)
            except InputError:
                task = None
        if task is None:
            if default is not None:
                raise InputError(f"{flag}: two checkpoints for every task ({default}, {item}); use TASK=PATH per task.")
            default = item
        elif task not in tasks:
            raise InputError(f"{flag} {item}: {task} is not a task of this sweep ({', '.join(tasks)}).")
        else:
            by_task[task] = path
    checkpoints = {task: by_task.get(task, default) for task in tasks}
    resolved = {}
    for task, path in checkpoints.items():
        if path is None:
            continue
        try:
            resolved[task] = str(resolve_source_path(flag, path))
        except FileNotFoundError:
            raise InputError(
                f"{flag}: {path} (for {task}) is not a file; give a checkpoint saved by DrQv2.save."
            ) from None
    return resolved


def check_checkpoints(trials: Iterable[Trial], checkpoints: Mapping[str, Mapping[str, str]]) -> None:
    """
    :param trials: the sweep's trials
    :param checkpoints: :func:`donor_key` (``"good_cnn"``...) -> task -> path
    :raises InputError: naming the first transplant-grid trial whose checkpoint is missing and the flag to add
    """
    for trial in trials:
        for part, source in (transplant_of(trial.variant) or {}).items():
            if source != "blank" and trial.task not in checkpoints.get(donor_key(source, part), {}):
                raise InputError(
                    f"Variant {trial.variant} takes the {part.upper()} of a {source} agent: pass --{source}-{part} "
                    f"PATH (or {trial.task}=PATH) for {trial.task}, or --donors-from a finished sweep."
                )


def trial_config(
    trial: Trial,
    out: str | Path,
    training: Mapping[str, Any],
    checkpoints: Mapping[str, Mapping[str, str]] | None = None,
    device: str = "cpu",
    torch_threads: int | None = None,
) -> TrainConfig:
    """
    The settings of one trial: the sweep's training settings, the trial's task and seed, its exact folder,
    the variant's algorithm, reset rule and intervention (:func:`variant_settings`) and initial weights, no
    progress bar. The DrQ-v2 settings the sweep leaves at
    ``None`` come from the trial's task preset (:func:`sb3_collapse.presets.preset`), so each task trains with its
    own; one given to the sweep overrides every task's preset. The config is resolved (:meth:`TrainConfig.resolve`).

    :param trial: the trial
    :param out: the sweep folder
    :param training: :class:`~sb3_collapse.run.config.TrainConfig` fields shared by all trials (``None``: the task's
        preset)
    :param checkpoints: :func:`donor_key` (``"good_cnn"``...) -> task -> checkpoint path, for transplant-grid cells
    :param device: the torch device of the trial
    :param torch_threads: threads of torch's CPU operations in the trial
    :return: the trial's :class:`~sb3_collapse.run.config.TrainConfig`
    """
    transplant = transplant_of(trial.variant)
    per_trial: dict[str, Any] = {
        "env": trial.task,
        "seed": trial.seed,
        "run_dir": str(trial_dir(out, trial)),
        **variant_settings(trial.variant),
        "variant": trial.variant,
        "transplant": transplant,
        "device": device,
        "torch_threads": torch_threads,
        "progress_bar": False,
    }
    if transplant is not None:
        checkpoints = checkpoints or {}
        for part, source in transplant.items():
            if source != "blank":
                per_trial[f"init_{part}"] = checkpoints[donor_key(source, part)][trial.task]
    return TrainConfig(**{**training, **per_trial}).resolve()
