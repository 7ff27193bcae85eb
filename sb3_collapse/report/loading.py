"""Read a sweep folder into one :class:`Trial` per ``<sweep>/<task>/<variant>/seed_<k>/``, through
:mod:`sb3_collapse.runfolder`; a trial whose files cannot be read is kept as damaged, with its reason."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from sb3_collapse.common.progress import progress_bar
from sb3_collapse.errors import InputError
from sb3_collapse.paper import PAPER
from sb3_collapse.protocol import COLLAPSE_METRICS_CSV, FINISHED, RESULT_JSON
from sb3_collapse.run.variants import BASELINE_VARIANT, RULE_VARIANT
from sb3_collapse.runfolder import (
    DAMAGED_RESULT_WAY_OUT,
    NOT_A_RUN,
    RunStatus,
    check_result_version,
    final_return_of,
    read_collapse_metrics,
    read_evaluations,
    read_result,
    run_status,
    trial_folders,
)


@dataclass
class Trial:
    """
    One trial folder of a sweep.

    :param task: the task folder name
    :param variant: the variant folder name
    :param seed: the seed of the ``seed_<k>`` folder
    :param path: the trial folder
    :param status: its :class:`~sb3_collapse.runfolder.RunStatus`
    :param result: the parsed result file (``None`` without one)
    :param frames: the scheduled evaluations' frames, increasing
    :param returns: mean evaluation return at each of ``frames``
    :param collapse_frames: frames of the checks that logged the collapse tag
    :param collapse_values: the tag's finite values at ``collapse_frames``
    :param notes: what the reader noticed and worked around
    :param reason: why a damaged trial cannot be read (its status is then ``failed``)
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
    reason: str = ""

    @property
    def finished(self) -> bool:
        """Whether its result file says finished."""
        return self.status == FINISHED

    @property
    def final_return(self) -> float:
        """The paper's final return (:func:`~sb3_collapse.runfolder.final_return_of`; nan unless finished)."""
        final = final_return_of(self.returns) if self.finished else None
        return float("nan") if final is None else final

    @property
    def resets(self) -> int:
        """The result file's ``resets`` (0 without one)."""
        return int(self.result["resets"]) if self.result is not None else 0

    @property
    def reset_frames(self) -> list[int]:
        """The result file's ``reset_frames``, the frames of the reset rule's interventions (empty without one)."""
        return [int(frame) for frame in (self.result or {}).get("reset_frames") or ()]

    @property
    def escaped(self) -> bool | None:
        """The result file's ``escaped``: ``None`` when the trial ran without the reset rule."""
        return None if self.result is None else self.result.get("escaped")


@dataclass
class Sweep:
    """
    The trials of a sweep folder.

    :param path: the sweep folder
    :param trials: every trial folder, sorted by task, variant and seed (finished, unfinished and damaged)
    """

    path: Path
    trials: list[Trial]

    @property
    def finished(self) -> list[Trial]:
        """The finished trials."""
        return [trial for trial in self.trials if trial.finished]

    @property
    def unfinished(self) -> list[Trial]:
        """The trials that are not finished (damaged ones included)."""
        return [trial for trial in self.trials if not trial.finished]

    def tasks(self) -> list[str]:
        """Task names, sorted."""
        return sorted({trial.task for trial in self.trials})

    def variants(self, task: str) -> list[str]:
        """Variant names of ``task`` in :func:`variant_order`."""
        return variant_order({trial.variant for trial in self.trials if trial.task == task})

    def select(self, task: str, variant: str, finished: bool = True) -> list[Trial]:
        """
        :param task: task name
        :param variant: variant name
        :param finished: the finished trials (``True``) or the others
        :return: those trials, by seed
        """
        return [t for t in self.trials if t.task == task and t.variant == variant and t.finished == finished]


def variant_order(variants: Iterable[str]) -> list[str]:
    """:return: the variant names in display order: ``drqv2``, ``drqv2+reset``, then the others sorted"""
    first = {BASELINE_VARIANT: 0, RULE_VARIANT: 1}
    return sorted(set(variants), key=lambda name: (first.get(name, 2), name))


