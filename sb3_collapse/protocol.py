"""The run-folder format in one place: the file names a run (and a sweep) writes, the CSV columns, the result file's
keys, and the atomic writers every module uses."""

from __future__ import annotations

import contextlib
import csv
import json
import os
import re
import tempfile
import traceback
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any

CONFIG_JSON = "config.json"  # the run's settings, written first (every value, and where preset ones came from)
RESULT_JSON = "result.json"  # the outcome, written last: a folder without it is unfinished (keys: RESULT_KEYS)
EVAL_CSV = "eval.csv"  # one row per scheduled evaluation (EVAL_FIELDS); the saved final model's is in the result
COLLAPSE_METRICS_CSV = "collapse_metrics.csv"  # one row per (collapse check, tag) (COLLAPSE_METRICS_FIELDS)
COLLAPSE_EVENTS_CSV = "collapse_events.csv"  # one row per intervention or escape of the reset rule
FINAL_MODEL = "final_model.zip"  # the final model, ``DrQv2.save``
CHECKPOINTS_DIR = "checkpoints"  # the run's checkpoints (run/checkpoints.py): one folder each, and the replay store
CHECKPOINT_FOLDER = "step_{step:012d}"  # a checkpoint's folder, named by the agent step it was taken at
CHECKPOINT_FOLDER_PATTERN = re.compile(r"^step_(\d{12})$")
CHECKPOINT_JSON = "checkpoint.json"  # written last into a checkpoint's folder, with the others' checksums
CHECKPOINT_MODEL = "model.zip"  # the model in a checkpoint (SB3's ``save``: weights, optimizers, counters)
CHECKPOINT_STATE = "state.pt"  # the rest of a checkpoint: random generators, episodes, callbacks, logger
REPLAY_DIR = "replay"  # the replay buffer's chunks, in :data:`CHECKPOINTS_DIR`, shared by the checkpoints
LOCK_FILE = "run.lock"  # the owner (pid, host) of a run folder while a process trains into it
PROGRESS_CSV = "progress.csv"  # SB3's CSV log (one row per log dump)
EXIT_INTERRUPTED = 75  # EX_TEMPFAIL: stopped by SIGTERM or SIGINT; run the same command again to resume
SNAPSHOTS_DIR = "snapshots"  # the run's snapshots (run/snapshots.py): encoder and actor at every evaluation
SNAPSHOT_FILE = "snapshot_{frames:010d}_frames.zip"  # a snapshot, named by its training frames (sorts by time)
ERROR_TXT = "error.txt"  # the traceback of a run that failed (:func:`write_failure`; a sweep's trial too)
SWEEP_JSON = "sweep.json"  # a sweep folder's settings
SWEEP_LOCK = "sweep.lock"  # while a sweep runs into its folder: the lock's owner (pid, host)
SWEEP_STOP = ".stop_requested"  # while a sweep's driver stops at a signal (its name): each trial checkpoints, stops
SWEEP_PROBE_DIR = "probe/{task}_{variant}"  # in a sweep folder: ``probe sweep``'s outputs per task and variant
PROBE_SUMMARY_JSON = "summary.json"  # written last into a probe's output folder: its summary (probe.summary_head)
FIGURE2_PNG = "figure2.png"  # Figure 2 in :data:`SWEEP_PROBE_DIR`
TABLES_1_6_CSV = "tables_1_6.csv"  # Tables 1-6 in :data:`SWEEP_PROBE_DIR`
REWARD_PREFIX = "reward:"  # of the probe's targets (and groups) that are reward inputs, e.g. ``reward:torso_height``

EVAL_FIELDS = ("frame", "step", "mean_reward", "std_reward", "episodes", "wall_time_s")
COLLAPSE_METRICS_FIELDS = ("frame", "step", "tag", "value")
COLLAPSE_EVENT_FIELDS = ("frame", "step", "event", "resets", "intervention", "detail")
"""``event``: ``reset`` (any intervention) or ``escape``; ``intervention``: the rule's (``reset``, ``redo``...);
``detail``: what the intervention did, one line."""
RESULT_KEYS = (
    "status", "task", "variant", "seed", "frames", "agent_steps", "final_eval", "saved_model_eval", "resets",
    "reset_frames", "escaped", "escape_frame", "wall_time_s", "timings", "resumes",
)  # fmt: skip
"""The keys of the result file, see :func:`sb3_collapse.run.runner.run_summary`."""
FINISHED = "finished"  # ``status`` of a finished run

