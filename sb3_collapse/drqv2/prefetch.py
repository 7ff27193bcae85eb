"""
Replay batches prepared ahead of the update, and copied to a CUDA device without blocking the training thread.

Without it, each update samples its batch on the training thread: ``FrameStackReplayBuffer.sample`` gathers the
frame stacks with NumPy into new (pageable) arrays, then six tensors go to the device with blocking copies (each
waits for the device to finish the work queued before it). :class:`ReplayPrefetcher` changes how a batch is
made, not which batch: ``DrQv2.train`` takes its batches from :meth:`ReplayPrefetcher.batches`.

**Same batches.** At the start of a ``train(gradient_steps)`` call, the training thread draws the indices of all
``gradient_steps`` batches with ``FrameStackReplayBuffer.sample_indices``: the draws of as many ``sample`` calls,
in the same order, from NumPy's global generator. Nothing else draws from it during the updates (augmentation
shifts and action noise come from torch's generators; a round's updates run no callback and add no transition),
and the buffer does not change during the call, so these are the indices today's loop would draw. Batches are
prepared ahead only within one call: the next call's indices depend on the transitions added in between (the
buffer's size, DrQ-v2's finished episodes). With one update per call (one environment, ``train_freq=2``,
``gradient_steps=1``: DrQ-v2's ratio), nothing is prepared ahead; what remains is the pinned, non-blocking copy.

**Prepared ahead.** The first batch of a call is gathered on the training thread (the update waits for it
anyway); each next one in a worker thread while the update of the previous one runs: one batch ahead. The
worker gathers only (NumPy, which releases the GIL), never draws a random number, and has finished before the
call returns (also when an update raises), so the buffer is never read while transitions are added. An exception
in the worker is raised in the training thread, with its message, when its batch is due. The worker is one thread
of a ``ThreadPoolExecutor``, made at the first call with two updates or more; it ends with the prefetcher (garbage
collection of the model) or :meth:`ReplayPrefetcher.close`. The prefetcher pickles as its setting only (``DrQv2``
does not save it: the loaded model has a new one).

**On CUDA** (:class:`HostStaging`): the batch is gathered straight into page-locked (``pin_memory``) host buffers
(the frame stacks with ``np.take(..., out=)``, no intermediate array) and copied to the device with
``non_blocking=True`` on the current CUDA stream: two copies per batch, the uint8 frames (``obs`` and
``next_obs``: uint8 on the bus; the float conversion, crop and normalization stay on the device as before) and
the float32 rest (actions, dones, n-step returns, discounts), each a contiguous view of its device copy. Two sets
of host buffers alternate (double buffering): a CUDA event is recorded after the copies out of a set, and the
set is written again only after that event has completed, so the host waits for the copy of two batches back
at most, never for the update. The copies are ordered on the stream with the updates (no side stream): what
runs concurrently with an update is the next batch's gather on the host, not its transfer. The staging buffers
cost twice a batch of host memory, page-locked (about 65 MB per set at batch 512 for 9x84x84 observations).

**On the CPU** nothing is pinned or copied twice: a batch is ``_get_samples``' own tensors, as today. By default
(``enabled=None``) the prefetcher is used on CUDA only; the CPU keeps today's loop (``sample`` per update), so
that a gather thread does not compete with the update for the cores. ``enabled=True`` uses the prefetching path
on the CPU too (same batches), ``False`` nowhere. Replay buffers other than ``FrameStackReplayBuffer`` (SB3's,
for state observations), and a ``VecNormalize`` environment (float observations), take today's loop.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from concurrent.futures import wait as wait_futures
from dataclasses import dataclass, field
from types import TracebackType
from typing import Any, Protocol, Self

import numpy as np
import torch as th
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.type_aliases import ReplayBufferSamples
from stable_baselines3.common.vec_env import VecNormalize

from sb3_collapse.drqv2.replay_buffer import FrameStackReplayBuffer

HOST_SLOTS = 2
"""Sets of staging buffers that alternate (double buffering)."""

ALIGNMENT_BYTES = 64
"""Alignment of each field in the staging buffers of its dtype."""

FRAME_FIELDS = ("observations", "next_observations")
"""The fields gathered into the uint8 frames buffer; the others go into one buffer per dtype."""

WORKER_NAME = "sb3-collapse-replay-prefetch"
"""Name prefix of the worker thread."""


class CopyEvent(Protocol):
    """What :class:`HostStaging` needs of an event: ``torch.cuda.Event``'s ``record`` and ``synchronize``."""

    def record(self, stream: Any = None) -> None: ...

    def synchronize(self) -> None: ...


