"""
``sb3_collapse.drqv2.prefetch``: the prefetched replay batches are ``sample()``'s for a seed (both sampling rules,
n-step), the double-buffered staging waits for the copy out of a buffer before writing it, the CUDA branch pins its
host buffers, the worker's errors surface, and seeded DrQv2 training is bit-identical with and without it.
"""

import gc
import pickle
import threading
import time

import gymnasium as gym
import numpy as np
import pytest
import torch as th

from sb3_collapse.drqv2 import DrQv2, FrameStackReplayBuffer, prefetch
from sb3_collapse.drqv2.prefetch import WORKER_NAME, HostStaging, ReplayPrefetcher, staging_for

FRAME_STACK = 3
FRAME = (3, 8, 8)
ACTIONS = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)


class FakeEvent:
    """A CUDA event's host-side behaviour: ``pending`` from ``record`` (a copy queued) until ``synchronize``."""

    def __init__(self):
        self.pending, self.records, self.syncs = False, 0, 0

    def record(self, stream=None):
        assert stream is None  # the CPU's copies have no stream
        self.pending, self.records = True, self.records + 1

    def synchronize(self):
        self.pending, self.syncs = False, self.syncs + 1


def filled_buffer(sampling="sb3", n_steps=3, n_envs=2, steps=60, seed=0):
    """A buffer of random shifted frame stacks, episodes of random length ended by terminations and time limits."""
    rng = np.random.default_rng(seed)
    space = gym.spaces.Box(0, 255, (FRAME[0] * FRAME_STACK, *FRAME[1:]), np.uint8)
    buffer = FrameStackReplayBuffer(
        200,
        space,
        ACTIONS,
        "cpu",
        n_envs=n_envs,
        n_steps=n_steps,
        gamma=0.9,
        frame_stack=FRAME_STACK,
        min_episode_length=2,
        sampling=sampling,
    )
    obs = rng.integers(0, 256, (n_envs, *space.shape), dtype=np.uint8)
    for _ in range(steps):
        next_obs = np.concatenate([obs[:, FRAME[0] :], rng.integers(0, 256, (n_envs, *FRAME), dtype=np.uint8)], 1)
        terminated, truncated = rng.random(n_envs) < 0.08, rng.random(n_envs) < 0.08
        infos = [{"TimeLimit.truncated": bool(tr and not te)} for te, tr in zip(terminated, truncated)]
        action = rng.uniform(-1, 1, (n_envs, 2)).astype(np.float32)
        buffer.add(obs, next_obs, action, rng.normal(size=n_envs), terminated | truncated, infos)
        obs = next_obs.copy()
        for i in np.flatnonzero(terminated | truncated):
            obs[i] = rng.integers(0, 256, space.shape, dtype=np.uint8)
    assert buffer.ready_to_sample and buffer.dones.any() and buffer.timeouts.any()
    return buffer


def assert_same_samples(a, b):
    for name in a._fields:
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and x.device == y.device and x.shape == y.shape, name
        assert x.is_contiguous(), name
        assert th.equal(x, y), name


def fake_staging(monkeypatch, pin_requests=None):
    """Route the prefetcher's CPU batches through HostStaging, with fake events (and fake pinning, recorded)."""
    made = []

    def make(device):
        staging = HostStaging(device, pin_memory=pin_requests is not None, event_factory=FakeEvent)
        made.append(staging)
        return staging

    monkeypatch.setattr(prefetch, "staging_for", make)
    if pin_requests is not None:

        def host_empty(shape, dtype, pin_memory):
            pin_requests.append(pin_memory)
            return th.empty(shape, dtype=dtype)  # no CUDA here: what would be pinned is a plain host tensor

        monkeypatch.setattr(prefetch, "_host_empty", host_empty)
    return made


def run_calls(prefetcher, buffer, calls, batch_size):
    """The batches of consecutive train() calls of ``calls`` gradient steps each, and the next np.random draw."""
    batches = []
    for gradient_steps in calls:
        with prefetcher.batches(buffer, gradient_steps, batch_size) as call:
            batches.extend(call)
    return batches, np.random.rand()


