"""Run the trials of a sweep on Ray: each trial is one Ray task that trains into its own folder (docs/sweeps.md)."""

from __future__ import annotations

import contextlib
import dataclasses
import os
import shutil
import signal
import threading
import traceback
from collections.abc import Collection, Iterator, Mapping, Sequence
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from typing import Any

from sb3_collapse import __version__
from sb3_collapse.common import progress
from sb3_collapse.errors import FULL_DISK_ERRNOS, InputError, OutputError, ParameterError, TrainingInterrupted
from sb3_collapse.presets import SETTING_NAMES
from sb3_collapse.protocol import (
    CHECKPOINTS_DIR,
    CONFIG_JSON,
    ERROR_TXT,
    FINISHED,
    RESULT_JSON,
    SWEEP_JSON,
    SWEEP_LOCK,
    SWEEP_STOP,
    blocking_file,
    write_json_atomically,
    write_text_atomically,
)
from sb3_collapse.run.checkpoints import CHECKPOINT_FORMAT, checkpoint_folders, read_checkpoint_info
from sb3_collapse.run.config import TrainConfig
from sb3_collapse.run.folder import settings_differences, tidy_finished_run
from sb3_collapse.run.lock import RunLock
from sb3_collapse.run.runner import train
from sb3_collapse.run.signals import clear_training_stop, request_training_stop, stop_signal_handlers
from sb3_collapse.run.variants import BLANK_SOURCE, transplant_of, variant_settings
from sb3_collapse.runfolder import (
    DAMAGED_RESULT_WAY_OUT,
    RESUMABLE,
    RunStatus,
    read_json,
    run_folder_owner,
    run_status,
    unreadable_result,
)
from sb3_collapse.sweep.cluster import CONNECT_TIMEOUT_S, check_resources, import_ray, ray_session
from sb3_collapse.sweep.trials import Trial, donor_key, trial_config, trial_dir


def check_sweep(
    trials: Sequence[Trial],
    out: str | Path,
    training: Mapping[str, Any],
    checkpoints: Mapping[str, Mapping[str, str]],
    cpus_per_trial: float = 1,
    gpus_per_trial: float = 0,
    connect_timeout_s: float = CONNECT_TIMEOUT_S,
) -> None:
    """Check what a sweep can check before it writes anything or starts Ray (an ``InputError`` names the parameter)."""
    if not connect_timeout_s > 0 or connect_timeout_s == float("inf"):
        raise InputError(
            f"connect_timeout_s must be a finite number of seconds > 0, got {connect_timeout_s}.",
            parameter="connect_timeout_s",
        )
    if cpus_per_trial <= 0:
        raise InputError(f"cpus_per_trial must be > 0, got {cpus_per_trial}.", parameter="cpus_per_trial")
    if gpus_per_trial < 0 or (gpus_per_trial > 1 and gpus_per_trial != int(gpus_per_trial)):
        raise InputError(
            f"gpus_per_trial must be a fraction in [0, 1] or a whole number, got {gpus_per_trial}.",
            parameter="gpus_per_trial",
        )
    if training.get("eval_every_frames") == 0:
        raise InputError(
            "eval_every_frames=0 turns the evaluations off, and a sweep's report compares evaluation returns: "
            "leave it to the presets or give a period in frames.",
            parameter="eval_every_frames",
        )
    blocking = blocking_file(out)
    if blocking is not None:
        raise InputError(f"out {out}: {blocking} is a file, not a folder.", parameter="out")
    unknown = sorted(set(training) - {field.name for field in dataclasses.fields(TrainConfig)})
    if unknown:
        raise InputError(f"Unknown training settings {unknown}: use TrainConfig field names.")
    for task, variant in dict.fromkeys((trial.task, trial.variant) for trial in trials):  # its preset, its rule
        TrainConfig(**{**training, "env": task, **variant_settings(variant)}).validate()
    for trial in trials:
        for part, source in (transplant_of(trial.variant) or {}).items():
            if source != BLANK_SOURCE and trial.task not in checkpoints.get(donor_key(source, part), {}):
                raise InputError(
                    f"Variant {trial.variant} takes the {part.upper()} of a {source} agent: pass --{source}-{part} "
                    f"PATH (or {trial.task}=PATH) for {trial.task}, or --donors-from a finished sweep."
                )


