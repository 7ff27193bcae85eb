import copy
import glob
import warnings

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3.common.buffers import NStepReplayBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
from torch._dynamo.eval_frame import _debug_get_cache_entry_list

from sb3_collapse import DrQv2, make_dmc_env
from sb3_collapse.common.layers import LAYER_NAMES
from sb3_collapse.drqv2 import FrameStackReplayBuffer
from sb3_collapse.drqv2.augmentation import draw_shifts
from sb3_collapse.drqv2.policies import exploration_noise
from tests.drqv2_reference import reference_update
from tests.random_env import RandomObservationEnv

SMALL = dict(buffer_size=500, learning_starts=20, batch_size=8, seed=0)
STATE_SPACE = gym.spaces.Box(-np.inf, np.inf, (5,), np.float32)


def pixel_env(size=32, action_repeat=2):
    return RandomObservationEnv(gym.spaces.Box(0, 255, (9, size, size), np.uint8), action_repeat=action_repeat)


def small_pixel_model(**kwargs):
    params = {**SMALL, "policy_kwargs": dict(hidden_dim=32), **kwargs}
    return DrQv2("CnnPolicy", pixel_env(), **params)


def _params(module):
    return [p.detach().clone() for p in module.parameters()]


def _changed(before, module):
    return any(not th.equal(b, p) for b, p in zip(before, module.parameters()))


def _filled(model, steps=40):
    model.learn(steps)
    return model


def test_defaults_are_drqv2s():
    model = DrQv2("CnnPolicy", pixel_env(), buffer_size=100)
    assert model.learning_rate == 1e-4
    assert model.batch_size == 256
    assert model.n_steps == 3
    assert model.gamma == 0.99
    assert model.tau == 0.01
    assert model.learning_starts == 2000
    assert model.train_freq.frequency == 2 and model.gradient_steps == 1
    assert model.stddev_clip == 0.3
    assert model.augmentation_pad == 4
    assert model.stddev_schedule.spec == "linear(1.0,0.1,100000)"
    assert isinstance(model.replay_buffer, NStepReplayBuffer)
    assert model.replay_buffer.n_steps == 3 and model.replay_buffer.gamma == 0.99
    assert model.policy.feature_dim == 50 and model.policy.hidden_dim == 1024


def _noise(model, batch_size, std=0.5):
    return exploration_noise((batch_size, model.action_space.shape[0]), std, model.stddev_clip)


def test_critic_step_changes_encoder_actor_step_does_not():
    model = _filled(small_pixel_model())
    data = model.replay_buffer.sample(8)
    shifts, next_shifts = draw_shifts(8, 4), draw_shifts(8, 4)
    encoder, actor, critic = _params(model.encoder), _params(model.actor), _params(model.critic)
    critic_loss, features, *_ = model._critic_loss(data.observations, data.next_observations, data.actions,
                                                   data.rewards, data.dones, data.discounts, shifts, next_shifts,
                                                   _noise(model, 8))
    model._update_critic(critic_loss)
    assert _changed(encoder, model.encoder) and _changed(critic, model.critic)
    assert not _changed(actor, model.actor)

    encoder, actor, critic = _params(model.encoder), _params(model.actor), _params(model.critic)
    model._update_actor(model._actor_loss(model.encoder(data.observations).detach(), _noise(model, 8)))
    assert _changed(actor, model.actor)
    assert not _changed(encoder, model.encoder)
    assert not _changed(critic, model.critic)


def test_actor_loss_never_reaches_encoder():
    model = _filled(small_pixel_model())
    data = model.replay_buffer.sample(8)
    for p in [*model.encoder.parameters(), *model.critic.parameters()]:
        p.grad = None
    model._update_actor(model._actor_loss(model.encoder(data.observations).detach(), _noise(model, 8)))
    assert all(p.grad is None for p in model.encoder.parameters())
    assert all(p.grad is None for p in model.critic.parameters())


def test_target_critic_soft_update():
    model = small_pixel_model()
    for p, t in zip(model.critic.parameters(), model.critic_target.parameters()):
        assert th.equal(p, t)
    model.learn(40)  # 20 warm-up steps, then 10 updates
    critic, target = _params(model.critic), _params(model.critic_target)
    assert any(not th.equal(c, t) for c, t in zip(critic, target))
    model.train(gradient_steps=1, batch_size=8)
    for old_target, new_critic, new_target in zip(target, model.critic.parameters(), model.critic_target.parameters()):
        assert th.allclose(new_target, 0.99 * old_target + 0.01 * new_critic, atol=1e-6)