SEED_FOLDER_PREFIX = "seed_"
SEED_FOLDER = re.compile(rf"^{SEED_FOLDER_PREFIX}(\d+)$")  # a sweep's trial folder: seed_<k>, <k> the seed


def trial_path(out: str | os.PathLike, task: str, variant: str, seed: int) -> Path:
    """:return: the folder of a sweep's trial, ``<out>/<task>/<variant>/seed_<seed>``"""
    return Path(out) / task / variant / f"{SEED_FOLDER_PREFIX}{seed}"


def snapshot_files(run_dir: str | os.PathLike) -> list[Path]:
    """:return: the snapshots of a run folder, in training order (another zip's name first)"""

    def frames(path: Path) -> int:
        match = re.search(r"_(\d+)_frames\.zip$", path.name)
        return int(match.group(1)) if match else -1

    return sorted((Path(run_dir) / SNAPSHOTS_DIR).glob("*.zip"), key=frames)


FAILURE_HEADER = "failed at agent step {step} (frame {frame})"  # first line of a failed run's error file


def write_failure(run_dir: str | os.PathLike, step: int, frame: int, error: BaseException) -> None:
    """Mark ``run_dir`` as failed at agent ``step`` and ``frame``: its error file gets :data:`FAILURE_HEADER` and
    ``error``'s traceback (best effort: nothing on a full or read-only disk, where the caller's error says so)."""
    lines = traceback.format_exception(type(error), error, error.__traceback__)
    header = FAILURE_HEADER.format(step=step, frame=frame)
    with contextlib.suppress(OSError):  # best effort: on a full or read-only disk, the error itself says so
        write_text_atomically(Path(run_dir) / ERROR_TXT, header + "\n" + "".join(lines))


def failed_before_training(run_dir: str | os.PathLike) -> bool:
    """:return: whether a run folder holds a run that failed before its first agent step (no result, an error file
    whose first line says step 0): a new run may take it"""
    run_dir = Path(run_dir)
    error_file = run_dir / ERROR_TXT
    if (run_dir / RESULT_JSON).exists() or not error_file.is_file():
        return False
    with error_file.open() as file:
        first = file.readline().strip()
    return first == FAILURE_HEADER.format(step=0, frame=0)


def blocking_file(folder: str | os.PathLike) -> Path | None:
    """:return: the file standing where ``folder`` or its nearest existing parent should be a folder, ``None`` when
    ``folder`` is one or can be created"""
    folder = Path(folder)
    for parent in (folder, *folder.parents):
        if parent.exists():
            return None if parent.is_dir() else parent
    return None


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike) -> Iterator[Path]:
    """A temporary path next to ``path`` (with its suffix: ``.zip`` for SB3's ``save``) to write into, flushed and
    renamed to ``path`` when the block ends without an error (removed after one), with a new file's permissions."""
    path = Path(path)
    handle, name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=f".partial{path.suffix}", dir=path.parent)
    os.close(handle)
    temporary = Path(name)
    try:
        yield temporary
        with temporary.open("rb+") as file:
            os.fsync(file.fileno())
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(temporary, 0o666 & ~umask)
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)


def write_text_atomically(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` into ``path`` atomically (:func:`atomic_output`): readers see the previous file or the new one."""
    with atomic_output(path) as temporary:
        temporary.write_text(text)


def write_json_atomically(path: str | os.PathLike, content: Any) -> None:
    """Write ``content`` (anything ``json.dumps`` takes) into ``path`` as indented JSON, atomically."""
    write_text_atomically(path, json.dumps(content, indent=2) + "\n")


def append_csv_rows(path: str | os.PathLike, fieldnames: Sequence[str], rows: Iterable[dict[str, Any]]) -> None:
    """
    Append rows to a CSV file, writing the header first when the file is new or empty.

    :param path: the CSV file (its folder must exist)
    :param fieldnames: the columns, in order
    :param rows: one dict per row, keyed by column
    :raises ValueError: when the file has another header: nothing is appended
    """

    path = Path(path)
    new_file = not path.exists() or path.stat().st_size == 0
    if not new_file:
        with path.open(newline="") as file:
            header = next(csv.reader(file), [])
        if header != list(fieldnames):
            raise ValueError(
                f"{path} has the columns {','.join(header)}, not {','.join(fieldnames)}: it was written by another "
                "version or another writer. Move it away (or write to another path); nothing was appended to it."
            )
    with path.open("a", newline="") as file:
        writer = csv.DictWriter(file, fieldnames=fieldnames)
        if new_file:
            writer.writeheader()
        writer.writerows(rows)