@contextlib.contextmanager
def _created_folder(folder: Path) -> Iterator[None]:
    """While inside, ``folder`` exists; the folders this created are removed at the end where left empty."""
    created = [path for path in (folder, *folder.parents) if not path.exists()]
    try:
        folder.mkdir(parents=True, exist_ok=True)
        yield
    finally:
        for path in created:  # the deepest first
            with contextlib.suppress(OSError):
                path.rmdir()


def _check_writable(folder: Path) -> None:
    """Raise ``OSError`` naming ``folder`` when it cannot be created and written into; leave nothing behind."""
    try:
        with _created_folder(folder):
            (folder / f".write_check_{os.getpid()}").mkdir()
            (folder / f".write_check_{os.getpid()}").rmdir()
    except OSError as error:
        raise OSError(error.errno, error.strerror, str(folder)) from None


class Attempt(str, Enum):
    """The status of one attempt at a trial: the word :func:`run_trial` returns it with and the driver reads."""

    FINISHED = FINISHED  # the run finished (its result file says so)
    FAILED = "failed"  # its error file says why
    INTERRUPTED = "interrupted"  # stopped by a signal at its checkpoint, or not started while the sweep stopped
    IN_USE = "in use"  # another process holds its folder (a train): left as it is, trained by a later rerun

    def __str__(self) -> str:
        return self.value


UNREADABLE_RESULT = f"an unreadable {RESULT_JSON}"  # a trial a rerun would not change: not run, failed...
OTHER_VERSION = "a checkpoint of another version"  # ... and neither is this one


def other_version_checkpoint(folder: Path) -> str | None:
    """:return: one line when the checkpoint the unfinished trial in ``folder`` would resume from (the newest whose
    checkpoint file reads, as ``train`` takes it) was written by another version of sb3-collapse, which ``train``
    refuses; ``None`` otherwise"""
    for checkpoint in checkpoint_folders(folder / CHECKPOINTS_DIR):
        try:
            info = read_checkpoint_info(checkpoint)
        except InputError:
            continue  # damaged: train passes over it to the one before
        if (
            info.get("format", CHECKPOINT_FORMAT) == CHECKPOINT_FORMAT
            and info.get("version", __version__) == __version__
        ):
            return None  # a file without them is left to train, which refuses it naming what it lacks
        return (
            f"its checkpoint {checkpoint} was written by sb3-collapse {info.get('version')}, this is {__version__}: "
            f"rerun with the version that wrote it, or {DAMAGED_RESULT_WAY_OUT}."
        )
    return None


def trial_left_as_is(folder: Path) -> tuple[str, str] | None:
    """
    :param folder: the folder of a trial that has not finished
    :return: why a sweep leaves it as it is, ``None`` when it trains it: ``(Attempt.IN_USE, owner)`` while another
        process holds its lock (a rerun once that ends trains it), ``(UNREADABLE_RESULT, line)`` or
        ``(OTHER_VERSION, line)`` where a rerun would not change it (the line says the way out)
    """
    owner = run_folder_owner(folder)
    if owner is not None:
        return Attempt.IN_USE, owner
    if (reason := unreadable_result(folder)) is not None:
        return UNREADABLE_RESULT, reason
    if (reason := other_version_checkpoint(folder)) is not None:
        return OTHER_VERSION, reason
    return None


def write_error_file(folder: Path, text: str, error_line: str) -> str:
    """Write ``text`` into the trial ``folder``'s error file; :return: ``error_line``, and when the file could not be
    written (a full disk) why, naming it: the reason reaches the sweep's summary either way"""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        write_text_atomically(folder / ERROR_TXT, text)
    except OSError as error:
        reason = error.strerror or str(error)
        return f"{error_line.rstrip('.')} (and its {ERROR_TXT} could not be written: {folder / ERROR_TXT}: {reason})."
    return error_line


