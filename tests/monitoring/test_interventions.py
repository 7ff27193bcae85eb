"""Each intervention changes exactly the parameters and state it names, on DrQv2, TD3, DDPG and SAC."""

import re

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3 import DDPG, SAC, TD3

from sb3_collapse import DrQv2
from sb3_collapse.monitoring import (
    MetricsBatchSampler,
    apply_intervention,
    collect_activations,
    dormant_ratio,
    grad_norms_of,
    gradient_norm,
    layer_parameters,
    track_grad_norms,
)
from sb3_collapse.monitoring.interventions import encoder_channels, hidden_layers
from tests.random_env import RandomObservationEnv

PIXELS = gym.spaces.Box(0, 255, (9, 36, 36), np.uint8)  # NatureCNN needs at least 36x36
STATE = gym.spaces.Box(-1, 1, (5,), np.float32)
ALGOS = {"drqv2": DrQv2, "td3": TD3, "ddpg": DDPG, "sac": SAC}
MODELS = [(algo, policy) for algo in ALGOS for policy in ("CnnPolicy", "MlpPolicy")]


def tiny(algo, policy="CnnPolicy", seed=0, **kwargs):
    space = PIXELS if policy == "CnnPolicy" else STATE
    env = RandomObservationEnv(space, gym.spaces.Box(-1, 1, (2,), np.float32), action_repeat=2)
    params = dict(buffer_size=300, learning_starts=10, batch_size=8, seed=seed)
    if algo == "drqv2":
        params.update(policy_kwargs=dict(hidden_dim=32, feature_dim=16), stddev_schedule="linear(1.0,0.1,100)")
    else:
        policy_kwargs = dict(net_arch=[16, 16])
        if policy == "CnnPolicy":
            policy_kwargs["features_extractor_kwargs"] = dict(features_dim=24)
        params.update(policy_kwargs=policy_kwargs)
    params.update(kwargs)
    return ALGOS[algo](policy, env, **params)


def trained(algo, policy, steps=40, **kwargs):
    """A tiny model after some updates: no weight is at its (often constant) initial value any more."""
    model = tiny(algo, policy, **kwargs)
    model.learn(steps)
    return model


def optimizers(model):
    policy = model.policy
    found = {part: getattr(policy, part).optimizer for part in ("encoder", "actor", "critic") if hasattr(policy, part)}
    found = {part: optimizer for part, optimizer in found.items() if optimizer is not None}
    if getattr(model, "ent_coef_optimizer", None) is not None:
        found["ent_coef"] = model.ent_coef_optimizer
    return found


def snapshot(model):
    """Every piece of training state, one entry per tensor or value: policy, optimizers, buffer, counters."""
    names = {id(p): name for name, p in model.policy.named_parameters()}
    if getattr(model, "log_ent_coef", None) is not None:
        names[id(model.log_ent_coef)] = "log_ent_coef"
    state = {f"policy/{key}": value.detach().clone() for key, value in model.policy.state_dict().items()}
    for part, optimizer in optimizers(model).items():
        for param, entries in optimizer.state.items():
            for key, value in entries.items():
                state[f"optim/{part}/{names[id(param)]}/{key}"] = value.clone() if th.is_tensor(value) else value
        for i, group in enumerate(optimizer.param_groups):
            state[f"optim/{part}/group{i}/lr"] = group["lr"]
    for key, value in vars(model.replay_buffer).items():
        if isinstance(value, np.ndarray):
            state[f"buffer/{key}"] = value.copy()
        elif isinstance(value, (int, bool)):
            state[f"buffer/{key}"] = value
    for key in ("num_timesteps", "_n_updates", "learning_starts", "_episode_num"):
        state[f"model/{key}"] = getattr(model, key)
    state["model/reset_step"] = getattr(model, "reset_step", 0)
    state["model/_last_obs"] = model._last_obs.copy()
    if getattr(model, "log_ent_coef", None) is not None:
        state["ent_coef/log_ent_coef"] = model.log_ent_coef.detach().clone()
    return state


