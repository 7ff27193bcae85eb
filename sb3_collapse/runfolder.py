"""Reading run folders, the only module that does: status, result, evaluations, final return, collapse metrics and
events, a sweep's trial folders. The file names and the writers are in :mod:`sb3_collapse.protocol`."""

from __future__ import annotations

__all__ = ["RunStatus", "final_return", "read_evaluations", "read_result", "run_status"]

import contextlib
import csv
import errno
import json
import math
import os
import re
import socket
from collections.abc import Iterable
from enum import Enum
from pathlib import Path
from typing import Any

import numpy as np

from sb3_collapse.errors import InputError
from sb3_collapse.protocol import (
    CONFIG_JSON,
    ERROR_TXT,
    EVAL_CSV,
    FINISHED,
    LOCK_FILE,
    RESULT_JSON,
    SEED_FOLDER,
    failed_before_training,
)


class RunStatus(str, Enum):
    """What a run folder holds, one word for ``train``, the sweep and the report (checked in this order: finished,
    running, new, failed, unfinished; docs/sweeps.md). Anything else is :data:`NOT_A_RUN`."""

    NEW = "new"
    RUNNING = "running"
    UNFINISHED = "unfinished"
    FINISHED = FINISHED
    FAILED = "failed"

    def __str__(self) -> str:
        return self.value

    __format__ = str.__format__


NOT_A_RUN = "not a run"  # the word shown for a folder that run_status does not take for a run folder
RESUMABLE = (RunStatus.UNFINISHED, RunStatus.FAILED)  # what a run with the same settings resumes (newest checkpoint)


def run_status(
    folder: str | os.PathLike, check_lock: bool = True, result: dict[str, Any] | None = None
) -> RunStatus | None:
    """
    :param folder: a run folder (or where one would go)
    :param check_lock: whether to tell :attr:`RunStatus.RUNNING`; ``False`` for the process that holds the lock
    :param result: its result file as :func:`read_result` read it, if the caller has (not read again)
    :return: its :class:`RunStatus`, ``None`` when it is not a run folder
    """
    folder = Path(folder)
    if not folder.exists():
        return RunStatus.NEW
    if not folder.is_dir():
        return None
    result = read_result(folder) if result is None else result
    if result is not None and result.get("status") == FINISHED:
        return RunStatus.FINISHED
    if check_lock and run_folder_owner(folder) is not None:
        return RunStatus.RUNNING
    if not any(entry.name != LOCK_FILE for entry in folder.iterdir()) or failed_before_training(folder):
        return RunStatus.NEW
    if (folder / ERROR_TXT).is_file() or (folder / RESULT_JSON).exists():
        return RunStatus.FAILED
    return RunStatus.UNFINISHED if (folder / CONFIG_JSON).is_file() else None


def run_folder_owner(folder: str | os.PathLike, lock_file: str = LOCK_FILE) -> str | None:
    """:return: the owner of ``folder``'s lock (:class:`~sb3_collapse.run.lock.RunLock` on ``lock_file``: a sweep's
    folder has its own) as its file says, ``None`` when no process holds it (an owner on this host whose pid is gone
    does not; else the lock is tried for an instant)"""
    import fcntl

    path = Path(folder) / lock_file
    try:
        owner = path.read_text().strip()
    except OSError:
        return None
    match = re.match(r"pid (\d+) on host (\S+)", owner)
    if match is not None and match.group(2) == socket.gethostname():
        try:
            os.kill(int(match.group(1)), 0)
        except ProcessLookupError:
            return None
        except PermissionError:  # another user's process: alive
            pass
    with contextlib.suppress(OSError), open(path) as file:  # the shared lock goes with the file
        try:
            fcntl.flock(file.fileno(), fcntl.LOCK_SH | fcntl.LOCK_NB)
        except OSError as error:
            if error.errno in (errno.EAGAIN, errno.EACCES):
                return owner or "another process"
            raise
    return None


