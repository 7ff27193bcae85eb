"""
Read a sweep folder (the trial-folder contract of ``python -m sb3_collapse.sweep``) into one :class:`Trial` per
``<sweep>/<task>/<variant>/seed_<k>/`` folder.

A trial is **finished** when its result file (``protocol.RESULT_JSON``) exists and says ``"status": "finished"``;
every other trial folder
(no result file (``protocol.RESULT_JSON``) yet, or another status) is **unfinished**: it is counted and reported,
never mixed into the
statistics. Files are read with :mod:`csv` and :mod:`json` only; a malformed file raises :class:`InputError`
naming the file.
"""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from tqdm.auto import tqdm

from sb3_collapse.errors import InputError
from sb3_collapse.paper import PAPER
from sb3_collapse.protocol import COLLAPSE_METRICS_CSV, EVAL_CSV, FINISHED, RESULT_JSON, SEED_FOLDER
from sb3_collapse.run.lock import run_folder_owner

DEFAULT_COLLAPSE_TAG = PAPER.collapse_tag
RUNNING, UNFINISHED = "running", "unfinished"
"""Statuses of a trial without a result file: a process holds its run folder's lock (it trains now), or none does."""
"""The collapse metric that decides "stuck in action collapse" (the paper's reset rule reads the same one)."""


@dataclass
class Trial:
    """
    One trial folder of a sweep.

    :param task: the task folder name, e.g. ``"walker-walk"``
    :param variant: the variant folder name, e.g. ``"drqv2+reset"``
    :param seed: the seed of the ``seed_<k>`` folder
    :param path: the trial folder
    :param status: ``"finished"``, :data:`RUNNING` (no result file yet, and a process trains into the folder),
        :data:`UNFINISHED` (no result file, and no process: stopped, killed or failed; a sweep resumes it) or the
        ``status`` of the result file
    :param result: the parsed result file (``None`` without one)
    :param frames: evaluation frames (agent steps x action repeat), increasing, from evaluation file
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
    The trial folders ``<sweep>/<task>/<variant>/seed_<k>/`` of a sweep folder. Hidden folders (``.name``) are
    skipped; so is any folder that does not have this three-level shape (e.g. ``<sweep>/report/``).

    :param sweep: the sweep folder
    :return: ``(task, variant, seed, path)`` sorted by task, variant (:func:`variant_order`) and seed
    :raises InputError: when the folder does not exist or holds no trial folder
    """
    root = Path(sweep)
    if not root.exists():
        raise InputError(f"sweep folder {root} does not exist; give the out folder of a sweep.", parameter="sweep")
    if not root.is_dir():
        raise InputError(f"sweep {root} is not a folder; give the out folder of a sweep.", parameter="sweep")
    found = []
    for task_dir in sorted(path for path in root.iterdir() if path.is_dir() and not path.name.startswith(".")):
        for variant_dir in sorted(
            path for path in task_dir.iterdir() if path.is_dir() and not path.name.startswith(".")
        ):
            for seed_dir in variant_dir.iterdir():
                match = SEED_FOLDER.match(seed_dir.name)
                if match and seed_dir.is_dir():
                    found.append((task_dir.name, variant_dir.name, int(match.group(1)), seed_dir))
    if not found:
        raise InputError(f"no trial folders <task>/<variant>/seed_<k>/ under {root}; is it the out folder of a sweep?")
    variants = variant_order(item[1] for item in found)
    return sorted(found, key=lambda item: (item[0], variants.index(item[1]), item[2]))


def read_json(path: Path) -> dict[str, Any]:
    """
    :param path: a JSON file holding an object
    :return: the object
    :raises InputError: when the file is not a valid JSON object
    """
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise InputError(f"{path}: not a readable JSON file ({error}).") from error
    if not isinstance(data, dict):
        raise InputError(f"{path}: expected a JSON object, got {type(data).__name__}.")
    return data


