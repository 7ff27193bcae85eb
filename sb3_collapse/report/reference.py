"""The published DrQ-v2 evaluation curves (facebookresearch/drqv2, MIT), shipped in ``data/drqv2_curves.csv.gz``
(``task, seed, frame, episode_reward``; frames include the action repeat). Origin: ``data/README.md``."""

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
    :param task: our task name (``<domain>-<task>``) or env id
    :return: the reference data's name (``walker-walk`` -> ``walker_walk``, ``ball_in_cup-catch`` -> ``cup_catch``)
    """
    name = task.strip().lower().removeprefix("sb3_collapse/").removesuffix("-v0").replace("-", "_")
    return _REFERENCE_ALIASES.get(name, name)


@dataclass
class ReferenceCurves:
    """The published curves of one task on the frames every seed has: ``(len(seeds), len(frames))`` ``returns``."""

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


def load_reference_curves(task: str) -> ReferenceCurves | None:
    """
    :param task: our task name or the reference name
    :return: the published DrQ-v2 curves of the task, ``None`` when the data has no such task
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
    """Write the shipped ``.csv.gz`` ``path`` from the ``dmc_*.csv`` files of DrQ-v2's ``curves/`` ``folder``; return
    the rows written (an InputError without ``dmc_*.csv``)."""
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
