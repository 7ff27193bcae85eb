"""Periodic ReDo (every F updates, convolution channels included), Ash and Adams' shrink and perturb, Leaky-ReLU."""

import copy

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from torch import nn

from sb3_collapse import DrQv2, PeriodicReDo
from sb3_collapse.drqv2.encoders import LEAKY_RELU_SLOPE
from sb3_collapse.errors import ParameterError
from sb3_collapse.monitoring import MetricsBatchSampler, apply_intervention, collect_activations, dead_fraction
from sb3_collapse.monitoring.interventions import (
    INTERVENTION_LABELS,
    encoder_channels,
    hidden_layers,
    perturbation_noise,
)
from tests.random_env import RandomObservationEnv

PIXELS = gym.spaces.Box(0, 255, (9, 36, 36), np.uint8)


def tiny(seed=0, channels_last=True, **policy_kwargs):
    env = RandomObservationEnv(PIXELS, gym.spaces.Box(-1, 1, (2,), np.float32), action_repeat=2)
    kwargs = dict(hidden_dim=32, feature_dim=16, encoder_kwargs=dict(channels=8, channels_last=channels_last))
    return DrQv2(
        "CnnPolicy", env, buffer_size=300, learning_starts=10, batch_size=8, seed=seed,
        stddev_schedule="linear(1.0,0.1,100)", policy_kwargs={**kwargs, **policy_kwargs},
    )  # fmt: skip


def kill(layer, units):
    """Units whose ReLU output is 0 on every input: a bias of -1000 (their gradient is 0: they stay dead)."""
    with th.no_grad():
        layer.linear.bias[list(units)] = -1e3


class Recorder(PeriodicReDo):
    """PeriodicReDo that keeps a copy of the policy and optimizer state just before and after each recycling."""

    def _init_callback(self):
        super()._init_callback()
        self.before, self.after = [], []

    def recycle(self, updates):
        self.before.append(self._state())
        super().recycle(updates)
        self.after.append(self._state())

    def _state(self):
        policy = self.model.policy
        return {
            "params": {k: v.detach().clone() for k, v in policy.state_dict().items()},
            "optim": [copy.deepcopy(o.state_dict()["state"]) for o in policy.optimizers],
        }


def moments(model, param):
    """Adam's exp_avg and exp_avg_sq of a parameter."""
    for optimizer in model.policy.optimizers:
        if param in optimizer.state:
            return optimizer.state[param]["exp_avg"], optimizer.state[param]["exp_avg_sq"]
    raise KeyError("no optimizer state")


@pytest.mark.parametrize("channels_last", [True, False])
def test_periodic_redo_recycles_dormant_units_and_channels_every_f_updates(channels_last):
    model = tiny(channels_last=channels_last)
    layers = {layer.name: layer for layer in encoder_channels(model) + hidden_layers(model)}
    assert list(layers)[:4] == ["cnn1", "cnn2", "cnn3", "cnn4"] and "mlp1" in layers and "q1.mlp2" in layers
    dead = {"cnn2": (3,), "cnn4": (1, 5), "mlp1": (0, 7)}
    for name, units in dead.items():
        kill(layers[name], units)
    redo = Recorder(every_updates=5, batch_size=16)
    model.learn(46, callback=redo)  # updates from agent step 10, one per 2 steps: 18 updates
    assert [updates for updates, _, _ in redo.history] == [5, 10, 15]  # every F updates, for the whole run
    first = redo.results[0]
    for name, units in dead.items():
        assert set(units) <= set(first.units[name])  # the killed units are dormant and recycled
    recycled = {name: units for name, units in first.units.items() if units}
    assert first.scalars["units_recycled"] == sum(len(units) for units in recycled.values())

    # at the first recycling, as ReDo does: new incoming weights (bias 0 with DrQ-v2's initializer), zero outgoing
    # weights, zero Adam moments of exactly those entries
    model_state = redo.after[0]["params"]
    before = redo.before[0]["params"]
    names = {id(p): n for n, p in model.policy.named_parameters()}
    conv = layers["cnn2"].linear
    weight, bias = names[id(conv.weight)], names[id(conv.bias)]
    assert not th.equal(model_state[weight][3], before[weight][3]) and model_state[bias][3] == 0
    assert th.equal(model_state[weight][0], before[weight][0]) or 0 in first.units["cnn2"]
    next_conv = names[id(layers["cnn3"].linear.weight)]
    assert (model_state[next_conv][:, list(first.units["cnn2"])] == 0).all()
    mlp1, mlp2 = names[id(layers["mlp1"].linear.weight)], names[id(layers["mlp2"].linear.weight)]
    assert (model_state[mlp2][:, [0, 7]] == 0).all() and model_state[names[id(layers["mlp1"].linear.bias)]][0] == 0
    assert not th.equal(model_state[mlp1][[0, 7]], before[mlp1][[0, 7]])


