"""The model interface (sb3_collapse.common.model.CollapseModel): DrQv2 and the TD3, SAC and DDPG wrappers of
sb3_collapse.baselines implement it; collapse_model gives it to a model of SB3's own classes."""

import gymnasium as gym
import numpy as np
import pytest
import stable_baselines3 as sb3
import torch as th

from sb3_collapse import DrQv2
from sb3_collapse.baselines import DDPG, SAC, TD3, collapse_model
from sb3_collapse.common.model import CollapseModel
from tests.random_env import RandomObservationEnv

ALGORITHMS = {"drqv2": DrQv2, "td3": TD3, "sac": SAC, "ddpg": DDPG}
STEPS, WARMUP = 30, 10


def env():
    return RandomObservationEnv(gym.spaces.Box(-1, 1, (5,), np.float32), gym.spaces.Box(-1, 1, (2,)), action_repeat=2)


def tiny(algorithm, cls=None, **kwargs):
    net = dict(hidden_dim=16, feature_dim=8) if algorithm == "drqv2" else dict(net_arch=[16, 16])
    cls = cls or ALGORITHMS[algorithm]
    params = dict(buffer_size=100, learning_starts=WARMUP, batch_size=8, seed=0, policy_kwargs=net)
    return cls("MlpPolicy", env(), **{**params, **kwargs})


def weights(model):
    return [p.detach().clone() for p in model.policy.parameters() if p.dim() > 1]


@pytest.mark.parametrize("algorithm", ALGORITHMS)
def test_frames_and_updates_are_counted_in_the_papers_units(algorithm):
    model = tiny(algorithm)
    assert isinstance(model, CollapseModel)
    assert (model.num_frames, model.n_updates, model.reset_step, model.action_repeat) == (0, 0, 0, 2)
    model.learn(STEPS)
    assert model.num_frames == 2 * STEPS and model.at_safe_point
    # SB3's loop: one update per step after the warm-up; DrQv2: one per train_freq=2 transitions after it.
    assert model.n_updates == ((STEPS - WARMUP) // 2 if algorithm == "drqv2" else STEPS - WARMUP)
    assert set(model.grad_norm_recorder.last()) >= {"mlp1", "mlp2", "action"}


@pytest.mark.parametrize("algorithm", ALGORITHMS)
def test_a_reset_from_scratch_gives_fresh_weights_and_keeps_training(algorithm):
    model = tiny(algorithm)
    initial = weights(model)
    model.learn(STEPS)
    trained, updates = weights(model), model.n_updates
    model.reset_from_scratch()
    fresh = weights(model)
    assert all(not th.equal(a, b) for a, b in zip(fresh, trained))
    assert all(not th.equal(a, b) for a, b in zip(fresh, initial))  # new draws, not the seed's initial weights again
    assert model.replay_buffer.size() == 0 and model.reset_step == STEPS and model.grad_norm_recorder.last() == {}
    assert model.n_updates == updates  # kept
    model.learn(STEPS, reset_num_timesteps=False)  # a warm-up of WARMUP steps, then updates again
    assert model.num_frames == 4 * STEPS and model.n_updates > updates
    assert all(not th.equal(a, b) for a, b in zip(weights(model), fresh))
    assert "mlp1" in model.grad_norm_recorder.last()  # recorded on the new optimizers
    model.learn(5)  # a new run from step 0: the warm-up has its length back
    assert model.reset_step == 0 and model.learning_starts == WARMUP


@pytest.mark.parametrize("sb3_class,wrapper", [(sb3.TD3, TD3), (sb3.SAC, SAC), (sb3.DDPG, DDPG)])
def test_collapse_model_gives_sb3s_own_classes_the_interface_in_place(sb3_class, wrapper):
    model = tiny("td3", sb3_class)
    assert not isinstance(model, CollapseModel)
    actor, buffer = model.actor, model.replay_buffer
    assert collapse_model(model) is model and type(model) is wrapper and type(model).__name__ == sb3_class.__name__
    assert isinstance(model, CollapseModel) and model.actor is actor and model.replay_buffer is buffer
    assert model.grad_norm_recorder.watches([model.actor.optimizer, model.critic.optimizer])
    assert collapse_model(model) is model and type(model) is wrapper  # once


def test_collapse_model_keeps_a_users_subclass_and_leaves_other_models():
    class MyTD3(sb3.TD3):
        pass

    model = collapse_model(tiny("td3", MyTD3))
    assert isinstance(model, MyTD3) and isinstance(model, CollapseModel) and type(model).__name__ == "MyTD3"
    ppo = sb3.PPO("MlpPolicy", env(), n_steps=8, batch_size=8)
    assert collapse_model(ppo) is ppo and type(ppo) is sb3.PPO and not isinstance(ppo, CollapseModel)


def test_a_saved_wrapper_loads_with_sb3s_class_and_its_own(tmp_path):
    model = tiny("td3")
    model.learn(STEPS)
    model.reset_from_scratch()
    model.save(tmp_path / "td3.zip")
    plain = sb3.TD3.load(tmp_path / "td3.zip")
    assert type(plain) is sb3.TD3 and plain.reset_step == STEPS  # a saved attribute SB3 ignores
    loaded = TD3.load(tmp_path / "td3.zip", env=env())
    assert loaded.reset_step == STEPS and loaded.learning_starts == STEPS + WARMUP
    assert loaded.grad_norm_recorder.watches([loaded.actor.optimizer, loaded.critic.optimizer])
