"""The interventions act on what the policy provides (``InterventionParts``); monitoring imports no algorithm."""

import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from torch import nn

from sb3_collapse.common.layers import LAYER_NAMES, LayerParts, sequential_hidden_parts
from sb3_collapse.drqv2.policies import CnnPolicy, MlpPolicy
from sb3_collapse.monitoring import apply_intervention
from sb3_collapse.monitoring.interventions import (
    InterventionParts,
    encoder_channels,
    hidden_layers,
    intervention_parts,
)

ROOT = Path(__file__).resolve().parents[2]
"""The repository root: the subprocesses import this checkout's package."""


def test_monitoring_imports_no_algorithm_of_the_package():
    # One fresh interpreter for both checks (each start-up imports torch): the check of the imports comes first.
    code = (
        "import sys, sb3_collapse.monitoring, sb3_collapse.common.layers; "
        "loaded = sorted(m for m in sys.modules if m.startswith('sb3_collapse.drqv2')); "
        "assert not loaded, loaded; "
        "import sb3_collapse; print(sb3_collapse.DrQv2.__module__)"
    )
    run = subprocess.run([sys.executable, "-c", code], check=False, capture_output=True, text=True, cwd=ROOT)
    # the package's DrQv2 is still there, imported at its first use
    assert run.returncode == 0 and run.stdout.strip() == "sb3_collapse.drqv2.drqv2", run.stderr


def _lr(_progress):
    return 1e-3


@pytest.mark.parametrize("policy_class", [CnnPolicy, MlpPolicy])
def test_the_drqv2_policy_provides_the_parts(policy_class):
    obs = gym.spaces.Box(0, 255, (9, 36, 36), np.uint8) if policy_class is CnnPolicy else gym.spaces.Box(-1, 1, (5,))
    policy = policy_class(obs, gym.spaces.Box(-1, 1, (2,), np.float32), _lr, hidden_dim=32, feature_dim=16)
    assert isinstance(policy, InterventionParts)
    assert list(policy.online_networks()) == ["encoder", "actor", "critic"]
    assert list(policy.target_networks()) == ["target critic"]
    assert policy.actor_modules() == policy.actor_mlp_modules() == [policy.actor]
    parts = policy.hidden_layer_parts()
    assert [p.name for p in parts] == ["mlp1", "mlp2", "q1.mlp1", "q1.mlp2", "q2.mlp1", "q2.mlp2"]
    assert parts[0] == LayerParts("mlp1", policy.actor.mlp1[0], policy.actor.mlp1[1], (policy.actor.mlp2[0],))
    assert parts[-1].consumers == (policy.critic.q2[4],)
    channels = policy.encoder_channel_parts()
    if policy_class is MlpPolicy:
        assert channels == []
    else:
        assert [p.name for p in channels] == list(LAYER_NAMES[1:5])  # cnn1..cnn4
        assert policy.feature_readers() == [policy.actor, policy.critic, policy.critic_target]
        assert channels[-1].consumers == (policy.actor.trunk[0], policy.critic.trunk[0], policy.critic_target.trunk[0])
        assert channels[-1].positions == policy.encoder.repr_dim // 32 and channels[-1].channels_last
        assert channels[0].consumers == (policy.encoder.cnn2[0],) and channels[0].positions == 1


class ToyPolicy(nn.Module):
    """Not a DrQ-v2 policy: an actor of two hidden layers and three Q networks, providing the parts."""

    def __init__(self):
        super().__init__()
        self.actor = nn.Sequential(nn.Linear(4, 8), nn.ReLU(), nn.Linear(8, 8), nn.ReLU(), nn.Linear(8, 2), nn.Tanh())
        self.critic = nn.ModuleList(
            nn.Sequential(nn.Linear(6, 8), nn.ReLU(), nn.Linear(8, 1)) for _ in range(3)
        )  # fmt: skip
        self._optimizers = [th.optim.Adam(net.parameters(), lr=1e-3) for net in (self.actor, self.critic)]

    @property
    def optimizers(self):
        return self._optimizers

    def named_layers(self):
        return {"mlp1": self.actor[1], "mlp2": self.actor[3], "action": self.actor[5]}

    def initialize_weights(self, module):
        for sub in module.modules():
            if isinstance(sub, nn.Linear):
                nn.init.orthogonal_(sub.weight)
                nn.init.zeros_(sub.bias)

    def online_networks(self):
        return {"actor": self.actor, "critic": self.critic}

    def target_networks(self):
        return {}

    def actor_modules(self):
        return [self.actor]

    def actor_mlp_modules(self):
        return [self.actor[2:]]

    def hidden_layer_parts(self):
        parts = sequential_hidden_parts("", list(self.actor))
        for k, head in enumerate(self.critic, start=1):
            parts += sequential_hidden_parts(f"q{k}.", list(head))
        return parts

    def encoder_channel_parts(self):
        return []

    def forward_hidden(self, observations, actions):
        self.actor(observations)
        for head in self.critic:
            head(th.cat([observations, actions], dim=-1))

    def set_training_mode(self, mode):
        self.train(mode)


