"""Parallel environments with DrQ-v2's update ratio, environment steps overlapped with updates, timings."""

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

from sb3_collapse import DrQv2
from sb3_collapse.run.timing import LearnTimer, TimedVecEnv
from tests.random_env import RandomObservationEnv


def state_space():
    return gym.spaces.Box(-np.inf, np.inf, (5,), np.float32)


def pixel_space():  # one per env: a space shared by several envs would share its random generator
    return gym.spaces.Box(0, 255, (9, 32, 32), np.uint8)


def state_envs(n_envs, vec_env_cls=DummyVecEnv, episode_length=50):
    return vec_env_cls(
        [lambda: RandomObservationEnv(state_space(), episode_length=episode_length) for _ in range(n_envs)]
    )


class RoundLog(BaseCallback):
    """Transitions and updates at the start of every rollout (after the previous round's updates), and per step."""

    def __init__(self, reset_at=None):
        super().__init__()
        self.rounds, self.steps, self.reset_at = [], [], reset_at

    def _on_rollout_start(self):
        self.rounds.append((self.model.num_timesteps, self.model._n_updates))

    def _on_step(self):
        self.steps.append((self.model.num_timesteps, self.model._n_updates))
        if self.reset_at is not None and self.model.num_timesteps >= self.reset_at and self.model.reset_step == 0:
            self.model.reset_from_scratch()
        return True