def same(a, b):
    if th.is_tensor(a):
        return th.is_tensor(b) and a.shape == b.shape and th.equal(a, b)
    if isinstance(a, np.ndarray):
        return isinstance(b, np.ndarray) and np.array_equal(a, b)
    return a == b


def changed_keys(before, after):
    return {
        key
        for key in before.keys() | after.keys()
        if key not in before or key not in after or not same(before[key], after[key])
    }


def param_of(key):
    """The parameter name in a policy/ or optim/ key, e.g. ``actor.mu.0.weight``."""
    if key.startswith("policy/"):
        return key.removeprefix("policy/")
    if key.startswith("optim/") and "/group" not in key:
        return key.split("/")[2]
    return None


# What each intervention names, per algorithm: a regular expression over the parameter names (policy and optimizer
# state keys); every other entry must be unchanged.
NAMED = {
    ("reset_actor", "drqv2"): r"actor\.",
    ("reset_actor", "td3"): r"actor(_target)?\.",
    ("reset_actor", "ddpg"): r"actor(_target)?\.",
    ("reset_actor", "sac"): r"actor\.",
    ("reset_mlp", "drqv2"): r"actor\.",
    ("reset_mlp", "td3"): r"actor(_target)?\.mu\.",
    ("reset_mlp", "ddpg"): r"actor(_target)?\.mu\.",
    ("reset_mlp", "sac"): r"actor\.(latent_pi|mu|log_std)\.",
    ("shrink_perturb", "drqv2"): r"(encoder|actor|critic)\.",
    ("shrink_perturb", "td3"): r"(actor|critic)\.",
    ("shrink_perturb", "ddpg"): r"(actor|critic)\.",
    ("shrink_perturb", "sac"): r"(actor|critic)\.",
    ("shrink_perturb_noise", "drqv2"): r"(encoder|actor|critic)\.",
    ("shrink_perturb_noise", "td3"): r"(actor|critic)\.",
    ("shrink_perturb_noise", "ddpg"): r"(actor|critic)\.",
    ("shrink_perturb_noise", "sac"): r"(actor|critic)\.",
}


@pytest.mark.parametrize("intervention", ["reset_actor", "reset_mlp", "shrink_perturb", "shrink_perturb_noise"])
@pytest.mark.parametrize("algo,policy", MODELS)
def test_partial_intervention_changes_exactly_what_it_names(algo, policy, intervention):
    model = trained(algo, policy)
    before = snapshot(model)
    result = apply_intervention(model, intervention)
    after = snapshot(model)
    named = re.compile(NAMED[(intervention, algo)])
    changed = changed_keys(before, after)
    weights = {key for key in before if key.startswith("policy/") and named.match(param_of(key))}
    assert weights and weights <= changed  # every named weight got new values...
    for key in sorted(changed):  # ...and nothing else changed
        param = param_of(key)
        assert param is not None and named.match(param), f"{intervention} changed {key}, which it does not name"
    if intervention.startswith("shrink_perturb"):  # optimizer state, targets: kept
        assert not any(key.startswith("optim/") for key in changed)
    else:  # the named parameters' optimizer state is forgotten (Adam starts again for them), the rest kept
        for key in before:
            if key.startswith("optim/") and "/group" not in key and named.match(param_of(key)):
                assert key not in after
    assert result.name == intervention and result.scalars["weights_changed"] > 0
    if (algo, intervention) in {("td3", "reset_actor"), ("ddpg", "reset_actor")}:
        target = model.policy.actor_target.state_dict()
        assert all(th.equal(value, target[key]) for key, value in model.policy.actor.state_dict().items())
    if intervention == "shrink_perturb":
        for key in (key for key in weights if before[key].dim() == 2):  # Linear weights
            difference = after[key] - 0.8 * before[key]  # = 0.2 x a fresh initialization: nonzero, |entries| <= 1
            assert 0 < difference.abs().max() <= 0.2 + 1e-6, key
    if intervention == "shrink_perturb_noise":  # every parameter gets a noise, biases and LayerNorm's included
        for key in weights:
            noise = (after[key] - 0.8 * before[key]) / 0.01
            if before[key].dim() > 1:  # weights: a fresh initialization (orthogonal, gain sqrt(2) for DrQ-v2's convs)
                bound = 2**0.5
            else:  # U(-1/sqrt(fan_in), 1/sqrt(fan_in)), fan_in of the layer's weight (LayerNorm: its features)
                weight = before.get(key.removesuffix("bias") + "weight", before[key])
                bound = (weight[0].numel() if weight.dim() > 1 else weight.numel()) ** -0.5
            assert (noise != 0).float().mean() > 0.99 and noise.abs().max() <= bound * (1 + 1e-3) + 1e-4, key
    model.learn(10, reset_num_timesteps=False)  # training continues from the changed state


