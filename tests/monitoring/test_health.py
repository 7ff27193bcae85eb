import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3 import DDPG, SAC, TD3

from sb3_collapse import DrQv2
from sb3_collapse.errors import ParameterError
from sb3_collapse.monitoring.health import (
    DEFAULT_METRICS,
    HEALTH_METRICS,
    HealthMemory,
    measure_health,
    network_taps,
)
from sb3_collapse.monitoring.metrics import layer_metrics
from tests.random_env import RandomObservationEnv

PIXELS = gym.spaces.Box(0, 255, (9, 32, 32), np.uint8)
VECTOR = gym.spaces.Box(-1, 1, (5,), np.float32)


def drqv2():
    env = RandomObservationEnv(PIXELS, action_repeat=2)
    return DrQv2(
        "CnnPolicy", env, buffer_size=100, learning_starts=20, batch_size=8, seed=0, policy_kwargs=dict(hidden_dim=32)
    )


def observations(space, n=16, seed=0):
    space.seed(seed)
    return np.stack([space.sample() for _ in range(n)])


def test_the_critic_layers_are_named_as_the_actor_s():
    model = drqv2()
    names = list(network_taps(model, ("critic",)))
    assert names == ["q1.mlp0", "q1.mlp1", "q1.mlp2", "q1", "q2.mlp0", "q2.mlp1", "q2.mlp2", "q2"]
    assert list(network_taps(model)) == [
        "cnn0",
        "cnn1",
        "cnn2",
        "cnn3",
        "cnn4",
        "mlp0",
        "mlp1",
        "mlp2",
        "action",
        *names,
    ]


def test_critic_activations_and_q_values_are_those_of_q_of_the_deterministic_action():
    model = drqv2()
    obs = observations(PIXELS)
    values = measure_health(model, obs, ("numerical_rank", "q_mean", "q_std"), networks=("critic",))
    policy = model.policy
    with th.no_grad():
        features = policy.extract_features(th.as_tensor(obs))
        q1, q2 = policy.critic(features, policy.actor(features))
        head_input = th.cat([policy.critic.trunk(features), policy.actor(features)], 1)
    assert values["collapse/q1/q_mean"] == pytest.approx(float(q1.double().mean()), rel=1e-5)
    assert values["collapse/q2/q_std"] == pytest.approx(float(q2.double().std(correction=0)), rel=1e-5)
    rank = layer_metrics(head_input, metrics=("numerical_rank",))["numerical_rank"]
    assert values["collapse/q1.mlp0/numerical_rank"] == pytest.approx(rank, rel=1e-5)
    assert not any(tag.startswith(("collapse/mlp", "collapse/action")) for tag in values)  # critic only


@pytest.mark.parametrize("algo", [TD3, DDPG, SAC])
def test_every_metric_on_sb3_actor_and_critic(algo):
    model = algo(
        "MlpPolicy", RandomObservationEnv(VECTOR), buffer_size=100, policy_kwargs=dict(net_arch=[16, 8]), seed=0
    )
    values = measure_health(model, observations(VECTOR), HEALTH_METRICS, ("actor", "critic"), memory=HealthMemory())
    layers = {tag.split("/")[1] for tag in values}
    critic = {"q1.mlp0", "q1.mlp1", "q1.mlp2", "q1"} | ({"q2"} if algo is not DDPG else set())  # DDPG: one Q network
    assert {"mlp0", "mlp1", "mlp2", "action"} | critic <= layers
    assert values["collapse/q1.mlp2/stable_rank"] <= 8 and 0 <= values["collapse/mlp1/active_fraction"] <= 1
    assert values["collapse/q1.mlp1/weight_change"] == 0.0  # the first measurement is the reference
    assert np.isnan(values["collapse/mlp1/persistent_dormant_fraction"])  # no previous measurement
    assert {
        "collapse/mlp1/dormant_ratio_tau0",
        "collapse/mlp1/dormant_ratio_tau0.025",
        "collapse/mlp1/dormant_ratio_tau0.1",
    } <= set(values)


