import warnings

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3.common.buffers import NStepReplayBuffer, ReplayBuffer

from sb3_collapse.drqv2 import DrQv2, FrameStackReplayBuffer
from sb3_collapse.drqv2.replay_buffer import frame_stack_storage_bytes
from tests.random_env import RandomObservationEnv

FRAME = (3, 6, 6)
ACTIONS = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)


def stacked_space(frame_stack, frame=FRAME):
    return gym.spaces.Box(0, 255, (frame[0] * frame_stack, *frame[1:]), np.uint8)


def random_episodes(rng, n_envs, frame_stack, steps, padding="copies", p_terminate=0.06, p_truncate=0.08):
    """
    ``add`` arguments of ``steps`` agent steps of ``n_envs`` envs that stack random frames, oldest first, as
    SB3's off-policy algorithms pass them (next_obs of an episode's last step is its terminal observation).
    A reset observation is ``frame_stack`` copies of a frame (``"copies"``, make_dmc_env) or zeros and a frame
    (``"zeros"``, VecFrameStack). Episodes end by termination or time limit, at random.
    """
    channels = FRAME[0]

    def reset_obs():
        frame = rng.integers(0, 256, FRAME, dtype=np.uint8)
        if padding == "copies":
            return np.concatenate([frame] * frame_stack)
        return np.concatenate([np.zeros((channels * (frame_stack - 1), *FRAME[1:]), np.uint8), frame])

    obs = np.stack([reset_obs() for _ in range(n_envs)])
    for _ in range(steps):
        new_frames = rng.integers(0, 256, (n_envs, *FRAME), dtype=np.uint8)
        next_obs = np.concatenate([obs[:, channels:], new_frames], axis=1)
        terminated = rng.random(n_envs) < p_terminate
        truncated = rng.random(n_envs) < p_truncate
        dones = terminated | truncated
        infos = [{"TimeLimit.truncated": bool(tr and not te)} for te, tr in zip(terminated, truncated)]
        action = rng.uniform(-1, 1, (n_envs, 2)).astype(np.float32)
        yield obs, next_obs, action, rng.normal(size=n_envs), dones, infos
        obs = next_obs.copy()
        for i in np.flatnonzero(dones):
            obs[i] = reset_obs()


def make_pair(buffer_size, n_envs, frame_stack, n_steps=3, handle_timeout_termination=True, **kwargs):
    """A FrameStackReplayBuffer (``kwargs``: its own) and an NStepReplayBuffer with the same settings."""
    space = stacked_space(frame_stack)
    common = dict(n_envs=n_envs, n_steps=n_steps, gamma=0.9, handle_timeout_termination=handle_timeout_termination)
    ours = FrameStackReplayBuffer(buffer_size, space, ACTIONS, "cpu", frame_stack=frame_stack, **common, **kwargs)
    theirs = NStepReplayBuffer(buffer_size, space, ACTIONS, "cpu", **common)
    return ours, theirs


def assert_same_samples(a, b):
    for name in a._fields:
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and x.device == y.device and x.shape == y.shape, name
        assert th.equal(x, y), name


def compare_all_indices(ours, theirs, seed):
    """Same indices, same env draws (same seed): identical tensors, for every position of every env."""
    inds = np.tile(np.arange(ours.size()), 4 * ours.n_envs)
    np.random.seed(seed)
    expected = theirs._get_samples(inds)
    np.random.seed(seed)
    assert_same_samples(ours._get_samples(inds), expected)


@pytest.mark.parametrize(
    "n_envs, frame_stack, n_steps, padding, timeouts",
    [
        (1, 3, 3, "copies", True),
        (3, 3, 3, "zeros", True),
        (2, 3, 1, "copies", True),
        (2, 1, 3, "copies", True),
        (2, 4, 5, "zeros", True),
        (2, 3, 3, "copies", False),
    ],
)
def test_samples_equal_nstep_replay_buffer(n_envs, frame_stack, n_steps, padding, timeouts):
    rng = np.random.default_rng(n_envs * 100 + n_steps)
    capacity = 40
    # Episodes of ~7 steps: a frame ring sized for episodes of >= 2 steps keeps every transition sampleable.
    ours, theirs = make_pair(capacity * n_envs, n_envs, frame_stack, n_steps, timeouts, min_episode_length=2)
    for step, args in enumerate(random_episodes(rng, n_envs, frame_stack, 130, padding)):
        ours.add(*args)
        theirs.add(*args)
        if step in (0, 17, capacity - 1, capacity + 5, 129):  # not full, full, wrapped (several times)
            assert ours.pos == theirs.pos and ours.full == theirs.full
            assert ours.is_sampleable(
                np.arange(ours.size()).repeat(n_envs), np.tile(np.arange(n_envs), ours.size())
            ).all()
            compare_all_indices(ours, theirs, seed=step)
    assert ours.dones.any() and ours.timeouts.any() == timeouts  # terminations and time limits both exercised
    # sample() draws (pos, env) with the same np.random calls as SB3.
    np.random.seed(1)
    expected = theirs.sample(64)
    np.random.seed(1)
    assert_same_samples(ours.sample(64), expected)