@pytest.mark.parametrize("algo,policy", MODELS)
def test_reset_from_scratch_renews_everything_but_the_counters(algo, policy):
    model = trained(algo, policy)
    before = snapshot(model)
    stored = model.replay_buffer.size()
    result = apply_intervention(model, "reset")
    after = snapshot(model)
    changed = changed_keys(before, after)
    policy_keys = {key for key in before if key.startswith("policy/")}
    assert policy_keys <= changed  # new weights everywhere (the targets included)
    assert not any(key.startswith("optim/") and "/group" not in key for key in after)  # fresh optimizers
    assert model.replay_buffer.size() == 0 and result.scalars["transitions_dropped"] == stored > 0
    for key in ("model/num_timesteps", "model/_n_updates", "model/_episode_num", "model/_last_obs"):
        assert key not in changed
    assert model.reset_step == model.num_timesteps == 40
    assert grad_norms_of(model) == {}
    if algo == "drqv2":
        assert model.learning_starts == 10 and model.current_stddev == 1.0
    else:  # the warm-up restarts: no update and random actions for learning_starts agent steps
        assert model.learning_starts == 40 + 10
        assert model.actor is model.policy.actor and model.critic_target is model.policy.critic_target
    if algo == "sac":  # a learned entropy coefficient starts again from 1 with a new optimizer
        assert model.log_ent_coef.item() == 0.0 and not model.ent_coef_optimizer.state
    updates = model._n_updates
    model.learn(10, reset_num_timesteps=False)  # steps 41..50: still the warm-up
    assert model._n_updates == updates
    model.learn(10, reset_num_timesteps=False)
    assert model._n_updates > updates and set(grad_norms_of(model)) >= {"mlp1", "action"}


def force_dormant(model, units):
    """Kill chosen units of the actor's first hidden layer and of the first Q network's: a bias of -1000."""
    layers = {layer.name: layer for layer in hidden_layers(model)}
    with th.no_grad():
        for name, indices in units.items():
            layers[name].linear.bias[list(indices)] = -1e3