def run_trial(
    trial: Trial,
    out: str,
    training: Mapping[str, Any],
    checkpoints: Mapping[str, Mapping[str, str]] | None = None,
    device: str = "cpu",
    torch_threads: int | None = None,
    snapshot_variants: Collection[str] | None = None,
) -> dict[str, Any]:
    """
    Run one trial into its folder (an unfinished attempt resumes; with other settings it is deleted first); a failure
    goes to the trial's error file. The parameters are :func:`~sb3_collapse.sweep.trials.trial_config`'s.

    :return: ``{"trial", "status": an :class:`Attempt`, "error": its line (the owner
        when in use) or None, "resumes"}``, ``"retryable"`` when failed, ``"checkpoint"`` when stopped by a signal or
        the driver; a folder another process holds is left as it is (``"in use"``), nothing written into it
    """
    stop_file = Path(out) / SWEEP_STOP
    if stop_file.exists():  # the driver is stopping: a trial that had not started stays as it is
        return {"trial": str(trial), "status": Attempt.INTERRUPTED, "error": "not started: the sweep was stopping"}
    folder = trial_dir(out, trial)
    owner = run_folder_owner(folder)
    if owner is not None:  # another process trains into it (checked again by train's lock): nothing written there
        return {"trial": str(trial), "status": Attempt.IN_USE, "error": owner}
    config = trial_config(trial, out, training, checkpoints, device, torch_threads, snapshot_variants)
    if run_status(folder) in RESUMABLE and (folder / CONFIG_JSON).is_file():
        try:
            differences = settings_differences(read_json(folder / CONFIG_JSON), config)
        except InputError:
            differences = ["unreadable settings"]
        if differences:  # the sweep's settings changed (allowed): this attempt cannot continue
            shutil.rmtree(folder)
    before = _error_file_stamp(folder)
    try:
        with _stop_requests_watched(stop_file):
            result = train(config)
    except TrainingInterrupted as error:  # a signal to the worker: the checkpoint is there for the next sweep
        checkpoint = str(error.checkpoint)
        return {"trial": str(trial), "status": Attempt.INTERRUPTED, "error": str(error), "checkpoint": checkpoint}
    except Exception as error:  # noqa: BLE001  reported in the error file and in the sweep's summary
        owner = run_folder_owner(folder) if isinstance(error, InputError) else None
        if owner is not None:  # taken since the check above (train's lock refused it): left as it is
            return {"trial": str(trial), "status": Attempt.IN_USE, "error": owner}
        error_line = f"{type(error).__name__}: {error}"
        if _error_file_stamp(folder) in (None, before):  # train wrote none (its own starts with the step it failed at)
            error_line = write_error_file(folder, traceback.format_exc(), error_line)
        return {"trial": str(trial), "status": Attempt.FAILED, "error": error_line, "retryable": retryable(error)}
    return {"trial": str(trial), "status": Attempt.FINISHED, "error": None, "resumes": result.summary.get("resumes", 0)}


@contextlib.contextmanager
def _stop_requests_watched(stop_file: Path, every_s: float = 0.25) -> Iterator[None]:
    """While inside, a thread passes the driver's stop request (``stop_file``) to this process's training."""
    done = threading.Event()

    def watch() -> None:
        while not done.wait(every_s):
            if stop_file.exists():
                name = "SIGTERM"
                with contextlib.suppress(OSError):
                    name = stop_file.read_text().strip() or name
                print(f"The sweep was stopped by {name}: writing a checkpoint at the end of this round.", flush=True)
                request_training_stop(name)
                return

    watcher = threading.Thread(target=watch, name="sweep-stop-watcher", daemon=True)
    watcher.start()
    try:
        yield
    finally:
        done.set()
        watcher.join()
        clear_training_stop()


def _error_file_stamp(folder: Path) -> tuple[int, int] | None:
    """The inode and modification time of a trial's error file, ``None`` without one."""
    with contextlib.suppress(OSError):
        stat = (folder / ERROR_TXT).stat()
        return stat.st_ino, stat.st_mtime_ns
    return None


def retryable(error: BaseException) -> bool:
    """Whether a rerun may succeed: only a fault of what the trial ran on (disk, memory); it resumes bit for bit. A
    full disk is one wherever it was met, also where it was reported as bad input (a run folder that cannot be
    written at the start of ``train``)."""
    import torch as th

    transient = (OSError, MemoryError, OutputError, th.cuda.OutOfMemoryError)
    if isinstance(error, transient) and not isinstance(error, InputError):
        return True
    cause: BaseException | None = error
    while cause is not None:  # the errors it was raised from or while handling
        if isinstance(cause, OSError) and cause.errno in FULL_DISK_ERRNOS:
            return True
        cause = cause.__cause__ or cause.__context__
    return False