def test_recycled_last_channel_no_longer_reaches_the_trunks():
    """cnn4's outgoing weights are the trunks' columns of that channel at every position (either flatten order), the
    target critic's included (it reads the online encoder): after recycling, changing the channel's activation
    changes no trunk's output."""
    for channels_last in (True, False):
        model = tiny(channels_last=channels_last)
        model.learn(30)
        cnn4 = encoder_channels(model)[-1]
        kill(cnn4, (2,))
        samples, _ = MetricsBatchSampler(0).sample_transitions(model, 16)
        result = apply_intervention(model, "redo", samples=samples, conv_channels=True)
        assert 2 in result.units["cnn4"]
        policy = model.policy
        with th.no_grad():
            h = policy.encoder.cnn4(policy.encoder.cnn3(policy.encoder.cnn2(policy.encoder.cnn1(
                policy.encoder.cnn0(th.as_tensor(samples.observations))))))  # fmt: skip
            changed = h.clone()
            changed[:, 2] += th.randn_like(changed[:, 2]) * 10
            flat = (lambda x: x.permute(0, 2, 3, 1).flatten(1)) if channels_last else (lambda x: x.flatten(1))
            assert th.equal(flat(h), policy.encoder(th.as_tensor(samples.observations)))
            for trunk in (policy.actor.trunk[0], policy.critic.trunk[0], policy.critic_target.trunk[0]):
                th.testing.assert_close(trunk(flat(changed)), trunk(flat(h)), rtol=0, atol=1e-5)
            for moment in moments(model, policy.actor.trunk[0].weight):
                columns = cnn4.consumer_columns(th.tensor([2]))
                assert len(columns) == h.shape[2] * h.shape[3] and (moment[:, columns] == 0).all()


def test_periodic_redo_zeroes_the_optimizer_moments_of_the_recycled_entries():
    model = tiny()
    layers = {layer.name: layer for layer in encoder_channels(model) + hidden_layers(model)}
    kill(layers["cnn1"], (4,))
    redo = Recorder(every_updates=4, batch_size=16)
    model.learn(30, callback=redo)
    assert redo.history and 4 in redo.results[0].units["cnn1"]
    after, before = redo.after[0]["optim"], redo.before[0]["optim"]
    encoder_optimizer = 0  # policy.optimizers: encoder, actor, critic
    conv1, conv2 = 0, 2  # parameter order of the encoder's optimizer: cnn1 weight, bias, cnn2 weight, bias...
    for key in ("exp_avg", "exp_avg_sq"):
        assert (after[encoder_optimizer][conv1][key][4] == 0).all() and after[encoder_optimizer][conv1 + 1][key][4] == 0
        assert (after[encoder_optimizer][conv2][key][:, 4] == 0).all()
        assert th.equal(after[encoder_optimizer][conv2][key][:, 5], before[encoder_optimizer][conv2][key][:, 5])
    assert th.equal(after[encoder_optimizer][conv1]["step"], before[encoder_optimizer][conv1]["step"])  # step kept


