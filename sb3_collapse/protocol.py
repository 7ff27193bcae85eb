"""
The action-collapse paper's protocol numbers and the run-folder format, in one place.

- :data:`PAPER` (a frozen :class:`PaperProtocol`): the numbers of Chen, Zhu & Perrault, *Understanding Learned
  Representations and Action Collapse in Visual Reinforcement Learning*, each with the passage it comes from.
  :class:`~sb3_collapse.CollapseReset`, :class:`~sb3_collapse.CollapseMetrics`, the train CLI, the sweep, the
  rl_zoo3 launcher and the report take their defaults from it.
- The **run folder**: what ``python -m sb3_collapse.train`` writes into one run's folder (and a sweep into each
  ``<out>/<task>/<variant>/seed_<k>/``): the file names, the CSV columns, the keys of the result file, and the
  atomic writers every module uses. The report and the sweep read the same names from here.

DrQ-v2's own per-task hyperparameters (budgets, schedules, batch sizes...) are in :mod:`sb3_collapse.presets`.
"""

from __future__ import annotations

import contextlib
import csv
import json
import os
import re
import tempfile
import traceback
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any


@dataclass(frozen=True)
class PaperProtocol:
    """
    The paper's protocol numbers. Frames count environment frames (agent steps x action repeat).

    :param check_every_frames: frames between two evaluations and two computations of the collapse metrics
        (Section 4.1: "The total number of training frames is 1.1e6 and there is an evaluation every 1e4 frames,
        resulting in x in [0, 109] on the x-axes for all the figures regarding VRL training"; the rule's
        "computations" of Section 5.2): :attr:`evaluations` evaluations, at frames 0, 1e4, ..., 1.09e6
    :param window_frames: the reset rule's window (Section 5.2: "reset the training from scratch every 2e5
        frames", the end of DrQ-v2's exploration decay, x = 20 in Figure 4)
    :param threshold: a gradient norm above it is healthy (Section 5.2: "a gradient norm larger than 0.001")
    :param patience: consecutive healthy computations that mean an escape (Section 5.2: "of consecutive five
        computations")
    :param layer: the layer whose gradient norm the rule reads (Section 5.2: "the gradient norm of mlp1")
    :param success_return: final return of a well-performing agent, at least (Section 4.1: "more than 900
        rewards"; Figure 3: "successful (rewards >= 900)")
    :param failure_return: final return of a poorly performing agent, below (Section 4.1: "less than 30 rewards")
    :param last_evals: evaluations averaged for the across-seed standard deviation (Section 5.2: "the average
        standard deviation over the last ten evaluations")
    :param percentiles: the band of Figure 5, in percent ("the 5th percentile and the 95th percentile")
    :param figure5_seeds: seeds per task and variant of Figure 5 ("40 seeds")
    :param figure5_tasks: the tasks of Figure 5 (walker_walk, hopper_stand, finger_spin)
    :param train_frames: frames of a run in Sections 4 and 5 (Section 4.1: "The total number of training frames is
        1.1e6")
    :param stage_frames: the four training stages of Tables 1-7 (their columns "x = 0, 35, 70, 110", in
        evaluations of 1e4 frames); a shorter run is read at the same fractions of its own length
    """

    check_every_frames: int = 10_000
    window_frames: int = 200_000
    threshold: float = 1e-3
    patience: int = 5
    layer: str = "mlp1"
    success_return: float = 900.0
    failure_return: float = 30.0
    last_evals: int = 10
    percentiles: tuple[float, float] = (5.0, 95.0)
    figure5_seeds: int = 40
    figure5_tasks: tuple[str, ...] = ("walker-walk", "hopper-stand", "finger-spin")
    train_frames: int = 1_100_000
    stage_frames: tuple[int, ...] = (0, 350_000, 700_000, 1_100_000)

    @property
    def stage_fractions(self) -> tuple[float, ...]:
        """:attr:`stage_frames` as fractions of :attr:`train_frames` (0, 0.32, 0.64, 1)."""
        return tuple(frame / self.train_frames for frame in self.stage_frames)

    @property
    def evaluations(self) -> int:
        """The evaluations of a run, the paper's x in [0, 109]: 110 (:func:`evaluation_schedule` of its budget)."""
        return len(evaluation_schedule(self.train_frames, self.check_every_frames))

    @property
    def collapse_tag(self) -> str:
        """The ``collapse_metrics.csv`` / TensorBoard tag of the rule's metric (``collapse/mlp1/grad_norm``)."""
        return metric_tag(self.layer, "grad_norm")


