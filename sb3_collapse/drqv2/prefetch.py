"""Replay batches drawn one update ahead (:class:`ReplayPrefetcher`), the batches ``replay_buffer.sample`` would draw:
docs/throughput.md#replay-batches-drawn-ahead-modelreplay_prefetcher."""

from __future__ import annotations

import contextlib
import weakref
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from concurrent.futures import wait as wait_futures
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch as th
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.type_aliases import ReplayBufferSamples
from stable_baselines3.common.vec_env import VecNormalize

from sb3_collapse.drqv2.replay_buffer import FrameStackReplayBuffer

HOST_SLOTS = 2  # sets of staging buffers that alternate (double buffering)
ALIGNMENT_BYTES = 64  # of each field in the staging buffer of its dtype
FRAME_FIELDS = ("observations", "next_observations")  # gathered into the frames buffer, the rest one per dtype
WORKER_NAME = "sb3-collapse-replay-prefetch"


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
    """Host staging buffers of replay batches (page-locked with ``pin_memory``) and their copy to ``device``, an
    ``event_factory()`` event (``torch.cuda.Event``) recorded after each copy unless ``None``."""

    def __init__(self, device: th.device, pin_memory: bool, event_factory: Callable[[], Any] | None = None) -> None:
        self.device = device
        self.pin_memory = pin_memory
        self.event_factory = event_factory
        self.slots = [_Slot() for _ in range(HOST_SLOTS)]
        self.events: list[Any] = [None] * HOST_SLOTS  # made at the first copy out of each set
        self._next = 0

    def claim(self) -> int:
        """:return: the set of buffers of the next batch (the sets alternate)"""
        slot, self._next = self._next, (self._next + 1) % HOST_SLOTS
        return slot

    def gather(
        self, slot: int, buffer: FrameStackReplayBuffer, batch_inds: np.ndarray, env_indices: np.ndarray
    ) -> None:
        """Gather the transitions ``(batch_inds, env_indices)``, each ``(batch,)``, into the buffers of ``slot``."""
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
        """:return: the batch in ``slot`` copied to the device (``non_blocking``, on the current stream), the slot's
        event recorded after the copies"""
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
    """:return: pinned staging with CUDA events for a CUDA ``device``; ``None`` elsewhere"""
    return HostStaging(device, pin_memory=True, event_factory=th.cuda.Event) if device.type == "cuda" else None


def buffer_counters(buffer: ReplayBuffer) -> tuple[Any, ...]:
    """:return: what identifies ``buffer``'s contents between two ``add`` calls"""
    counters = (getattr(buffer, "transitions_added", None), getattr(buffer, "resets", None))
    return (type(buffer).__name__, int(buffer.pos), bool(buffer.full), *counters)


def _same_generator_state(a: tuple[Any, ...], b: tuple[Any, ...]) -> bool:
    """Whether two ``np.random.get_state()`` values are equal."""
    return a[0] == b[0] and np.array_equal(a[1], b[1]) and tuple(a[2:]) == tuple(b[2:])


def _tensors(batch: Any) -> Iterator[th.Tensor]:
    """The tensors of a batch (``ReplayBufferSamples`` or ``DictReplayBufferSamples``: dicts of tensors too)."""
    for value in batch:
        if isinstance(value, th.Tensor):
            yield value
        elif isinstance(value, dict):
            yield from (item for item in value.values() if isinstance(item, th.Tensor))