def test_learn_logs_grad_norms_and_keeps_last(tmp_path):
    model = small_pixel_model(tensorboard_log=str(tmp_path))
    model.learn(120, log_interval=1)
    norms = model.last_grad_norms
    assert tuple(norms) == LAYER_NAMES[1:]
    assert all(np.isfinite(v) and v > 0 for v in norms.values())
    assert model._n_updates == 50
    events = glob.glob(str(tmp_path / "DrQv2_1" / "events.out.tfevents.*"))
    assert len(events) == 1
    accumulator = EventAccumulator(events[0])
    accumulator.Reload()
    tags = set(accumulator.Tags()["scalars"])
    expected = {"train/critic_loss", "train/actor_loss", "train/q1_mean", "train/target_q_mean", "train/stddev"}
    expected |= {f"train/grad_norm/{layer}" for layer in LAYER_NAMES[1:]}
    assert expected <= tags
    assert "time/frames" in tags
    steps = [event.step for event in accumulator.Scalars("train/critic_loss")]
    assert steps == sorted(steps) and steps[-1] <= 120


def test_frames_use_env_action_repeat():
    model = DrQv2("MlpPolicy", RandomObservationEnv(STATE_SPACE, action_repeat=2), **SMALL)
    assert model.env_config["action_repeat"] == 2 and model.env_config["task_id"] is None
    model.learn(30)
    assert model.num_frames == 60
    # An env that reports no action repeat: one frame per agent step.
    model = DrQv2("MlpPolicy", "Pendulum-v1", **SMALL)
    assert model.env_config is None and model.action_repeat == 1
    model.learn(30)
    assert model.num_frames == 30


def test_exploration_uses_schedule_after_warmup():
    model = DrQv2("MlpPolicy", RandomObservationEnv(STATE_SPACE), stddev_schedule=0.0, **SMALL)
    model.learn(30)
    obs = model._last_obs
    action, buffer_action = model._sample_action(model.learning_starts, n_envs=1)
    deterministic, _ = model.predict(obs, deterministic=True)
    assert np.allclose(action, deterministic, atol=1e-5)
    model.stddev_schedule = type(model.stddev_schedule)(0.5)
    action, _ = model._sample_action(model.learning_starts, n_envs=1)
    assert not np.allclose(action, deterministic, atol=1e-3)
    assert model.policy.exploration_std == 0.5


def test_warmup_actions_are_uniform():
    model = DrQv2("MlpPolicy", RandomObservationEnv(STATE_SPACE), **{**SMALL, "learning_starts": 10_000})
    model._last_obs = np.zeros((1, 5), np.float32)
    actions = np.concatenate([model._sample_action(model.learning_starts)[0] for _ in range(2000)])
    assert actions.min() < -0.95 and actions.max() > 0.95
    assert abs(actions.mean()) < 0.05


def test_constructor_callback_is_combined_with_learn_callback():
    calls = {"ctor": 0, "learn": 0}

    class Count(BaseCallback):
        def __init__(self, key):
            super().__init__()
            self.key = key

        def _on_step(self):
            calls[self.key] += 1
            return True

    model = DrQv2("MlpPolicy", RandomObservationEnv(STATE_SPACE), callback=Count("ctor"), **SMALL)
    model.learn(10, callback=Count("learn"))
    assert calls == {"ctor": 10, "learn": 10}
    model.learn(4)
    assert calls == {"ctor": 14, "learn": 10}


def test_save_load_round_trip(tmp_path):
    model = small_pixel_model(stddev_schedule="linear(1.0,0.1,1000)")
    model.learn(60)
    obs = np.stack([model.observation_space.sample() for _ in range(5)])
    expected, _ = model.predict(obs, deterministic=True)
    model.save(tmp_path / "model.zip")

    loaded = DrQv2.load(tmp_path / "model.zip", env=pixel_env())
    actions, _ = loaded.predict(obs, deterministic=True)
    np.testing.assert_array_equal(actions, expected)
    assert loaded.num_timesteps == 60
    assert loaded.current_stddev == model.current_stddev
    assert loaded._n_updates == model._n_updates
    for name in ("encoder", "actor", "critic"):
        saved = getattr(model, name).optimizer.state_dict()
        restored = getattr(loaded, name).optimizer.state_dict()
        for key, state in saved["state"].items():
            for field, value in state.items():
                assert th.equal(th.as_tensor(value), th.as_tensor(restored["state"][key][field])), (name, field)
    for a, b in zip(model.critic_target.parameters(), loaded.critic_target.parameters()):
        assert th.equal(a, b)
    assert loaded.callback is None

    # learn() continues after load, with the schedule where it stopped.
    loaded.learn(20, reset_num_timesteps=False)
    assert loaded.num_timesteps == 80
    assert loaded._n_updates > model._n_updates

    # A new schedule given to load() as a specification, as to the constructor (rl_zoo3's `-i` does this).
    continued = DrQv2.load(tmp_path / "model.zip", env=pixel_env(), stddev_schedule="linear(0.5,0.1,100)")
    assert continued.current_stddev == pytest.approx(0.5 + (0.1 - 0.5) * 60 / 100)
    with pytest.raises(ValueError, match="linear"):
        DrQv2.load(tmp_path / "model.zip", stddev_schedule="linear(0.5,0.1)")


