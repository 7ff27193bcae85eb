"""
Incremental checkpoints of a ``FrameStackReplayBuffer`` (:class:`ReplayStore`): each save writes what was added since
the previous one as append-only chunk files and returns the manifest the run's checkpoint keeps. See
docs/checkpoints.md#the-replay-buffer-incremental-chunks.
"""

from __future__ import annotations

import errno
import os
import re
import secrets
import warnings
import weakref
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from sb3_collapse.drqv2.replay_buffer import FrameStackReplayBuffer
from sb3_collapse.errors import CheckpointError, InputError

FORMAT = "sb3_collapse.replay_store/1"
"""``manifest["format"]``: the manifest and chunk layout this module writes and reads."""
CHUNK_PREFIX = "chunk-"
CHUNK_SUFFIX = ".bin"
TEMP_SUFFIX = ".tmp"
CHUNK_NAME = re.compile(rf"^{CHUNK_PREFIX}(\d+)-[0-9a-f]+{re.escape(CHUNK_SUFFIX)}$")
FILES_PER_BUFFER = 32
"""The default ``max_file_bytes`` is the buffer's array bytes divided by this, at least ``MIN_FILE_BYTES``."""
MIN_FILE_BYTES = 1 << 20
BLOCK_BYTES = 32 << 20  # bytes copied, checksummed and written (or read) at once
TRANSITION_ARRAYS = ("frame_starts", "actions", "rewards", "dones", "timeouts")  # in a transitions segment's order
TRANSITIONS, FRAMES = "transitions", "frames"
STATE_KEYS = ("pos", "full", "transitions_added", "resets", "frame_heads", "steps_since_done", "episodes_done")


@dataclass
class _Tracked:
    """What a store last saved or restored: the base of its next incremental save."""

    buffer: weakref.ref
    resets: int
    transitions_added: int
    frame_heads: np.ndarray
    chunks: list[dict[str, Any]]


def _damaged(message: str) -> CheckpointError:
    """The error of a damaged replay checkpoint: ``message`` and the way out."""
    return CheckpointError(f"{message} Resume from another checkpoint.", damaged=True)


def check_file_size(path: Path, expected: int, name: str | None = None) -> None:
    """:raises CheckpointError: (damaged) naming the file (``name``, default ``path``) when it is missing or not
    ``expected`` bytes long"""
    name = name or str(path)
    if not path.is_file():
        raise CheckpointError(f"{name} is missing", damaged=True)
    if (size := path.stat().st_size) != expected:
        how = "truncated" if size < expected else "changed"
        raise CheckpointError(f"{name} has {size} bytes, {expected} were written ({how})", damaged=True)


def _write(file: BinaryIO, data: np.ndarray) -> None:
    """Write ``data``'s bytes (one function, so tests can make it fail as a full disk would)."""
    file.write(data)