@dataclass
class SweepSummary:
    """
    :param trials: every trial of the sweep
    :param skipped: trials already finished before this run
    :param finished: trials finished in this run
    :param failed: trial -> the file that says why it failed (its error file, or its unreadable result file)
    :param repeating: the failed trials that a rerun would fail the same way (:func:`retryable`)
    :param resumed: the trials finished in this run that continued from a checkpoint
    :param interrupted: trial -> the checkpoint it wrote as it stopped by a signal (``None``: it had not started)
    :param stopped_by: the signal that stopped the sweep's driver (``"SIGTERM"``, ``"SIGINT"``), ``None`` if none
    :param damaged: trial -> why a rerun would not change it (an unreadable result file, a checkpoint of another
        version) and the way out (not run; in ``failed``, ``repeating``)
    :param in_use: trial -> the process that holds its folder (a ``train``): left as it is, nothing written into it;
        a rerun once that process ended trains it
    :param reasons: failed trial -> its one-line reason (the error file holds the traceback where it could be written)
    """

    trials: list[Trial]
    skipped: list[Trial]
    finished: list[Trial]
    failed: dict[Trial, Path]
    repeating: list[Trial] = dataclasses.field(default_factory=list)
    resumed: list[Trial] = dataclasses.field(default_factory=list)
    interrupted: dict[Trial, Path | None] = dataclasses.field(default_factory=dict)
    stopped_by: str | None = None
    damaged: dict[Trial, str] = dataclasses.field(default_factory=dict)
    in_use: dict[Trial, str] = dataclasses.field(default_factory=dict)
    reasons: dict[Trial, str] = dataclasses.field(default_factory=dict)

    @property
    def ok(self) -> bool:
        """Whether no trial failed."""
        return not self.failed


TRIAL_RETRIES = 3  # times Ray runs a trial's task again after its worker died; each run resumes from its checkpoint


def sweep_settings(
    trials: Sequence[Trial],
    training: Mapping[str, Any],
    checkpoints: Mapping[str, Mapping[str, str]],
    resources: Mapping[str, Any],
    donors: Mapping[str, Any] | None = None,
    plan: Mapping[str, Any] | None = None,
    snapshot_variants: Collection[str] | None = None,
) -> dict[str, Any]:
    """The content of the sweep's settings file (``task_settings``: the DrQ-v2 settings each task's trials use;
    ``plan``: :func:`~sb3_collapse.sweep.plan.sweep_plan`'s; ``snapshot_variants``: the variants whose trials save
    snapshots, when not every trial's ``training`` says it)."""
    tasks = list(dict.fromkeys(trial.task for trial in trials))
    configs = {task: TrainConfig(**{**training, "env": task}).resolve() for task in tasks}
    return {
        "training": dict(training),
        "task_settings": {task: {name: getattr(configs[task], name) for name in SETTING_NAMES} for task in tasks},
        "checkpoints": {source: dict(paths) for source, paths in checkpoints.items() if paths},
        "tasks": tasks,
        "variants": list(dict.fromkeys(trial.variant for trial in trials)),
        "seeds": sorted({trial.seed for trial in trials}),
        "resources": dict(resources),
        **({} if donors is None else {"donors": dict(donors)}),
        **({} if plan is None else {"plan": dict(plan)}),
        **({} if snapshot_variants is None else {"snapshot_variants": sorted(snapshot_variants)}),
    }


TRAINING_DEFAULTS: dict[str, Any] = {
    field.name: field.default for field in dataclasses.fields(TrainConfig) if field.default is not dataclasses.MISSING
}
"""A training setting's value where a settings file does not record it (``None``: the presets')."""
KEPT_RECORDS = ("donors", "snapshot_variants")
"""What a sweep's settings file keeps from an earlier run that this one does not set (the donors it drew, the variants
whose trials keep snapshots)."""


