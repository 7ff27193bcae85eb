"""
``sb3_collapse.drqv2.prefetch``: each replay batch is drawn while the update before it runs (also across ``train``
calls, at one update per round), and the batches are those of a serial sampler calling ``sample()`` at the same
points, for every replay buffer class (both sampling rules, n-step, dict observations); the double-buffered staging
waits for the copy out of a buffer before writing it, the worker's errors surface, a batch drawn ahead survives
pickling with its replay buffer, and seeded DrQv2 training is the same in the worker and on the training thread.
"""

import gc
import pickle
import threading
import time

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3.common.buffers import DictReplayBuffer, NStepReplayBuffer, ReplayBuffer

from sb3_collapse.drqv2 import DrQv2, FrameStackReplayBuffer, prefetch
from sb3_collapse.drqv2.prefetch import WORKER_NAME, HostStaging, ReplayPrefetcher, staging_for
from sb3_collapse.drqv2.sb3_compat import DictNStepReplayBuffer

FRAME_STACK = 3
FRAME = (3, 8, 8)
STACK = gym.spaces.Box(0, 255, (FRAME[0] * FRAME_STACK, *FRAME[1:]), np.uint8)
ACTIONS = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
DICT_SPACE = gym.spaces.Dict({"pixels": STACK, "state": gym.spaces.Box(-1.0, 1.0, (3,), np.float32)})

# name -> (class, observation space, keyword arguments)
BUFFERS = {
    "frames-sb3": (FrameStackReplayBuffer, STACK, dict(n_steps=3, gamma=0.9, frame_stack=FRAME_STACK, n_envs=2)),
    "frames-drqv2": (
        FrameStackReplayBuffer, STACK, dict(n_steps=2, gamma=0.9, frame_stack=FRAME_STACK, n_envs=3, sampling="drqv2")
    ),
    "frames-1-step": (FrameStackReplayBuffer, STACK, dict(n_steps=1, gamma=0.9, frame_stack=FRAME_STACK, n_envs=1)),
    "sb3": (ReplayBuffer, STACK, dict(n_envs=2)),
    "sb3-n-step": (NStepReplayBuffer, STACK, dict(n_steps=3, gamma=0.9, n_envs=2)),
    "dict": (DictReplayBuffer, DICT_SPACE, dict(n_envs=2)),
    "dict-n-step": (DictNStepReplayBuffer, DICT_SPACE, dict(n_steps=3, gamma=0.9, n_envs=2)),
}  # fmt: skip


class FakeEvent:
    """A CUDA event's host-side behaviour: ``pending`` from ``record`` (a copy queued) until ``synchronize``."""

    def __init__(self):
        self.pending, self.records, self.syncs = False, 0, 0

    def record(self, stream=None):
        assert stream is None  # the CPU's copies have no stream
        self.pending, self.records = True, self.records + 1

    def synchronize(self):
        self.pending, self.syncs = False, self.syncs + 1


class Feeder:
    """Adds transitions to a buffer: shifted stacks of random frames, episodes ended by terminations and time
    limits; the same seed gives the same transitions."""

    def __init__(self, buffer, seed=0):
        self.buffer, self.rng, n_envs = buffer, np.random.default_rng(seed), buffer.n_envs
        self.obs = self.rng.integers(0, 256, (n_envs, *STACK.shape), dtype=np.uint8)

    def _observation(self, stacks):
        if isinstance(self.buffer.observation_space, gym.spaces.Dict):
            return {"pixels": stacks, "state": self.rng.uniform(-1, 1, (len(stacks), 3)).astype(np.float32)}
        return stacks

    def add(self, steps):
        n_envs = self.buffer.n_envs
        for _ in range(steps):
            new = self.rng.integers(0, 256, (n_envs, *FRAME), dtype=np.uint8)
            next_obs = np.concatenate([self.obs[:, FRAME[0] :], new], 1)
            terminated, truncated = self.rng.random(n_envs) < 0.08, self.rng.random(n_envs) < 0.08
            infos = [{"TimeLimit.truncated": bool(tr and not te)} for te, tr in zip(terminated, truncated)]
            action = self.rng.uniform(-1, 1, (n_envs, 2)).astype(np.float32)
            rewards = self.rng.normal(size=n_envs)
            obs, next_ = self._observation(self.obs), self._observation(next_obs)
            self.buffer.add(obs, next_, action, rewards, terminated | truncated, infos)
            self.obs = next_obs.copy()
            for i in np.flatnonzero(terminated | truncated):
                self.obs[i] = self.rng.integers(0, 256, STACK.shape, dtype=np.uint8)
        return self.buffer