PAPER = PaperProtocol()
"""The paper's protocol."""


@dataclass(frozen=True)
class PaperResult:
    """
    The paper's headline numbers of one task of Figure 5 (Section 5.2, "Results"), DrQ-v2 against DrQ-v2 plus the
    rule, 40 seeds each.

    :param task: the task, ``<domain>-<task>``
    :param seeds: seeds per variant ("The performance comparison of 40 seeds", Figure 5)
    :param stuck_baseline: DrQ-v2's seeds stuck in action collapse ("we count the number of seeds stuck in action
        collapse continuously. There are 13, 8, and 7 seeds out of 40 respectively for DrQ-v2")
    :param stuck_rule: the rule's ("In comparison, all 40 seeds of ours escape action collapse")
    :param std_baseline: DrQ-v2's "average standard deviation over the last ten evaluations" ("drops a lot, from
        418.2 to 38.2, from 359.5 to 93.8, and from 362.7 to 116.2 for the three tasks, respectively")
    :param std_rule: the same with the rule
    """

    task: str
    seeds: int
    stuck_baseline: int
    stuck_rule: int
    std_baseline: float
    std_rule: float


PAPER_RESULTS: tuple[PaperResult, ...] = (
    PaperResult("walker-walk", 40, 13, 0, 418.2, 38.2),
    PaperResult("hopper-stand", 40, 8, 0, 359.5, 93.8),
    PaperResult("finger-spin", 40, 7, 0, 362.7, 116.2),
)
"""The paper's headline numbers, in the order of its tasks (walker_walk, hopper_stand, finger_spin: Section 5.2)."""

PROPOSITION_1 = (
    "Supposing the number of training frames is n · m (m is the frames where the exploration decreases to the "
    "smallest) and the probability of getting stuck in action collapse is p, then the probability of escaping action "
    "collapse when applying our proposed rule is 1 - p^n."
)
"""Proposition 1 of the paper (Section 5.2), word for word."""