def test_deterministic_predict_is_tanh_mean():
    model = small_pixel_model()
    obs = model.observation_space.sample()[None]
    action, _ = model.predict(obs, deterministic=True)
    with th.no_grad():
        mean = model.actor(model.encoder(th.as_tensor(obs)))
    np.testing.assert_allclose(action, mean.numpy(), atol=1e-6)


def test_several_envs():
    env = DummyVecEnv([lambda: RandomObservationEnv(STATE_SPACE) for _ in range(2)])
    model = DrQv2("MlpPolicy", env, **SMALL)
    model.learn(60)
    assert model.num_timesteps == 60 and model._n_updates > 0


def test_bad_inputs():
    with pytest.raises(ValueError, match="stddev schedule"):
        DrQv2("MlpPolicy", RandomObservationEnv(STATE_SPACE), stddev_schedule="linear(1,0.1)", **SMALL)
    with pytest.raises(TypeError, match="continuous actions"):
        DrQv2("MlpPolicy", RandomObservationEnv(STATE_SPACE, gym.spaces.Discrete(3)), **SMALL)
    with pytest.raises(ValueError, match="CnnPolicy needs channel-first uint8 image"):
        DrQv2("CnnPolicy", RandomObservationEnv(STATE_SPACE), **SMALL)
    with pytest.raises(ValueError, match="use CnnPolicy"):
        DrQv2("MlpPolicy", pixel_env(), **SMALL)
    with pytest.raises(ValueError, match="augmentation_pad"):
        DrQv2("CnnPolicy", pixel_env(), augmentation_pad=-1, **SMALL)


def test_replay_buffer_too_big_for_ram_warns(monkeypatch):
    monkeypatch.setattr("sb3_collapse.drqv2.replay_memory.physical_memory_bytes", lambda: 10**9)
    with pytest.warns(UserWarning, match=r"will not fit in memory once full.*127 KB per transition.*buffer_size=5_5"):
        DrQv2("CnnPolicy", RandomObservationEnv(), buffer_size=10_000)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        DrQv2("CnnPolicy", RandomObservationEnv(), buffer_size=5_000)


def test_replay_buffer_allocation_failure_says_what_to_do(monkeypatch):
    def fail(self):
        raise MemoryError("Unable to allocate 59.1 GiB")

    monkeypatch.setattr("stable_baselines3.common.off_policy_algorithm.OffPolicyAlgorithm._setup_model", fail)
    with pytest.raises(
        MemoryError, match=r"1,000,000 transitions \(Unable to allocate 59.1 GiB\).*Pass a smaller buffer_size"
    ):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            DrQv2("CnnPolicy", RandomObservationEnv())


def test_learn_on_dm_control_pixels(tmp_path):
    env = make_dmc_env("walker-walk", seed=0)
    model = DrQv2("CnnPolicy", env, buffer_size=200, learning_starts=40, batch_size=8, seed=0,
                  policy_kwargs=dict(hidden_dim=64), tensorboard_log=str(tmp_path))
    model.learn(80)
    assert model.env_config["task_id"] == "walker-walk" and model.action_repeat == 2
    assert model.num_frames == 160
    assert model._n_updates == 20
    # Frame-stacked pixels: each 3x84x84 render is stored once, and sampled stacks are 9x84x84.
    assert isinstance(model.replay_buffer, FrameStackReplayBuffer)
    assert model.replay_buffer.frames.shape[1:] == (1, 3, 84, 84)
    assert model.replay_buffer.sample(4).next_observations.shape == (4, 9, 84, 84)
    model.save(tmp_path / "walker.zip")
    loaded = DrQv2.load(tmp_path / "walker.zip", env=env)
    assert loaded.env_config == model.env_config
    obs, _ = env.reset(seed=1)
    np.testing.assert_array_equal(loaded.predict(obs, deterministic=True)[0], model.predict(obs, deterministic=True)[0])