def test_each_frame_stored_once():
    rng = np.random.default_rng(0)
    ours, _ = make_pair(1000, 2, 3, min_episode_length=2)
    episode_starts = np.ones(2, dtype=int)
    for obs, next_obs, *_, dones, infos in random_episodes(rng, 2, 3, 200):
        ours.add(obs, next_obs, _[0], _[1], dones, infos)
        episode_starts += dones
    episode_starts -= ours.dones[199].astype(int)  # the reset after the last step was not added
    # One frame per agent step, plus frame_stack frames for the first observation of each episode.
    np.testing.assert_array_equal(ours.frame_heads, 200 + 3 * episode_starts)


def test_short_episodes_never_sample_overwritten_frames():
    """Episodes much shorter than min_episode_length: the oldest transitions lose their frames first."""
    rng = np.random.default_rng(5)
    ours, theirs = make_pair(60, 2, 3, min_episode_length=250)
    for args in random_episodes(rng, 2, 3, 100, p_terminate=0.2, p_truncate=0.2):
        ours.add(*args)
        theirs.add(*args)
    pos, envs = np.arange(30).repeat(2), np.tile(np.arange(2), 30)
    sampleable = ours.is_sampleable(pos, envs)
    assert 0 < sampleable.sum() < len(pos)
    # The sampleable ones are the newest of each env, and they still equal SB3's.
    for env_index in range(2):
        in_age_order = np.roll(sampleable[envs == env_index], -ours.pos)
        assert np.all(np.diff(in_age_order.astype(int)) >= 0)
    for p, e in zip(pos[sampleable], envs[sampleable]):
        assert_same_samples(ours._get_samples(np.array([p]), env_indices=np.array([e])), sb3_sample_at(theirs, p, e))
    with pytest.raises(ValueError, match="overwritten"):
        ours._get_samples(pos[~sampleable][:1], env_indices=envs[~sampleable][:1])
    drawn = []
    original = ours._get_samples
    ours._get_samples = lambda inds, env=None, env_indices=None: (
        drawn.append((inds, env_indices)) or original(inds, env, env_indices)
    )
    ours.sample(256)
    inds, env_indices = drawn[0]
    assert ours.is_sampleable(inds, env_indices).all()


def sb3_sample_at(buffer, position, env_index):
    """SB3's sample of (position, env_index): its _get_samples draws the env, so seed until it draws env_index."""
    for seed in range(1000):
        np.random.seed(seed)
        if np.random.randint(0, buffer.n_envs, size=(1,))[0] == env_index:
            np.random.seed(seed)
            return buffer._get_samples(np.array([position]))
    raise AssertionError("no seed draws the env")


def test_reset_empties_the_buffer():
    rng = np.random.default_rng(2)
    ours, _ = make_pair(50, 2, 3, min_episode_length=2)
    for args in random_episodes(rng, 2, 3, 70):
        ours.add(*args)
    ours.reset()
    assert ours.size() == 0 and ours.pos == 0 and not ours.full
    np.testing.assert_array_equal(ours.frame_heads, 0)
    with pytest.raises(ValueError):
        ours.sample(4)
    # Refilled after the reset, it is a fresh buffer: nothing of the earlier episodes is continued or sampled.
    fresh, theirs = make_pair(50, 2, 3, min_episode_length=2)
    for args in random_episodes(np.random.default_rng(3), 2, 3, 30):
        for buffer in (ours, fresh, theirs):
            buffer.add(*args)
    np.testing.assert_array_equal(ours.frame_heads, fresh.frame_heads)
    compare_all_indices(ours, theirs, seed=0)