def evaluation_schedule(frames: int, every_frames: int, frames_per_step: int = 1) -> list[int]:
    """
    The frames of a run's scheduled evaluations, as the reference (facebookresearch/drqv2's ``train.py``) has them:
    one before the first agent step (frame 0), then one every ``every_frames`` frames while the run still has agent
    steps to take, never at the budget's end (the reference's loop stops there). For the paper's budget of 1.1e6
    frames and an evaluation every 1e4 frames: 0, 1e4, ..., 1.09e6, 110 evaluations ("x in [0, 109]", Section
    4.1). The paper's statistics (the last ten evaluations, the 900/30 classes) come from these; the evaluation of
    the saved final model (at ``frames``) is not one of them.

    :param frames: the run's budget, in frames
    :param every_frames: frames between two evaluations (> 0)
    :param frames_per_step: frames an agent step adds (action repeat x environments): an evaluation falls on the
        first agent step at or after its frame
    :return: the frames, increasing
    """
    if every_frames <= 0 or frames_per_step <= 0:
        raise ValueError(f"every_frames and frames_per_step must be > 0, got {every_frames} and {frames_per_step}.")
    schedule = []
    for target in range(0, frames, every_frames):
        frame = -(-target // frames_per_step) * frames_per_step
        if frame < frames and (not schedule or frame > schedule[-1]):
            schedule.append(frame)
    return schedule


def metric_tag(layer: str, metric: str) -> str:
    """
    :param layer: a named layer (``"mlp1"``)
    :param metric: a metric name (``"grad_norm"``, ``"numerical_rank"``...)
    :return: its TensorBoard and ``collapse_metrics.csv`` tag, ``collapse/<layer>/<metric>``
    """
    return f"collapse/{layer}/{metric}"


# ---------------------------------------------------------------------------------------------- the run folder
CONFIG_JSON = "config.json"
"""The run's settings, written first (every value, and for preset settings whether it came from the preset)."""
RESULT_JSON = "result.json"
"""The outcome, written last and atomically: a folder without it is an unfinished run (keys: :data:`RESULT_KEYS`)."""
EVAL_CSV = "eval.csv"
"""One row per scheduled evaluation (columns :data:`EVAL_FIELDS`, frames :func:`evaluation_schedule`); the saved
final model's evaluation is in the result file (``saved_model_eval``), not here. Files of earlier versions end
with that evaluation, at the run's last frame: the report leaves it out."""
COLLAPSE_METRICS_CSV = "collapse_metrics.csv"
"""One row per (collapse check, tag), long format (columns :data:`COLLAPSE_METRICS_FIELDS`)."""
COLLAPSE_EVENTS_CSV = "collapse_events.csv"
"""One row per intervention (reset...) or escape of the reset rule (columns :data:`COLLAPSE_EVENT_FIELDS`)."""
FINAL_MODEL = "final_model.zip"
"""The final model, ``DrQv2.save``."""
CHECKPOINTS_DIR = "checkpoints"
"""The run's checkpoints, to resume it (:mod:`sb3_collapse.checkpoints`): one folder each, and the replay store."""
CHECKPOINT_FOLDER = "step_{step:012d}"
"""One checkpoint's folder in :data:`CHECKPOINTS_DIR`, named by the agent step (transitions) it was taken at."""
CHECKPOINT_FOLDER_PATTERN = re.compile(r"^step_(\d{12})$")
CHECKPOINT_JSON = "checkpoint.json"
"""Written last into a checkpoint's folder (checksums of the others): a folder without it is not a checkpoint."""
CHECKPOINT_MODEL = "model.zip"
"""The model in a checkpoint (SB3's ``save``: weights, optimizers, counters)."""
CHECKPOINT_STATE = "state.pt"
"""Everything else in a checkpoint: random generators, environments' episodes, callbacks, logger."""
REPLAY_DIR = "replay"
"""The replay buffer's chunks, in :data:`CHECKPOINTS_DIR`, shared by the checkpoints."""
LOCK_FILE = "run.lock"
"""The owner (pid, host) of a run folder while a process trains into it."""
PROGRESS_CSV = "progress.csv"
"""SB3's CSV log (one row per log dump)."""
EXIT_INTERRUPTED = 75
"""Exit status of ``python -m sb3_collapse.train`` stopped by SIGTERM or SIGINT after writing a checkpoint, of the
sweep whose trials did so, and of the probe stopped before writing anything (``EX_TEMPFAIL``: run the same command
again to resume)."""
PROBE_CHECKPOINTS_DIR = "probe_checkpoints"
"""The weights the probe needs (encoder and actor), one zip per evaluation (:data:`PROBE_CHECKPOINT`)."""
PROBE_CHECKPOINT = "probe_{frames:010d}_frames.zip"
"""A probe checkpoint's file name in :data:`PROBE_CHECKPOINTS_DIR`: the training frames, 10 digits (sorts by time)."""
ERROR_TXT = "error.txt"
"""The traceback of a run that failed (:func:`write_failure`; a sweep's trial too)."""
SWEEP_JSON = "sweep.json"
"""A sweep folder's settings."""
SWEEP_STOP = ".stop_requested"
"""In a sweep folder while its driver stops at a SIGTERM or SIGINT: the signal's name. Each running trial, on any
node, writes a checkpoint and stops when it sees the file; the driver deletes it before it exits."""
SWEEP_PROBE_DIR = "probe/{task}_{variant}"
"""Inside a sweep folder: the outputs of ``python -m sb3_collapse.probe sweep`` for one task and variant (Figure 2)."""
FIGURE2_PNG = "figure2.png"
"""Figure 2 in :data:`SWEEP_PROBE_DIR`."""
TABLES_1_6_CSV = "tables_1_6.csv"
"""Tables 1-6 in :data:`SWEEP_PROBE_DIR`."""

EVAL_FIELDS = ("frame", "step", "mean_reward", "std_reward", "episodes", "wall_time_s")
COLLAPSE_METRICS_FIELDS = ("frame", "step", "tag", "value")
COLLAPSE_EVENT_FIELDS = ("frame", "step", "event", "resets", "intervention", "detail")
"""``event``: ``reset`` (any intervention) or ``escape``; ``intervention``: the rule's (``reset``, ``redo``...);
``detail``: what the intervention did, one line. Files of earlier versions have the first four columns only."""
RESULT_KEYS = (
    "status",
    "task",
    "variant",
    "seed",
    "frames",
    "agent_steps",
    "final_eval",
    "saved_model_eval",
    "resets",
    "reset_frames",
    "escaped",
    "escape_frame",
    "wall_time_s",
    "timings",
    "resumes",
)
"""The keys of the result file, see :func:`sb3_collapse.run.runner.run_summary`."""
FINISHED = "finished"
"""``status`` of a finished run."""

SEED_FOLDER_PREFIX = "seed_"
SEED_FOLDER = re.compile(rf"^{SEED_FOLDER_PREFIX}(\d+)$")
"""The name of a sweep's trial folder: ``seed_<k>`` with ``<k>`` the seed."""


def trial_path(out: str | os.PathLike, task: str, variant: str, seed: int) -> Path:
    """
    :param out: a sweep folder
    :param task: the task, ``<domain>-<task>``
    :param variant: the variant name
    :param seed: the seed
    :return: the trial's folder, ``<out>/<task>/<variant>/seed_<seed>``
    """
    return Path(out) / task / variant / f"{SEED_FOLDER_PREFIX}{seed}"


FAILURE_HEADER = "failed at agent step {step} (frame {frame})"
"""First line of the error file that a run writes into its folder when it fails."""


def write_failure(run_dir: str | os.PathLike, step: int, frame: int, error: BaseException) -> None:
    """
    Mark a run folder as failed: its error file (:data:`ERROR_TXT`) gets :data:`FAILURE_HEADER` and the traceback.
    Best effort: where the folder cannot be written (a full or read-only disk) nothing is written, and the caller's
    error, which says so, is what the user sees.

    :param run_dir: the run folder
    :param step: the agent step the run had reached
    :param frame: the frame it had reached
    :param error: the exception
    """
    lines = traceback.format_exception(type(error), error, error.__traceback__)
    header = FAILURE_HEADER.format(step=step, frame=frame)
    with contextlib.suppress(OSError):  # best effort: on a full or read-only disk, the error itself says so
        write_text_atomically(Path(run_dir) / ERROR_TXT, header + "\n" + "".join(lines))


def failed_before_training(run_dir: str | os.PathLike) -> bool:
    """
    :param run_dir: a run folder
    :return: whether it holds a run that failed before its first agent step (no result, an error file whose first
        line says step 0): nothing of value, a new run may take the folder
    """
    run_dir = Path(run_dir)
    error_file = run_dir / ERROR_TXT
    if (run_dir / RESULT_JSON).exists() or not error_file.is_file():
        return False
    with error_file.open() as file:
        first = file.readline().strip()
    return first == FAILURE_HEADER.format(step=0, frame=0)


def blocking_file(folder: str | os.PathLike) -> Path | None:
    """
    :param folder: a folder to create (or that exists)
    :return: the file that stands where ``folder`` or its nearest existing parent should be a folder, ``None`` when
        ``folder`` can be created (or is a folder)
    """
    folder = Path(folder)
    for parent in (folder, *folder.parents):
        if parent.exists():
            return None if parent.is_dir() else parent
    return None


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike) -> Iterator[Path]:
    """
    A temporary path next to ``path`` to write into; when the block ends without an error, the file is flushed to disk
    and renamed to ``path`` (readers see the previous file, or none, or the complete new one); after an error it is
    removed, and ``path`` is left as it was. The file gets the permissions of a new file under the process's umask.

    :param path: the final file; the temporary one ends with the same suffix (``.zip`` for SB3's ``save``)
    :return: the temporary path
    """
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
    """
    Write ``text`` to a temporary file next to ``path``, flush it to disk, then rename it to ``path``: readers see
    either the previous file (or none) or the complete new one. The file gets the permissions of a new file under
    the process's umask.

    :param path: the file
    :param text: its content
    """
    with atomic_output(path) as temporary:
        temporary.write_text(text)


def write_json_atomically(path: str | os.PathLike, content: Any) -> None:
    """
    Write ``content`` as indented JSON with :func:`write_text_atomically`.

    :param path: the JSON file
    :param content: anything ``json.dumps`` accepts
    """
    write_text_atomically(path, json.dumps(content, indent=2) + "\n")


def append_csv_rows(path: str | os.PathLike, fieldnames: Sequence[str], rows: Iterable[dict[str, Any]]) -> None:
    """
    Append rows to a CSV file, writing the header first when the file is new or empty.

    :param path: the CSV file (its folder must exist)
    :param fieldnames: the columns, in order
    :param rows: one dict per row, keyed by column
    :raises ValueError: when the file has another header (e.g. written by an older version): nothing is appended
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