@pytest.mark.parametrize("algo,policy", MODELS)
def test_redo_recycles_exactly_the_dormant_units(algo, policy):
    model = trained(algo, policy)
    names = [layer.name for layer in hidden_layers(model)]
    q_networks = 1 if algo == "ddpg" else 2  # DDPG: one Q network
    assert names == ["mlp1", "mlp2", *[f"q{k}.mlp{j}" for k in range(1, q_networks + 1) for j in (1, 2)]]
    force_dormant(model, {"mlp1": (0, 1), "q1.mlp1": (2,)})
    before = snapshot(model)
    result = apply_intervention(model, "redo", batch_size=32, sampler=MetricsBatchSampler(0))
    after = snapshot(model)
    assert {0, 1} <= set(result.units["mlp1"]) and {2} <= set(result.units["q1.mlp1"])
    assert result.scalars["units_recycled"] == sum(len(units) for units in result.units.values())

    # Entries each recycled unit may change: its incoming row (weight and bias), its consumers' column.
    param_names = {id(p): name for name, p in model.policy.named_parameters()}
    allowed = {}
    for layer in hidden_layers(model):
        units = list(result.units[layer.name])
        for param in [layer.linear.weight, layer.linear.bias]:
            mask = th.zeros(param.shape, dtype=th.bool)
            mask[units] = True
            allowed[param_names[id(param)]] = allowed.get(param_names[id(param)], mask) | mask
        for consumer in layer.consumers:
            mask = th.zeros(consumer.weight.shape, dtype=th.bool)
            mask[:, units] = True
            name = param_names[id(consumer.weight)]
            allowed[name] = allowed.get(name, th.zeros_like(mask)) | mask
    for key in changed_keys(before, after):
        param = param_of(key)
        assert param in allowed, f"redo changed {key}, which belongs to no recycled unit"
        if key.endswith("/step"):
            raise AssertionError(f"redo changed the step count {key}")
        outside = (before[key] != after[key]) & ~allowed[param]
        assert not outside.any(), f"redo changed entries of {key} outside the recycled units"
    for layer in hidden_layers(model):
        units = list(result.units[layer.name])
        if not units:
            continue
        weight = param_names[id(layer.linear.weight)]
        rows_before, rows_after = before[f"policy/{weight}"][units], after[f"policy/{weight}"][units]
        assert (rows_before != rows_after).any(1).all()  # new incoming weights
        for consumer in layer.consumers:
            assert (consumer.weight[:, units] == 0).all()  # outgoing weights zeroed
            for moment in ("exp_avg", "exp_avg_sq"):
                key = f"optim/actor/{param_names[id(consumer.weight)]}/{moment}"
                key = key if key in after else key.replace("optim/actor/", "optim/critic/")
                assert (after[key][:, units] == 0).all()
        for moment in ("exp_avg", "exp_avg_sq"):
            key = next(k for k in after if k.startswith("optim/") and k.endswith(f"/{weight}/{moment}"))
            assert (after[key][units] == 0).all()
    assert all(same(before[key], after[key]) for key in before if key.startswith(("buffer/", "model/")))
    assert any(key.startswith("policy/actor.") for key in changed_keys(before, after))
    assert not any("target" in key for key in changed_keys(before, after))


def test_redo_measures_dormancy_as_the_dormant_ratio_metric():
    model = trained("td3", "CnnPolicy")
    samples, _ = MetricsBatchSampler(3).sample_transitions(model, 32)
    ratio = dormant_ratio(collect_activations(model, samples.observations, layers=["mlp1"])["mlp1"])
    result = apply_intervention(model, "redo", samples=samples)
    assert len(result.units["mlp1"]) / 16 == ratio
    empty = tiny("drqv2", "CnnPolicy")
    result = apply_intervention(empty, "redo", batch_size=8)  # nothing stored yet
    assert result.scalars["units_recycled"] == 0 and "fewer than 8 transitions" in result.detail


def test_intervention_errors_say_what_to_do():
    with pytest.raises(ValueError, match="share_features_extractor=True would reset the critic's features extractor"):
        apply_intervention(tiny("sac", "MlpPolicy", policy_kwargs=dict(share_features_extractor=True)), "reset_actor")
    with pytest.raises(ValueError, match="intervention must be one of"):
        apply_intervention(tiny("td3", "MlpPolicy"), "reinit")
    with pytest.raises(ValueError, match="shrink must be in"):
        apply_intervention(tiny("td3", "MlpPolicy"), "shrink_perturb", shrink=0.0)