def test_refuses_what_it_cannot_deduplicate():
    space = stacked_space(3)
    with pytest.raises(ValueError, match="needs frame_stack"):
        FrameStackReplayBuffer(10, space, ACTIONS)
    with pytest.raises(
        ValueError, match=r"shape \(channels \* 4, height, width\).*replay_buffer_class=NStepReplayBuffer"
    ):
        FrameStackReplayBuffer(10, space, ACTIONS, frame_stack=4)
    with pytest.raises(ValueError, match="shape"):
        FrameStackReplayBuffer(10, gym.spaces.Box(-1, 1, (9,)), ACTIONS, frame_stack=3)
    with pytest.raises(ValueError, match="optimize_memory_usage=False"):
        FrameStackReplayBuffer(10, space, ACTIONS, frame_stack=3, optimize_memory_usage=True)

    buffer = FrameStackReplayBuffer(10, space, ACTIONS, frame_stack=3, n_envs=2)
    obs, next_obs, action, reward, dones, infos = next(random_episodes(np.random.default_rng(0), 2, 3, 1))
    not_shifted = next_obs.copy()
    not_shifted[1, :3] = 255 - not_shifted[1, :3]
    with pytest.raises(ValueError, match=r"env 1 .* is not.*replay_buffer_class=NStepReplayBuffer"):
        buffer.add(obs, not_shifted, action, reward, dones, infos)
    assert buffer.pos == 0 and not buffer.frame_heads.any()  # nothing stored, env 0 included
    buffer.add(obs, next_obs, action, reward, dones, infos)
    assert buffer.pos == 1


def test_memory_per_transition_and_lazy_allocation():
    """9x84x84 pixels, 6-d actions (walker): nbytes of a 550,000-transition buffer, never touched."""
    space = gym.spaces.Box(0, 255, (9, 84, 84), np.uint8)
    actions = gym.spaces.Box(-1.0, 1.0, (6,), np.float32)
    rss_before = _resident_bytes()
    buffer = FrameStackReplayBuffer(550_000, space, actions, frame_stack=3)
    assert _resident_bytes() - rss_before < 50e6  # np.zeros reserves, the pages are not filled
    per_transition = buffer.nbytes / 550_000
    assert per_transition <= 22_000
    assert buffer.nbytes <= 12e9
    assert buffer.nbytes == frame_stack_storage_bytes(550_000, space, actions, 3)
    sb3_per_transition = 2 * 9 * 84 * 84 + 6 * 4 + 3 * 4  # obs, next_obs, action, reward, done, timeout
    assert sb3_per_transition / per_transition >= 5.7
    del buffer


def _resident_bytes():
    with open("/proc/self/statm") as statm:
        return int(statm.read().split()[1]) * 4096


class ShiftedStackEnv(gym.Env):
    """
    Random frames stacked as make_dmc_env does (a reset repeats the first frame), with its frame_stack and
    action_repeat attributes; ``shifted=False`` draws every stack afresh (not a frame stack).
    """

    def __init__(self, frame_stack=3, size=32, episode_length=15, shifted=True):
        self.frame_stack, self.episode_length, self.shifted = frame_stack, episode_length, shifted
        self.action_repeat = 2
        self.observation_space = gym.spaces.Box(0, 255, (3 * frame_stack, size, size), np.uint8)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)

    def _frame(self):
        return self.np_random.integers(0, 256, (3, *self.observation_space.shape[1:]), dtype=np.uint8)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self._steps = 0
        self._obs = np.concatenate([self._frame()] * self.frame_stack)
        return self._obs.copy(), {}

    def step(self, action):
        self._steps += 1
        if self.shifted:
            self._obs = np.concatenate([self._obs[3:], self._frame()])
        else:
            self._obs = self.observation_space.sample()
        terminated = bool(self.np_random.random() < 0.05)
        truncated = self._steps >= self.episode_length
        return self._obs.copy(), float(self.np_random.random()), terminated, truncated, {}


SMALL = dict(buffer_size=100, learning_starts=30, batch_size=8, seed=0, policy_kwargs=dict(hidden_dim=32))