def read_json(path: str | os.PathLike) -> dict[str, Any]:
    """The one reader of the run folder's JSON files: a run's or a sweep's settings (:data:`CONFIG_JSON`,
    :data:`SWEEP_JSON`), a result, a checkpoint's file.

    :return: the object of the JSON file ``path``
    :raises InputError: naming the file, when it is not a readable JSON object (an ``OSError`` or bad JSON included)"""
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise InputError(f"{path}: not a readable JSON file ({error}).") from None
    if not isinstance(data, dict):
        raise InputError(f"{path}: expected a JSON object, got {type(data).__name__}.")
    return data


def read_result(folder: str | os.PathLike, strict: bool = False) -> dict[str, Any] | None:
    """
    :param folder: a run folder
    :param strict: raise for a result file that is not a readable JSON object, instead of returning ``None``
    :return: its result file (keys :data:`~sb3_collapse.protocol.RESULT_KEYS`), ``None`` without one (or an unreadable
        one, unless ``strict``)
    :raises InputError: with ``strict``, one line naming the file and the reason
    """
    path = Path(folder) / RESULT_JSON
    if not path.exists():
        return None
    try:
        return read_json(path)
    except InputError:
        if strict:
            raise
        return None


def check_result_version(folder: str | os.PathLike, result: dict[str, Any]) -> None:
    """:raises InputError: naming the file, when the ``result`` of a finished run in ``folder`` has no
    ``saved_model_eval`` (another version's)"""
    if result.get("status") == FINISHED and "saved_model_eval" not in result:
        raise InputError(
            f"{Path(folder) / RESULT_JSON} has no 'saved_model_eval': it was written by another version of "
            "sb3-collapse."
        )


DAMAGED_RESULT_WAY_OUT = "move the folder aside to train this seed again"
"""What to do with a run folder whose result file is unreadable (its status stays ``failed``; nothing repairs it)."""


def unreadable_result(folder: str | os.PathLike) -> str | None:
    """:return: for a run folder whose result file exists and cannot be read, one line: :func:`read_result`'s reason
    and :data:`DAMAGED_RESULT_WAY_OUT`; ``None`` otherwise"""
    try:
        read_result(folder, strict=True)
    except InputError as error:
        return f"{str(error).rstrip('.')}; {DAMAGED_RESULT_WAY_OUT}."
    return None


def csv_rows(path: Path, columns: tuple[str, ...], partial: bool = False) -> list[tuple[int, dict[str, str]]]:
    """:return: ``(line number, row)`` of each row of the CSV file ``path`` (with ``partial``, one still written: a
    short last row dropped); :raises InputError: naming the file (and line): unreadable, a column of ``columns``
    missing, a row of another length"""
    try:
        with path.open(newline="") as file:
            reader = csv.DictReader(file)
            missing = [c for c in columns if c not in (reader.fieldnames or [])]
            if missing:
                header = f"(header: {reader.fieldnames}); expected {', '.join(columns)}"
                raise InputError(f"{path}: missing column(s) {', '.join(missing)} {header}.")
            rows = [(reader.line_num, row) for row in reader]
    except (OSError, UnicodeDecodeError, csv.Error) as error:
        raise InputError(f"{path}: not a readable CSV file ({error}).") from None
    if partial and rows and None in rows[-1][1].values():
        rows = rows[:-1]
    for line, row in rows:
        if None in row.values() or None in row:
            raise InputError(f"{path}, line {line}: the number of fields differs from the header's.")
    return rows


def csv_number(path: Path, line: int, row: dict[str, str], column: str, kind: type) -> Any:
    """:return: ``row[column]`` as a float, or as an int (``"1000"`` or ``"1000.0"``) for ``kind=int``"""
    text = row.get(column)
    try:
        value = float(text)  # type: ignore[arg-type]
        if kind is int and not value.is_integer():
            raise ValueError
        return int(value) if kind is int else value
    except (TypeError, ValueError):
        what = "an integer" if kind is int else "a number"
        raise InputError(f"{path}, line {line}: column {column!r} is {text!r}, not {what}.") from None