@pytest.mark.parametrize("algo", ["drqv2", "td3", "sac"])
def test_recorded_grad_norms_are_those_of_the_last_update(algo):
    model = tiny(algo, "CnnPolicy")
    recorder = track_grad_norms(model)
    assert recorder is track_grad_norms(model)  # once per optimizer set
    model.learn(30)
    # The .grad of each layer is the one of its optimizer's last step (the next update clears it first); DrQv2's
    # encoder layers are recorded when the encoder's optimizer steps (critic loss), the others with the actor's.
    recorded = grad_norms_of(model)
    assert list(recorded) == list(layer_parameters(model))
    for name, params in layer_parameters(model).items():
        assert recorded[name] == pytest.approx(gradient_norm(p.grad for p in params), rel=1e-5), name
    assert recorded["mlp1"] > 0


def agent_outputs(model, samples):
    """Every function of the agent on a batch: the actor's, the critic's and the target networks' outputs."""
    policy = model.policy
    obs, actions = th.as_tensor(samples.observations), th.as_tensor(samples.actions)
    policy.set_training_mode(False)
    with th.no_grad():
        if isinstance(model, DrQv2):  # one encoder, read by the actor, the critic and the target critic
            features = policy.encoder(obs)
            return {
                "actor": policy.actor(features),
                "critic": th.cat(policy.critic(features, actions), 1),
                "target critic": th.cat(policy.critic_target(features, actions), 1),
            }
        outputs = {"critic": th.cat(policy.critic(obs, actions), 1)}
        outputs["target critic"] = th.cat(policy.critic_target(obs, actions), 1)
        if isinstance(model, SAC):
            outputs["actor"] = th.cat(policy.actor.get_action_dist_params(obs)[:2], 1)  # mean and log std
        else:
            outputs["actor"], outputs["target actor"] = policy.actor(obs), policy.actor_target(obs)
        return outputs


@pytest.mark.parametrize("algo,policy", MODELS)
def test_recycling_dead_units_changes_no_function_of_the_agent(algo, policy):
    """ReDo on units that are exactly dead on the batch (tau 0): new incoming weights, zero outgoing weights in every
    network that reads them (DrQ-v2's target critic reads the online encoder's cnn4), and the actor's, the critic's
    and the target networks' outputs unchanged."""
    model = trained(algo, policy)
    conv = algo == "drqv2" and policy == "CnnPolicy"
    layers = {layer.name: layer for layer in hidden_layers(model)}
    if conv:
        layers["cnn4"] = encoder_channels(model)[-1]
    killed = {"mlp1": (0, 3), "q1.mlp2": (1,), **({"cnn4": (2, 5)} if conv else {})}
    with th.no_grad():
        for name, units in killed.items():
            layers[name].linear.bias[list(units)] = -1e3
    samples, _ = MetricsBatchSampler(0).sample_transitions(model, 32)
    before = agent_outputs(model, samples)
    incoming = {name: layers[name].linear.weight[list(units)].clone() for name, units in killed.items()}
    result = apply_intervention(model, "redo", samples=samples, tau=0.0, conv_channels=conv)
    after = agent_outputs(model, samples)
    assert (
        set(before)
        == set(after)
        == {"actor", "critic", "target critic"} | ({"target actor"} if algo in ("td3", "ddpg") else set())
    )
    for name in before:
        th.testing.assert_close(after[name], before[name], rtol=0, atol=1e-6, msg=f"redo changed the {name}")
    for name, units in killed.items():
        layer = layers[name]
        assert set(units) <= set(result.units[name])
        assert (layer.linear.bias[list(units)] > -1e3).all()  # new incoming weights and bias for each unit
        assert (layer.linear.weight[list(units)] != incoming[name]).flatten(1).any(1).all()
        columns = layer.consumer_columns(th.tensor(units))
        for consumer in layer.consumers:
            assert (consumer.weight[:, columns] == 0).all()
    if conv:  # the readers of cnn4: the trunk Linear of the actor, the critic and the target critic
        trunks = [model.policy.actor.trunk[0], model.policy.critic.trunk[0], model.policy.critic_target.trunk[0]]
        assert list(layers["cnn4"].consumers) == trunks