def test_drqv2_uses_it_by_default_on_frame_stacks(tmp_path):
    model = DrQv2("CnnPolicy", ShiftedStackEnv(frame_stack=3), **{**SMALL, "buffer_size": 32})
    assert type(model.replay_buffer) is FrameStackReplayBuffer
    buffer = model.replay_buffer
    assert (buffer.frame_stack, buffer.n_steps, buffer.gamma) == (3, model.n_steps, model.gamma)
    model.learn(40)  # wraps around the buffer; 5 updates on its samples
    assert model._n_updates == 5
    assert buffer.full and buffer.pos == 8

    model.save_replay_buffer(tmp_path / "buffer.pkl")
    other = DrQv2("CnnPolicy", ShiftedStackEnv(frame_stack=3), **SMALL)
    other.load_replay_buffer(tmp_path / "buffer.pkl")
    assert type(other.replay_buffer) is FrameStackReplayBuffer
    np.random.seed(4)
    expected = buffer.sample(32)
    np.random.seed(4)
    assert_same_samples(other.replay_buffer.sample(32), expected)

    model.save(tmp_path / "model.zip")
    loaded = DrQv2.load(tmp_path / "model.zip", env=ShiftedStackEnv(frame_stack=3))
    assert type(loaded.replay_buffer) is FrameStackReplayBuffer and loaded.replay_buffer.frame_stack == 3


def test_drqv2_keeps_sb3_buffer_when_it_cannot_or_is_told():
    assert type(DrQv2("CnnPolicy", ShiftedStackEnv(frame_stack=1), **SMALL).replay_buffer) is NStepReplayBuffer
    assert type(DrQv2("CnnPolicy", RandomObservationEnv(stacked_space(3, (3, 32, 32))), **SMALL).replay_buffer) is (
        NStepReplayBuffer
    )
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no "n_steps is ignored" warning: DrQv2 passes its n_steps and gamma
        explicit = DrQv2("CnnPolicy", ShiftedStackEnv(), replay_buffer_class=NStepReplayBuffer, gamma=0.9, **SMALL)
    assert type(explicit.replay_buffer) is NStepReplayBuffer
    assert (explicit.replay_buffer.n_steps, explicit.replay_buffer.gamma) == (3, 0.9)
    explicit = DrQv2("CnnPolicy", ShiftedStackEnv(), replay_buffer_class=ReplayBuffer, n_steps=1, **SMALL)
    assert type(explicit.replay_buffer) is ReplayBuffer
    # An env that reports a frame stack but whose stacks are not shifted frames: a clear error, with the way out.
    model = DrQv2("CnnPolicy", ShiftedStackEnv(shifted=False), **SMALL)
    with pytest.raises(ValueError, match="replay_buffer_class=NStepReplayBuffer"):
        model.learn(5)


def test_drqv2_memory_advice_uses_frame_bytes(monkeypatch):
    monkeypatch.setattr("sb3_collapse.drqv2.replay_memory.physical_memory_bytes", lambda: 10**9)
    env = ShiftedStackEnv(size=84)
    with pytest.warns(UserWarning, match=r"FrameStackReplayBuffer stores each frame once: 21 KB per transition"):
        DrQv2("CnnPolicy", env, **{**SMALL, "buffer_size": 60_000})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        DrQv2("CnnPolicy", env, **{**SMALL, "buffer_size": 40_000})


def test_probe_batches_skip_overwritten_frames():
    """CollapseMetrics' metrics batch sampler draws only sampleable (pos, env) pairs, and leaves np.random alone."""
    from sb3_collapse.monitoring import MetricsBatchSampler

    rng = np.random.default_rng(5)
    ours, _ = make_pair(60, 2, 3, min_episode_length=250)
    for args in random_episodes(rng, 2, 3, 100, p_terminate=0.2, p_truncate=0.2):
        ours.add(*args)
    pos, envs = np.arange(30).repeat(2), np.tile(np.arange(2), 30)
    n_sampleable = int(ours.is_sampleable(pos, envs).sum())
    model = type("Model", (), {"replay_buffer": ours, "get_vec_normalize_env": lambda self: None})()
    state = np.random.get_state()[1].copy()
    observations, _ = MetricsBatchSampler(seed=0).sample(model, n_sampleable)
    assert observations.shape == (n_sampleable, 9, *FRAME[1:])
    assert np.array_equal(np.random.get_state()[1], state)
    assert MetricsBatchSampler(seed=0).sample(model, n_sampleable + 1) is None
