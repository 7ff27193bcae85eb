"""
Run checkpoints: what a run needs to continue in another process exactly as if it had not stopped, written between
two rounds of ``learn()`` (:class:`ResumableCheckpoints`) and read back newest intact first. See docs/checkpoints.md.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import pickle
import random
import shutil
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.save_util import load_from_zip_file, recursive_setattr

from sb3_collapse import __version__
from sb3_collapse.common.saved_callbacks import callback_states, load_callback_states
from sb3_collapse.drqv2.divergence import all_finite, first_non_finite
from sb3_collapse.drqv2.replay_buffer import FrameStackReplayBuffer
from sb3_collapse.drqv2.update_stats import UpdateStats
from sb3_collapse.envs.replay import episode_records, replay_episodes
from sb3_collapse.errors import READ_ONLY_ERRNOS, CheckpointError, DivergenceError, OutputError, TrainingInterrupted
from sb3_collapse.monitoring.callbacks import FrameScheduleCallback, frames_of
from sb3_collapse.monitoring.grad_norms import grad_norm_recorder
from sb3_collapse.protocol import (
    CHECKPOINT_FOLDER,
    CHECKPOINT_FOLDER_PATTERN,
    CHECKPOINT_JSON,
    CHECKPOINT_MODEL,
    CHECKPOINT_STATE,
    REPLAY_DIR,
    atomic_output,
    write_json_atomically,
)
from sb3_collapse.run.replay_checkpoint import ReplayStore, check_file_size, fsync_path
from sb3_collapse.runfolder import read_json

CHECKPOINT_FORMAT = 1  # version of the checkpoint layout; a checkpoint of another format is refused
DAMAGED_NOTE = "damaged.txt"  # in a folder set aside as damaged (set_aside): why


def checkpoint_folders(directory: str | os.PathLike) -> list[Path]:
    """:return: the checkpoint folders of a run's checkpoints folder, newest first (not those being written)"""
    directory = Path(directory)
    if not directory.is_dir():
        return []
    folders = [path for path in directory.iterdir() if CHECKPOINT_FOLDER_PATTERN.match(path.name) and path.is_dir()]
    return sorted(folders, key=lambda path: path.name, reverse=True)


def read_checkpoint_info(folder: Path) -> dict[str, Any]:
    """:return: a checkpoint folder's ``checkpoint.json`` (not verified); :raises InputError: when unreadable"""
    return read_json(folder / CHECKPOINT_JSON)


def _digest(path: Path) -> dict[str, Any]:
    sha = hashlib.sha256()
    with path.open("rb") as file:
        for block in iter(lambda: file.read(1 << 22), b""):
            sha.update(block)
    return {"bytes": path.stat().st_size, "sha256": sha.hexdigest()}


def tensors_to(value: Any, device: th.device | str) -> Any:
    """:return: a copy of ``value`` (e.g. a checkpoint's state) with every tensor detached and moved to ``device``,
    through dicts, lists and tuples; other values kept as they are (not copied)"""
    if isinstance(value, th.Tensor):
        return value.detach().to(device, copy=True)
    if isinstance(value, dict):
        return {key: tensors_to(item, device) for key, item in value.items()}
    if isinstance(value, (list, tuple)) and not hasattr(value, "_fields"):  # not a namedtuple
        return type(value)(tensors_to(item, device) for item in value)
    return value


def _cuda_rng_state(device: th.device) -> dict[str, Any] | None:
    """The CUDA generator of ``device`` (the model's), ``None`` off CUDA."""
    if device.type != "cuda" or not th.cuda.is_available():
        return None
    index = device.index if device.index is not None else th.cuda.current_device()
    return {"device": index, "state": th.cuda.get_rng_state(index)}


def _restore_cuda_rng_state(saved: dict[str, Any] | None, device: th.device) -> None:
    """Restore a :func:`_cuda_rng_state` on the CUDA device ``device`` (the resuming model's), whatever its index."""
    if saved is not None and device.type == "cuda" and th.cuda.is_available():
        th.cuda.set_rng_state(
            saved["state"].cpu(), device.index if device.index is not None else th.cuda.current_device()
        )