def settings_changes(previous: Mapping[str, Any], current: Mapping[str, Any]) -> list[str]:
    """
    :param previous: the settings in the sweep's settings file
    :param current: the settings of this run
    :return: one line per training setting that differs (tasks, seeds, variants and donors may be added)
    """
    changes = []
    # A setting missing from one side is at its default: the command line records every training setting, a library
    # call (the reproduction's stages) the ones it sets.
    old, new = ({**TRAINING_DEFAULTS, **settings.get("training", {})} for settings in (previous, current))
    for name in sorted(set(previous.get("training", {})) | set(current.get("training", {}))):
        if old.get(name) != new.get(name):
            before, now = ("the presets'" if value is None else repr(value) for value in (old.get(name), new.get(name)))
            changes.append(f"`{name}`: {before} in {SWEEP_JSON}, {now} now")
    for task, settings in current.get("task_settings", {}).items():
        before_settings = previous.get("task_settings", {}).get(task, settings)
        for name in sorted(set(before_settings) | set(settings)):
            if old.get(name) == new.get(name) and before_settings.get(name) != settings.get(name):
                changes.append(
                    f"`{name}` of {task}: {before_settings.get(name)!r} in {SWEEP_JSON}, {settings.get(name)!r} now"
                )
    for source, paths in current.get("checkpoints", {}).items():
        for task, path in paths.items():
            before = previous.get("checkpoints", {}).get(source, {}).get(task)
            if before not in (None, path):
                changes.append(f"`{source}` checkpoint for {task}: {before} in {SWEEP_JSON}, {path} now")
    return changes


def prepare_sweep_folder(
    out: str | Path, settings: Mapping[str, Any], allow_changed_settings: bool = False, write: bool = True
) -> None:
    """
    Check this run's :func:`sweep_settings` against the sweep's settings file (an ``InputError`` when they changed
    and that is not allowed), then, with ``write``, write there the tasks, variants, seeds and checkpoints of both.
    """
    path = Path(out) / SWEEP_JSON
    previous: dict[str, Any] = read_json(path) if path.is_file() else {}
    changes = settings_changes(previous, settings) if path.is_file() else []
    if changes and not allow_changed_settings:
        raise InputError(
            f"{out} holds a sweep with other training settings:\n  "
            + "\n  ".join(changes)
            + "\nUse another `out`, the same settings, or `allow_changed_settings=True` to mix them "
            "(finished trials are not rerun)."
        )
    if not write:
        return
    merged = {**{key: previous[key] for key in KEPT_RECORDS if key in previous}, **settings}  # nothing written lost
    merged["task_settings"] = {**previous.get("task_settings", {}), **settings.get("task_settings", {})}
    for key in ("tasks", "variants"):
        merged[key] = list(dict.fromkeys([*previous.get(key, []), *settings.get(key, [])]))
    merged["seeds"] = sorted({*previous.get("seeds", []), *settings.get("seeds", [])})
    merged["checkpoints"] = {source: dict(paths) for source, paths in previous.get("checkpoints", {}).items()}
    for source, paths in settings.get("checkpoints", {}).items():
        merged["checkpoints"].setdefault(source, {}).update(paths)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_json_atomically(path, merged)