def test_periodic_redo_resumes_with_the_saved_model(tmp_path):
    model = tiny()
    redo = PeriodicReDo(every_updates=5, batch_size=16)
    model.callback = redo
    model.learn(26)  # updates 1..8: one recycling at 5, the next due at 10
    assert [u for u, _, _ in redo.history] == [5] and redo.next_check == 10
    model.save(tmp_path / "model.zip")
    loaded = DrQv2.load(tmp_path / "model.zip", env=model.get_env())
    restored = loaded.callback
    assert isinstance(restored, PeriodicReDo) and restored is not redo
    assert (restored.every_updates, restored.batch_size, restored.conv_channels) == (5, 16, True)
    loaded.learn(20, reset_num_timesteps=False)
    assert [u for u, _, _ in restored.history] == [5, 10, 15]  # continued, not started over
    # a state_dict taken in one callback and loaded in another carries the schedule and the batch sampler
    state = restored.state_dict()
    fresh = PeriodicReDo(every_updates=5, batch_size=16)
    fresh.load_state_dict(state)
    assert fresh._pending_state["next_check"] == restored.next_check and "sampler" in state


def test_periodic_redo_checks_its_arguments():
    for bad in (0, 2.5, True):
        with pytest.raises(ValueError, match="every_updates must be an integer >= 1"):
            PeriodicReDo(every_updates=bad)
    with pytest.raises(ValueError, match="tau must be >= 0"):
        PeriodicReDo(tau=-1)


# ------------------------------------------------------------------------------------------ shrink and perturb
def test_ash_and_adams_shrink_perturb_is_lambda_theta_plus_sigma_noise():
    model = tiny()
    model.learn(30)
    policy = model.policy
    before = {k: v.detach().clone() for k, v in policy.state_dict().items()}
    th.manual_seed(7)
    result = apply_intervention(model, "shrink_perturb_noise", shrink=0.6, noise=0.05)
    after = policy.state_dict()
    online = [k for k in after if k.startswith(("encoder.", "actor.", "critic.")) and "running" not in k]
    noise = {k: (after[k] - 0.6 * before[k]) / 0.05 for k in online}
    for key, value in noise.items():  # every parameter moves by its own noise, biases and LayerNorm's included
        assert (value != 0).float().mean() > 0.99, key
    # the weights' noise: a fresh draw of DrQ-v2's initializer (orthogonal Linear weights)
    th.testing.assert_close(
        noise["actor.mlp2.0.weight"] @ noise["actor.mlp2.0.weight"].T, th.eye(32), atol=1e-3, rtol=0
    )
    # the other parameters' noise: U(-1/sqrt(fan_in), 1/sqrt(fan_in)), fan_in the inputs of one unit of the layer
    fan_in = {"encoder.cnn1.0.bias": 9 * 9, "encoder.cnn2.0.bias": 8 * 9, "actor.trunk.0.bias": policy.encoder.repr_dim}
    fan_in.update({"actor.trunk.1.weight": 16, "actor.trunk.1.bias": 16, "actor.mlp1.0.bias": 16})
    fan_in.update({"actor.mlp2.0.bias": 32, "critic.q1.0.bias": 16 + 2, "critic.q1.4.bias": 32})
    for key, inputs in fan_in.items():
        assert noise[key].abs().max() <= inputs**-0.5 * (1 + 1e-4), key
    # the LayerNorm gain gets a centred noise, not +sigma: all normalized noises pooled are U(-1, 1)
    pooled = []
    for key, value in noise.items():
        if value.dim() == 1:
            weight = after.get(key.removesuffix("bias") + "weight", value)
            pooled.append(value * (weight[0].numel() if weight.dim() > 1 else weight.numel()) ** 0.5)
    pooled = th.cat(pooled)
    assert len(pooled) > 300 and pooled.abs().max() <= 1 + 1e-3
    assert abs(float(pooled.mean())) < 0.1 and float(pooled.std()) == pytest.approx(3**-0.5, rel=0.1)
    assert all(th.equal(after[k], before[k]) for k in after if k.startswith("critic_target."))  # targets kept
    assert result.name == "shrink_perturb_noise" and "Ash & Adams" in result.detail
    assert result.scalars["weights_changed"] == sum(after[k].numel() for k in online)