def make_buffer(kind="frames-sb3", steps=45, capacity=50):
    """A buffer of ``kind`` (``BUFFERS``) holding ``steps`` transitions per environment of ``capacity``, and its
    feeder."""
    cls, space, kwargs = BUFFERS[kind]
    kwargs = dict(kwargs)
    if cls is FrameStackReplayBuffer:
        kwargs["min_episode_length"] = 2
    buffer = cls(capacity * kwargs["n_envs"], space, ACTIONS, "cpu", **kwargs)
    feeder = Feeder(buffer)
    feeder.add(steps)
    return buffer, feeder


def filled_buffer(sampling="sb3"):
    buffer, _ = make_buffer("frames-drqv2" if sampling == "drqv2" else "frames-sb3")
    assert buffer.ready_to_sample and buffer.dones.any() and buffer.timeouts.any()
    return buffer


def assert_same_samples(a, b):
    for name in a._fields:
        x, y = getattr(a, name), getattr(b, name)
        if x is None or y is None:  # SB3's one-step buffers have no discounts
            assert x is None and y is None, name
            continue
        if isinstance(x, dict):
            assert x.keys() == y.keys(), name
            for key in x:
                assert x[key].dtype == y[key].dtype and th.equal(x[key], y[key]), f"{name}[{key}]"
            continue
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


CALLS = (0, 4, 1, 1, 3, 1, 2)
"""Updates of consecutive train() calls (a call of 0 draws nothing); three transitions per env added after each."""


def run_calls(prefetcher, buffer, feeder, calls=CALLS, batch_size=16, update=None):
    """The batches of consecutive train() calls, a round of transitions added after each; and the next np.random
    draw."""
    batches = []
    for gradient_steps in calls:
        with prefetcher.batches(buffer, gradient_steps, batch_size) as call:
            for batch in call:
                batches.append(batch)
                if update is not None:
                    update(batch)
        feeder.add(3)
    return batches, np.random.rand()


def serial_batches(buffer, feeder, calls=CALLS, batch_size=16):
    """``sample()`` called on the training thread at the prefetcher's points: the first batch when the first
    update is due, each next one during the update before it, before the round of transitions after it."""
    drawn = []
    for gradient_steps in calls:
        if gradient_steps and not drawn:
            drawn.append(buffer.sample(batch_size))
        drawn.extend(buffer.sample(batch_size) for _ in range(gradient_steps))
        feeder.add(3)
    return drawn, np.random.rand()


MODES = {"training-thread": dict(worker=False), "worker": dict(worker=True)}


@pytest.mark.parametrize(
    "kind, mode",
    [(kind, mode) for kind in BUFFERS for mode in ("training-thread", "worker")]
    + [(kind, "staged") for kind in BUFFERS if kind.startswith("frames")],  # staging: FrameStackReplayBuffer's
)
def test_batches_are_those_of_a_serial_sampler_drawing_at_the_same_points(monkeypatch, kind, mode):
    np.random.seed(3)
    serial, serial_next = serial_batches(*make_buffer(kind))
    made = fake_staging(monkeypatch) if mode == "staged" else []
    prefetcher = ReplayPrefetcher(**MODES.get(mode, dict(worker=True)))
    np.random.seed(3)
    batches, next_draw = run_calls(prefetcher, *make_buffer(kind))
    assert len(batches) == sum(CALLS) == len(serial) - 1
    for batch, reference in zip(batches, serial):  # held until the end: no batch aliases a reused buffer
        assert_same_samples(batch, reference)
    assert_same_samples(prefetcher.prepared.batch, serial[-1])  # drawn during the last update, for the next call
    assert next_draw == serial_next  # the same draws from np.random, no more
    if made:
        (staging,) = made  # one staging, reused across calls
        assert [event.records for event in staging.events] == [7, 6]  # one copy out per batch, alternating sets