def run_sweep(
    trials: Sequence[Trial],
    out: str | Path,
    training: Mapping[str, Any],
    checkpoints: Mapping[str, Mapping[str, str]] | None = None,
    cpus_per_trial: float = 1,
    gpus_per_trial: float = 0,
    address: str | None = None,
    allow_changed_settings: bool = False,
    progress_bar: bool = True,
    donors: Mapping[str, Any] | None = None,
    connect_timeout_s: float = CONNECT_TIMEOUT_S,
    plan: Mapping[str, Any] | None = None,
    snapshot_variants: Collection[str] | None = None,
    trials_per_worker: int = 1,
) -> SweepSummary:
    """
    Run every unfinished trial as an independent Ray task (resuming from its newest checkpoint) and wait for all of
    them; a SIGTERM or SIGINT stops every trial at a checkpoint (a second one at once). See docs/sweeps.md.

    :param trials: the trials (:func:`~sb3_collapse.sweep.trials.expand_trials`)
    :param out: the sweep folder; with ``address`` it must be on storage that every node sees at the same path
    :param training: :class:`~sb3_collapse.run.config.TrainConfig` fields shared by all trials (not ``env``, ``seed``)
    :param checkpoints: :func:`~sb3_collapse.sweep.trials.donor_key` -> task -> checkpoint path, for grid cells
    :param cpus_per_trial: CPUs Ray reserves per trial; also the trial's torch threads (at least 1)
    :param gpus_per_trial: GPUs Ray reserves per trial (``0.25``: four trials share a GPU); > 0 trains on ``cuda``
    :param address: Ray cluster address, ``None`` for a local instance (or the Ray already initialized)
    :param allow_changed_settings: run even if the sweep's settings file has other training settings
    :param progress_bar: show a progress bar over the trials
    :param donors: how the donors were picked (:func:`~sb3_collapse.sweep.donors.donors_record`), ``None`` if given
    :param connect_timeout_s: seconds to wait for the cluster at ``address`` to answer (:func:`ray_session`)
    :param plan: the sweep's plan for its settings file (:func:`~sb3_collapse.sweep.plan.sweep_plan`), if any
    :param snapshot_variants: only the trials of these variants save snapshots (``None``: as ``training`` says)
    :param trials_per_worker: trials a Ray worker process runs before a fresh one replaces it: ``1`` (each trial in
        a fresh process: nothing a trial leaves in its process reaches the next), ``0`` no limit (for trials so short
        that a process's start, its imports and rendering check, is most of their time: the tiny reproduction's)
    :return: what was skipped, finished, failed and interrupted
    :raises InputError: for settings that cannot run, or another sweep running into ``out`` (nothing written)
    :raises MissingDependencyError: when there are trials to run and Ray is not installed
    :raises ClusterUnreachable: when the cluster at ``address`` did not answer in time (nothing written)
    """
    checkpoints = {source: dict(paths) for source, paths in (checkpoints or {}).items()}
    check_sweep(trials, out, training, checkpoints, cpus_per_trial, gpus_per_trial, connect_timeout_s)
    out = Path(out).resolve()
    resources = {"cpus_per_trial": cpus_per_trial, "gpus_per_trial": gpus_per_trial, "address": address}
    settings = sweep_settings(trials, training, checkpoints, resources, donors, plan, snapshot_variants)
    prepare_sweep_folder(out, settings, allow_changed_settings, write=False)
    _check_writable(out)  # before starting Ray: a read-only folder is said at once
    with sweep_folder_locked(out):  # a second sweep into the folder is refused, before its Ray starts
        summary = SweepSummary(trials=list(trials), skipped=[], finished=[], failed={})
        for trial in trials:
            folder = trial_dir(out, trial)
            if run_status(folder) == RunStatus.FINISHED:
                summary.skipped.append(trial)
                tidy_finished_run(folder)  # a trial killed after its result file left its checkpoints behind
            elif (left := trial_left_as_is(folder)) is not None and left[0] == Attempt.IN_USE:
                summary.in_use[trial] = left[1]
            elif left is not None:  # not repaired: neither run nor retryable
                summary.damaged[trial] = left[1]
                summary.failed[trial] = folder / (RESULT_JSON if left[0] == UNREADABLE_RESULT else CHECKPOINTS_DIR)
                summary.repeating.append(trial)
        to_run = [trial for trial in trials if trial not in {*summary.skipped, *summary.damaged, *summary.in_use}]
        if not to_run:
            prepare_sweep_folder(out, settings, allow_changed_settings)
            return summary
        if isinstance(trials_per_worker, bool) or not isinstance(trials_per_worker, int) or trials_per_worker < 0:
            raise ParameterError(
                "trials_per_worker", f"trials_per_worker must be an integer >= 0, got {trials_per_worker!r}."
            )
        import_ray()  # before writing anything: a missing Ray leaves the folder as it was
        with ray_session(address, connect_timeout_s=connect_timeout_s) as ray:
            check_resources(ray.cluster_resources(), cpus_per_trial, gpus_per_trial)
            prepare_sweep_folder(out, settings, allow_changed_settings)  # the cluster answered: now the folder
            (out / SWEEP_STOP).unlink(missing_ok=True)  # the request of an earlier run that did not end cleanly
            # max_calls=1 (the default): every trial in a fresh worker process (nothing a trial leaves in its process
            # reaches the next); max_retries: Ray runs the task again when its worker dies (not when the trial
            # raises): it resumes.
            remote = ray.remote(max_calls=trials_per_worker)(run_trial).options(
                num_cpus=cpus_per_trial, num_gpus=gpus_per_trial, max_retries=TRIAL_RETRIES
            )
            device, threads = ("cuda" if gpus_per_trial > 0 else "cpu"), max(1, int(cpus_per_trial))
            pending = {
                remote.remote(trial, str(out), dict(training), checkpoints, device, threads, snapshot_variants): trial
                for trial in to_run
            }
            _wait_for_trials(ray, pending, out, summary, progress_bar)
    return summary