@pytest.mark.parametrize("staged", [False, True])
@pytest.mark.parametrize("sampling, n_steps, n_envs", [("sb3", 3, 2), ("drqv2", 3, 2), ("sb3", 1, 1), ("drqv2", 2, 3)])
def test_prefetched_batches_are_those_of_sample(monkeypatch, staged, sampling, n_steps, n_envs):
    buffer = filled_buffer(sampling, n_steps, n_envs)
    if staged:
        made = fake_staging(monkeypatch)
    calls, batch_size = (4, 1, 3, 2), 16
    np.random.seed(3)
    expected = [buffer.sample(batch_size) for _ in range(sum(calls))]
    expected_next = np.random.rand()
    np.random.seed(3)
    prefetcher = ReplayPrefetcher(enabled=True)
    batches, next_draw = run_calls(prefetcher, buffer, (0, *calls), batch_size)  # a call of 0 steps draws nothing
    assert len(batches) == len(expected) == 10
    for batch, reference in zip(batches, expected):  # held until the end: no batch aliases a reused buffer
        assert_same_samples(batch, reference)
    assert next_draw == expected_next  # the same draws from np.random, no more
    if staged:
        (staging,) = made  # one staging, reused across calls
        assert [event.records for event in staging.events] == [5, 5]  # one copy out per batch, alternating sets


def test_default_prefetches_on_cuda_only_and_for_frame_stack_buffers():
    buffer = filled_buffer()
    assert not ReplayPrefetcher().active(buffer)  # CPU: today's loop
    assert ReplayPrefetcher(enabled=True).active(buffer)
    buffer.device = th.device("cuda")  # what a CUDA model's buffer has
    assert ReplayPrefetcher().active(buffer)
    assert not ReplayPrefetcher(enabled=False).active(buffer)
    assert not ReplayPrefetcher().active(buffer, env=object())  # VecNormalize: float observations, today's loop
    from stable_baselines3.common.buffers import ReplayBuffer

    other = ReplayBuffer(10, buffer.observation_space, ACTIONS, "cpu")
    other.device = th.device("cuda")
    assert not ReplayPrefetcher(enabled=True).active(other)
    # CUDA: pinned host buffers and CUDA events (nothing is allocated or recorded until the first batch).
    staging = staging_for(th.device("cuda"))
    assert staging is not None and staging.pin_memory and staging.event_factory is th.cuda.Event
    assert staging_for(th.device("cpu")) is None and staging_for(th.device("meta")) is None


def test_disabled_prefetcher_calls_sample(monkeypatch):
    buffer = filled_buffer()
    calls = []
    monkeypatch.setattr(buffer, "sample", lambda batch_size, env=None: calls.append(batch_size) or batch_size)
    with ReplayPrefetcher(enabled=False).batches(buffer, 3, 7) as batches:
        assert list(batches) == [7, 7, 7]


def test_staging_writes_a_set_only_after_the_copy_out_of_it(monkeypatch):
    buffer = filled_buffer()
    pins = []
    made = fake_staging(monkeypatch, pin_requests=pins)
    writes = []
    original = buffer.sample_arrays

    def sample_arrays(batch_inds, env_indices, env=None, frames_out=None):
        (staging,) = made
        pointers = [None if s.frames is None else s.frames.data_ptr() for s in staging.slots]
        slot = pointers.index(frames_out.__array_interface__["data"][0])
        event = staging.events[slot]
        # (no event yet: nothing was ever copied out of this set)
        assert event is None or not event.pending, "a staging set written while its copy out may be in flight"
        writes.append((slot, threading.current_thread().name))
        return original(batch_inds, env_indices, env=env, frames_out=frames_out)

    monkeypatch.setattr(buffer, "sample_arrays", sample_arrays)
    prefetcher = ReplayPrefetcher(enabled=True)
    for gradient_steps in (3, 1, 2):
        with prefetcher.batches(buffer, gradient_steps, 8) as batches:
            for _ in batches:
                time.sleep(0.01)  # the update: the worker gathers the next batch meanwhile
    assert [slot for slot, _ in writes] == [0, 1, 0, 1, 0, 1]
    # The first batch of a call is gathered on the training thread, the next ones in the worker.
    threads = [name.startswith(WORKER_NAME) for _, name in writes]
    assert threads == [False, True, True, False, False, True]
    (staging,) = made
    assert [event.records for event in staging.events] == [3, 3]
    assert pins and all(pins)  # every host buffer asked pinned


