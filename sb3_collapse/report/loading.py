"""
Read a sweep folder (the trial-folder contract of ``python -m sb3_collapse.sweep``) into one :class:`Trial` per
``<sweep>/<task>/<variant>/seed_<k>/`` folder, through :mod:`sb3_collapse.runfolder`. Only finished trials
(:class:`~sb3_collapse.runfolder.RunStatus`) enter the statistics; the others are counted and reported. A malformed
file raises :class:`InputError` naming the file.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from tqdm.auto import tqdm

from sb3_collapse.errors import InputError
from sb3_collapse.paper import PAPER
from sb3_collapse.protocol import COLLAPSE_METRICS_CSV, FINISHED, RESULT_JSON
from sb3_collapse.runfolder import (
    NOT_A_RUN,
    check_result_version,
    read_collapse_metrics,
    read_evaluations,
    read_result,
    run_status,
    trial_folders,
)

DEFAULT_COLLAPSE_TAG = PAPER.collapse_tag
"""The collapse metric that decides "stuck in action collapse" (the paper's reset rule reads the same one)."""


@dataclass
class Trial:
    """
    One trial folder of a sweep.

    :param task: the task folder name, e.g. ``"walker-walk"``
    :param variant: the variant folder name, e.g. ``"drqv2+reset"``
    :param seed: the seed of the ``seed_<k>`` folder
    :param path: the trial folder
    :param status: its :class:`~sb3_collapse.runfolder.RunStatus` (``"finished"``, ``"running"``...)
    :param result: the parsed result file (``None`` without one)
    :param frames: the scheduled evaluations' frames (agent steps x action repeat), increasing
    :param returns: mean evaluation return at each of ``frames``
    :param collapse_frames: frames of the checks that logged the collapse tag, increasing
    :param collapse_values: the tag's value at each of ``collapse_frames`` (non-finite values dropped)
    :param notes: what the reader noticed and worked around (shown in the report's notes)
    """

    task: str
    variant: str
    seed: int
    path: Path
    status: str
    result: dict[str, Any] | None
    frames: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    returns: np.ndarray = field(default_factory=lambda: np.zeros(0))
    collapse_frames: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    collapse_values: np.ndarray = field(default_factory=lambda: np.zeros(0))
    notes: list[str] = field(default_factory=list)

    @property
    def finished(self) -> bool:
        """Whether result file says the trial finished."""
        return self.status == FINISHED

    @property
    def final_return(self) -> float:
        """The mean return of its last scheduled evaluation, nan unless finished: the paper's final return."""
        return float(self.returns[-1]) if self.finished and len(self.returns) else float("nan")

    @property
    def resets(self) -> int:
        """Resets of the reset rule in this trial (result file's ``resets``; 0 for an unfinished trial)."""
        return int(self.result["resets"]) if self.result is not None else 0

    @property
    def escaped(self) -> bool | None:
        """result file's ``escaped``: ``None`` when the trial ran without the reset rule."""
        return None if self.result is None else self.result.get("escaped")


@dataclass
class Sweep:
    """
    The trials of a sweep folder.

    :param path: the sweep folder
    :param trials: every trial folder, sorted by task, variant and seed (finished and unfinished)
    """

    path: Path
    trials: list[Trial]

    @property
    def finished(self) -> list[Trial]:
        """The finished trials."""
        return [trial for trial in self.trials if trial.finished]

    @property
    def unfinished(self) -> list[Trial]:
        """The trials that are not finished."""
        return [trial for trial in self.trials if not trial.finished]

    def tasks(self) -> list[str]:
        """Task names in sorted order."""
        return sorted({trial.task for trial in self.trials})

    def variants(self, task: str) -> list[str]:
        """Variant names of ``task`` in :func:`variant_order`."""
        return variant_order({trial.variant for trial in self.trials if trial.task == task})

    def select(self, task: str, variant: str, finished: bool = True) -> list[Trial]:
        """
        :param task: task name
        :param variant: variant name
        :param finished: the finished trials (``True``) or the unfinished ones (``False``)
        :return: those trials of ``(task, variant)``, by seed
        """
        return [t for t in self.trials if t.task == task and t.variant == variant and t.finished == finished]


def variant_order(variants: Iterable[str]) -> list[str]:
    """
    The order in which variants are shown: ``drqv2``, ``drqv2+reset``, then the others alphabetically.

    :param variants: variant names
    :return: the names, sorted
    """
    first = {"drqv2": 0, "drqv2+reset": 1}
    return sorted(set(variants), key=lambda name: (first.get(name, 2), name))


def find_trial_folders(sweep: str | Path) -> list[tuple[str, str, int, Path]]:
    """
    :param sweep: the sweep folder
    :return: its trial folders (:func:`~sb3_collapse.runfolder.trial_folders`) sorted by task, variant
        (:func:`variant_order`) and seed
    :raises InputError: when the folder does not exist or holds no trial folder
    """
    root = Path(sweep)
    if not root.exists():
        raise InputError(f"sweep folder {root} does not exist; give the out folder of a sweep.", parameter="sweep")
    if not root.is_dir():
        raise InputError(f"sweep {root} is not a folder; give the out folder of a sweep.", parameter="sweep")
    found = trial_folders(root)
    if not found:
        raise InputError(f"no trial folders <task>/<variant>/seed_<k>/ under {root}; is it the out folder of a sweep?")
    variants = variant_order(item[1] for item in found)
    return sorted(found, key=lambda item: (item[0], variants.index(item[1]), item[2]))


def check_result(path: Path, result: dict[str, Any]) -> None:
    """
    :param path: a finished trial's folder
    :param result: its result file
    :raises InputError: when ``resets`` is not an integer >= 0, ``escaped`` not a bool or null, or the file is of
        another version (:func:`~sb3_collapse.runfolder.check_result_version`)
    """
    check_result_version(path, result)
    resets = result.get("resets")
    if isinstance(resets, bool) or not isinstance(resets, int) or resets < 0:
        raise InputError(f"{path / RESULT_JSON}: 'resets' must be an integer >= 0, got {resets!r}.")
    if result.get("escaped") not in (None, True, False):
        raise InputError(f"{path / RESULT_JSON}: 'escaped' must be true, false or null, got {result['escaped']!r}.")


def load_trial(
    task: str, variant: str, seed: int, path: Path, collapse_tag: str = DEFAULT_COLLAPSE_TAG, partial: bool = False
) -> Trial:
    """
    Read one trial folder.

    A finished trial must have a well-formed evaluation file with at least one row; its collapse metrics file is
    optional (without it, or without rows of ``collapse_tag``, the trial's collapse state is unknown). An
    unfinished trial's files are read only when ``partial`` is true (to plot partial curves), and a malformed or
    missing evaluation file there (a file being written) is noted, not raised.

    :param task: task folder name
    :param variant: variant folder name
    :param seed: seed of the folder
    :param path: the trial folder
    :param collapse_tag: the collapse metric to read
    :param partial: read the evaluation curve of an unfinished trial too
    :return: the trial
    :raises InputError: when a file of a finished trial is malformed
    """
    result = read_result(path, strict=True)
    status = run_status(path)
    trial = Trial(task, variant, seed, path, str(status or NOT_A_RUN), result)
    if trial.finished:
        check_result(path, result)  # type: ignore[arg-type]
        for key, expected in (("task", task), ("variant", variant), ("seed", seed)):
            if result.get(key, expected) != expected:  # type: ignore[union-attr]
                trial.notes.append(
                    f"{path / RESULT_JSON}: {key} is {result[key]!r} but the folder says {expected!r}; "  # type: ignore[index]
                    "the folder names are used"
                )
        trial.frames, trial.returns = read_evaluations(path)
        if len(trial.frames) == 0:
            raise InputError(f"{path}: no evaluation rows although the trial finished.")
        metrics_path = path / COLLAPSE_METRICS_CSV
        if metrics_path.exists():
            metric = read_collapse_metrics(metrics_path, (collapse_tag,)).get(collapse_tag)
            trial.collapse_frames, trial.collapse_values = metric or (trial.collapse_frames, trial.collapse_values)
    elif partial:
        try:
            trial.frames, trial.returns = read_evaluations(path, partial=True)
        except InputError as error:
            trial.notes.append(f"partial curve not shown: {error}")
    return trial


def load_sweep(
    sweep: str | Path,
    collapse_tag: str = DEFAULT_COLLAPSE_TAG,
    include_unfinished: bool = False,
    tasks: Iterable[str] | None = None,
    variants: Iterable[str] | None = None,
    progress: bool = True,
) -> Sweep:
    """
    Read every trial folder of a sweep.

    :param sweep: the sweep folder (``--out`` of ``python -m sb3_collapse.sweep``)
    :param collapse_tag: the collapse metric read from collapse metrics file
    :param include_unfinished: also read the (partial) evaluation curves of unfinished trials
    :param tasks: keep only these task folders (``None``: all)
    :param variants: keep only these variant folders (``None``: all)
    :param progress: show a progress bar over the trial folders
    :return: the sweep
    :raises InputError: when the folder is missing, holds no (selected) trial, or a finished trial's file is
        malformed
    """
    found = find_trial_folders(sweep)
    for name, wanted, index in (("tasks", tasks, 0), ("variants", variants, 1)):
        if wanted is not None:
            wanted = list(wanted)
            available = sorted({item[index] for item in found})
            unknown = [w for w in wanted if w not in available]
            if unknown:
                raise InputError(
                    f"{name} {' '.join(unknown)} not in {sweep}; available: {', '.join(available)}.", parameter=name
                )
            found = [item for item in found if item[index] in wanted]
    trials = [
        load_trial(task, variant, seed, path, collapse_tag, partial=include_unfinished)
        for task, variant, seed, path in tqdm(found, desc="reading trials", unit="trial", disable=not progress)
    ]
    return Sweep(path=Path(sweep), trials=trials)