@contextlib.contextmanager
def sweep_folder_locked(out: Path) -> Iterator[None]:
    """While inside, this process holds the sweep folder's lock (a second sweep: ``InputError``); removed at the end."""
    with (
        _created_folder(out),
        RunLock(out, SWEEP_LOCK, folder="sweep folder", instead="give this sweep another `out`") as lock,
    ):
        try:
            yield
        finally:
            lock.path.unlink(missing_ok=True)  # still held: a sweep that locked the deleted file takes a new one


def _wait_for_trials(ray: Any, pending: dict[Any, Trial], out: Path, summary: SweepSummary, progress_bar: bool) -> None:
    """Collect each trial's outcome into ``summary``; a signal writes the stop file, a second one stops at once."""

    def handler(signum: int, _frame: Any) -> None:
        if summary.stopped_by is not None:
            raise KeyboardInterrupt
        summary.stopped_by = signal.Signals(signum).name
        write_text_atomically(out / SWEEP_STOP, summary.stopped_by + "\n")
        bar.write(
            f"\n{summary.stopped_by}: asking the running trials to write a checkpoint and stop (a second signal: stop "
            "now, each trial resuming from its last checkpoint)."
        )

    with progress.progress_bar(None, "trials", "trial", progress_bar, len(pending)) as bar:
        try:
            with stop_signal_handlers(handler):
                while pending:
                    done, _ = ray.wait(list(pending), num_returns=1, timeout=0.5)  # signals run between waits
                    if done:
                        _collect(ray, done[0], pending.pop(done[0]), out, summary, bar)
        finally:
            for ref in pending:  # stopped at once (a second signal): the trials rerun from their checkpoints
                ray.cancel(ref, force=True)
            (out / SWEEP_STOP).unlink(missing_ok=True)


def _collect(ray: Any, ref: Any, trial: Trial, out: Path, summary: SweepSummary, bar: Any) -> None:
    """Record the outcome of a trial's finished Ray task in ``summary``."""
    try:
        outcome = ray.get(ref)
    except Exception as error:  # noqa: BLE001  the Ray task itself died (worker crash, out of memory...)
        line = f"{type(error).__name__}: {error}".splitlines()[0]
        # The first line reads on in the rerun's "The previous attempt failed: ...; resuming."
        text = f"failed: the Ray task of {trial} died\n{error}\n"
        outcome = {"status": Attempt.FAILED, "error": write_error_file(trial_dir(out, trial), text, line)}
    if outcome["status"] == Attempt.FINISHED:
        summary.finished.append(trial)
        if outcome.get("resumes"):
            summary.resumed.append(trial)
    elif outcome["status"] == Attempt.INTERRUPTED:
        checkpoint = outcome.get("checkpoint")
        summary.interrupted[trial] = Path(checkpoint) if checkpoint else None
        if checkpoint:
            bar.write(f"stopped {trial} at its checkpoint {checkpoint}")
    elif outcome["status"] == Attempt.IN_USE:
        summary.in_use[trial] = outcome["error"]
        bar.write(f"in use: {trial}: its folder is held by {outcome['error']}; left as it is")
    else:
        summary.failed[trial] = trial_dir(out, trial) / ERROR_TXT
        summary.reasons[trial] = outcome["error"]
        if not outcome.get("retryable", True):  # a dead Ray task (a crash, memory) is retryable
            summary.repeating.append(trial)
        bar.write(f"FAILED {trial}: {outcome['error']} (traceback in {summary.failed[trial]})")
    bar.set_postfix(failed=len(summary.failed))
    bar.update()