def test_learn_on_dm_control_states():
    env = make_dmc_env("cartpole-swingup", seed=0, obs_type="state")
    model = DrQv2("MlpPolicy", env, buffer_size=500, learning_starts=50, batch_size=16, seed=0)
    model.learn(150)
    assert model._n_updates == 50
    action, _ = model.predict(env.reset(seed=0)[0], deterministic=True)
    assert env.action_space.contains(action)


def test_learn_with_subprocess_pixel_envs():
    env = make_vec_env("sb3_collapse/walker-walk-v0", n_envs=2, seed=0, vec_env_cls=SubprocVecEnv,
                       env_kwargs=dict(action_repeat=8))
    try:
        model = DrQv2("CnnPolicy", env, buffer_size=200, learning_starts=20, batch_size=8, seed=0,
                      policy_kwargs=dict(hidden_dim=32))
        assert model.action_repeat == 8
        model.learn(60)
        assert model.num_timesteps == 60 and model.num_frames == 480
        assert model._n_updates > 0
    finally:
        env.close()


@pytest.mark.parametrize(("channels_last", "compile_update"), [(False, False), (True, False), (True, True)])
def test_update_equals_reference_update(channels_last, compile_update):
    """
    Same weights, batch and random draws: our update gives the reference implementation's parameters, with
    ``torch.compile`` (``compile_update=True``, ~1 minute of compilation on 2 CPU cores) or without.
    """
    kwargs = dict(buffer_size=200, learning_starts=10, batch_size=16, seed=3, stddev_schedule=0.4)
    oracle = DrQv2("CnnPolicy", pixel_env(), **kwargs, policy_kwargs=dict(
        hidden_dim=32, encoder_kwargs=dict(channels_last=False, fused_relu=False), optimizer_kwargs=dict(fused=False)))
    oracle.learn(40)  # fills the buffer and moves the weights and Adam state away from their initial values
    ours = DrQv2("CnnPolicy", pixel_env(), **kwargs, compile_update=compile_update, policy_kwargs=dict(
        hidden_dim=32, encoder_kwargs=dict(channels_last=channels_last)))
    ours.policy.load_state_dict(oracle.policy.state_dict())
    for name in ("encoder", "actor", "critic"):
        # A deep copy: load_state_dict would otherwise share the Adam state tensors of both models.
        getattr(ours, name).optimizer.load_state_dict(copy.deepcopy(getattr(oracle, name).optimizer.state_dict()))
    if channels_last:
        # The (H, W, C) flatten order of channels_last: permute the trunks' input columns to match.
        c, h, w = 32, 9, 9  # encoder output of 9x32x32 images
        order = th.arange(c * h * w).view(c, h, w).permute(1, 2, 0).flatten()
        with th.no_grad():
            for trunk in (ours.actor.trunk[0], ours.critic.trunk[0], ours.critic_target.trunk[0]):
                trunk.weight.copy_(trunk.weight[:, order])
            for part in (ours.actor, ours.critic):
                adam_state = part.optimizer.state[part.trunk[0].weight]
                for key in ("exp_avg", "exp_avg_sq"):
                    adam_state[key].copy_(adam_state[key][:, order])
    data = oracle.replay_buffer.sample(16)
    ours.num_timesteps = oracle.num_timesteps

    th.manual_seed(0)
    reference_update(oracle, data)
    th.manual_seed(0)
    ours._update(data, data.discounts, ours.current_stddev)

    expected = dict(oracle.policy.named_parameters())
    for name, param in ours.policy.named_parameters():
        reference = expected[name]
        if channels_last and name.endswith("trunk.0.weight"):
            reference = reference[:, order]
        assert th.allclose(param, reference, atol=1e-6, rtol=1e-5), name

    if compile_update:  # resets keep the compiled update: nothing compiled again (whatever other tests compiled)
        losses = (DrQv2._critic_loss, DrQv2._actor_loss)
        compiled = [len(_debug_get_cache_entry_list(loss.__code__)) for loss in losses]
        assert all(count >= 1 for count in compiled)
        for _ in range(2):
            ours.reset_from_scratch()
            ours._update(data, data.discounts, ours.current_stddev)
        assert [len(_debug_get_cache_entry_list(loss.__code__)) for loss in losses] == compiled