def read_result(path: Path) -> dict[str, Any]:
    """
    Read and check a trial's result file: ``status`` (str); for a finished trial also ``resets`` (int >= 0),
    ``escaped`` (bool or null, may be absent) and ``saved_model_eval`` (the key of this version's files).

    :param path: the result file file
    :return: the parsed object
    :raises InputError: when the file is malformed
    """
    result = read_json(path)
    if not isinstance(result.get("status"), str):
        raise InputError(f"{path}: 'status' must be a string such as \"finished\", got {result.get('status')!r}.")
    if result["status"] == FINISHED:
        resets = result.get("resets")
        if isinstance(resets, bool) or not isinstance(resets, int) or resets < 0:
            raise InputError(f"{path}: 'resets' must be an integer >= 0, got {resets!r}.")
        if result.get("escaped") not in (None, True, False):
            raise InputError(f"{path}: 'escaped' must be true, false or null, got {result['escaped']!r}.")
        if "saved_model_eval" not in result:
            raise InputError(f"{path} has no 'saved_model_eval': it was written by another version of sb3-collapse.")
    return result


def _rows(path: Path, columns: tuple[str, ...]) -> Iterable[tuple[int, dict[str, str]]]:
    """The rows of a CSV file with at least ``columns``, with their line numbers."""
    try:
        with path.open(newline="") as file:
            reader = csv.DictReader(file)
            missing = [c for c in columns if c not in (reader.fieldnames or [])]
            if missing:
                raise InputError(
                    f"{path}: missing column(s) {', '.join(missing)} (header: {reader.fieldnames}); "
                    f"expected {', '.join(columns)}."
                )
            for row in reader:
                yield reader.line_num, row
    except (OSError, UnicodeDecodeError, csv.Error) as error:
        raise InputError(f"{path}: not a readable CSV file ({error}).") from error


def _number(path: Path, line: int, row: dict[str, str], column: str, kind: type) -> Any:
    """``row[column]`` as a float, or as an int (``"1000"`` or ``"1000.0"``) for ``kind=int``."""
    text = row.get(column)
    try:
        value = float(text)  # type: ignore[arg-type]
        if kind is int:
            if not value.is_integer():
                raise ValueError
            return int(value)
        return value
    except (TypeError, ValueError) as error:
        what = "an integer" if kind is int else "a number"
        raise InputError(f"{path}, line {line}: column {column!r} is {text!r}, not {what}.") from error