@pytest.mark.parametrize("n_envs", [1, 2, 3])
def test_one_update_per_train_freq_transitions_whatever_n_envs(n_envs):
    """
    After T transitions (summed over the envs) a model has made T // 2 - learning_starts // 2 updates, at every
    round, whatever the number of envs; the buffer holds T transitions and each env.step adds n_envs.
    """
    model = DrQv2("MlpPolicy", state_envs(n_envs), buffer_size=500, learning_starts=20, batch_size=8, seed=0,
                  policy_kwargs=dict(hidden_dim=32))
    log, timer = RoundLog(), LearnTimer()
    model.learn(60, callback=[log, timer])
    assert model.num_timesteps == 60
    assert model.replay_buffer.size() * n_envs == 60
    assert model._n_updates == 60 // 2 - 20 // 2 == 20
    # Between two env.step calls: every update due so far was made, none in advance (fractions carried exactly).
    for transitions, updates in log.rounds:
        assert updates == max(0, transitions // 2 - 20 // 2), (transitions, updates)
    assert [t for t, _ in log.steps] == list(range(n_envs, 61, n_envs))
    # Per env.step, n_envs / 2 updates on average: 3 envs alternate 1 and 2.
    per_step = np.diff([u for t, u in log.rounds if t >= 20 + n_envs])
    if n_envs == 3:
        assert set(per_step) == {1, 2}
    assert timer.timings.learning.updates == 20
    assert timer.timings.warmup.transitions + timer.timings.learning.transitions == 60


@pytest.mark.parametrize("n_envs", [1, 2, 3])
def test_reset_warmup_is_counted_in_transitions(n_envs):
    """After reset_from_scratch at transition R, no update until R + learning_starts, then the same ratio again."""
    model = DrQv2("MlpPolicy", state_envs(n_envs), buffer_size=500, learning_starts=12, batch_size=4, seed=0,
                  policy_kwargs=dict(hidden_dim=32))
    log = RoundLog(reset_at=30)
    model.learn(78, callback=log)
    reset = model.reset_step
    assert 30 <= reset < 30 + n_envs
    before = max(u for t, u in log.steps if t <= reset)
    # The updates due up to the step before the reset's; the one due at the reset's own step is not made (the reset
    # in that step restarted the warm-up).
    assert before == (reset - n_envs) // 2 - 12 // 2
    for transitions, updates in log.rounds:
        if transitions > reset:
            assert updates == before + max(0, transitions // 2 - (reset + 12) // 2), (transitions, updates)
    assert model._n_updates == before + 78 // 2 - (reset + 12) // 2


def test_gradient_steps_and_episodic_train_freq():
    model = DrQv2("MlpPolicy", state_envs(3), buffer_size=500, learning_starts=0, batch_size=4, seed=0,
                  gradient_steps=-1, policy_kwargs=dict(hidden_dim=32))
    model.learn(30)
    assert model._n_updates == 30  # -1: one per transition
    model = DrQv2("MlpPolicy", state_envs(2), train_freq=(4, "transition"), gradient_steps=3, buffer_size=500,
                  learning_starts=8, batch_size=4, seed=0, policy_kwargs=dict(hidden_dim=32))
    model.learn(40)
    assert model._n_updates == 3 * (40 // 4 - 8 // 4)
    episodic = DrQv2("MlpPolicy", state_envs(1, episode_length=10), train_freq=(1, "episode"), buffer_size=500,
                     learning_starts=15, batch_size=4, seed=0, policy_kwargs=dict(hidden_dim=32))
    episodic.learn(40)
    assert episodic._n_updates == 3  # after episodes ending at 20, 30 and 40
    with pytest.raises(ValueError, match=r"counts episodes, which needs one environment.*has 2"):
        DrQv2("MlpPolicy", state_envs(2), train_freq=(1, "episode"), buffer_size=500, seed=0).learn(10)


class LaggedSequential(DrQv2):
    """
    The oracle of the overlapped loop, written on SB3's sequential loop (env.step, then the updates): the actions of
    the step after each round of updates (if there is one) are chosen just before the round, with the weights before
    it.
    """

    _lagged = None

    def train(self, gradient_steps, batch_size=256):
        if self.num_timesteps < self._total_timesteps:
            self._lagged = super()._sample_action(self.learning_starts, None, self.env.num_envs)
        super().train(gradient_steps, batch_size)

    def _sample_action(self, learning_starts, action_noise=None, n_envs=1):
        if self._lagged is not None:
            lagged, self._lagged = self._lagged, None
            return lagged
        return super()._sample_action(learning_starts, action_noise, n_envs)


def _pixel_model(cls, vec_env_cls, n_envs, **kwargs):
    env = vec_env_cls([lambda: RandomObservationEnv(pixel_space(), episode_length=30) for _ in range(n_envs)])
    return cls("CnnPolicy", env, buffer_size=300, learning_starts=16, batch_size=8, seed=0,
               policy_kwargs=dict(hidden_dim=32), **kwargs)


def _run(model, steps=60):
    model.learn(steps)
    model.env.close()
    buffer = model.replay_buffer
    stored = {name: getattr(buffer, name)[: buffer.pos].copy()
              for name in ("observations", "next_observations", "actions", "rewards", "dones")}
    stored["counts"] = np.array([model.num_timesteps, model._n_updates])
    return stored, {name: p.detach().clone() for name, p in model.policy.named_parameters()}


def test_overlapped_env_steps_are_the_sequential_loop_with_a_one_round_policy_lag():
    """
    Two envs in subprocesses stepping during the updates store exactly the transitions, make exactly the updates (and
    as many)
    and end with exactly the weights of the sequential loop in which the actions of the step after each round of
    updates are chosen before that round (DrQ-v2's reference order: act, update, step). Without that lag, the
    sequential loop's first differing action is the first one after the first update.
    """
    overlapped = _pixel_model(DrQv2, SubprocVecEnv, 2, step_envs_during_updates=True)
    stored, weights = _run(overlapped)
    oracle_stored, oracle_weights = _run(_pixel_model(LaggedSequential, DummyVecEnv, 2))
    sequential_stored, _ = _run(_pixel_model(DrQv2, DummyVecEnv, 2))

    assert overlapped.num_timesteps == 60 and overlapped._n_updates == 60 // 2 - 16 // 2
    for name, values in oracle_stored.items():
        np.testing.assert_array_equal(stored[name], values, err_msg=name)
    for name, value in oracle_weights.items():
        assert th.equal(weights[name], value), name

    # The lag: identical up to the first round of updates (at transition 18, after the 9th env.step), then the
    # sequential loop acts with the updated weights, the overlapped one with those of before.
    first_update_step = 18 // 2
    actions, sequential_actions = stored["actions"], sequential_stored["actions"]
    np.testing.assert_array_equal(actions[:first_update_step], sequential_actions[:first_update_step])
    assert not np.array_equal(actions[first_update_step], sequential_actions[first_update_step])


def test_overlap_without_subprocesses_and_interrupted_update():
    """A DummyVecEnv steps after the updates (same result); an exception in an update completes the step in flight."""
    model = _pixel_model(DrQv2, DummyVecEnv, 1, step_envs_during_updates=True)
    original_train = model.train
    calls = {"n": 0}

    def failing_train(gradient_steps, batch_size=256):
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt
        original_train(gradient_steps, batch_size)

    model.train = failing_train
    with pytest.raises(KeyboardInterrupt):
        model.learn(60)
    # The step sent before the failed round was completed and stored: the model's last observation is the env's.
    assert model._pending_step is None
    assert model.num_timesteps == 16 + 3 * 2 + 1 and model.replay_buffer.pos == model.num_timesteps
    np.testing.assert_array_equal(model.replay_buffer.next_observations[model.replay_buffer.pos - 1], model._last_obs)
    model.train = original_train
    model.learn(20, reset_num_timesteps=False)
    assert model.num_timesteps >= 43


def test_timings_split_warmup_and_learning():
    env = TimedVecEnv(DummyVecEnv([lambda: RandomObservationEnv(pixel_space(), episode_length=30) for _ in range(2)]))
    model = DrQv2("CnnPolicy", env, buffer_size=300, learning_starts=16, batch_size=8, seed=0,
                  policy_kwargs=dict(hidden_dim=32))
    timer = LearnTimer(env)
    model.learn(40, callback=timer)
    timings = timer.timings
    assert timings.warmup.transitions == 16 and timings.warmup.updates == 0 and timings.warmup.update_s == 0
    assert timings.learning.transitions == 24 and timings.learning.updates == 40 // 2 - 16 // 2
    for phase in (timings.warmup, timings.learning):
        assert phase.total_s > 0 and 0 < phase.env_s < phase.total_s and phase.overhead_s >= 0
    assert 0 < timings.first_round_s <= timings.learning.update_s and timings.first_round_updates == 1
    later_mean = (timings.learning.update_s - timings.first_round_s) / 11  # the first round counted as a later one
    expected = timings.learning.total_s - timings.first_round_s + later_mean
    assert timings.steady_learning_s() == pytest.approx(expected)
    as_dict = timings.as_dict()
    assert as_dict["learning"]["updates"] == 12 and as_dict["learning"]["overhead_s"] == timings.learning.overhead_s


def test_compile_update_is_checked_and_not_saved(tmp_path):
    with pytest.raises(ValueError, match=r"compile_update must be True, False or a torch.compile mode"):
        DrQv2("MlpPolicy", state_envs(1), compile_update="fast", buffer_size=100)
    model = DrQv2("MlpPolicy", state_envs(1), compile_update="default", step_envs_during_updates=True, buffer_size=100)
    model.save(tmp_path / "model.zip")
    loaded = DrQv2.load(tmp_path / "model.zip")
    assert loaded.compile_update == "default" and loaded.step_envs_during_updates is True
    assert loaded._compiled_losses is None and loaded._pending_step is None


def test_soft_update_equals_sb3_polyak_update():
    from stable_baselines3.common.utils import polyak_update

    from sb3_collapse.drqv2.policies import soft_update

    th.manual_seed(0)
    source = [th.randn(50, 300), th.randn(7), th.randn(3, 3, 4)]
    ours = [th.randn_like(p) for p in source]
    theirs = [p.clone() for p in ours]
    soft_update(source, ours, 0.01)
    polyak_update(source, theirs, 0.01)
    assert all(th.equal(a, b) for a, b in zip(ours, theirs))
    assert not th.equal(ours[0], source[0])