def test_worker_error_surfaces_with_its_message(monkeypatch):
    buffer = filled_buffer()
    original, calls = buffer._get_samples, []

    def failing(batch_inds, env=None, env_indices=None):
        calls.append(threading.current_thread().name)
        if len(calls) == 3:
            raise ValueError("gather failed at batch 3")
        return original(batch_inds, env=env, env_indices=env_indices)

    monkeypatch.setattr(buffer, "_get_samples", failing)
    got = []
    with pytest.raises(ValueError, match="gather failed at batch 3"):
        with ReplayPrefetcher(enabled=True).batches(buffer, 4, 8) as batches:
            got.extend(batches)
    assert len(got) == 2 and calls[2].startswith(WORKER_NAME)


def test_an_interrupted_call_waits_for_the_worker(monkeypatch):
    buffer = filled_buffer()
    original, finished = buffer._get_samples, []

    def slow(batch_inds, env=None, env_indices=None):
        time.sleep(0.2)
        finished.append(True)
        return original(batch_inds, env=env, env_indices=env_indices)

    monkeypatch.setattr(buffer, "_get_samples", slow)
    with pytest.raises(RuntimeError, match="update failed"):
        with ReplayPrefetcher(enabled=True).batches(buffer, 3, 8) as batches:
            for _ in batches:
                raise RuntimeError("update failed")  # the worker is gathering batch 2
    assert len(finished) == 2  # batch 2's gather had finished when the block ended: no reader left on the buffer


def _worker_threads(prefetcher):
    threads = list(prefetcher._executor._threads)
    assert len(threads) == 1 and threads[0].name.startswith(WORKER_NAME) and threads[0].is_alive()
    return threads[0]


def test_worker_ends_with_the_prefetcher_and_it_pickles():
    buffer = filled_buffer()
    prefetcher = ReplayPrefetcher(enabled=True)
    with prefetcher.batches(buffer, 1, 8) as batches:
        list(batches)
    assert prefetcher._executor is None  # one update per call: no thread at all
    with prefetcher.batches(buffer, 2, 8) as batches:
        list(batches)
    worker = _worker_threads(prefetcher)
    copy = pickle.loads(pickle.dumps(prefetcher))
    assert copy.enabled is True and copy._executor is None and copy._staging is None
    prefetcher.close()
    assert not worker.is_alive()
    with prefetcher.batches(buffer, 2, 8) as batches:  # usable after close: a new worker
        list(batches)
    worker = _worker_threads(prefetcher)
    del prefetcher, batches
    gc.collect()
    worker.join(timeout=5)  # the pool's thread ends when the prefetcher (the model) is collected
    assert not worker.is_alive()


class FrameStackEnv(gym.Env):
    """Shifted stacks of random 3x16x16 frames, with the frame_stack and action_repeat of make_dmc_env."""

    frame_stack, action_repeat = FRAME_STACK, 2
    observation_space = gym.spaces.Box(0, 255, (3 * FRAME_STACK, 16, 16), np.uint8)
    action_space = ACTIONS

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self._steps = 0
        self._obs = np.concatenate([self._frame()] * FRAME_STACK)
        return self._obs.copy(), {}

    def _frame(self):
        return self.np_random.integers(0, 256, (3, 16, 16), dtype=np.uint8)

    def step(self, action):
        self._steps += 1
        self._obs = np.concatenate([self._obs[3:], self._frame()])
        return self._obs.copy(), float(self.np_random.random()), False, self._steps >= 12, {}