@dataclass(repr=False)
class PreparedBatch:
    """A batch drawn ahead of its update, and what draws it again after a load."""

    batch_size: int
    generator_state: tuple[Any, ...]  # np.random.get_state() before the draw
    counters: tuple[Any, ...]  # buffer_counters() at the draw
    batch: Any = None  # on the device; None once pickled (ReplayPrefetcher.restore makes it again)
    ready: Any = None  # CUDA event after the batch's copies on the side stream
    source: tuple[Any, ...] = ()  # weak references to the buffer and VecNormalize env, and the device

    def drawn_from(self, buffer: ReplayBuffer, batch_size: int, env: VecNormalize | None) -> bool:
        """Whether this batch is one of ``buffer.sample(batch_size, env)`` in this process, since its last reset."""
        resets = buffer_counters(buffer)[-1]
        if self.batch is None or not self.source or batch_size != self.batch_size or resets != self.counters[-1]:
            return False
        buffer_ref, env_ref, device = self.source
        same_env = env is None if env_ref is None else env_ref() is env
        return buffer_ref() is buffer and same_env and device == buffer.device

    def __getstate__(self) -> dict[str, Any]:
        return {"batch_size": self.batch_size, "generator_state": self.generator_state, "counters": self.counters}

    def __repr__(self) -> str:  # short: SB3's save writes str() of the saved objects' attributes into its JSON
        made = "made" if self.batch is not None else "to draw again"
        return f"PreparedBatch(batch_size={self.batch_size}, counters={self.counters}, {made})"