def read_eval_curve(path: Path, partial: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """
    Read an evaluation file (columns ``frame, step, mean_reward, ...``; one row per evaluation).

    :param path: the file
    :param partial: the file may still be written: a last row with fewer fields than the header is dropped
    :return: ``(frames, returns)``: frames (int, increasing) and the mean evaluation return at each
    :raises InputError: when the file is malformed (a row with a wrong number of fields, a value that is not a
        number, frames that repeat or decrease)
    """
    rows = list(_rows(path, ("frame", "mean_reward")))
    if partial and rows and None in rows[-1][1].values():
        rows = rows[:-1]
    frames, returns = [], []
    for line, row in rows:
        if None in row.values() or None in row:
            raise InputError(f"{path}, line {line}: the number of fields differs from the header's.")
        frames.append(_number(path, line, row, "frame", int))
        returns.append(_number(path, line, row, "mean_reward", float))
    frames_array = np.asarray(frames, dtype=np.int64)
    if np.any(np.diff(frames_array) <= 0):
        where = int(np.argmax(np.diff(frames_array) <= 0))
        raise InputError(
            f"{path}: frames must increase row by row, but frame {frames[where + 1]} follows {frames[where]}; "
            "was the trial folder written twice? Delete it and run the trial again."
        )
    return frames_array, np.asarray(returns, dtype=np.float64)


def read_collapse_metric(path: Path, tag: str = DEFAULT_COLLAPSE_TAG) -> tuple[np.ndarray, np.ndarray]:
    """
    One metric's values from a long-format collapse metrics file (columns ``frame, step, tag, value``).

    :param path: the file
    :param tag: the TensorBoard tag to read, e.g. ``PAPER.collapse_tag``
    :return: ``(frames, values)`` sorted by frame; rows whose value is not finite (nan, inf) are dropped
    :raises InputError: when the file is malformed or a value is not a number
    """
    frames, values = [], []
    for line, row in _rows(path, ("frame", "tag", "value")):
        if None in row.values() or None in row:
            raise InputError(f"{path}, line {line}: the number of fields differs from the header's.")
        if row["tag"] != tag:
            continue
        value = _number(path, line, row, "value", float)
        if math.isfinite(value):
            frames.append(_number(path, line, row, "frame", int))
            values.append(value)
    order = np.argsort(np.asarray(frames, dtype=np.int64), kind="stable")
    return np.asarray(frames, dtype=np.int64)[order], np.asarray(values, dtype=np.float64)[order]


def read_collapse_metrics(path: Path, tags: Iterable[str] | None = None) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """
    Every metric (or the ``tags``) of a long-format collapse metrics file, in one pass.

    :param path: the file (columns ``frame, step, tag, value``)
    :param tags: the tags to keep (``None``: all)
    :return: tag -> ``(frames, values)`` sorted by frame, non-finite values dropped (tags in file order)
    :raises InputError: when the file is malformed or a value is not a number
    """
    wanted = None if tags is None else set(tags)
    columns: dict[str, tuple[list[int], list[float]]] = {}
    for line, row in _rows(path, ("frame", "tag", "value")):
        if None in row.values() or None in row:
            raise InputError(f"{path}, line {line}: the number of fields differs from the header's.")
        if wanted is not None and row["tag"] not in wanted:
            continue
        value = _number(path, line, row, "value", float)
        if math.isfinite(value):
            frames, values = columns.setdefault(row["tag"], ([], []))
            frames.append(_number(path, line, row, "frame", int))
            values.append(value)
    metrics = {}
    for tag, (frames, values) in columns.items():
        order = np.argsort(np.asarray(frames, dtype=np.int64), kind="stable")
        metrics[tag] = (np.asarray(frames, dtype=np.int64)[order], np.asarray(values, dtype=np.float64)[order])
    return metrics


def read_collapse_events(path: Path) -> list[tuple[int, str]]:
    """
    The events of a collapse events file (``protocol.COLLAPSE_EVENTS_CSV``).

    :param path: the file
    :return: ``(frame, event)`` in file order, ``event`` being ``"reset"`` (any intervention) or ``"escape"``
    :raises InputError: when the file is malformed
    """
    events = []
    for line, row in _rows(path, ("frame", "event")):
        if row.get("frame") is None or row.get("event") is None:
            raise InputError(f"{path}, line {line}: the number of fields differs from the header's.")
        events.append((_number(path, line, row, "frame", int), row["event"]))
    return events


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
    result_path = path / RESULT_JSON
    result = read_result(result_path) if result_path.exists() else None
    if result is not None:
        status = result["status"]
    else:  # no result: running only while a process holds the folder's lock, else stopped before its end
        status = RUNNING if run_folder_owner(path) is not None else UNFINISHED
    trial = Trial(task=task, variant=variant, seed=seed, path=path, status=status, result=result)
    eval_path = path / EVAL_CSV
    if trial.finished:
        for key, expected in (("task", task), ("variant", variant), ("seed", seed)):
            if key in result and result[key] != expected:  # type: ignore[index]
                trial.notes.append(
                    f"{result_path}: {key} is {result[key]!r} but the folder says {expected!r}; "  # type: ignore[index]
                    "the folder names are used"
                )
        if not eval_path.exists():
            raise InputError(f"{eval_path} is missing although {result_path} says the trial finished.")
        trial.frames, trial.returns = read_eval_curve(eval_path)
        if len(trial.frames) == 0:
            raise InputError(f"{eval_path} has no evaluation rows although {result_path} says the trial finished.")
        metrics_path = path / COLLAPSE_METRICS_CSV
        if metrics_path.exists():
            trial.collapse_frames, trial.collapse_values = read_collapse_metric(metrics_path, collapse_tag)
    elif partial:
        if not eval_path.exists():
            trial.notes.append(f"{eval_path}: no evaluation yet")
        else:
            try:
                trial.frames, trial.returns = read_eval_curve(eval_path, partial=True)
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