def capture_state(
    model: BaseAlgorithm,
    callbacks: Sequence[BaseCallback] = (),
    eval_env: Any = None,
    csv_files: Sequence[Path] = (),
    extra: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """:return: what a run between two rounds of ``learn()`` needs beyond the model's ``save`` and the replay store:
    random generators, episodes, the ``callbacks``' states, logger, the ``csv_files``' content, ``extra`` (CPU only)"""
    env = model.get_env()
    assert env is not None
    recorder = grad_norm_recorder(model)
    logger = model.logger
    stats = getattr(model, "update_stats", None)  # DrQv2's statistics of the updates not logged yet
    csv = {path.name: path.read_bytes() if path.is_file() else b"" for path in csv_files}
    state = {
        "format": CHECKPOINT_FORMAT,
        "num_timesteps": int(model.num_timesteps),
        "device": str(model.device),
        "rng": {
            "python": random.getstate(),
            "numpy": np.random.get_state(),
            "torch": th.get_rng_state(),
            "cuda": _cuda_rng_state(model.device),
        },
        "action_space": model.action_space.np_random.bit_generator.state,
        "envs": episode_records(env),
        "eval_env": None if eval_env is None else eval_env.get_wrapper_attr("episode_record")(),
        "callbacks": callback_states(callbacks),
        "grad_norms": None if recorder is None else recorder.state_dict(),
        "logger": {
            "values": dict(logger.name_to_value),
            "counts": dict(logger.name_to_count),
            "excluded": dict(logger.name_to_excluded),
        },
        "csv": csv,
        "update_stats": stats.state_dict() if isinstance(stats, UpdateStats) else None,
        "extra": dict(extra or {}),
    }
    return tensors_to(state, "cpu")  # unpickled where it was written: a GPU's tensors would need that GPU


def save_checkpoint(
    model: BaseAlgorithm, directory: str | os.PathLike, store: ReplayStore, state: dict[str, Any], keep: int = 2
) -> Path:
    """
    Write a checkpoint of ``model`` and ``state`` (:func:`capture_state`) into ``directory/step_<agent step>``, then
    delete the checkpoints older than the newest ``keep`` and the replay chunks none of them needs; return its folder.

    :raises OutputError: when it cannot be written (e.g. a full disk): the previous checkpoints are intact
    """
    directory = Path(directory)
    name = CHECKPOINT_FOLDER.format(step=model.num_timesteps)
    final, partial = directory / name, directory / f".{name}.partial"
    try:
        directory.mkdir(parents=True, exist_ok=True)
        for stale in directory.glob(".step_*.partial"):  # left by a process killed while writing (the run is locked)
            shutil.rmtree(stale)
        partial.mkdir()
        if isinstance(model.replay_buffer, FrameStackReplayBuffer):  # the chunks first, durable; the manifest in info
            replay: dict[str, Any] = {"store": store.save(model.replay_buffer)}
        else:  # another buffer class: pickled whole into the state
            replay, state = {"pickle": True}, {**state, "replay_buffer": model.replay_buffer}
        model.save(partial / CHECKPOINT_MODEL)
        with (partial / CHECKPOINT_STATE).open("wb") as file:
            pickle.dump(state, file, protocol=pickle.HIGHEST_PROTOCOL)
        files = (partial / CHECKPOINT_MODEL, partial / CHECKPOINT_STATE)
        for path in files:
            fsync_path(path)
        info = {
            "format": CHECKPOINT_FORMAT,
            "version": __version__,
            "agent_steps": int(model.num_timesteps),
            "frames": int(frames_of(model)),
            "written": time.strftime("%Y-%m-%d %H:%M:%S"),
            "files": {path.name: _digest(path) for path in files},
            "replay": replay,
        }
        write_json_atomically(partial / CHECKPOINT_JSON, info)  # manifest last: it lists only chunks on disk
        if final.exists():  # a stale one of an earlier process at this step (resumed from an older checkpoint)
            shutil.rmtree(final)
        os.replace(partial, final)
        fsync_path(directory)
    except OSError as error:
        shutil.rmtree(partial, ignore_errors=True)
        previous = checkpoint_folders(directory)
        kept = f"the previous checkpoint {previous[0].name} is intact" if previous else "there is no earlier checkpoint"
        fix = "Make the folder writable again" if error.errno in READ_ONLY_ERRNOS else "Free space (or fix the folder)"
        raise OutputError(
            f"could not write a checkpoint into {directory} ({error.strerror or error}); {kept}. {fix}, then run the "
            "same command again to resume."
        ) from error
    kept = checkpoint_folders(directory)
    for folder in kept[max(1, keep) :]:
        shutil.rmtree(folder, ignore_errors=True)
    kept, manifests = kept[: max(1, keep)], []
    for folder in kept:
        with contextlib.suppress(OSError, ValueError, KeyError):
            manifests.append(read_checkpoint_info(folder)["replay"].get("store"))
    # After the new checkpoint is in place (manifest last), so that its chunks are among those kept.
    if len(manifests) == len(kept) and None not in manifests:  # else a manifest's chunks would go
        store.collect_garbage(manifests)
    return final


def checkpoint_frames(directory: str | os.PathLike) -> int | None:
    """:return: the frames of the newest checkpoint in ``directory`` as it says (not verified), ``None`` without one"""
    for folder in checkpoint_folders(directory):
        with contextlib.suppress(OSError, ValueError, KeyError):
            return int(read_checkpoint_info(folder)["frames"])
    return None


@dataclass
class LoadedCheckpoint:
    """A checkpoint's ``folder``, its ``checkpoint.json`` (``info``), its :func:`capture_state` and the damaged newer
    checkpoints passed over (``skipped``: folder and reason)."""

    folder: Path
    info: dict[str, Any]
    state: dict[str, Any]
    skipped: list[tuple[Path, str]]

    @property
    def frames(self) -> int:
        return int(self.info["frames"])


def _read_checkpoint(folder: Path) -> tuple[dict[str, Any], dict[str, Any]]:
    try:
        info = read_checkpoint_info(folder)
    except (OSError, ValueError) as error:
        raise CheckpointError(f"no readable {CHECKPOINT_JSON}: {error}", damaged=True) from None
    if info.get("format") != CHECKPOINT_FORMAT or info.get("version") != __version__:
        raise CheckpointError(
            f"checkpoint {folder} was written by sb3-collapse {info.get('version')}, this is {__version__}: resume "
            "with the version that wrote it, or train into a new folder."
        )
    for name, expected in info["files"].items():
        check_file_size(folder / name, expected["bytes"], name)
        if _digest(folder / name)["sha256"] != expected["sha256"]:
            raise CheckpointError(f"{name} does not have the checksum it was written with", damaged=True)
    try:
        with (folder / CHECKPOINT_STATE).open("rb") as file:
            state = pickle.load(file)
    except Exception as error:  # noqa: BLE001 - any unpickling failure means a damaged file
        raise CheckpointError(f"{CHECKPOINT_STATE} cannot be read: {error}", damaged=True) from None
    if "store" in info["replay"]:  # their checksums are verified as the replay store reads them
        ReplayStore(folder.parent / REPLAY_DIR).check_files(info["replay"]["store"])
    return info, state


def set_aside(folder: Path, reason: str | None = None) -> Path:
    """Rename a damaged checkpoint's (or checkpoints) ``folder`` to ``damaged_<name>`` (``-2``... when taken), with
    ``reason`` in it (:data:`DAMAGED_NOTE`, best effort); return its new path."""
    target, number = folder.with_name(f"damaged_{folder.name}"), 2
    while target.exists():
        target, number = folder.with_name(f"damaged_{folder.name}-{number}"), number + 1
    folder.replace(target)
    if reason is not None:
        with contextlib.suppress(OSError):
            (target / DAMAGED_NOTE).write_text(reason + "\n")
    return target


def read_checkpoints(directory: str | os.PathLike) -> tuple[LoadedCheckpoint | None, list[tuple[Path, str]]]:
    """:return: the newest checkpoint in ``directory`` whose files have their sizes and checksums (``None`` without one)
    and the damaged newer ones passed over, with the reason; :raises CheckpointError: for another format or version"""
    skipped: list[tuple[Path, str]] = []
    for folder in checkpoint_folders(directory):
        try:
            info, state = _read_checkpoint(folder)
        except CheckpointError as error:
            if not error.damaged:
                raise
            skipped.append((folder, str(error)))
            continue
        return LoadedCheckpoint(folder=folder, info=info, state=state, skipped=skipped), skipped
    return None, skipped


def load_checkpoint(directory: str | os.PathLike) -> LoadedCheckpoint | None:
    """:return: the newest readable checkpoint in ``directory`` (:func:`read_checkpoints`), ``None`` without one"""
    return read_checkpoints(directory)[0]


def restore_model(model: BaseAlgorithm, path: str | os.PathLike) -> None:
    """Put the zip of SB3's ``save`` at ``path`` back into ``model`` (built with the same settings) as
    ``BaseAlgorithm.load`` does, without a new model and replay buffer; :raises CheckpointError: for other spaces,
    (damaged) for weights that are not finite."""
    data, params, variables = load_from_zip_file(path, device=model.device, print_system_info=False)
    assert data is not None and params is not None
    if (name := first_non_finite(params["policy"])) is not None:  # never written so (save refuses): damaged
        raise CheckpointError(f"{CHECKPOINT_MODEL}'s weight {name!r} is not finite", damaged=True)
    for name in ("observation_space", "action_space"):
        saved, current = data[name], getattr(model, name)
        if getattr(saved, "shape", None) != getattr(current, "shape", None):
            raise CheckpointError(f"the checkpoint's {name} is {saved}, the run's is {current}.")
    model.__dict__.update(data)
    model.set_parameters(params, exact_match=True, device=model.device)
    for name, value in (variables or {}).items():
        recursive_setattr(model, f"{name}.data", value.data)


def restore_run(
    model: BaseAlgorithm,
    checkpoint: LoadedCheckpoint,
    store: ReplayStore,
    callbacks: Sequence[BaseCallback] = (),
    eval_env: Any = None,
) -> list[str]:
    """Make ``model`` (built with the run's settings, on ``EpisodeReplay`` environments), ``callbacks`` (in the order
    saved) and ``eval_env`` continue from ``checkpoint`` and ``store``, as the run that wrote it would have; return
    warnings for the user (empty when everything is as it was)."""
    state = checkpoint.state
    notes: list[str] = []
    restore_model(model, checkpoint.folder / CHECKPOINT_MODEL)
    replay = checkpoint.info["replay"]
    if "store" in replay:
        store.restore(model.replay_buffer, replay["store"])  # type: ignore[arg-type]
    else:  # pickled with the device of the run that wrote it: sampled onto the resuming model's device
        model.replay_buffer = state["replay_buffer"]
        model.replay_buffer.device = model.device
    env = model.get_env()
    assert env is not None
    observations = replay_episodes(env, state["envs"])
    if model._last_obs is not None and not np.array_equal(np.stack(observations), model._last_obs):  # type: ignore[arg-type]
        notes.append(
            "the replayed episodes do not give the saved observations (another machine, device or library version?): "
            "the resumed run will not be bit-identical to an uninterrupted one."
        )
    if eval_env is not None:
        eval_env.get_wrapper_attr("replay_episode")(state["eval_env"])
    try:
        load_callback_states(callbacks, state["callbacks"])
    except ValueError as error:  # other callbacks than the run that wrote it, or a state written by another version
        raise CheckpointError(f"checkpoint {checkpoint.folder}: {error}") from None
    if state["update_stats"] is not None:
        model.update_stats.load_state_dict(tensors_to(state["update_stats"], model.device))  # type: ignore[attr-defined]
    model.action_space.np_random.bit_generator.state = state["action_space"]
    rng = state["rng"]
    random.setstate(rng["python"])
    np.random.set_state(rng["numpy"])
    th.set_rng_state(rng["torch"])
    _restore_cuda_rng_state(rng["cuda"], model.device)
    if th.device(state["device"]).type != model.device.type:
        notes.append(
            f"the checkpoint was written on {state['device']} and the run resumes on {model.device}: it continues, "
            "but not bit for bit as an uninterrupted run would (other kernels, other random generators)."
        )
    return notes


def restore_csv_files(paths: Sequence[Path], saved: dict[str, bytes], frame: int) -> str | None:
    """Write the run's CSV files ``paths`` back atomically as the checkpoint at ``frame`` holds them (``saved``): rows
    after it go; return one line naming those that did not start with it (shorter, cut mid-row, changed), or None."""
    rewritten, newline = [], b"\n"
    for path in paths:
        if path.name not in saved:
            continue
        content, current = saved[path.name], path.read_bytes() if path.is_file() else b""
        if current == content:
            continue
        if not current.startswith(content):  # not only rows written after the checkpoint: damaged
            short = f"{content.count(newline) - current.count(newline)} line(s) short"
            cut = current and not current.endswith(newline)
            why = "changed" if not content.startswith(current) else "cut mid-row" if cut else short
            rewritten.append(f"{path.name} ({why})")
        with atomic_output(path) as temporary:
            temporary.write_bytes(content)
    if not rewritten:
        return None
    return (
        f"{', '.join(rewritten)} did not hold what the checkpoint at frame {frame:,} recorded: rewritten from it (the "
        "rows after it are written again as the run goes on)."
    )


class ResumableCheckpoints(FrameScheduleCallback):
    """
    Writes a run checkpoint (:func:`save_checkpoint`) every ``every_frames`` frames, at the first safe point after
    (docs/checkpoints.md#using-them), and one at a :meth:`request_stop`, then stops with ``TrainingInterrupted``.


    :param directory: the run's checkpoints folder
    :param every_frames: frames between two checkpoints (``0``: only at a stop request)
    :param callbacks: the run's other callbacks, whose states the checkpoints hold (in this order)
    :param eval_env: the evaluation environment (wrapped in ``EpisodeReplay``), if any
    :param csv_files: the run's CSV files, written back as the checkpoint holds them on resume
    :param extra_state: called at each checkpoint for more picklable state (e.g. the run's elapsed time)
    :param keep: complete checkpoints kept
    :param verbose: 1 prints a line per checkpoint
    """

    period_parameter = "every_frames"
    min_period = 0

    def __init__(
        self,
        directory: str | os.PathLike,
        every_frames: int,
        callbacks: Sequence[BaseCallback] = (),
        eval_env: Any = None,
        csv_files: Sequence[Path] = (),
        extra_state: Callable[[], dict[str, Any]] | None = None,
        keep: int = 2,
        verbose: int = 0,
    ) -> None:
        super().__init__(every_frames, verbose)
        if keep < 1:
            raise ValueError(f"keep must be >= 1 checkpoint, got {keep}.")
        self.directory = Path(directory)
        self.callbacks = list(callbacks)
        self.eval_env = eval_env
        self.csv_files = list(csv_files)
        self.extra_state = extra_state
        self.keep = keep
        self.store = ReplayStore(self.directory / REPLAY_DIR)
        self.due = False
        self.stop_signal: str | None = None
        self.last_checkpoint: Path | None = None
        self._grad_norms: dict[str, Any] | None = None

    def resume(self, checkpoint: LoadedCheckpoint) -> tuple[LoadedCheckpoint, list[str]]:
        """Put the model, environments, callbacks and CSV files back as ``checkpoint`` holds them (one whose replay
        chunks are damaged is set aside for the one before); return the checkpoint resumed from and notes for the user.

        :raises CheckpointError: (``damaged``) when no checkpoint is left (``train`` restarts the run from frame 0)
        """

        notes: list[str] = []
        while True:
            try:
                notes += restore_run(self.model, checkpoint, self.store, self.callbacks, self.eval_env)
                break
            except CheckpointError as error:
                if not error.damaged:
                    raise
                notes.append(f"checkpoint {checkpoint.folder} is damaged ({error}): falling back to the one before.")
                set_aside(checkpoint.folder, str(error))
                older = load_checkpoint(self.directory)
                if older is None:
                    raise CheckpointError(
                        f"no readable checkpoint is left in {self.directory} (each is set aside as damaged_step_...): "
                        "the run restarts from frame 0.",
                        damaged=True,
                    ) from error
                notes += [f"checkpoint {folder} is damaged ({reason})." for folder, reason in older.skipped]
                checkpoint = older
        rewritten = restore_csv_files(self.csv_files, checkpoint.state["csv"], checkpoint.frames)
        self._grad_norms = checkpoint.state["grad_norms"]
        self.last_checkpoint = checkpoint.folder
        return checkpoint, notes + ([rewritten] if rewritten else [])

    def request_stop(self, signal_name: str) -> None:
        """Write a checkpoint at the next round and stop ``learn()`` (safe to call from a signal handler)."""
        self.stop_signal = signal_name

    def _on_training_start(self) -> None:
        super()._on_training_start()
        if self._grad_norms is not None:  # the recorder exists now (the callbacks hook SB3 models' optimizers)
            recorder = grad_norm_recorder(self.model)
            if recorder is not None:
                recorder.load_state_dict(self._grad_norms)
            self._grad_norms = None

    def _on_check(self, count: int) -> None:
        self.due = True

    def _on_step(self) -> bool:
        super()._on_step()
        if self.due or self.stop_signal:
            self.model.request_safe_point()  # type: ignore[attr-defined]  # a CollapseModel
        return True

    def _on_rollout_start(self) -> None:
        if not (self.due or self.stop_signal) or not self.model.at_safe_point:  # type: ignore[attr-defined]
            return  # a step in flight: _on_step holds the next one back, the checkpoint comes one round later
        self.save()
        self.due = False
        if self.stop_signal:
            raise TrainingInterrupted(self.last_checkpoint, self.stop_signal)  # type: ignore[arg-type]

    def capture(self) -> dict[str, Any]:
        """:return: the run's state now (:func:`capture_state`), for a :meth:`save` after a step that changes it but
        is given up (the evaluation of the final model, stopped by a signal)"""
        extra = self.extra_state() if self.extra_state is not None else None
        return capture_state(self.model, self.callbacks, self.eval_env, self.csv_files, extra)

    def save(self, state: dict[str, Any] | None = None) -> Path:
        """Write a checkpoint now (between two rounds of ``learn()``, or after it), of the run's state ``state`` (of
        :meth:`capture`; ``None``: now); return its folder."""
        name = CHECKPOINT_FOLDER.format(step=self.model.num_timesteps)
        if self.last_checkpoint is not None and self.last_checkpoint.name == name:
            return self.last_checkpoint  # taken at this step already (a signal right after a scheduled checkpoint)
        start = time.perf_counter()
        if not bool(all_finite(self.model.policy.parameters())):  # never a checkpoint of diverged weights
            raise DivergenceError(
                f"training diverged: a weight is not finite at frame {self.frames:,}; no checkpoint was written."
            )
        state = self.capture() if state is None else state
        self.last_checkpoint = save_checkpoint(self.model, self.directory, self.store, state, keep=self.keep)
        if self.verbose >= 1:
            took = time.perf_counter() - start
            print(f"Checkpoint at frame {self.frames:,}: {self.last_checkpoint} ({took:.1f} s)", flush=True)
        return self.last_checkpoint
