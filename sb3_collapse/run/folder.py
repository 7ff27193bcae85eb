"""The run folder of one training run as :func:`~sb3_collapse.run.runner.train` takes it: whether it may, which one
(:func:`new_run_dir`) and how it is opened (:func:`open_run_dir`: new settings, or the checkpoint to resume)."""

from __future__ import annotations

import contextlib
import io
import json
import shutil
import time
import zipfile
from pathlib import Path
from typing import Any

import torch as th

from sb3_collapse.errors import InputError, ParameterError
from sb3_collapse.protocol import (
    CHECKPOINT_MODEL,
    CHECKPOINTS_DIR,
    CONFIG_JSON,
    ERROR_TXT,
    LOCK_FILE,
    RESULT_JSON,
    blocking_file,
    write_json_atomically,
)
from sb3_collapse.run.checkpoints import DAMAGED_NOTE, LoadedCheckpoint, read_checkpoints, set_aside
from sb3_collapse.run.config import RESUME_FREE_SETTINGS, TrainConfig
from sb3_collapse.run.lock import RunLock
from sb3_collapse.runfolder import RESUMABLE, RunStatus, read_json, run_status, unreadable_result


def _check_run_dir(run_dir: Path) -> RunStatus:
    """:return: the status of an explicit ``run_dir`` that a run may take (new, unfinished, failed)
    :raises ParameterError: naming ``run_dir``: a finished run (its leftovers removed), an unreadable result, no run"""
    state = run_status(run_dir, check_lock=False)  # a held lock refuses the run later, naming its owner
    problem = None
    if state is None:
        problem = " exists and is not an empty folder (nor the folder of a run): remove it or choose another."
    elif state == RunStatus.FINISHED:
        tidy_finished_run(run_dir)
        problem = f" holds a finished run ({RESULT_JSON}): choose another folder."
    elif (damaged := unreadable_result(run_dir)) is not None:
        problem = f": {damaged}"
    if problem is not None or state is None:
        raise ParameterError("run_dir", f"run_dir {run_dir}{problem}")
    return state


def check_run_folder(config: TrainConfig) -> None:
    """The checks of ``config`` that read the file system, before anything is written: an explicit ``run_dir`` must be
    new, empty or an unfinished run; ``logdir`` must not be (under) a file. :raises ParameterError: naming either."""
    if config.run_dir is not None:
        _check_run_dir(Path(config.run_dir))
    blocking = blocking_file(config.logdir)
    if blocking is not None:
        raise ParameterError("logdir", f"logdir {config.logdir}: {blocking} is a file, not a folder.")


def settings_differences(saved: dict[str, Any], config: TrainConfig) -> list[str]:
    """:return: one line per setting of a run folder's settings file (``saved``) that is not ``config``'s (but
    :data:`~sb3_collapse.run.config.RESUME_FREE_SETTINGS`), empty when the run of ``config`` can resume it"""

    current = json.loads(json.dumps(config.record()))
    return [
        f"`{name}={current.get(name)}` (the run folder has {saved.get(name)!r})"
        for name in sorted(set(saved) | set(current))
        if name not in RESUME_FREE_SETTINGS and saved.get(name) != current.get(name)
    ]


def _resume_differences(run_dir: Path, config: TrainConfig, checkpoint: Path | None = None) -> list[str]:
    """:return: one line per setting of ``run_dir``'s settings file (or learning rate its ``checkpoint`` trained with:
    a settings file edited later) that is not ``config``'s; :raises ParameterError: for an unreadable settings file"""
    if checkpoint is None:
        try:
            saved = read_json(run_dir / CONFIG_JSON)
        except InputError as error:
            raise ParameterError("run_dir", f"run_dir {run_dir}: its {CONFIG_JSON} cannot be read ({error}).") from None
        return settings_differences(saved, config)
    rates: set[float] = set()
    with zipfile.ZipFile(checkpoint / CHECKPOINT_MODEL) as archive:  # the optimizers' states, not the weights
        for name in archive.namelist():
            if name.endswith("optimizer.pth"):
                state = th.load(io.BytesIO(archive.read(name)), map_location="cpu", weights_only=True)
                rates.update(float(group["lr"]) for group in state["param_groups"])
    if not rates or rates == {config.learning_rate}:
        return []
    trained = ", ".join(f"{rate:g}" for rate in sorted(rates))
    return [f"`learning_rate={config.learning_rate}` (its checkpoint {checkpoint.name} trained with {trained})"]


def _refuse_other_settings(run_dir: Path, differences: list[str], settings: str) -> None:
    """:raises ParameterError: naming ``run_dir`` and the ``differences``, when there are any"""
    if differences:
        raise ParameterError(
            "run_dir",
            f"run_dir {run_dir} holds an unfinished run with other settings: {'; '.join(differences)}. Run it with "
            f"{settings} to resume it, or train into another folder.",
        )


def new_run_dir(logdir: Path, name: str, config: TrainConfig) -> Path:
    """:return: the first of ``<logdir>/<name>``, ``<name>_2``... that can take the run of ``config``: a new folder, or
    an unfinished run with the same settings (resumed); one line says why when it is not the first"""
    run_dir, index, passed = logdir / name, 1, []
    while (state := run_status(run_dir, check_lock=False)) != RunStatus.NEW:
        if state == RunStatus.FINISHED:
            tidy_finished_run(run_dir)
            passed.append(f"{run_dir.name} holds a finished run ({RESULT_JSON})")
        elif state is None:
            passed.append(f"{run_dir.name} is not a run folder")
        damaged = unreadable_result(run_dir) if state == RunStatus.FAILED else None
        if damaged is not None:
            print(f"{run_dir}: {damaged} Not resuming it.")
            passed.append(f"{run_dir.name} holds an unreadable result file")
        elif state in RESUMABLE:
            differences = _resume_differences(run_dir, config)
            if not differences:
                break
            print(f"{run_dir} holds an unfinished run with other settings ({'; '.join(differences)}): not resuming it.")
            passed.append(f"{run_dir.name} holds an unfinished run with other settings")
        index += 1
        run_dir = logdir / f"{name}_{index}"
    if passed:
        print(f"Training into {run_dir}: {'; '.join(passed)}.")
    return run_dir


