import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3 import DDPG, PPO, SAC, TD3

from sb3_collapse import DrQv2
from sb3_collapse.errors import LayerMappingError
from sb3_collapse.monitoring import collect_activations, layer_parameters, layer_taps
from tests.random_env import RandomObservationEnv

PIXELS = gym.spaces.Box(0, 255, (9, 84, 84), np.uint8)
STATE = gym.spaces.Box(-np.inf, np.inf, (5,), np.float32)


def drqv2(space=PIXELS, policy="CnnPolicy"):
    return DrQv2(policy, RandomObservationEnv(space), buffer_size=100, policy_kwargs=dict(hidden_dim=64), seed=0)


def observations(space, n=7):
    space.seed(0)
    return np.stack([space.sample() for _ in range(n)])


def test_drqv2_pixel_activations_have_every_name_and_shape():
    model = drqv2()
    acts = collect_activations(model, observations(PIXELS), batch_size=3)
    assert list(acts) == ["cnn0", "cnn1", "cnn2", "cnn3", "cnn4", "mlp0", "mlp1", "mlp2", "action"]
    shapes = {name: tuple(a.shape) for name, a in acts.items()}
    assert shapes["cnn0"] == (7, 9, 84, 84) and shapes["cnn1"] == (7, 32, 41, 41)
    assert shapes["cnn4"] == (7, 32, 35, 35) and shapes["mlp0"] == (7, 50)
    assert shapes["mlp1"] == shapes["mlp2"] == (7, 64) and shapes["action"] == (7, 6)
    obs = observations(PIXELS)
    th.testing.assert_close(acts["cnn0"], th.as_tensor(obs, dtype=th.float32) / 255.0 - 0.5)
    assert (acts["mlp1"] >= 0).all() and all(a.dtype == th.float32 for a in acts.values())
    np.testing.assert_allclose(acts["action"].numpy(), model.predict(obs, deterministic=True)[0], atol=1e-6)


def test_collect_activations_leaves_training_state_alone():
    model = drqv2()
    model.policy.set_training_mode(True)
    before = [p.detach().clone() for p in model.policy.parameters()]
    acts = collect_activations(model.policy, observations(PIXELS, 2), layers=["mlp1", "cnn2"])
    assert list(acts) == ["cnn2", "mlp1"]
    assert model.policy.training and model.actor.training
    assert all(not a.requires_grad for a in acts.values())
    assert all(p.grad is None for p in model.policy.parameters())
    assert all(th.equal(b, p) for b, p in zip(before, model.policy.parameters()))
    assert all(not m._forward_hooks and not m._forward_pre_hooks for m in model.policy.modules())
    with pytest.raises(KeyError, match="cnn9"):
        collect_activations(model, observations(PIXELS, 2), layers=["cnn9"])


def test_drqv2_state_policy_has_no_cnn_layers():
    acts = collect_activations(drqv2(STATE, "MlpPolicy"), observations(STATE))
    assert list(acts) == ["mlp0", "mlp1", "mlp2", "action"]


def test_dict_observations_are_sliced_per_key():
    space = gym.spaces.Dict(
        {"pixels": gym.spaces.Box(0, 255, (3, 36, 36), np.uint8), "state": gym.spaces.Box(-1, 1, (4,), np.float32)}
    )
    model = DrQv2(
        "MultiInputPolicy",
        RandomObservationEnv(space),
        buffer_size=100,
        policy_kwargs=dict(hidden_dim=16, feature_dim=8, encoder_kwargs=dict(channels=4)),
        seed=0,
    )
    space.seed(0)
    samples = [space.sample() for _ in range(5)]
    obs = {key: np.stack([sample[key] for sample in samples]) for key in space.spaces}
    acts = collect_activations(model, obs, batch_size=2)  # forward passes of 2, 2 and 1 observations
    assert list(acts) == ["cnn0", "cnn1", "cnn2", "cnn3", "cnn4", "mlp0", "mlp1", "mlp2", "action"]
    th.testing.assert_close(acts["cnn0"], th.as_tensor(obs["pixels"], dtype=th.float32) / 255.0 - 0.5)
    np.testing.assert_allclose(acts["action"].numpy(), model.predict(obs, deterministic=True)[0], atol=1e-6)
    tensors = collect_activations(model, {key: th.as_tensor(value) for key, value in obs.items()}, ["action"])
    th.testing.assert_close(tensors["action"], acts["action"])
    with pytest.raises(ValueError, match="same number of observations"):
        collect_activations(model, {"pixels": obs["pixels"], "state": obs["state"][:3]})


@pytest.mark.parametrize("algo", [TD3, DDPG, SAC])
@pytest.mark.parametrize("policy", ["CnnPolicy", "MlpPolicy"])
def test_sb3_actor_layers_are_mapped(algo, policy):
    space = PIXELS if policy == "CnnPolicy" else STATE
    env = RandomObservationEnv(space)
    model = algo(policy, env, buffer_size=10, policy_kwargs=dict(net_arch=[16, 8]), seed=0)
    obs = observations(space, 5)
    acts = collect_activations(model, obs)
    cnn = ["cnn0", "cnn1", "cnn2", "cnn3"] if policy == "CnnPolicy" else []
    assert list(acts) == [*cnn, "mlp0", "mlp1", "mlp2", "action"]
    assert acts["mlp1"].shape == (5, 16) and acts["mlp2"].shape == (5, 8)
    # Box(-1, 1) actions: the deterministic prediction is the named action.
    np.testing.assert_allclose(acts["action"].numpy(), model.predict(obs, deterministic=True)[0], atol=1e-6)
    if cnn:
        th.testing.assert_close(acts["cnn0"], th.as_tensor(obs, dtype=th.float32) / 255.0)
    params = layer_parameters(model)
    assert "cnn0" not in params and params["mlp1"] == tuple(
        model.actor.latent_pi[0].parameters() if algo is SAC else model.actor.mu[0].parameters()
    )


def test_unmappable_policy_is_refused():
    with pytest.raises(LayerMappingError, match="SB3 algorithm or policy"):
        layer_taps(th.nn.Linear(2, 2))
    with pytest.raises(LayerMappingError, match="DrQv2 and for SB3's TD3, DDPG and SAC"):
        layer_taps(PPO("MlpPolicy", RandomObservationEnv(STATE), n_steps=8, batch_size=8))