def _trained(enabled, sampling):
    th.manual_seed(0)
    model = DrQv2(
        "CnnPolicy",
        FrameStackEnv(),
        buffer_size=200,
        learning_starts=24,
        batch_size=8,
        gradient_steps=3,
        seed=0,
        policy_kwargs=dict(hidden_dim=16, feature_dim=8),
        replay_buffer_kwargs=dict(sampling=sampling),
    )
    assert type(model.replay_buffer) is FrameStackReplayBuffer
    model.replay_prefetcher.enabled = enabled
    model.learn(36)
    return model


@pytest.mark.parametrize("sampling, staged", [("sb3", False), ("drqv2", True)])
def test_drqv2_training_is_bit_identical_with_the_prefetcher(monkeypatch, tmp_path, sampling, staged):
    reference = _trained(False, sampling)  # today's loop: replay_buffer.sample per update
    made = fake_staging(monkeypatch) if staged else []
    model = _trained(True, sampling)
    assert model._n_updates == reference._n_updates == 18  # 6 rounds of 3 updates: batches prepared ahead
    assert model.replay_prefetcher._executor is not None  # the worker gathered
    assert not staged or sum(event.records for event in made[0].events) == 18  # through the staging buffers
    for name, value in reference.policy.state_dict().items():
        assert th.equal(model.policy.state_dict()[name], value), name
    model.save(tmp_path / "model.zip")  # the prefetcher is not saved; the loaded model has a default one
    loaded = DrQv2.load(tmp_path / "model.zip", env=FrameStackEnv())
    assert isinstance(loaded.replay_prefetcher, ReplayPrefetcher) and loaded.replay_prefetcher.enabled is None


cuda = pytest.mark.skipif(not th.cuda.is_available(), reason="needs a CUDA GPU")


@pytest.mark.cuda
@cuda
def test_cuda_batches_equal_cpu_batches_through_pinned_buffers():
    cpu_buffer = filled_buffer("drqv2", n_steps=3, n_envs=2)
    buffer = filled_buffer("drqv2", n_steps=3, n_envs=2)
    buffer.device = th.device("cuda")
    prefetcher = ReplayPrefetcher()  # default: on, on CUDA
    assert prefetcher.active(buffer)
    calls, batch_size = (1, 4, 3), 64
    np.random.seed(5)
    expected = [cpu_buffer.sample(batch_size) for _ in range(sum(calls))]
    np.random.seed(5)
    batches, _ = run_calls(prefetcher, buffer, calls, batch_size)
    th.cuda.synchronize()
    for batch, reference in zip(batches, expected):
        for name in reference._fields:
            x, y = getattr(batch, name), getattr(reference, name)
            assert x.device.type == "cuda" and x.dtype == y.dtype and x.shape == y.shape, name
            assert th.equal(x.cpu(), y), name
    staging = prefetcher._staging
    assert staging is not None and all(s.frames.is_pinned() for s in staging.slots)
    assert all(flat.is_pinned() for s in staging.slots for flat in s.flats.values())
    assert batches[0].observations.dtype == th.uint8  # uint8 over the bus


@pytest.mark.cuda
@cuda
def test_cuda_drqv2_trains_with_the_prefetcher():
    th.manual_seed(0)
    model = DrQv2(
        "CnnPolicy",
        FrameStackEnv(),
        buffer_size=200,
        learning_starts=24,
        batch_size=8,
        gradient_steps=3,
        seed=0,
        policy_kwargs=dict(hidden_dim=16, feature_dim=8),
        device="cuda",
    )
    assert model.replay_prefetcher.active(model.replay_buffer)
    model.learn(36)
    assert model._n_updates == 18 and model.replay_prefetcher._staging is not None