@pytest.mark.parametrize("worker", [False, True])
def test_the_next_batch_is_drawn_before_the_update_ends_and_before_the_next_round(monkeypatch, worker):
    """DrQ-v2's ratio, one update per call: the draw of update k + 1 starts before update k ends (with the
    worker: while it runs) and before the transitions of the round after it are added."""
    buffer, feeder = make_buffer("frames-drqv2")
    log, drawing = [], threading.Condition()
    original_sample = buffer.sample

    def sample(batch_size, env=None):
        with drawing:
            log.append("draw start")
            drawing.notify_all()
        batch = original_sample(batch_size, env)
        with drawing:
            log.append("draw end")
        return batch

    monkeypatch.setattr(buffer, "sample", sample)
    original_add = feeder.add

    def add(steps):
        log.append("round")
        return original_add(steps)

    monkeypatch.setattr(feeder, "add", add)
    overlapped = []

    def update(batch):
        with drawing:
            k = log.count("update start")
            log.append("update start")
            if worker:  # update k waits for the draw of batch k + 1 to start: it cannot end first
                overlapped.append(drawing.wait_for(lambda: log.count("draw start") >= k + 2, timeout=10))
            log.append("update end")

    calls = (1, 1, 1, 1)
    run_calls(ReplayPrefetcher(worker=worker), buffer, feeder, calls, update=update)
    assert not worker or overlapped == [True] * 4
    starts = [i for i, event in enumerate(log) if event == "draw start"]
    ends = [i for i, event in enumerate(log) if event == "draw end"]
    updates = [i for i, event in enumerate(log) if event == "update start"]
    update_ends = [i for i, event in enumerate(log) if event == "update end"]
    rounds = [i for i, event in enumerate(log) if event == "round"]
    assert len(starts) == len(ends) == 5 and len(updates) == len(rounds) == 4
    for k in range(4):
        assert ends[k] < updates[k]  # batch k is ready before its update
        assert starts[k + 1] < update_ends[k]  # batch k + 1 is drawn before update k ends
        assert ends[k + 1] < rounds[k]  # ... and before the transitions collected after update k exist
        if not worker:
            assert ends[k + 1] < updates[k]  # the CPU's reordering: drawn just before update k


def test_disabled_prefetcher_calls_sample_when_each_update_is_due(monkeypatch):
    buffer = filled_buffer()
    calls = []
    monkeypatch.setattr(buffer, "sample", lambda batch_size, env=None: calls.append(batch_size) or batch_size)
    prefetcher = ReplayPrefetcher(enabled=False)
    with prefetcher.batches(buffer, 3, 7) as batches:
        assert list(batches) == [7, 7, 7]
    assert calls == [7, 7, 7] and prefetcher.prepared is None