def partial_outputs(run_dir: Path) -> list[Path]:
    """:return: the temporary files of atomic writes a killed process left in ``run_dir`` (but the checkpoints')"""
    return [
        path
        for path in run_dir.rglob(".*.partial*")
        if path.is_file() and CHECKPOINTS_DIR not in path.relative_to(run_dir).parts
    ]


def tidy_finished_run(run_dir: Path) -> list[str]:
    """Remove what the process of the finished run in ``run_dir``, killed after its result file, left: checkpoints,
    temporary files and the lock file (not while a process holds the lock); return what was removed, for the user."""
    checkpoints, lock = run_dir / CHECKPOINTS_DIR, run_dir / LOCK_FILE
    leftovers = [path for path in (checkpoints, lock) if path.exists()] + partial_outputs(run_dir)
    if not leftovers or not (run_dir / RESULT_JSON).is_file():
        return []
    removed = []
    with contextlib.suppress(InputError, OSError), RunLock(run_dir):
        for path in leftovers:
            if path.is_dir():
                size = sum(file.stat().st_size for file in path.rglob("*") if file.is_file())
                shutil.rmtree(path)
                removed.append(f"{path.name}/ ({size / 1e6:.1f} MB)")
            elif path != lock:
                path.unlink()
                removed.append(path.name)
        lock.unlink()  # still locked: no process may take a finished run's folder
        removed += [LOCK_FILE] if lock in leftovers else []
    if removed:
        listed = ", ".join(removed)
        print(f"Removed what the finished run in {run_dir} left behind (killed after it finished): {listed}.")
    return removed


def set_aside_damaged_checkpoints(run_dir: Path, skipped: list[tuple[Path, str]]) -> Path | None:
    """When no checkpoint of ``run_dir`` (locked) can be read and some are damaged (``skipped``, or set aside earlier),
    set the checkpoints folder aside with one line (printed, and in it) on why the run restarts from frame 0; return
    where it went, ``None`` when none was damaged."""
    checkpoints = run_dir / CHECKPOINTS_DIR
    damaged = [f"{folder.name}: {reason}" for folder, reason in skipped]
    for folder in sorted(checkpoints.glob("damaged_*")):  # set aside by an earlier process, with the reason
        try:
            reason = (folder / DAMAGED_NOTE).read_text().strip()
        except OSError:
            reason = "set aside as damaged"
        damaged.append(f"{folder.name.removeprefix('damaged_')}: {reason}")
    if not damaged:
        return None
    target = set_aside(checkpoints)
    line = (
        f"Every checkpoint of {run_dir} is damaged ({'; '.join(damaged)}): the run restarts from frame 0. They are "
        f"kept in {target}."
    )
    with contextlib.suppress(OSError):
        (target / DAMAGED_NOTE).write_text(line + "\n")
    print(f"Note: {line}", flush=True)
    return target


def open_run_dir(run_dir: Path, config: TrainConfig) -> LoadedCheckpoint | None:
    """With ``run_dir`` locked: a new run writes its settings (``config``); an unfinished run with the same settings is
    resumed from its newest readable checkpoint (returned; damaged newer ones set aside), or restarted (``None``).

    :raises ParameterError: for a folder with a finished run, another run's settings or other content
    """

    if _check_run_dir(run_dir) in RESUMABLE:
        _refuse_other_settings(run_dir, _resume_differences(run_dir, config), "its own settings")
        for partial in partial_outputs(run_dir):  # a write of a killed process: written again as the run goes on
            partial.unlink()
        checkpoint, skipped = read_checkpoints(run_dir / CHECKPOINTS_DIR)
        if checkpoint is not None:
            for folder, reason in skipped:  # kept aside under another name, never read again
                print(f"Checkpoint {folder} is damaged ({reason}): falling back to the one before.")
                set_aside(folder, reason)
            _refuse_other_settings(  # the settings file was edited: the run would change its settings mid-run
                run_dir,
                _resume_differences(run_dir, config, checkpoint.folder),
                f"the settings it trained with (and its {CONFIG_JSON} as it wrote it)",
            )
            error_file = run_dir / ERROR_TXT
            if error_file.is_file():  # kept with the checkpoints, out of the way of the sweep's status
                first = error_file.read_text().splitlines()[:1]
                print(f"The previous attempt {first[0] if first else 'failed'}; resuming.")
                error_file.replace(run_dir / CHECKPOINTS_DIR / f"error_{time.strftime('%Y%m%d-%H%M%S')}.txt")
            return checkpoint  # train says which it resumes from, once its replay chunks are read
        if set_aside_damaged_checkpoints(run_dir, skipped) is None:
            print(f"{run_dir} holds an unfinished run without a checkpoint: restarting it from frame 0.")
    for path in run_dir.iterdir():  # but the lock (held) and what was set aside as damaged (it cannot be rebuilt)
        if path.name != LOCK_FILE and not path.name.startswith("damaged_"):
            shutil.rmtree(path) if path.is_dir() else path.unlink()
    write_json_atomically(run_dir / CONFIG_JSON, config.record())
    return None