class ReplayStore:
    """
    Append-only chunk store of a :class:`FrameStackReplayBuffer`'s data in one folder (``<run>/checkpoints/replay/``).

    :param directory: the folder (created at the first save)
    :param max_file_bytes: largest chunk file; ``None``: the buffer's array bytes / 32, at least 1 MiB
    """

    def __init__(self, directory: str | os.PathLike, max_file_bytes: int | None = None) -> None:
        if max_file_bytes is not None and (isinstance(max_file_bytes, bool) or max_file_bytes < 1):
            raise InputError(f"max_file_bytes must be None or >= 1, got {max_file_bytes!r}.", "max_file_bytes")
        self.directory = Path(directory)
        if self.directory.exists() and not self.directory.is_dir():
            raise InputError(f"directory {self.directory} is a file, not a folder.", "directory")
        self.max_file_bytes = max_file_bytes
        self._tracked: _Tracked | None = None

    def save(self, buffer: FrameStackReplayBuffer) -> dict[str, Any]:
        """
        Write, as new ``fsync``'d files, what ``buffer`` gained since this store's last :meth:`save` or :meth:`restore`
        of it (all live data the first time, after ``buffer.reset()``, or when its earlier chunks are gone).

        :return: the JSON-serialisable manifest: the chunk files needed, with sizes and CRC-32s, counters and layout
        :raises OSError: when a write fails (full disk): nothing this call wrote remains, older chunks are intact
        :raises CheckpointError: when ``pos``/``full`` disagree with ``transitions_added`` (changed outside ``add``)
        """
        _check_counters(buffer)
        live = _live_windows(buffer)
        base = self._base(buffer)
        # Chunks are append-only (never modified, no name reused): the base's chunks still hold what they held, so
        # the new manifest lists them again and adds only what is new.
        chain: list[dict[str, Any]] = [] if base is None else list(base.chunks)
        new = live
        if base is not None:
            previous = {TRANSITIONS: base.transitions_added}
            previous.update({_frames_key(env): int(head) for env, head in enumerate(base.frame_heads)})
            new = {key: (max(previous[key], low), high) for key, (low, high) in live.items()}
        segments = [_segment(key, low, high) for key, (low, high) in new.items() if high > low]
        max_bytes = self.max_file_bytes or max(MIN_FILE_BYTES, buffer.nbytes // FILES_PER_BUFFER)
        plans = _plan_files(segments, _row_bytes(buffer), max_bytes)
        if plans:
            chain += self._write_chunks(buffer, plans)
        chain = [chunk for chunk in chain if _is_live(chunk, live)]
        manifest = {"format": FORMAT, "layout": _layout(buffer), "state": _state(buffer), "chunks": chain}
        self._track(buffer, manifest)
        return manifest

    def _base(self, buffer: FrameStackReplayBuffer) -> _Tracked | None:
        """The last saved or restored state of this buffer when the next save can be incremental to it."""
        tracked = self._tracked
        if tracked is None or tracked.buffer() is not buffer or tracked.resets != buffer.resets:
            return None
        if buffer.transitions_added < tracked.transitions_added or (buffer.frame_heads < tracked.frame_heads).any():
            return None
        for chunk in tracked.chunks:  # append-only: a chunk still there with its size holds what was saved
            path = self.directory / chunk["file"]
            if not path.is_file() or path.stat().st_size != chunk["bytes"]:
                warnings.warn(
                    f"The replay checkpoint chunk {path} is gone or changed: saving the whole replay buffer again.",
                    stacklevel=3,
                )
                return None
        return tracked

    def _track(self, buffer: FrameStackReplayBuffer, manifest: dict[str, Any]) -> None:
        added, heads = int(buffer.transitions_added), buffer.frame_heads.copy()
        self._tracked = _Tracked(weakref.ref(buffer), int(buffer.resets), added, heads, list(manifest["chunks"]))

    def _write_chunks(self, buffer: FrameStackReplayBuffer, plans: list[list[dict[str, Any]]]) -> list[dict]:
        """Write one chunk file per plan; on failure delete them all and raise an ``OSError``."""
        written: list[dict[str, Any]] = []
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
            names = [int(match.group(1)) for name in os.listdir(self.directory) if (match := CHUNK_NAME.match(name))]
            for number, plan in enumerate(plans, start=max(names, default=0) + 1):  # no save reuses a name
                written.append(self._write_chunk(buffer, plan, number))
            # Manifest last: the caller writes the manifest that lists these chunks only after this returns, so
            # their names are durable first and a manifest on disk never lists a chunk that is not.
            fsync_path(self.directory)
        except OSError as error:
            for chunk in written:
                (self.directory / chunk["file"]).unlink(missing_ok=True)
            needed = sum(_plan_bytes(plan, _row_bytes(buffer)) for plan in plans)
            raise OSError(  # the cause only: the caller says what to do (save_checkpoint: once, in its own words)
                error.errno,
                f"{error.strerror or error} ({needed:,} bytes of replay chunks to write; none kept, the earlier ones "
                "intact)",
                str(self.directory),
            ) from error
        return written

    def _write_chunk(self, buffer: FrameStackReplayBuffer, plan: list[dict[str, Any]], number: int) -> dict:
        name = f"{CHUNK_PREFIX}{number:06d}-{secrets.token_hex(4)}{CHUNK_SUFFIX}"
        temporary = self.directory / f".{name}{TEMP_SUFFIX}"
        crc, size = 0, 0
        try:
            with open(temporary, "xb") as file:
                for block in _chunk_blocks(buffer, plan):
                    data = np.ascontiguousarray(block).reshape(-1).view(np.uint8)
                    crc = zlib.crc32(data, crc)
                    _write(file, data)
                    size += data.nbytes
                file.flush()
                os.fsync(file.fileno())
            os.rename(temporary, self.directory / name)  # a chunk has its name only once complete and fsync'd
        except BaseException:
            temporary.unlink(missing_ok=True)
            raise
        return {"file": name, "bytes": size, "crc32": crc, "segments": plan}

    def restore(self, buffer: FrameStackReplayBuffer, manifest: dict[str, Any]) -> None:
        """
        Make ``buffer`` (built with the saved buffer's arguments) hold the state of ``manifest`` (of :meth:`save`);
        the next :meth:`save` is incremental to it.

        :raises CheckpointError: for a malformed manifest, another layout, a missing chunk or one of another size
            (the buffer unchanged), or a chunk that fails its CRC-32 or cannot be read (the buffer ``reset()``)
        """
        _check_manifest(manifest)
        _check_layout(buffer, manifest["layout"])
        _check_state(buffer, manifest["state"])
        row_bytes = _row_bytes(buffer)
        for chunk in manifest["chunks"]:
            path = self.directory / chunk["file"]
            rings = {TRANSITIONS: buffer.buffer_size, FRAMES: buffer.frame_capacity}
            if any(
                _key(segment) not in row_bytes or segment["stop"] - segment["start"] > rings[segment["ring"]]
                for segment in chunk["segments"]
            ):
                raise _damaged(f"The replay checkpoint manifest is inconsistent: chunk {path} lists segments outside "
                               "this buffer's environments or rings.")  # fmt: skip
            expected = _plan_bytes(chunk["segments"], row_bytes)
            if expected != chunk["bytes"]:
                raise _damaged(f"The replay checkpoint manifest is inconsistent: chunk {path} is listed with "
                               f"{chunk['bytes']:,} bytes but its segments hold {expected:,}.")  # fmt: skip
        self.check_files(manifest)
        try:
            for chunk in manifest["chunks"]:
                _read_chunk(buffer, self.directory / chunk["file"], chunk)
        except BaseException:
            buffer.reset()
            raise
        state = manifest["state"]
        buffer.pos, buffer.full = int(state["pos"]), bool(state["full"])
        buffer.transitions_added, buffer.resets = int(state["transitions_added"]), int(state["resets"])
        buffer.frame_heads[:] = state["frame_heads"]
        buffer.steps_since_done[:] = state["steps_since_done"]
        buffer.episodes_done[:] = state["episodes_done"]
        buffer._sampleable_checked = None  # ready_to_sample scans the restored content again
        self._track(buffer, manifest)

    def check_files(self, manifest: dict[str, Any]) -> None:
        """:raises CheckpointError: for a malformed ``manifest`` (of :meth:`save`), a missing chunk or one of another
        size (not read: :meth:`restore` checks the CRC-32s), naming the file"""
        _check_manifest(manifest)
        for chunk in manifest["chunks"]:
            check_file_size(self.directory / chunk["file"], chunk["bytes"])

    def collect_garbage(self, keep: list[dict[str, Any]]) -> int:
        """Delete the chunk files that neither a ``keep`` manifest nor this store's last save or restore needs, and the
        temporary files of interrupted saves; return the bytes freed."""

        needed = set()
        for manifest in keep:
            _check_manifest(manifest)
            needed.update(chunk["file"] for chunk in manifest["chunks"])
        if self._tracked is not None:
            needed.update(chunk["file"] for chunk in self._tracked.chunks)
        if not self.directory.is_dir():
            return 0
        freed = 0
        # Manifest last: a chunk that no kept manifest lists belongs to a save whose checkpoint was never written, or
        # is no longer needed; a temporary file is a save that never completed. Neither can be read by a resume.
        for path in self.directory.iterdir():
            name = path.name
            stray = name.startswith(f".{CHUNK_PREFIX}") and name.endswith(TEMP_SUFFIX)
            if stray or (CHUNK_NAME.match(name) and name not in needed):
                try:
                    size = path.stat().st_size
                    path.unlink()
                except FileNotFoundError:
                    continue
                freed += size
        return freed

    @staticmethod
    def bytes_needed(manifest: dict[str, Any]) -> int:
        """:return: bytes of the chunk files ``manifest`` (of :meth:`save`) lists"""
        return sum(int(chunk["bytes"]) for chunk in manifest["chunks"])

    def disk_bytes(self) -> int:
        """Bytes of all chunk and temporary files in the folder now."""
        if not self.directory.is_dir():
            return 0
        return sum(
            path.stat().st_size
            for path in self.directory.iterdir()
            if CHUNK_NAME.match(path.name) or path.name.endswith(TEMP_SUFFIX)
        )


def _frames_key(env: int) -> str:
    return f"{FRAMES}/{env}"


def _key(segment: dict[str, Any]) -> str:
    return TRANSITIONS if segment["ring"] == TRANSITIONS else _frames_key(segment["env"])


def _segment(key: str, start: int, stop: int) -> dict[str, Any]:
    ring = {"ring": TRANSITIONS} if key == TRANSITIONS else {"ring": FRAMES, "env": int(key.split("/")[1])}
    return {**ring, "start": int(start), "stop": int(stop)}


def _check_counters(buffer: FrameStackReplayBuffer) -> None:
    added, size = buffer.transitions_added, buffer.buffer_size
    if buffer.pos != added % size or buffer.full != (added >= size):
        raise CheckpointError(
            f"The replay buffer's pos={buffer.pos} and full={buffer.full} disagree with transitions_added={added} "
            f"(buffer_size {size}): changed outside add() and reset(), so what is new since the last save is unknown."
        )


def _live_windows(buffer: FrameStackReplayBuffer) -> dict[str, tuple[int, int]]:
    """Counter ranges ``[low, high)`` of the data the rings hold: key -> range."""
    added = int(buffer.transitions_added)
    windows = {TRANSITIONS: (max(0, added - buffer.buffer_size), added)}
    for env, head in enumerate(buffer.frame_heads):
        windows[_frames_key(env)] = (max(0, int(head) - buffer.frame_capacity), int(head))
    return windows


def _is_live(chunk: dict[str, Any], live: dict[str, tuple[int, int]]) -> bool:
    """Whether any segment of ``chunk`` holds data the rings still hold."""
    return any(live[_key(s)][0] < s["stop"] and s["start"] < live[_key(s)][1] for s in chunk["segments"])


def _row_bytes(buffer: FrameStackReplayBuffer) -> dict[str, int]:
    """Bytes one counter of each ring takes in a chunk: key -> bytes."""
    sizes = {TRANSITIONS: sum(getattr(buffer, name)[0].nbytes for name in TRANSITION_ARRAYS)}
    sizes.update({_frames_key(env): buffer.frames[0, env].nbytes for env in range(buffer.n_envs)})
    return sizes


def _plan_bytes(plan: list[dict[str, Any]], row_bytes: dict[str, int]) -> int:
    return sum((segment["stop"] - segment["start"]) * row_bytes[_key(segment)] for segment in plan)


def _plan_files(segments: list[dict[str, Any]], row_bytes: dict[str, int], max_bytes: int) -> list[list[dict]]:
    """Split the segments, in order, into files of at most ``max_bytes`` (at least one row each)."""
    files: list[list[dict[str, Any]]] = []
    current: list[dict[str, Any]] = []
    used = 0
    for segment in segments:
        row = row_bytes[_key(segment)]
        start = segment["start"]
        while start < segment["stop"]:
            room = (max_bytes - used) // row
            if room < 1 and current:
                files.append(current)
                current, used = [], 0
                continue
            stop = min(segment["stop"], start + max(room, 1))
            current.append({**segment, "start": start, "stop": stop})
            used += (stop - start) * row
            start = stop
    if current:
        files.append(current)
    return files


def _pieces(start: int, stop: int, size: int) -> Iterator[tuple[int, int]]:
    """The contiguous ring position ranges of the counters ``[start, stop)`` in a ring of ``size``."""
    first = start % size
    count = stop - start
    head = min(count, size - first)
    yield first, first + head
    if count > head:
        yield 0, count - head


def _chunk_blocks(buffer: FrameStackReplayBuffer, segments: list[dict[str, Any]]) -> Iterator[np.ndarray]:
    """The buffer's array slices (of about :data:`BLOCK_BYTES`) that ``segments`` cover, in their chunk's order."""
    for segment in segments:
        transitions = segment["ring"] == TRANSITIONS
        size = buffer.buffer_size if transitions else buffer.frame_capacity
        for low, high in _pieces(segment["start"], segment["stop"], size):
            if transitions:
                views = [getattr(buffer, name)[low:high] for name in TRANSITION_ARRAYS]
            else:
                views = [buffer.frames[low:high, segment["env"]]]
            for view in views:
                rows = max(1, BLOCK_BYTES // max(1, view[0].nbytes)) if len(view) else 1
                for start in range(0, len(view), rows):
                    yield view[start : start + rows]


def _read_chunk(buffer: FrameStackReplayBuffer, path: Path, chunk: dict[str, Any]) -> None:
    """Read a chunk's rows into the buffer, checking its CRC-32, then that its floats (rewards, actions, float
    frames) are finite: a chunk written with a NaN (by a version that stored an env's NaN) is damaged too."""
    crc, non_finite = 0, None
    try:
        with open(path, "rb") as file:
            for block in _chunk_blocks(buffer, chunk["segments"]):
                target = block if block.flags.c_contiguous else np.empty_like(block)
                data = target.reshape(-1).view(np.uint8)
                if file.readinto(data) != data.nbytes:
                    raise _damaged(f"The replay checkpoint chunk {path} ended early (truncated).")
                crc = zlib.crc32(data, crc)
                if non_finite is None and target.dtype.kind == "f" and not np.isfinite(target).all():
                    non_finite = (_array_name(buffer, block), target[~np.isfinite(target)][0])
                if target is not block:
                    block[...] = target
    except OSError as error:
        raise CheckpointError(f"Could not read the replay checkpoint chunk {path}: {error}.", damaged=True) from error
    if crc != chunk["crc32"]:
        raise _damaged(f"The replay checkpoint chunk {path} is corrupt (CRC-32 {crc:#010x}, the checkpoint expects "
                       f"{chunk['crc32']:#010x}).")  # fmt: skip
    if non_finite is not None:
        raise _damaged(f"The replay checkpoint chunk {path} holds a non-finite value ({non_finite[1]}) in its "
                       f"{non_finite[0]}, though its CRC-32 matches: it was written so (an environment's reward or "
                       "observation stored as it came).")  # fmt: skip


def _array_name(buffer: FrameStackReplayBuffer, block: np.ndarray) -> str:
    """:return: the name of the buffer's storage array that ``block`` is a view of"""
    return next(name for name, array in buffer.storage_arrays.items() if np.may_share_memory(block, array))


def fsync_path(path: Path) -> None:
    """Flush a file, or a folder's entries (the renames), to disk, where the system allows opening a folder."""
    try:
        handle = os.open(path, os.O_RDONLY)
    except OSError:
        if path.is_dir():  # e.g. Windows
            return
        raise
    try:
        os.fsync(handle)
    except OSError as error:
        if error.errno not in (errno.EINVAL, errno.EBADF):  # folders that cannot be fsync'd
            raise
    finally:
        os.close(handle)


def _layout(buffer: FrameStackReplayBuffer) -> dict[str, Any]:
    return {
        "n_envs": int(buffer.n_envs),
        "buffer_size": int(buffer.buffer_size),
        "frame_capacity": int(buffer.frame_capacity),
        "frame_stack": int(buffer.frame_stack),
        "arrays": {
            name: {"shape": list(array.shape), "dtype": array.dtype.str}
            for name, array in buffer.storage_arrays.items()
        },
    }


def _state(buffer: FrameStackReplayBuffer) -> dict[str, Any]:
    state = {key: int(getattr(buffer, key)) for key in ("pos", "transitions_added", "resets")}
    state["full"] = bool(buffer.full)
    state.update({key: [int(value) for value in getattr(buffer, key)] for key in STATE_KEYS[4:]})
    return state


def _check_manifest(manifest: Any) -> None:
    """Raise :class:`CheckpointError` unless ``manifest`` looks like one :meth:`ReplayStore.save` returned."""
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
        found = manifest.get("format") if isinstance(manifest, dict) else type(manifest).__name__
        raise _damaged(f"Not a replay checkpoint manifest of format {FORMAT!r} (found {found!r}): it was written by "
                       "another version of sb3-collapse, or is damaged.")  # fmt: skip
    layout, state, chunks = (manifest.get(key) for key in ("layout", "state", "chunks"))
    problems = [] if isinstance(layout, dict) else ["layout is not a mapping"]
    if not isinstance(state, dict) or any(key not in state for key in STATE_KEYS):
        problems.append(f"state lacks some of {', '.join(STATE_KEYS)}")
    if not isinstance(chunks, list):
        problems.append("chunks is not a list")
    else:
        problems += [f"chunk entry {str(chunk)[:120]} is malformed" for chunk in chunks if not _valid_chunk(chunk)][:1]
    if problems:
        raise _damaged(f"The replay checkpoint manifest is damaged: {'; '.join(problems)}.")


def _valid_chunk(chunk: Any) -> bool:
    """Whether a manifest's chunk entry has a chunk file name (no path), integer sizes and valid segments."""
    if not isinstance(chunk, dict) or not isinstance(chunk.get("file"), str) or not CHUNK_NAME.match(chunk["file"]):
        return False
    if not all(isinstance(chunk.get(key), int) and chunk[key] >= 0 for key in ("bytes", "crc32")):
        return False
    segments = chunk.get("segments")
    return isinstance(segments, list) and all(
        isinstance(segment, dict)
        and segment.get("ring") in (TRANSITIONS, FRAMES)
        and (segment["ring"] == TRANSITIONS or isinstance(segment.get("env"), int))
        and isinstance(segment.get("start"), int)
        and isinstance(segment.get("stop"), int)
        and 0 <= segment["start"] <= segment["stop"]
        for segment in segments
    )


def _check_state(buffer: FrameStackReplayBuffer, state: dict[str, Any]) -> None:
    """Raise :class:`CheckpointError` unless the saved counters fit the buffer and agree with one another."""
    try:
        added = int(state["transitions_added"])
        consistent = (
            all(len(state[key]) == buffer.n_envs for key in ("frame_heads", "steps_since_done", "episodes_done"))
            and int(state["pos"]) == added % buffer.buffer_size
            and bool(state["full"]) == (added >= buffer.buffer_size)
        )
    except (TypeError, ValueError):
        consistent = False
    if not consistent:
        buffer_text = f"{buffer.n_envs} environments and {buffer.buffer_size} transitions each"
        raise _damaged(f"The replay checkpoint manifest is damaged: its state {str(state)[:200]} does not describe a "
                       f"buffer of {buffer_text}.")  # fmt: skip


def _check_layout(buffer: FrameStackReplayBuffer, saved: dict[str, Any]) -> None:
    """Raise :class:`CheckpointError` when the buffer's sizes, shapes or dtypes differ from the saved ones."""
    current = _layout(buffer)
    if not isinstance(saved.get("arrays"), dict):
        raise _damaged("The replay checkpoint manifest is damaged: its layout lacks the arrays' shapes.")
    differences = [
        f"{key} is {saved.get(key)} in the checkpoint and {current[key]} in this buffer"
        for key in ("n_envs", "buffer_size", "frame_capacity", "frame_stack")
        if saved.get(key) != current[key]
    ]
    differences += [
        f"{name} is {saved['arrays'].get(name)} in the checkpoint and {spec} here"
        for name, spec in current["arrays"].items()
        if saved["arrays"].get(name) != spec
    ]
    if differences:
        raise CheckpointError(
            "The replay buffer does not match the checkpoint: "
            + "; ".join(differences)
            + ". Build it with the run's buffer_size, n_envs, frame_stack, min_episode_length and spaces.",
            damaged=True,
        )