def load_trial(
    task: str, variant: str, seed: int, path: Path, collapse_tag: str = PAPER.collapse_tag, partial: bool = False
) -> Trial:
    """Read one trial folder (an unfinished trial's partial curve with ``partial``: unreadable, it is noted); an
    InputError names the file when a finished trial's file (or any result file) is malformed."""
    result = read_result(path, strict=True)
    finished = result is not None and result.get("status") == FINISHED
    status = RunStatus.FINISHED if finished else run_status(path)
    trial = Trial(task, variant, seed, path, str(status or NOT_A_RUN), result)
    if trial.finished:
        check_result_version(path, result)  # type: ignore[arg-type]
        resets = result.get("resets")  # type: ignore[union-attr]
        if isinstance(resets, bool) or not isinstance(resets, int) or resets < 0:
            raise InputError(f"{path / RESULT_JSON}: 'resets' must be an integer >= 0, got {resets!r}.")
        if result.get("escaped") not in (None, True, False):  # type: ignore[union-attr]
            escaped = result["escaped"]  # type: ignore[index]
            raise InputError(f"{path / RESULT_JSON}: 'escaped' must be true, false or null, got {escaped!r}.")
        for key, expected in (("task", task), ("variant", variant), ("seed", seed)):
            if result.get(key, expected) != expected:  # type: ignore[union-attr]
                trial.notes.append(
                    f"{path / RESULT_JSON}: {key} is {result[key]!r} but the folder says {expected!r}; "  # type: ignore[index]
                    "the folder names are used"
                )
        trial.frames, trial.returns = read_evaluations(path)
        if len(trial.frames) == 0:
            raise InputError(f"{path}: no evaluation rows although the trial finished.")
        if (path / COLLAPSE_METRICS_CSV).exists():
            metric = read_collapse_metrics(path / COLLAPSE_METRICS_CSV, (collapse_tag,)).get(collapse_tag)
            trial.collapse_frames, trial.collapse_values = metric or (trial.collapse_frames, trial.collapse_values)
    elif partial:
        try:
            trial.frames, trial.returns = read_evaluations(path, partial=True)
        except InputError as error:
            trial.notes.append(f"partial curve not shown: {error}")
    return trial


def load_sweep(
    sweep: str | Path,
    collapse_tag: str = PAPER.collapse_tag,
    include_unfinished: bool = False,
    tasks: Iterable[str] | None = None,
    variants: Iterable[str] | None = None,
    progress: bool = True,
) -> Sweep:
    """
    Read every trial folder of a sweep; a trial whose files :func:`load_trial` refuses is kept with status
    ``failed`` and its :attr:`Trial.reason`.

    :param sweep: the sweep folder (``--out`` of ``python -m sb3_collapse.sweep``)
    :param collapse_tag: the collapse metric to read
    :param include_unfinished: also read the (partial) evaluation curves of unfinished trials
    :param tasks: keep only these task folders (``None``: all)
    :param variants: keep only these variant folders (``None``: all)
    :param progress: show the progress (:func:`~sb3_collapse.common.progress.progress_bar`)
    :return: the sweep
    :raises InputError: when the folder is missing, holds no (selected) trial, or no trial can be read
    """
    root = Path(sweep)
    if not root.is_dir():
        what = "does not exist" if not root.exists() else "is not a folder"
        raise InputError(f"sweep folder {root} {what}; give the out folder of a sweep.", parameter="sweep")
    found = trial_folders(root)
    if not found:
        raise InputError(f"no trial folders <task>/<variant>/seed_<k>/ under {root}; is it the out folder of a sweep?")
    order = variant_order(item[1] for item in found)
    found = sorted(found, key=lambda item: (item[0], order.index(item[1]), item[2]))
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
    trials = []
    for task, variant, seed, path in progress_bar(found, "reading trials", "trial", progress):
        try:
            trials.append(load_trial(task, variant, seed, path, collapse_tag, partial=include_unfinished))
        except InputError as error:
            reason = f"{str(error).rstrip('.')}; {DAMAGED_RESULT_WAY_OUT}."
            trials.append(Trial(task, variant, seed, path, str(RunStatus.FAILED), None, reason=reason))
    if all(trial.reason for trial in trials):
        raise InputError(f"no trial of {sweep} can be read; the first: {trials[0].reason}")
    return Sweep(path=Path(sweep), trials=trials)