class ToyModel:
    """A model that is no SB3 algorithm: a policy and a seed."""

    seed = 0

    def __init__(self):
        self.policy = ToyPolicy()


class Batch:
    def __init__(self, n=64):
        self.observations = th.randn(n, 4)
        self.actions = th.rand(n, 2) * 2 - 1


def _train(model):
    """One Adam step on every parameter: every optimizer has state."""
    batch = Batch()
    for optimizer in model.policy.optimizers:
        optimizer.zero_grad()
    loss = model.policy.actor(batch.observations).sum()
    loss = loss + sum(head(th.cat([batch.observations, batch.actions], -1)).sum() for head in model.policy.critic)
    loss.backward()
    for optimizer in model.policy.optimizers:
        optimizer.step()


def test_the_interventions_act_on_any_policy_that_provides_the_parts():
    th.manual_seed(0)
    model = ToyModel()
    _train(model)
    policy = model.policy
    assert intervention_parts(model) is policy
    assert [layer.name for layer in hidden_layers(model)] == ["mlp1", "mlp2", "q1.mlp1", "q2.mlp1", "q3.mlp1"]
    assert encoder_channels(model) == []

    # reset_mlp: the actor's layers after the first one, their optimizer state forgotten; the rest kept
    first, critic = policy.actor[0].weight.detach().clone(), policy.critic[2][0].weight.detach().clone()
    result = apply_intervention(model, "reset_mlp")
    assert result.detail == "new actor MLP (mlp2..action), its optimizer state"
    assert th.equal(policy.actor[0].weight, first) and th.equal(policy.critic[2][0].weight, critic)
    assert policy.actor[0].weight in policy.optimizers[0].state
    assert policy.actor[2].weight not in policy.optimizers[0].state
    assert th.equal(policy.actor[2].bias, th.zeros(8))  # the policy's own initializer
    assert result.scalars["weights_changed"] == 8 * 8 + 8 + 8 * 2 + 2

    # shrink and perturb: the online networks it names
    result = apply_intervention(model, "shrink_perturb")
    assert "on the actor, critic;" in result.detail
    assert result.scalars["weights_changed"] == sum(p.numel() for p in policy.parameters())

    # ReDo: a dead unit of the third Q network recycled, its outgoing weight zeroed
    with th.no_grad():
        policy.critic[2][0].bias[3] = -1e3
    result = apply_intervention(model, "redo", samples=Batch())
    assert 3 in result.units["q3.mlp1"]
    assert policy.critic[2][0].bias[3] == 0.0 and policy.critic[2][2].weight[0, 3] == 0.0

    # a reset from scratch is the model's own
    with pytest.raises(TypeError, match=r"needs ToyModel.reset_from_scratch\(\)"):
        apply_intervention(model, "reset")


def test_sb3_models_get_an_adapter_and_other_models_a_type_error():
    from stable_baselines3 import TD3

    env = gym.make("Pendulum-v1")
    model = TD3("MlpPolicy", env, policy_kwargs=dict(net_arch=[8]), buffer_size=10)
    parts = intervention_parts(model)
    assert isinstance(parts, InterventionParts)
    assert list(parts.online_networks()) == ["actor", "critic"]
    assert list(parts.target_networks()) == ["target actor", "target critic"]
    # the details name what the adapter gives: the layers of layer_taps, the networks by name
    result = apply_intervention(model, "reset_mlp")
    assert result.detail == "new actor MLP (mlp1..action) and target actor, its optimizer state"
    result = apply_intervention(model, "reset")
    assert result.detail.startswith("new actor, critic, target actor, target critic and their optimizers; replay")

    class Other:
        policy = nn.Linear(1, 1)

    with pytest.raises(TypeError, match="The interventions work on DrQv2 and on SB3's TD3, DDPG and SAC; Other"):
        intervention_parts(Other())


class ToyPolicyWithTargetActor(ToyPolicy):
    """A target actor: the interventions keep it a copy of what they renew in the actor."""

    def __init__(self):
        super().__init__()
        self.actor_target = nn.Sequential(*(nn.Linear(4, 8), nn.ReLU(), nn.Linear(8, 8), nn.ReLU()))
        self.actor_target.append(nn.Linear(8, 2)).append(nn.Tanh())
        nn.init.constant_(self.actor_target[0].weight, 7.0)

    def target_networks(self):
        return {"target actor": self.actor_target}


def test_a_target_actor_gets_a_copy_of_the_renewed_actor_modules():
    th.manual_seed(0)
    model = ToyModel()
    model.policy = policy = ToyPolicyWithTargetActor()
    result = apply_intervention(model, "reset_mlp")  # renews actor[2:]: the target's copies follow, its first stays
    assert result.detail == "new actor MLP (mlp2..action) and target actor, its optimizer state"
    for online, copied in zip(policy.actor[2:].parameters(), policy.actor_target[2:].parameters()):
        assert th.equal(online, copied)
    assert th.equal(policy.actor_target[0].weight, th.full((8, 4), 7.0))
    assert result.scalars["weights_changed"] == 2 * (8 * 8 + 8 + 8 * 2 + 2)