def test_default_worker_on_cuda_only_and_staging_on_cuda():
    assert not ReplayPrefetcher().uses_worker(th.device("cpu"))  # the CPU: on the training thread
    assert ReplayPrefetcher().uses_worker(th.device("cuda"))
    assert ReplayPrefetcher(worker=True).uses_worker(th.device("cpu"))
    assert not ReplayPrefetcher(worker=False).uses_worker(th.device("cuda"))
    # CUDA: pinned host buffers and CUDA events (nothing is allocated or recorded until the first batch).
    staging = staging_for(th.device("cuda"))
    assert staging is not None and staging.pin_memory and staging.event_factory is th.cuda.Event
    assert staging_for(th.device("cpu")) is None and staging_for(th.device("meta")) is None


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
    prefetcher = ReplayPrefetcher(worker=True)
    for gradient_steps in (3, 1, 2):
        with prefetcher.batches(buffer, gradient_steps, 8) as batches:
            for _ in batches:
                time.sleep(0.01)  # the update: the worker gathers the next batch meanwhile
    assert [slot for slot, _ in writes] == [0, 1, 0, 1, 0, 1, 0]
    # The first batch is gathered on the training thread, every next one in the worker (also across calls).
    threads = [name.startswith(WORKER_NAME) for _, name in writes]
    assert threads == [False, True, True, True, True, True, True]
    (staging,) = made
    assert [event.records for event in staging.events] == [4, 3]
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
    prefetcher = ReplayPrefetcher(worker=True)
    with pytest.raises(ValueError, match="gather failed at batch 3"):
        with prefetcher.batches(buffer, 4, 8) as batches:
            got.extend(batches)
    assert len(got) == 2 and calls[2].startswith(WORKER_NAME) and prefetcher.prepared is None


def test_an_interrupted_call_waits_for_the_worker(monkeypatch):
    buffer = filled_buffer()
    original, finished = buffer._get_samples, []

    def slow(batch_inds, env=None, env_indices=None):
        time.sleep(0.2)
        finished.append(True)
        return original(batch_inds, env=env, env_indices=env_indices)

    monkeypatch.setattr(buffer, "_get_samples", slow)
    prefetcher = ReplayPrefetcher(worker=True)
    with pytest.raises(RuntimeError, match="update failed"):
        with prefetcher.batches(buffer, 3, 8) as batches:
            for _ in batches:
                raise RuntimeError("update failed")  # the worker is gathering batch 2
    assert len(finished) == 2  # batch 2's gather had finished when the block ended: no reader left on the buffer
    assert prefetcher.prepared is None  # not kept for the next call


def test_a_batch_drawn_for_another_buffer_or_batch_size_is_not_used():
    buffer, other = filled_buffer(), filled_buffer()
    prefetcher = ReplayPrefetcher()
    np.random.seed(0)
    with prefetcher.batches(buffer, 1, 8) as batches:
        list(batches)
    state = np.random.get_state()
    expected = other.sample(8)  # the next call draws afresh: the prepared batch was buffer's
    np.random.set_state(state)
    with prefetcher.batches(other, 1, 8) as batches:
        assert_same_samples(next(iter(batches)), expected)
    for batch_size in (4, 8):
        with prefetcher.batches(other, 1, batch_size) as batches:
            assert next(iter(batches)).actions.shape == (batch_size, 2)
    with prefetcher.batches(other, 1, 8) as batches:
        list(batches)
    other.reset()  # emptied: the batch drawn ahead from its old transitions is not used
    Feeder(other).add(10)
    state = np.random.get_state()
    expected = other.sample(8)
    np.random.set_state(state)
    with prefetcher.batches(other, 1, 8) as batches:
        assert_same_samples(next(iter(batches)), expected)
    prefetcher.discard()
    assert prefetcher.prepared is None


@pytest.mark.parametrize("kind", ["frames-drqv2", "dict-n-step"])
def test_a_pickled_batch_drawn_ahead_is_drawn_again_from_the_restored_buffer(kind):
    buffer, feeder = make_buffer(kind)
    prefetcher = ReplayPrefetcher()
    np.random.seed(1)
    with prefetcher.batches(buffer, 2, 8) as batches:
        list(batches)
    saved, state = pickle.dumps((prefetcher, feeder)), np.random.get_state()  # a checkpoint (feeder: its buffer)
    # The run goes on: a round, then a call whose first batch was drawn before that round.
    feeder.add(3)
    with prefetcher.batches(buffer, 2, 8) as batches:
        expected = list(batches)
    expected_next = np.random.rand()

    resumed, feeder = pickle.loads(saved)  # the resumed run: the checkpoint's prefetcher, buffer and generator
    assert resumed.prepared.batch is None  # the draw was saved, not the batch
    np.random.set_state(state)
    assert resumed.restore(feeder.buffer)
    assert prefetch._same_generator_state(np.random.get_state(), state)  # left where the checkpoint had it
    feeder.add(3)
    with resumed.batches(feeder.buffer, 2, 8) as batches:
        got = list(batches)
    for batch, reference in zip(got, expected, strict=True):
        assert_same_samples(batch, reference)
    assert np.random.rand() == expected_next

    # A buffer that is not the one of the draw (a transition more): the draw is dropped, the generator untouched.
    resumed, feeder = pickle.loads(saved)
    feeder.add(1)
    np.random.set_state(state)
    assert not resumed.restore(feeder.buffer) and resumed.prepared is None
    assert prefetch._same_generator_state(np.random.get_state(), state)