def read_evaluations(folder: str | os.PathLike, partial: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """
    The scheduled evaluations of a run, from its evaluation file.

    :param folder: a run folder
    :param partial: the file may still be written (an unfinished run): an incomplete last row is dropped
    :return: ``(frames, returns)``: the frames (int, increasing) and the mean evaluation return at each
    :raises InputError: naming the file when it is missing or malformed (a row of another length, a value not a
        number, frames that do not increase)
    """
    path = Path(folder) / EVAL_CSV
    if not path.exists():
        raise InputError(f"{path} is missing.")
    rows = csv_rows(path, ("frame", "mean_reward"), partial=partial)
    frames = np.asarray([csv_number(path, line, row, "frame", int) for line, row in rows], dtype=np.int64)
    returns = np.asarray([csv_number(path, line, row, "mean_reward", float) for line, row in rows], dtype=np.float64)
    if np.any(np.diff(frames) <= 0):
        where = int(np.argmax(np.diff(frames) <= 0))
        raise InputError(
            f"{path}: frames must increase row by row, but frame {frames[where + 1]} follows {frames[where]}; "
            "was the run folder written twice? Delete it and run the trial again."
        )
    return frames, returns


def read_collapse_metrics(path: Path, tags: Iterable[str] | None = None) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """
    :param path: a collapse metrics file (columns ``frame, step, tag, value``)
    :param tags: the tags to keep (``None``: all)
    :return: tag -> ``(frames, values)`` sorted by frame, non-finite values dropped (tags in file order)
    :raises InputError: when the file is malformed or a value is not a number
    """

    wanted = None if tags is None else set(tags)
    columns: dict[str, tuple[list[int], list[float]]] = {}
    for line, row in csv_rows(path, ("frame", "tag", "value")):
        if wanted is not None and row["tag"] not in wanted:
            continue
        value = csv_number(path, line, row, "value", float)
        if math.isfinite(value):
            frames, values = columns.setdefault(row["tag"], ([], []))
            frames.append(csv_number(path, line, row, "frame", int))
            values.append(value)
    metrics = {}
    for tag, (frames, values) in columns.items():
        order = np.argsort(np.asarray(frames, dtype=np.int64), kind="stable")
        metrics[tag] = (np.asarray(frames, dtype=np.int64)[order], np.asarray(values, dtype=np.float64)[order])
    return metrics


def read_collapse_events(path: Path) -> list[tuple[int, str]]:
    """
    :param path: a collapse events file
    :return: ``(frame, event)`` in file order, ``event`` being ``"reset"`` (any intervention) or ``"escape"``
    :raises InputError: when the file is malformed
    """
    return [
        (csv_number(path, line, row, "frame", int), row["event"]) for line, row in csv_rows(path, ("frame", "event"))
    ]


def trial_folders(sweep: str | os.PathLike) -> list[tuple[str, str, int, Path]]:
    """:return: the trial folders ``<sweep>/<task>/<variant>/seed_<k>/`` as ``(task, variant, seed, path)``, sorted
    (hidden folders and folders of another shape skipped; empty when ``sweep`` is not a folder)"""

    def folders(parent: Path) -> list[Path]:
        if not parent.is_dir():
            return []
        return sorted(path for path in parent.iterdir() if path.is_dir() and not path.name.startswith("."))

    found = [
        (task.name, variant.name, int(match.group(1)), seed)
        for task in folders(Path(sweep))
        for variant in folders(task)
        for seed in folders(variant)
        if (match := SEED_FOLDER.match(seed.name))
    ]
    return sorted(found, key=lambda item: item[:3])


def final_return_of(returns: np.ndarray) -> float | None:
    """
    The paper's final return of a run, the one its agent classes read: the mean return of the last scheduled
    evaluation (not the saved final model's, which the result file holds).

    :param returns: the mean return of each scheduled evaluation, in order (:func:`read_evaluations`)
    :return: the last one, ``None`` without any
    """
    return float(returns[-1]) if len(returns) else None


def final_return(folder: str | os.PathLike) -> float | None:
    """
    :param folder: a run folder
    :return: its :func:`final_return_of`; ``None`` when the run is not finished, its result file is of another
        version, or its evaluation file is missing, malformed or empty
    """
    result = read_result(folder)
    if result is None or run_status(folder, result=result) != RunStatus.FINISHED:
        return None
    try:
        check_result_version(folder, result)
        _, returns = read_evaluations(folder)
    except InputError:
        return None
    return final_return_of(returns)
