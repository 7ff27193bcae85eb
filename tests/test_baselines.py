"""SB3's TD3 and SAC on pixels, sized like DrQ-v2 (sb3_collapse.baselines)."""

import gymnasium as gym
import numpy as np
import pytest
from stable_baselines3 import SAC, TD3
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.noise import NormalActionNoise
from stable_baselines3.common.torch_layers import NatureCNN

from sb3_collapse.baselines import TD3_ACTION_NOISE, build_baseline
from sb3_collapse.drqv2.replay_buffer import FrameStackReplayBuffer
from sb3_collapse.monitoring import layer_parameters
from tests.random_env import RandomObservationEnv

SETTINGS = dict(learning_rate=3e-4, buffer_size=100, learning_starts=7, batch_size=16, seed=0)


def pixels(size=48):
    return RandomObservationEnv(gym.spaces.Box(0, 255, (9, size, size), np.uint8), gym.spaces.Box(-1, 1, (2,)))


@pytest.mark.parametrize("algorithm", ["td3", "sac"])
def test_baselines_have_drqv2_sizes_and_store_each_frame_once(algorithm):
    model = build_baseline(algorithm, pixels(), feature_dim=50, hidden_dim=96, gamma=0.9, frame_stack=3, **SETTINGS)
    assert isinstance(model, {"td3": TD3, "sac": SAC}[algorithm])
    assert (model.learning_rate, model.buffer_size, model.learning_starts, model.batch_size) == (3e-4, 100, 7, 16)
    assert model.gamma == 0.9 and model.tau == 0.005  # the discount is shared, tau is SB3's
    actor = model.actor
    assert isinstance(actor.features_extractor, NatureCNN) and actor.features_extractor.features_dim == 50
    assert not model.policy.share_features_extractor  # SB3's default: the critic has its own NatureCNN
    params = layer_parameters(model)
    assert [tuple(params[name][0].shape) for name in ("mlp0", "mlp1", "mlp2")] == [(50, 256), (96, 50), (96, 96)]
    assert [q[0].out_features for q in model.critic.q_networks] == [96, 96]
    buffer = model.replay_buffer
    assert isinstance(buffer, FrameStackReplayBuffer) and buffer.n_steps == 1 and buffer.gamma == 0.9
    if algorithm == "td3":
        assert isinstance(model.action_noise, NormalActionNoise)
        assert np.allclose(model.action_noise._sigma, TD3_ACTION_NOISE) and model.policy_delay == 2
    else:
        assert model.action_noise is None and model.ent_coef == "auto"
    plain = build_baseline(algorithm, pixels(), **SETTINGS)  # no frame stack: SB3's own buffer
    assert type(plain.replay_buffer) is ReplayBuffer


def test_baseline_errors_say_what_to_do():
    with pytest.raises(ValueError, match="algorithm must be one of td3, sac, got 'ppo'"):
        build_baseline("ppo", pixels(), **SETTINGS)
    with pytest.raises(ValueError, match="NatureCNN needs images of at least 36x36 pixels, got 32x32"):
        build_baseline("td3", pixels(32), **SETTINGS)