def test_memory_carries_the_dormant_units_and_the_reference_weights():
    model = drqv2()
    obs, memory = observations(PIXELS), HealthMemory()
    metrics = ("dormant_ratio", "persistent_dormant_fraction", "weight_change")
    first = measure_health(model, obs, metrics, ("actor", "critic"), memory=memory)
    again = measure_health(model, obs, metrics, ("actor", "critic"), memory=memory)
    for layer in ("mlp1", "q2.mlp1"):  # the same units dormant twice: persistent = dormant ratio
        assert again[f"collapse/{layer}/persistent_dormant_fraction"] == first[f"collapse/{layer}/dormant_ratio"]
    linear = model.policy.actor.mlp1[0]
    with th.no_grad():
        linear.weight.add_(1.0)  # every weight moves by 1, the bias stays: RMS change sqrt(weights / entries)
    moved = measure_health(model, obs, ("weight_change",), memory=memory)
    entries = linear.weight.numel() + linear.bias.numel()
    assert moved["collapse/mlp1/weight_change"] == pytest.approx(np.sqrt(linear.weight.numel() / entries))
    assert moved["collapse/mlp2/weight_change"] == 0.0
    memory.remember_weights(model)
    assert measure_health(model, obs, ("weight_change",), memory=memory)["collapse/mlp1/weight_change"] == 0.0
    assert memory.dormant == {}


def test_default_metrics_are_the_callback_s_and_layers_filter_both_networks():
    model = TD3("CnnPolicy", RandomObservationEnv(gym.spaces.Box(0, 255, (3, 36, 36), np.uint8)), buffer_size=100)
    obs = observations(gym.spaces.Box(0, 255, (3, 36, 36), np.uint8), n=8)
    values = measure_health(model, obs, layers=["mlp1", "q1.mlp1"], networks=("actor", "critic"))
    assert {tag.split("/")[1] for tag in values} == {"mlp1", "q1.mlp1"}
    assert len(values) == 2 * 9  # the nine activation metrics; no gradient yet; no action measured
    assert set(DEFAULT_METRICS) <= set(HEALTH_METRICS)


def test_bad_arguments_name_the_parameter():
    model, obs = drqv2(), observations(PIXELS, n=4)
    for kwargs, parameter in (
        (dict(metrics=("rank",)), "metrics"),
        (dict(networks=("encoder",)), "networks"),
        (dict(networks=()), "networks"),
        (dict(taus=(-1.0,)), "taus"),
        (dict(taus=()), "taus"),
        (dict(metrics=("weight_change",)), "memory"),
    ):
        with pytest.raises(ParameterError, match=f"^{parameter}") as raised:
            measure_health(model, obs, **kwargs)
        assert raised.value.parameter == parameter
    with pytest.raises(KeyError, match="q3.mlp1"):
        measure_health(model, obs, layers=["q3.mlp1"], networks=("actor", "critic"))


@pytest.mark.parametrize("policy", ["MlpPolicy", "MultiInputPolicy"])
def test_critic_of_drqv2_state_and_dict_policies(policy):
    from tests.monitoring.test_callbacks import POLICY_SPACES

    space = POLICY_SPACES[policy]
    kwargs = dict(
        hidden_dim=16, feature_dim=8, **({} if policy == "MlpPolicy" else dict(encoder_kwargs=dict(channels=4)))
    )
    env = RandomObservationEnv(space, gym.spaces.Box(-1, 1, (2,), np.float32))
    model = DrQv2(policy, env, buffer_size=100, seed=0, policy_kwargs=kwargs)
    space.seed(0)
    samples = [space.sample() for _ in range(6)]
    obs = (
        {key: np.stack([s[key] for s in samples]) for key in space.spaces}
        if policy != "MlpPolicy"
        else np.stack(samples)
    )
    values = measure_health(model, obs, ("feature_norm", "q_mean"), ("actor", "critic"), batch_size=4)
    assert values["collapse/q1.mlp0/feature_norm"] > 0 and "collapse/q2/q_mean" in values
    assert values["collapse/q1.mlp0/feature_norm"] == values["collapse/q2.mlp0/feature_norm"]  # one shared trunk