def _worker_threads(prefetcher):
    threads = list(prefetcher._executor._threads)
    assert len(threads) == 1 and threads[0].name.startswith(WORKER_NAME) and threads[0].is_alive()
    return threads[0]


def test_worker_ends_with_the_prefetcher_and_it_pickles():
    buffer = filled_buffer()
    prefetcher = ReplayPrefetcher(worker=False)
    with prefetcher.batches(buffer, 2, 8) as batches:
        list(batches)
    assert prefetcher._executor is None  # on the training thread: no thread at all
    prefetcher.worker = True
    with prefetcher.batches(buffer, 1, 8) as batches:  # one update: the next call's batch drawn in the worker
        list(batches)
    worker = _worker_threads(prefetcher)
    copy = pickle.loads(pickle.dumps(prefetcher))
    assert copy.enabled is True and copy.worker is True and copy._executor is None and copy._staging is None
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


def _model(sampling="sb3", gradient_steps=1):
    th.manual_seed(0)
    return DrQv2(
        "CnnPolicy",
        FrameStackEnv(),
        buffer_size=200,
        learning_starts=24,
        batch_size=8,
        gradient_steps=gradient_steps,
        seed=0,
        policy_kwargs=dict(hidden_dim=16, feature_dim=8),
        replay_buffer_kwargs=dict(sampling=sampling),
    )


def test_drqv2_draws_the_next_rounds_batch_during_this_rounds_update():
    """One update per round (train_freq=2): update k + 1's batch is drawn at update k, before the next round."""
    model = _model("sb3")
    buffer, drawn, used = model.replay_buffer, [], []
    original_indices, original_update = buffer.sample_indices, model._update

    def sample_indices(batch_size):
        drawn.append(buffer.transitions_added)
        return original_indices(batch_size)

    def update(data, discounts, std):
        used.append(buffer.transitions_added)
        return original_update(data, discounts, std)

    buffer.sample_indices, model._update = sample_indices, update
    model.learn(36)
    assert used == [26, 28, 30, 32, 34, 36]  # one update every other transition, after the warm-up of 24
    assert drawn == [26, *used]  # update k + 1's batch drawn at update k; the last one kept for the next call
    assert model.replay_prefetcher.prepared is not None
    model.reset_from_scratch()  # the emptied buffer's batch is not used after the warm-up
    assert model.replay_prefetcher.prepared is None


@pytest.mark.parametrize("sampling, staged", [("sb3", False), ("drqv2", True)])
def test_drqv2_training_is_the_same_in_the_worker_and_on_the_training_thread(monkeypatch, tmp_path, sampling, staged):
    reference = _model(sampling, gradient_steps=3)
    reference.replay_prefetcher.worker = False
    reference.learn(36)
    made = fake_staging(monkeypatch) if staged else []
    model = _model(sampling, gradient_steps=3)
    model.replay_prefetcher.worker = True
    model.learn(36)
    assert model._n_updates == reference._n_updates == 18  # 6 rounds of 3 updates
    assert model.replay_prefetcher._executor is not None  # the worker gathered
    assert not staged or sum(event.records for event in made[0].events) == 19  # 18 batches and the next one
    for name, value in reference.policy.state_dict().items():
        assert th.equal(model.policy.state_dict()[name], value), name
    model.save(tmp_path / "model.zip")  # with the prefetcher's settings and its draw ahead
    loaded = DrQv2.load(tmp_path / "model.zip", env=FrameStackEnv())
    assert loaded.replay_prefetcher.worker is True and loaded.replay_prefetcher.prepared.batch is None