@pytest.mark.parametrize("device", ["cpu", *(["cuda"] if th.cuda.is_available() else [])])
def test_shrink_perturb_noise_is_drawn_on_each_parameter_device_and_dtype(device):
    module = nn.Sequential(nn.Linear(4, 3), nn.LayerNorm(3), nn.Conv2d(2, 5, 3)).to(device, th.float64)
    fresh = copy.deepcopy(module)
    th.manual_seed(1)
    drawn = perturbation_noise(module, fresh)
    assert [param for param, _ in drawn] == list(module.parameters())
    assert drawn[0][1] is fresh[0].weight and drawn[4][1] is fresh[2].weight  # weights: the fresh initialization
    for (param, value), bound in zip(drawn, [None, 4, 3, 3, None, 2 * 9]):
        assert value.device == param.device and value.dtype == th.float64 and value.shape == param.shape
        if bound is not None:
            assert 0 < value.abs().max() <= bound**-0.5
    th.manual_seed(1)
    again = perturbation_noise(module, fresh)
    assert all(th.equal(value, repeated) for (_, value), (_, repeated) in zip(drawn, again))  # a fixed generator


def test_each_shrink_and_perturb_is_labelled():
    assert "interpolation" in INTERVENTION_LABELS["shrink_perturb"]
    assert "Ash & Adams" in INTERVENTION_LABELS["shrink_perturb_noise"]
    assert "one-shot" in INTERVENTION_LABELS["redo"]
    model = tiny()
    result = apply_intervention(model, "shrink_perturb")
    assert "toward a fresh init" in result.detail
    with pytest.raises(ValueError, match="noise must be >= 0"):
        apply_intervention(model, "shrink_perturb_noise", noise=-0.1)


# ------------------------------------------------------------------------------------------ Leaky-ReLU
def test_leaky_relu_everywhere_and_no_unit_dead(tmp_path):
    model = tiny(activation="leaky_relu")
    relus = [m for m in model.policy.modules() if type(m) is nn.ReLU]
    leaky = [m for m in model.policy.modules() if isinstance(m, nn.LeakyReLU)]
    assert not relus and len(leaky) == 4 + 2 + 4 + 4  # encoder, actor, critic and target critic
    assert all(m.negative_slope == LEAKY_RELU_SLOPE == 0.01 for m in leaky)
    assert not model.policy.encoder.cnn1.fused  # the fused kernel is ReLU only

    # the same units killed in a ReLU and a Leaky-ReLU network: dead in the first, not in the second
    for activation, expected_dead in (("relu", True), ("leaky_relu", False)):
        net = tiny(activation=activation)
        net.learn(30)
        layers = {layer.name: layer for layer in encoder_channels(net) + hidden_layers(net)}
        kill(layers["cnn3"], (0,))
        kill(layers["mlp2"], (1, 2))
        observations = MetricsBatchSampler(0).sample(net, 16)[0]
        activations = collect_activations(net, observations)
        fractions = {
            name: dead_fraction(activations[name]) for name in ("cnn1", "cnn2", "cnn3", "cnn4", "mlp1", "mlp2")
        }
        if expected_dead:
            assert fractions["cnn3"] >= 1 / 8 and fractions["mlp2"] >= 2 / 32
        else:
            assert set(fractions.values()) == {0.0}  # no unit is exactly 0 on every input
            assert (activations["mlp2"][:, 1] < 0).all()  # the killed units pass slope x input instead
            th.testing.assert_close(
                activations["mlp2"][:, 1], LEAKY_RELU_SLOPE * net.policy.actor.mlp2[0](
                    net.policy.actor.mlp1(net.policy.actor.trunk(net.policy.encoder(observations))))[:, 1]
            )  # fmt: skip

    # saved and loaded with the model
    model.save(tmp_path / "leaky.zip")
    loaded = DrQv2.load(tmp_path / "leaky.zip")
    assert loaded.policy_kwargs["activation"] == "leaky_relu"
    assert isinstance(loaded.policy.actor.mlp1[1], nn.LeakyReLU) and isinstance(
        loaded.policy.encoder.cnn4[1], nn.LeakyReLU
    )
    with pytest.raises(ParameterError, match="activation must be one of relu, leaky_relu"):
        tiny(activation="gelu")


def test_the_package_exports_the_redo_function_not_a_module():
    """``from sb3_collapse.monitoring import redo`` is the intervention of ``__all__``, not a submodule of that name."""
    import inspect

    from sb3_collapse.monitoring import interventions, redo

    assert inspect.isfunction(redo) and redo is interventions.redo