class ReplayPrefetcher:
    """
    ``DrQv2.train``'s replay batches, each drawn while the update before it runs (docs/throughput.md).

    :param enabled: ``False``: call ``replay_buffer.sample`` when each update is due
    :param worker: make batches in a worker thread (``None``: on CUDA only)
    """

    def __init__(self, enabled: bool = True, worker: bool | None = None) -> None:
        self.enabled = enabled
        self.worker = worker
        self._executor: ThreadPoolExecutor | None = None
        self._staging: HostStaging | None = None
        self._stream: Any = None  # torch.cuda.Stream of the batches (CUDA only)
        self._device: th.device | None = None
        self._prepared: PreparedBatch | None = None

    def uses_worker(self, device: th.device) -> bool:
        """:return: whether batches for ``device`` are made in the worker thread"""
        return self.worker if self.worker is not None else device.type == "cuda"

    @property
    def prepared(self) -> PreparedBatch | None:
        """The batch drawn for the next update, if any."""
        return self._prepared

    def batches(
        self, replay_buffer: ReplayBuffer, gradient_steps: int, batch_size: int, env: VecNormalize | None = None
    ) -> contextlib.closing[Iterator[Any]]:
        """:return: the ``gradient_steps`` samples of ``batch_size`` transitions of ``replay_buffer`` (normalized by
        ``env``), a context manager: the worker has finished when the block ends"""
        if not self.enabled:
            return contextlib.closing(replay_buffer.sample(batch_size, env=env) for _ in range(gradient_steps))
        return contextlib.closing(self._ahead(replay_buffer, gradient_steps, batch_size, env))

    def _ahead(
        self, buffer: ReplayBuffer, gradient_steps: int, batch_size: int, env: VecNormalize | None
    ) -> Iterator[Any]:
        if gradient_steps < 1:
            return
        self._setup(buffer.device)
        prepared, self._prepared = self._prepared, None
        if prepared is None or not prepared.drawn_from(buffer, batch_size, env):
            prepared = self._prepare(buffer, batch_size, env, reserve=True)
        upcoming: Future[PreparedBatch] | PreparedBatch | None = None
        try:
            for _ in range(gradient_steps):
                batch = self._hand_over(prepared)
                # The draw for the next update takes np.random's global generator while this update runs: the
                # batches of a serial sampler calling sample() here, on either thread, because nothing else draws
                # from it during an update (augmentation and action noise use torch's generators, callbacks run
                # between rounds) and no transition is added during train() (the finally below waits for the worker).
                if self.uses_worker(buffer.device):
                    upcoming = self._worker().submit(self._prepare, buffer, batch_size, env)
                else:
                    upcoming = self._prepare(buffer, batch_size, env)  # before the update: the same batches
                yield batch
                prepared = upcoming.result() if isinstance(upcoming, Future) else upcoming  # a worker's error here
                upcoming = None
            self._prepared = prepared
        finally:
            if isinstance(upcoming, Future):  # stopped early: the worker must not read the buffer after train()
                wait_futures([upcoming])

    def _prepare(
        self, buffer: ReplayBuffer, batch_size: int, env: VecNormalize | None, reserve: bool = False
    ) -> PreparedBatch:
        """Draw and make a batch; ``reserve``: allocate the other staging sets now (on the training thread)."""
        # Before the draw: what restore() sets back to draw this batch again after a load (the same draws, as above).
        generator_state, counters = np.random.get_state(), buffer_counters(buffer)
        staging = self._staging if isinstance(buffer, FrameStackReplayBuffer) and env is None else None
        ready = None
        with self._on_stream():
            if staging is None:
                batch = buffer.sample(batch_size, env=env)
            else:
                assert isinstance(buffer, FrameStackReplayBuffer)
                batch_inds, env_indices = buffer.sample_indices(batch_size)  # sample()'s draws, in its order
                slot = staging.claim()
                staging.gather(slot, buffer, batch_inds, env_indices)
                if reserve:
                    staging.reserve_like(slot)
                batch = staging.to_device(slot)
            if self._stream is not None:
                ready = th.cuda.Event()
                ready.record(self._stream)
        source = (weakref.ref(buffer), None if env is None else weakref.ref(env), buffer.device)
        return PreparedBatch(batch_size, generator_state, counters, batch, ready, source)

    def _hand_over(self, prepared: PreparedBatch) -> Any:
        """The batch, usable on the current stream: it waits for the side stream's copies, which cannot reuse its
        memory before the current stream is done with it."""
        if prepared.ready is not None:
            stream = th.cuda.current_stream(self._device)
            stream.wait_event(prepared.ready)
            for tensor in _tensors(prepared.batch):
                tensor.record_stream(stream)
        return prepared.batch

    def _on_stream(self) -> contextlib.ExitStack:
        stack = contextlib.ExitStack()
        if self._stream is not None:
            stack.enter_context(th.cuda.device(self._device))
            stack.enter_context(th.cuda.stream(self._stream))
        return stack

    def _setup(self, device: th.device) -> None:
        """Staging buffers and side stream for ``device`` (on the training thread)."""
        if device.type == "cuda" and device.index is None:
            device = th.device("cuda", th.cuda.current_device())
        if self._device != device:
            self._staging, self._device = staging_for(device), device
            self._stream = th.cuda.Stream(device) if device.type == "cuda" else None

    def _worker(self) -> ThreadPoolExecutor:
        if self._executor is None:
            self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix=WORKER_NAME)
        return self._executor

    def restore(self, replay_buffer: ReplayBuffer, env: VecNormalize | None = None) -> bool:
        """Make again the batch prepared when the prefetcher was pickled, if ``replay_buffer`` is the one it was drawn
        from (else drop it). :return: whether a batch was made again"""
        prepared = self._prepared
        if prepared is None or prepared.batch is not None:
            return False
        self._prepared = None
        if not self.enabled or buffer_counters(replay_buffer) != prepared.counters:
            return False
        now = np.random.get_state()
        np.random.set_state(prepared.generator_state)
        try:
            self._setup(replay_buffer.device)
            again = self._prepare(replay_buffer, prepared.batch_size, env, reserve=True)
        finally:
            drawn_to = np.random.get_state()
            np.random.set_state(now)
        if not _same_generator_state(drawn_to, now):  # the draw must end where the checkpoint left the generator
            return False  # not the draw it was (another buffer with the same counters)
        self._prepared = again
        return True

    def discard(self) -> None:
        """Drop the batch prepared for the next update (``DrQv2.reset_from_scratch``: the buffer was emptied)."""
        self._prepared = None

    def close(self) -> None:
        """End the worker thread and free the staging buffers (a later call makes new ones)."""
        if self._executor is not None:
            self._executor.shutdown(wait=True)
        self._executor, self._staging, self._stream, self._device = None, None, None, None

    def __getstate__(self) -> dict[str, Any]:
        return {"enabled": self.enabled, "worker": self.worker, "prepared": self._prepared}  # no thread, no buffers

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__init__(state["enabled"], state["worker"])  # type: ignore[misc]
        self._prepared = state["prepared"]