def test_drqv2_loaded_with_its_replay_buffer_uses_the_batch_drawn_ahead(tmp_path):
    model = _model("drqv2")
    model.learn(30)
    model.save(tmp_path / "model.zip")
    model.save_replay_buffer(tmp_path / "replay.pkl")
    state = np.random.get_state()
    first = []
    model._update = lambda data, discounts, std: first.append(data)
    model.learn(2, reset_num_timesteps=False)

    loaded = DrQv2.load(tmp_path / "model.zip", env=FrameStackEnv())
    loaded.load_replay_buffer(tmp_path / "replay.pkl")
    np.random.set_state(state)
    again = []
    loaded._update = lambda data, discounts, std: again.append(data)
    loaded.learn(2, reset_num_timesteps=False)  # the environment restarts its episode: the batch was drawn before
    assert len(first) == len(again) == 1
    assert_same_samples(again[0], first[0])


def _busy():
    """Queue long kernels on the current stream (20 matmuls of 4096 x 4096, tens of ms on any GPU)."""
    x = th.randn(4096, 4096, device="cuda")
    for _ in range(20):
        x = th.tanh(x @ x)


@pytest.mark.cuda
@pytest.mark.skipif(not th.cuda.is_available(), reason="needs a CUDA GPU (benchmarks/gpu.sh runs these)")
@pytest.mark.parametrize("kind", ["frames-drqv2", "sb3"])
def test_cuda_batches_survive_long_kernels_before_their_copy_and_their_use(kind):
    """
    The double buffer under stress: before each batch is read, long kernels are queued on the side stream (the next
    batch's copy waits behind them while the worker gathers the one after) and on the update's stream (the batch is
    read after them: its memory must not be given to a later batch meanwhile). Every batch read equals the one a
    serial sampler draws on the CPU; the staging buffers are pinned.
    """
    np.random.seed(5)
    expected, _ = serial_batches(*make_buffer(kind), batch_size=64)
    buffer, feeder = make_buffer(kind)
    buffer.device = th.device("cuda")
    prefetcher = ReplayPrefetcher()  # default on CUDA: the worker, a side stream, pinned buffers
    assert prefetcher.uses_worker(buffer.device)
    read = []

    def update(batch):
        with th.cuda.stream(prefetcher._stream):
            _busy()
        _busy()
        read.append([tensor.clone() for tensor in prefetch._tensors(batch)])  # on the update's stream

    np.random.seed(5)
    run_calls(prefetcher, buffer, feeder, batch_size=64, update=update)
    th.cuda.synchronize()
    assert len(read) == sum(CALLS)
    for tensors, reference in zip(read, expected):
        cpu = list(prefetch._tensors(reference))
        assert len(tensors) == len(cpu)
        for x, y in zip(tensors, cpu):
            assert x.device.type == "cuda" and x.dtype == y.dtype and th.equal(x.cpu(), y)
    if kind.startswith("frames"):
        staging = prefetcher._staging
        assert staging is not None and all(s.frames.is_pinned() for s in staging.slots)
        assert all(flat.is_pinned() for s in staging.slots for flat in s.flats.values())
        assert read[0][0].dtype == th.uint8  # uint8 over the bus


@pytest.mark.cuda
@pytest.mark.skipif(not th.cuda.is_available(), reason="needs a CUDA GPU (benchmarks/gpu.sh runs these)")
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
    model.learn(36)
    assert model._n_updates == 18 and model.replay_prefetcher._staging is not None
    assert model.replay_prefetcher._executor is not None and model.replay_prefetcher.prepared is not None
