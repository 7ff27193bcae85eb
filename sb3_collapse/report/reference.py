"""
The published DrQ-v2 evaluation curves (facebookresearch/drqv2, folder ``curves/``, MIT licence), shipped in
``sb3_collapse/report/data/drqv2_curves.csv.gz``: columns ``task, seed, frame, episode_reward``, one row per
(task, seed, evaluation), 24 DMC tasks, returns rounded to 0.01. ``frame`` counts environment frames (action
repeat included), the unit of our evaluation files. See ``data/README.md`` for the origin.
"""

from __future__ import annotations

import csv
import functools
import gzip
import io
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sb3_collapse.errors import InputError

REFERENCE_FILE = Path(__file__).resolve().parent / "data" / "drqv2_curves.csv.gz"
REFERENCE_LABEL = "DrQ-v2 published"

# DrQ-v2 writes the ball_in_cup domain as "cup".
_REFERENCE_ALIASES = {"ball_in_cup_catch": "cup_catch"}


def reference_task_name(task: str) -> str:
    """
    The reference data's name of one of our tasks: ``walker-walk`` -> ``walker_walk``, ``cup-catch`` and
    ``ball_in_cup-catch`` -> ``cup_catch``. Registered env ids (``sb3_collapse/walker-walk-v0``) are accepted.

    :param task: our task name (``<domain>-<task>``) or env id
    :return: the name in the reference data (``<domain>_<task>``)
    """
    name = task.strip().lower()
    name = name.removeprefix("sb3_collapse/").removesuffix("-v0")
    name = name.replace("-", "_")
    return _REFERENCE_ALIASES.get(name, name)


@dataclass
class ReferenceCurves:
    """
    The published curves of one task, aligned on the frames that every seed has.

    :param task: the reference task name, e.g. ``walker_walk``
    :param seeds: the seeds, sorted
    :param frames: the evaluation frames (action repeat included)
    :param returns: ``(len(seeds), len(frames))`` evaluation returns
    """

    task: str
    seeds: np.ndarray
    frames: np.ndarray
    returns: np.ndarray


@functools.lru_cache(maxsize=1)
def _reference_rows(path: Path = REFERENCE_FILE) -> dict[str, dict[int, dict[int, float]]]:
    """task -> seed -> frame -> return, read once."""
    if not path.exists():
        raise InputError(f"the reference curves {path} are missing; reinstall sb3-collapse with its package data.")
    table: dict[str, dict[int, dict[int, float]]] = defaultdict(lambda: defaultdict(dict))
    with gzip.open(path, "rt", newline="") as file:
        for row in csv.DictReader(file):
            table[row["task"]][int(row["seed"])][int(row["frame"])] = float(row["episode_reward"])
    return {task: dict(seeds) for task, seeds in table.items()}


def reference_tasks() -> list[str]:
    """The reference data's task names, sorted."""
    return sorted(_reference_rows())


def load_reference_curves(task: str) -> ReferenceCurves | None:
    """
    The published DrQ-v2 curves of a task, on the frames that every seed of the task has.

    :param task: our task name (``walker-walk``, ``cup-catch``, ...) or the reference name (``walker_walk``)
    :return: the curves, or ``None`` when the reference data has no such task
    """
    name = reference_task_name(task)
    seeds = _reference_rows().get(name)
    if seeds is None:
        return None
    seed_ids = np.array(sorted(seeds), dtype=np.int64)
    frames = sorted(set.intersection(*(set(seeds[s]) for s in seed_ids)))
    returns = np.array([[seeds[s][f] for f in frames] for s in seed_ids], dtype=np.float64)
    return ReferenceCurves(task=name, seeds=seed_ids, frames=np.array(frames, dtype=np.int64), returns=returns)


def pack_reference_curves(folder: str | Path, path: str | Path, decimals: int = 2) -> int:
    """
    Build the shipped data file from the ``dmc_<task>.csv`` files of DrQ-v2's ``curves/`` folder (columns
    ``agent, task, seed, frame, episode_reward, hour``): keep ``task, seed, frame, episode_reward``, round the
    return to ``decimals`` and gzip.

    :param folder: the folder of ``dmc_*.csv`` files
    :param path: the ``.csv.gz`` file to write
    :param decimals: decimals kept of ``episode_reward``
    :return: the number of rows written
    :raises InputError: when the folder holds no ``dmc_*.csv``
    """
    files = sorted(Path(folder).glob("dmc_*.csv"))
    if not files:
        raise InputError(f"no dmc_*.csv files in {folder}; give DrQ-v2's curves/ folder.")
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(["task", "seed", "frame", "episode_reward"])
    count = 0
    for file in files:
        with file.open(newline="") as handle:
            for row in csv.DictReader(handle):
                writer.writerow(
                    [row["task"], int(row["seed"]), int(row["frame"]), f"{float(row['episode_reward']):.{decimals}f}"]
                )
                count += 1
    # mtime=0: the same input gives the same bytes.
    Path(path).write_bytes(gzip.compress(buffer.getvalue().encode(), compresslevel=9, mtime=0))
    return count