def _host_empty(shape: tuple[int, ...], dtype: th.dtype, pin_memory: bool) -> th.Tensor:
    """A host tensor, page-locked when ``pin_memory`` (only on a machine with CUDA)."""
    return th.empty(shape, dtype=dtype, pin_memory=pin_memory)


def _torch_dtype(dtype: np.dtype) -> th.dtype:
    return th.from_numpy(np.empty(0, dtype=dtype)).dtype


@dataclass
class _Slot:
    """One set of staging buffers: the frames ``(2, batch, C, H, W)`` and one flat buffer per dtype of the rest."""

    frames: th.Tensor | None = None
    flats: dict[str, th.Tensor] = field(default_factory=dict)  # numpy dtype string -> flat host tensor
    fields: dict[str, tuple[str, int, tuple[int, ...]]] = field(default_factory=dict)  # name -> (dtype, offset, shape)

    def frames_match(self, shape: tuple[int, ...], dtype: th.dtype) -> bool:
        return self.frames is not None and tuple(self.frames.shape) == shape and self.frames.dtype == dtype


class HostStaging:
    """
    Host staging buffers of replay batches and their copy to the device (see the module docstring).

    The training thread calls :meth:`claim` (which set the next batch goes to) and :meth:`to_device`; :meth:`gather`
    may run in another thread, one at a time per set. A set is written only after the event recorded after the last
    copy out of it has completed.

    :param device: where the batches go
    :param pin_memory: page-lock the host buffers (CUDA)
    :param event_factory: makes the event recorded after each copy (``torch.cuda.Event``); ``None``: none (the
        copies are synchronous, as on the CPU)
    """

    def __init__(
        self, device: th.device, pin_memory: bool, event_factory: Callable[[], CopyEvent] | None = None
    ) -> None:
        self.device = device
        self.pin_memory = pin_memory
        self.event_factory = event_factory
        self.slots = [_Slot() for _ in range(HOST_SLOTS)]
        self.events: list[CopyEvent | None] = [None] * HOST_SLOTS  # made at the first copy out of each set
        self._next = 0

    def claim(self) -> int:
        """:return: the set of buffers of the next batch (the sets alternate)"""
        slot, self._next = self._next, (self._next + 1) % HOST_SLOTS
        return slot

    def gather(
        self, slot: int, buffer: FrameStackReplayBuffer, batch_inds: np.ndarray, env_indices: np.ndarray
    ) -> None:
        """
        Gather the transitions ``(batch_inds, env_indices)`` into the buffers of ``slot``, after the copy out of
        them has completed.

        :param slot: from :meth:`claim`
        :param buffer: the replay buffer
        :param batch_inds: positions ``(batch,)``
        :param env_indices: environments ``(batch,)``
        """
        event = self.events[slot]
        if event is not None:
            event.synchronize()  # the copy of two batches back, out of these buffers, has completed
        target = self.slots[slot]
        frames_shape = (len(FRAME_FIELDS), len(batch_inds), *buffer.obs_shape)
        frames_dtype = _torch_dtype(buffer.frames.dtype)
        if not target.frames_match(frames_shape, frames_dtype):
            target.frames = _host_empty(frames_shape, frames_dtype, self.pin_memory)
        arrays = buffer.sample_arrays(batch_inds, env_indices, frames_out=target.frames.numpy())
        rest = {name: array for name, array in arrays.items() if name not in FRAME_FIELDS}
        self._fit(target, rest)
        for name, array in rest.items():
            dtype, offset, shape = target.fields[name]
            flat = target.flats[dtype].numpy()
            np.copyto(flat[offset : offset + array.size].reshape(shape), array)

    def reserve_like(self, slot: int) -> None:
        """Give the other sets the buffers of ``slot`` (on the calling thread), waiting for their copies first."""
        model = self.slots[slot]
        assert model.frames is not None
        for other, target in enumerate(self.slots):
            if other == slot or (
                target.frames_match(tuple(model.frames.shape), model.frames.dtype) and target.fields == model.fields
            ):
                continue
            event = self.events[other]
            if event is not None:
                event.synchronize()
            target.frames = _host_empty(tuple(model.frames.shape), model.frames.dtype, self.pin_memory)
            target.fields = dict(model.fields)
            target.flats = {
                dtype: _host_empty(tuple(flat.shape), flat.dtype, self.pin_memory)
                for dtype, flat in model.flats.items()
            }

    def _fit(self, target: _Slot, arrays: dict[str, np.ndarray]) -> None:
        """(Re)allocate the flat buffers of ``target`` when the fields' dtypes or shapes changed."""
        sizes: dict[str, int] = {}
        fields = {}
        for name, array in arrays.items():
            dtype = array.dtype.str
            align = max(ALIGNMENT_BYTES // array.dtype.itemsize, 1)
            offset = -(-sizes.get(dtype, 0) // align) * align
            fields[name] = (dtype, offset, tuple(array.shape))
            sizes[dtype] = offset + array.size
        if fields == target.fields:
            return
        target.fields = fields
        target.flats = {
            dtype: _host_empty((size,), _torch_dtype(np.dtype(dtype)), self.pin_memory) for dtype, size in sizes.items()
        }

    def to_device(self, slot: int) -> ReplayBufferSamples:
        """
        Copy the batch in ``slot`` to the device (``non_blocking``, on the current stream) and record the slot's
        event after the copies. Call it on the training thread, after :meth:`gather` of that slot has returned.

        :return: the batch on the device: contiguous views of one copy of the frames and one per dtype of the rest
        """
        target = self.slots[slot]
        assert target.frames is not None
        frames = self._copy(target.frames)
        flats = {dtype: self._copy(flat) for dtype, flat in target.flats.items()}
        if self.event_factory is not None:
            if self.events[slot] is None:
                self.events[slot] = self.event_factory()
            stream = th.cuda.current_stream(self.device) if self.device.type == "cuda" else None
            self.events[slot].record(stream)  # type: ignore[union-attr]
        values = {name: frames[index] for index, name in enumerate(FRAME_FIELDS)}
        for name, (dtype, offset, shape) in target.fields.items():
            values[name] = flats[dtype][offset : offset + int(np.prod(shape))].view(shape)
        return ReplayBufferSamples(**{name: values[name] for name in ReplayBufferSamples._fields})

    def _copy(self, host: th.Tensor) -> th.Tensor:
        """A new device tensor holding ``host`` (a copy on the CPU too: the host buffers are reused)."""
        return th.empty(host.shape, dtype=host.dtype, device=self.device).copy_(host, non_blocking=True)


def staging_for(device: th.device) -> HostStaging | None:
    """
    :param device: the replay buffer's device
    :return: pinned staging with CUDA events on CUDA; ``None`` elsewhere (the batches are ``_get_samples``')
    """
    if device.type != "cuda":
        return None
    return HostStaging(device, pin_memory=True, event_factory=th.cuda.Event)


class ReplayPrefetcher:
    """
    Where ``DrQv2.train`` takes its replay batches from (see the module docstring): the batches of
    ``replay_buffer.sample``, drawn in the same order, gathered one batch ahead in a worker thread, through pinned
    host buffers and non-blocking copies on CUDA.

    :param enabled: ``None`` (default): on CUDA only; ``True``: on any device; ``False``: never (today's loop,
        ``replay_buffer.sample`` per update)
    """

    def __init__(self, enabled: bool | None = None) -> None:
        self.enabled = enabled
        self._executor: ThreadPoolExecutor | None = None
        self._staging: HostStaging | None = None
        self._staging_device: th.device | None = None

    def active(self, replay_buffer: ReplayBuffer, env: VecNormalize | None = None) -> bool:
        """
        :param replay_buffer: the model's replay buffer
        :param env: the ``VecNormalize`` env the samples are normalized with, if any
        :return: whether :meth:`batches` prefetches (otherwise it calls ``replay_buffer.sample`` per batch)
        """
        if not isinstance(replay_buffer, FrameStackReplayBuffer) or env is not None:
            return False
        return self.enabled if self.enabled is not None else replay_buffer.device.type == "cuda"

    def batches(
        self, replay_buffer: ReplayBuffer, gradient_steps: int, batch_size: int, env: VecNormalize | None = None
    ) -> ReplayBatches:
        """
        The ``gradient_steps`` batches of a ``train`` call. Use it as a context manager, so that the worker has
        finished when the block ends, also on an exception::

            with prefetcher.batches(buffer, gradient_steps, batch_size) as batches:
                for replay_data in batches:
                    ...

        :param replay_buffer: the replay buffer (not changed until the block ends)
        :param gradient_steps: number of batches
        :param batch_size: transitions per batch
        :param env: ``VecNormalize`` env to normalize the samples with, as in SB3
        :return: an iterable of ``gradient_steps`` ``ReplayBufferSamples`` on the buffer's device
        """
        if not self.active(replay_buffer, env):
            return ReplayBatches(replay_buffer.sample(batch_size, env=env) for _ in range(gradient_steps))
        assert isinstance(replay_buffer, FrameStackReplayBuffer)
        return ReplayBatches(self._prefetched(replay_buffer, gradient_steps, batch_size))

    def _prefetched(
        self, buffer: FrameStackReplayBuffer, gradient_steps: int, batch_size: int
    ) -> Iterator[ReplayBufferSamples]:
        if gradient_steps < 1:
            return
        indices = [buffer.sample_indices(batch_size) for _ in range(gradient_steps)]  # all draws, in sample()'s order
        staging = self._staging_on(buffer.device)
        pending: Future[Any] | None = None
        try:
            ready = self._gather(staging, self._claim(staging), buffer, *indices[0])
            if staging is not None:
                staging.reserve_like(ready)  # the other set's buffers allocated here, not in the worker
            for step in range(gradient_steps):
                batch = ready if staging is None else staging.to_device(ready)  # records the set's event
                if step + 1 < gradient_steps:
                    slot = self._claim(staging)  # the other set: its last copy out was recorded a batch ago
                    pending = self._worker().submit(self._gather, staging, slot, buffer, *indices[step + 1])
                yield batch
                if pending is not None:
                    ready, pending = pending.result(), None  # a worker's exception is raised here
        finally:
            if pending is not None:  # stopped early: the worker must not read the buffer after train() returns
                wait_futures([pending])

    @staticmethod
    def _claim(staging: HostStaging | None) -> int | None:
        return None if staging is None else staging.claim()

    @staticmethod
    def _gather(
        staging: HostStaging | None,
        slot: int | None,
        buffer: FrameStackReplayBuffer,
        batch_inds: np.ndarray,
        env_indices: np.ndarray,
    ) -> Any:
        """Runs on either thread. :return: the batch (no staging), or ``slot``, the staging buffers holding it"""
        if staging is None or slot is None:
            return buffer._get_samples(batch_inds, env_indices=env_indices)
        staging.gather(slot, buffer, batch_inds, env_indices)
        return slot

    def _staging_on(self, device: th.device) -> HostStaging | None:
        if self._staging_device != device:
            self._staging, self._staging_device = staging_for(device), device
        return self._staging

    def _worker(self) -> ThreadPoolExecutor:
        if self._executor is None:
            self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix=WORKER_NAME)
        return self._executor

    def close(self) -> None:
        """End the worker thread and free the staging buffers (a later call makes new ones)."""
        if self._executor is not None:
            self._executor.shutdown(wait=True)
        self._executor, self._staging, self._staging_device = None, None, None

    def __getstate__(self) -> dict[str, Any]:
        return {"enabled": self.enabled}  # no thread, no buffers

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__init__(**state)  # type: ignore[misc]


class ReplayBatches:
    """The batches of one ``train`` call (:meth:`ReplayPrefetcher.batches`): an iterator and a context manager."""

    def __init__(self, batches: Iterator[ReplayBufferSamples]) -> None:
        self._batches = batches

    def __iter__(self) -> Iterator[ReplayBufferSamples]:
        return self._batches

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self, kind: type[BaseException] | None, error: BaseException | None, traceback: TracebackType | None
    ) -> None:
        close = getattr(self._batches, "close", None)
        if close is not None:
            close()  # a generator's finally: waits for the batch in the worker
