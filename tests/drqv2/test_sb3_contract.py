"""SB3's contract: code written for SB3's TD3 runs with DrQv2 in its place, SB3's own test bodies included."""

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import DictReplayBuffer, NStepReplayBuffer, ReplayBuffer
from stable_baselines3.common.callbacks import BaseCallback, CallbackList, ConvertCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.envs import FakeImageEnv, SimpleMultiObsEnv
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.noise import ActionNoise, NormalActionNoise
from stable_baselines3.common.preprocessing import get_flattened_obs_dim
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from stable_baselines3.common.type_aliases import TrainFreq, TrainFrequencyUnit
from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize
from torch import nn

from sb3_collapse import DrQv2
from sb3_collapse.common.layers import LAYER_NAMES
from sb3_collapse.drqv2 import FrameStackReplayBuffer
from sb3_collapse.drqv2.encoders import DictEncoder, FeaturesExtractorEncoder
from sb3_collapse.drqv2.policies import MultiInputPolicy
from sb3_collapse.drqv2.rounds import TRANSITION
from sb3_collapse.drqv2.sb3_compat import DictNStepReplayBuffer, combine_callbacks
from sb3_collapse.errors import ParameterError, SpaceError
from sb3_collapse.run.config import TrainConfig, drqv2_kwargs
from tests.random_env import RandomObservationEnv

th.set_num_threads(1)

SMALL = dict(buffer_size=300, learning_starts=10, batch_size=8, seed=0)
ACTIONS = spaces.Box(-1.0, 1.0, (2,), np.float32)
PIXELS = spaces.Box(0, 255, (3, 36, 36), np.uint8)
POLICIES = ("MlpPolicy", "CnnPolicy", "MultiInputPolicy")


def dict_space(state_dim=4, size=36):
    return spaces.Dict(
        {"pixels": spaces.Box(0, 255, (3, size, size), np.uint8), "state": spaces.Box(-1, 1, (state_dim,), np.float32)}
    )


def make_env(policy, other_shape=False):
    """Pendulum for MlpPolicy; small random image and dict envs for the others (``other_shape``: another obs shape)."""
    if policy == "MlpPolicy":
        if other_shape:
            return RandomObservationEnv(spaces.Box(-1, 1, (5,), np.float32), spaces.Box(-2, 2, (1,), np.float32))
        return gym.make("Pendulum-v1", max_episode_steps=20)
    if policy == "CnnPolicy":
        space = spaces.Box(0, 255, (3, 40, 40), np.uint8) if other_shape else PIXELS
        return RandomObservationEnv(space, ACTIONS, episode_length=20)
    return RandomObservationEnv(dict_space(5 if other_shape else 4), ACTIONS, episode_length=20)


def tiny(policy, **policy_kwargs):
    kwargs = dict(feature_dim=8, hidden_dim=16)
    if policy != "MlpPolicy":
        kwargs["encoder_kwargs"] = dict(channels=4)
    return {**kwargs, **policy_kwargs}


def model_for(policy, env=None, policy_kwargs=None, **kwargs):
    env = env if env is not None else make_env(policy)
    return DrQv2(policy, env, **{**SMALL, "policy_kwargs": tiny(policy, **(policy_kwargs or {})), **kwargs})


def sample_obs(model, n=None):
    space = model.observation_space
    if n is None:
        return space.sample()
    samples = [space.sample() for _ in range(n)]
    if isinstance(space, spaces.Dict):
        return {key: np.stack([s[key] for s in samples]) for key in space.spaces}
    return np.stack(samples)


def params_equal(a, b):
    return all(th.equal(x, y) for x, y in zip(a.policy.state_dict().values(), b.policy.state_dict().values()))


# ----------------------------------------------------------------------------- 1. callbacks


class Count(BaseCallback):
    def __init__(self):
        super().__init__()
        self.calls = 0

    def _on_step(self):
        self.calls += 1
        return True


def test_function_callback_as_sb3_converts_it():
    calls = []
    model = DrQv2("MlpPolicy", "Pendulum-v1", **SMALL, policy_kwargs=tiny("MlpPolicy"))
    model.learn(10, callback=lambda locals_, globals_: calls.append(1) or True)
    assert len(calls) == 10


@pytest.mark.parametrize("kind", ["function", "list", "callback_list", "none"])
def test_constructor_and_learn_callbacks_combine(kind):
    ctor, learned, calls = Count(), Count(), []

    def function(locals_, globals_):
        calls.append(locals_["self"].num_timesteps)
        return True

    given = {
        "function": function,
        "list": [function, learned],
        "callback_list": CallbackList([learned, ConvertCallback(function)]),
        "none": None,
    }[kind]
    model = model_for("MlpPolicy", callback=[ctor, function] if kind != "none" else ctor)
    model.learn(10, callback=given)
    assert ctor.calls == 10
    assert len(calls) == {"function": 20, "list": 20, "callback_list": 20, "none": 0}[kind]
    assert learned.calls == (10 if kind in ("list", "callback_list") else 0)


def test_a_function_returning_false_stops_learning():
    model = model_for("MlpPolicy")
    model.learn(50, callback=lambda locals_, globals_: locals_["self"].num_timesteps < 5)
    assert model.num_timesteps == 5


def test_combine_callbacks():
    assert combine_callbacks(None, None) is None
    one = Count()
    assert combine_callbacks(None, one) is one
    combined = combine_callbacks([one], lambda locals_, globals_: True)
    assert isinstance(combined, CallbackList) and len(combined.callbacks) == 2
    with pytest.raises(TypeError, match="BaseCallback, a function"):
        combine_callbacks(3)


# ----------------------------------------------------------------------------- 2. policy keywords


def test_default_architecture_is_drqv2s():
    model = DrQv2("CnnPolicy", make_env("CnnPolicy"), buffer_size=100)
    assert model.policy.actor_arch == [1024, 1024] and model.policy.critic_arch == [1024, 1024]
    assert model.policy.n_critics == 2 and model.critic.q_names == ["q1", "q2"]
    assert tuple(model.policy.named_layers()) == LAYER_NAMES
    explicit = DrQv2(
        "CnnPolicy",
        make_env("CnnPolicy"),
        buffer_size=100,
        policy_kwargs=dict(
            net_arch=[1024, 1024],
            n_critics=2,
            share_features_extractor=True,
            normalize_images=True,
            activation_fn=nn.ReLU,
        ),
    )
    shapes = {name: p.shape for name, p in model.policy.state_dict().items()}
    assert {name: p.shape for name, p in explicit.policy.state_dict().items()} == shapes


@pytest.mark.parametrize(
    ("net_arch", "actor", "critic"),
    [
        ([32, 16, 8], [32, 16, 8], [32, 16, 8]),
        (dict(pi=[12], qf=[20, 24]), [12], [20, 24]),
        ([], [], []),
    ],
)
def test_net_arch(net_arch, actor, critic):
    model = model_for("CnnPolicy", policy_kwargs=dict(net_arch=net_arch, hidden_dim=1024))
    linear = [m.out_features for m in model.actor.modules() if isinstance(m, nn.Linear)]
    assert linear == [8, *actor, 2]  # trunk (feature_dim 8), hidden layers, action
    head = [m.out_features for m in model.critic.q1 if isinstance(m, nn.Linear)]
    assert head == [*critic, 1]
    names = list(model.policy.named_layers())
    assert names == [
        "cnn0",
        "cnn1",
        "cnn2",
        "cnn3",
        "cnn4",
        "mlp0",
        *[f"mlp{k}" for k in range(1, len(actor) + 1)],
        "action",
    ]
    model.learn(20)
    assert model._n_updates > 0 and set(model.last_grad_norms) == set(names) - {"cnn0"}


def test_net_arch_refusals():
    for bad, match in [(dict(pi=[8]), "'pi'.*'qf'"), ([8, 0], "layer sizes"), ("big", "layer sizes")]:
        with pytest.raises(ParameterError, match=match):
            model_for("MlpPolicy", policy_kwargs=dict(net_arch=bad))
    with pytest.raises(ParameterError, match="pass one"):
        model_for("MlpPolicy", policy_kwargs=dict(net_arch=[8], hidden_dim=32))


@pytest.mark.parametrize("n_critics", [1, 3])
def test_n_critics(n_critics):
    model = model_for("MlpPolicy", policy_kwargs=dict(n_critics=n_critics))
    assert len(model.critic.q_networks) == n_critics == len(model.critic_target.q_networks)
    model.learn(30)
    assert model._n_updates > 0
    with pytest.raises(ParameterError, match="n_critics"):
        model_for("MlpPolicy", policy_kwargs=dict(n_critics=0))


def test_share_features_extractor():
    assert model_for("CnnPolicy", policy_kwargs=dict(share_features_extractor=True)).policy.share_features_extractor
    with pytest.raises(ParameterError, match="trained by the critic loss only") as error:
        model_for("CnnPolicy", policy_kwargs=dict(share_features_extractor=False))
    assert error.value.parameter == "policy_kwargs['share_features_extractor']"


def test_activation_fn():
    model = model_for("MlpPolicy", policy_kwargs=dict(activation_fn=nn.LeakyReLU))
    assert model.policy.activation == "leaky_relu" and isinstance(model.actor.mlp1[1], nn.LeakyReLU)
    with pytest.raises(ParameterError, match="nn.ReLU"):
        model_for("MlpPolicy", policy_kwargs=dict(activation_fn=nn.Tanh))


class SmallCnn(BaseFeaturesExtractor):
    def __init__(self, observation_space, features_dim=12):
        super().__init__(observation_space, features_dim)
        self.net = nn.Sequential(nn.Conv2d(observation_space.shape[0], 4, 8, stride=4), nn.ReLU(), nn.Flatten())
        with th.no_grad():
            n = self.net(th.zeros(1, *observation_space.shape)).shape[1]
        self.linear = nn.Linear(n, features_dim)
        self.inputs = []

    def forward(self, obs):
        self.inputs.append(obs.detach())
        return self.linear(self.net(obs))


def test_features_extractor_class_replaces_the_encoder():
    model = model_for(
        "CnnPolicy",
        policy_kwargs=dict(features_extractor_class=SmallCnn, features_extractor_kwargs=dict(features_dim=12)),
    )
    encoder = model.policy.encoder
    assert isinstance(encoder, FeaturesExtractorEncoder) and encoder.repr_dim == 12 and encoder.has_cnn
    assert model.actor.trunk[0].in_features == 12
    actor_params = {id(p) for p in model.actor.parameters()}
    assert not actor_params & {id(p) for p in encoder.parameters()}  # trained by the critic loss only
    before = [p.detach().clone() for p in encoder.parameters()]
    model.learn(20)
    assert any(not th.equal(b, p) for b, p in zip(before, encoder.parameters()))
    seen = encoder.extractor.inputs[-1]
    assert seen.dtype == th.float32 and 0.0 <= seen.min() and seen.max() <= 1.0  # SB3's preprocess_obs: / 255
    with pytest.raises(ParameterError, match="BaseFeaturesExtractor"):
        model_for("CnnPolicy", policy_kwargs=dict(features_extractor_class=nn.Linear))


def test_features_extractor_kwargs_alone_configure_drqv2s_encoder():
    model = model_for("CnnPolicy", policy_kwargs=dict(encoder_kwargs={}, features_extractor_kwargs=dict(channels=6)))
    assert model.encoder.cnn1[0].out_channels == 6


def test_float_images_with_normalize_images_false():
    space = spaces.Box(0.0, 1.0, (3, 36, 36), np.float32)
    model = model_for("CnnPolicy", env=RandomObservationEnv(space, ACTIONS), policy_kwargs=dict(normalize_images=False))
    obs = th.rand(2, 3, 36, 36)
    assert th.equal(model.encoder.cnn0(obs), obs)  # taken as they are
    model.learn(20)
    assert model._n_updates > 0
    with pytest.raises(SpaceError, match="normalize_images=False"):
        model_for("CnnPolicy", env=RandomObservationEnv(space, ACTIONS))


def test_custom_optimizer():
    model = model_for(
        "CnnPolicy", policy_kwargs=dict(optimizer_class=th.optim.SGD, optimizer_kwargs=dict(momentum=0.9))
    )
    assert all(type(opt) is th.optim.SGD and opt.defaults["momentum"] == 0.9 for opt in model.policy.optimizers)
    model.learn(20)
    model.reset_from_scratch()
    assert all(type(opt) is th.optim.SGD for opt in model.policy.optimizers)
    model.learn(20, reset_num_timesteps=False)


# ----------------------------------------------------------------------------- 3. algorithm keywords


class ConstantNoise(ActionNoise):
    def __call__(self):
        return np.array([0.25, -2.0], np.float32)


def test_action_noise_replaces_the_scheduled_gaussian():
    model = model_for("CnnPolicy", action_noise=ConstantNoise(), stddev_schedule=0.5)
    assert model.action_noise is not None
    model.learn(12)
    actions, buffer_actions = model._sample_action(model.learning_starts, model.action_noise)
    mean, _ = model.predict(model._last_obs, deterministic=True)
    np.testing.assert_allclose(buffer_actions, np.clip(mean + [0.25, -2.0], -1, 1), atol=1e-6)
    assert model.stddev_clip == 0.3 and model.current_stddev == 0.5  # the target smoothing noise stays DrQ-v2's
    model = model_for("MlpPolicy", action_noise=NormalActionNoise(np.zeros(1), 0.1 * np.ones(1)))
    model.learn(30)
    assert model._n_updates > 0


def test_gradient_steps_zero_collects_without_updating():
    model = model_for("MlpPolicy", gradient_steps=0)
    before = [p.detach().clone() for p in model.policy.parameters()]
    model.learn(40)
    assert model._n_updates == 0 and model.replay_buffer.size() == 40
    assert all(th.equal(b, p) for b, p in zip(before, model.policy.parameters()))
    with pytest.raises(ParameterError, match="gradient_steps"):
        model_for("MlpPolicy", gradient_steps=-2)


def test_optimize_memory_usage():
    with pytest.warns(UserWarning, match="optimize_memory_usage=True is ignored.*NStepReplayBuffer"):
        model = model_for("MlpPolicy", optimize_memory_usage=True)
    assert not model.optimize_memory_usage and not model.replay_buffer.optimize_memory_usage
    # SB3's ReplayBuffer supports it (without its handling of time limits, as in SB3)
    model = model_for(
        "MlpPolicy", optimize_memory_usage=True, n_steps=1, replay_buffer_kwargs=dict(handle_timeout_termination=False)
    )
    assert type(model.replay_buffer) is ReplayBuffer and model.replay_buffer.optimize_memory_usage
    model.learn(30)
    assert model._n_updates > 0
    with pytest.warns(UserWarning, match="FrameStackReplayBuffer already stores each frame once"):
        model_for(
            "CnnPolicy",
            env=RandomObservationEnv(spaces.Box(0, 255, (9, 36, 36), np.uint8), ACTIONS),
            optimize_memory_usage=True,
            replay_buffer_class=FrameStackReplayBuffer,
            replay_buffer_kwargs=dict(frame_stack=3),
        )


# ----------------------------------------------------------------------------- 4. observation spaces


def test_multi_input_policy():
    assert DrQv2.policy_aliases["MultiInputPolicy"] is MultiInputPolicy
    model = model_for("MultiInputPolicy")
    assert isinstance(model.encoder, DictEncoder) and isinstance(model.replay_buffer, DictNStepReplayBuffer)
    assert model.encoder.image_keys == ["pixels"] and model.encoder.vector_keys == ["state"]
    assert tuple(model.policy.named_layers()) == LAYER_NAMES
    assert model.encoder.repr_dim == model.encoder.pixel_encoders["pixels"].repr_dim + 4
    model.learn(30)
    assert model._n_updates > 0 and set(model.last_grad_norms) == set(LAYER_NAMES) - {"cnn0"}
    data = model.replay_buffer.sample(4)
    shifted = model.encoder.augment(data.observations, 4, th.tensor([[0, 0], [8, 8], [4, 4], [1, 7]]))
    assert th.equal(shifted["state"], data.observations["state"])  # vector keys are not augmented
    assert not th.equal(shifted["pixels"], data.observations["pixels"])
    assert th.equal(shifted["pixels"][2], data.observations["pixels"][2])  # shift (4, 4) with pad 4: identity
    assert type(model_for("MultiInputPolicy", n_steps=1).replay_buffer) is DictReplayBuffer


def test_multi_input_policy_on_sb3_env():
    env = SimpleMultiObsEnv(random_start=False, discrete_actions=False, channel_last=False)
    model = model_for("MultiInputPolicy", env=env)
    model.learn(20)
    assert model._n_updates > 0


def test_several_image_keys_name_their_layers():
    space = spaces.Dict({"front": PIXELS, "side": PIXELS, "joints": spaces.MultiBinary(3)})
    model = model_for("MultiInputPolicy", env=RandomObservationEnv(space, ACTIONS))
    assert "cnn1.front" in model.policy.named_layers() and "cnn4.side" in model.policy.named_layers()
    assert model.encoder.repr_dim == 2 * model.encoder.pixel_encoders["front"].repr_dim + 3
    model.learn(20)


def test_dict_n_step_buffer_equals_sb3_n_step_buffer():
    box = spaces.Box(-1, 1, (3,), np.float32)
    kwargs = dict(n_envs=2, n_steps=3, gamma=0.9)
    flat = NStepReplayBuffer(20, box, ACTIONS, **kwargs)
    nested = DictNStepReplayBuffer(20, spaces.Dict({"x": box}), ACTIONS, **kwargs)
    rng = np.random.default_rng(0)
    for _ in range(30):  # wraps around
        obs, next_obs = rng.random((2, 3), np.float32), rng.random((2, 3), np.float32)
        action, reward = rng.random((2, 2), np.float32), rng.random(2, np.float32)
        done = rng.random(2) < 0.2
        infos = [{"TimeLimit.truncated": bool(rng.random() < 0.2)} for _ in range(2)]
        flat.add(obs, next_obs, action, reward, done, infos)
        nested.add({"x": obs}, {"x": next_obs}, action, reward, done, infos)
    np.random.seed(1)
    expected = flat.sample(16)
    np.random.seed(1)
    got = nested.sample(16)
    for field in ("actions", "rewards", "dones", "discounts"):
        assert th.allclose(getattr(got, field), getattr(expected, field)), field
    assert th.equal(got.observations["x"], expected.observations)
    assert th.equal(got.next_observations["x"], expected.next_observations)


@pytest.mark.parametrize(
    ("space", "repr_dim"),
    [
        (spaces.Discrete(5), 5),
        (spaces.MultiDiscrete([3, 2]), 5),
        (spaces.MultiBinary(4), 4),
    ],
)
def test_discrete_observations_through_preprocess_obs(space, repr_dim):
    model = model_for("MlpPolicy", env=RandomObservationEnv(space, ACTIONS))
    assert model.encoder.repr_dim == repr_dim  # one-hot encodings
    model.learn(20)
    assert model._n_updates > 0
    action, _ = model.predict(space.sample(), deterministic=True)
    assert action.shape == (2,)


def test_observation_space_refusals():
    with pytest.raises(ValueError, match="MultiInputPolicy"):
        model_for("MlpPolicy", env=make_env("MultiInputPolicy"))
    with pytest.raises(SpaceError, match="MultiInputPolicy takes dict observations"):
        model_for("MultiInputPolicy", env=make_env("CnnPolicy"))


# ----------------------------------------------------------------------------- 5. error types


def test_unsupported_action_space_is_also_an_assertion_error():
    env = RandomObservationEnv(spaces.Box(-1, 1, (3,), np.float32), spaces.Discrete(3))
    for kind in (AssertionError, ParameterError, TypeError):
        with pytest.raises(kind, match="continuous actions"):
            DrQv2("MlpPolicy", env, **SMALL)
    env = RandomObservationEnv(spaces.Box(-1, 1, (3,), np.float32), spaces.Box(-np.inf, np.inf, (2,), np.float32))
    with pytest.raises(AssertionError, match="finite"):  # SB3's own assertion comes first
        DrQv2("MlpPolicy", env, **SMALL)


@pytest.mark.skipif(th.cuda.is_available(), reason="the refusal is for machines without a GPU")
def test_cuda_without_gpu_is_refused():
    with pytest.raises(ParameterError, match="torch sees none"):
        model_for("MlpPolicy", device="cuda")


# ----------------------------------------------------------------------------- 6. the rest of SB3's contract


@pytest.mark.parametrize("policy", POLICIES)
def test_save_load_parameters_and_replay_buffer(policy, tmp_path):
    model = model_for(policy)
    model.learn(30)
    obs = sample_obs(model, 3)
    expected, _ = model.predict(obs, deterministic=True)
    model.save(tmp_path / "model.zip")
    model.save_replay_buffer(tmp_path / "buffer.pkl")

    without_env = DrQv2.load(tmp_path / "model.zip")
    assert without_env.get_env() is None
    np.testing.assert_array_equal(without_env.predict(obs, deterministic=True)[0], expected)
    for kind in (ValueError, AssertionError):  # SB3 asserts
        with pytest.raises(kind, match="needs an environment"):
            without_env.learn(10)

    loaded = DrQv2.load(tmp_path / "model.zip", env=make_env(policy), custom_objects={"learning_rate": 3e-4})
    assert loaded.learning_rate == 3e-4 and loaded.lr_schedule(1.0) == 3e-4
    assert params_equal(loaded, model) and loaded.num_timesteps == 30
    loaded.load_replay_buffer(tmp_path / "buffer.pkl")
    assert type(loaded.replay_buffer) is type(model.replay_buffer)
    assert loaded.replay_buffer.size() == model.replay_buffer.size() == 30
    loaded.learn(10, reset_num_timesteps=False)
    assert loaded.num_timesteps == 40

    # get_parameters / set_parameters
    fresh = model_for(policy, seed=1)
    assert not params_equal(fresh, model)
    parameters = model.get_parameters()
    assert {"policy", "actor.optimizer", "critic.optimizer"} <= set(parameters)
    fresh.set_parameters(parameters, exact_match=True)
    assert params_equal(fresh, model)
    np.testing.assert_array_equal(fresh.predict(obs, deterministic=True)[0], expected)


@pytest.mark.parametrize("policy", POLICIES)
def test_set_env(policy):
    model = model_for(policy)
    model.set_env(DummyVecEnv([lambda: make_env(policy)]))
    model.learn(10)
    with pytest.raises(ValueError, match="spaces do not match"):
        model.set_env(make_env(policy, other_shape=True))


@pytest.mark.parametrize("policy", POLICIES)
def test_predict_shapes(policy):
    model = model_for(policy)
    single = sample_obs(model)
    for deterministic in (True, False):
        action, state = model.predict(single, deterministic=deterministic)
        assert action.shape == (2,) or (policy == "MlpPolicy" and action.shape == (1,))
        assert state is None
        actions, _ = model.predict(sample_obs(model, 4), deterministic=deterministic)
        assert actions.shape[0] == 4 and actions.shape[1:] == action.shape
        assert model.action_space.contains(actions[0].astype(np.float32))
    actions, state = model.predict(
        sample_obs(model, 2), state=None, episode_start=np.array([True, False]), deterministic=True
    )
    assert actions.shape[0] == 2 and state is None


@pytest.mark.parametrize("policy", POLICIES)
def test_evaluate_policy(policy):
    model = model_for(policy)
    mean, std = evaluate_policy(model, model.get_env(), n_eval_episodes=2)
    assert np.isfinite(mean) and np.isfinite(std)


@pytest.mark.parametrize("policy", POLICIES)
def test_seeded_runs_are_identical(policy):
    runs = []
    for _ in range(2):
        model = model_for(policy, seed=7)
        model.learn(24)
        runs.append(model)
    assert runs[0]._n_updates > 0 and params_equal(*runs)


@pytest.mark.parametrize("policy", POLICIES)
def test_tensorboard_folder_and_learning_twice(policy, tmp_path):
    model = model_for(policy, tensorboard_log=str(tmp_path))
    model.learn(12)
    assert (tmp_path / "DrQv2_1").is_dir()
    model.learn(12, reset_num_timesteps=False)
    assert model.num_timesteps == 24 and sorted(p.name for p in tmp_path.iterdir()) == ["DrQv2_1"]
    model.learn(12)
    assert model.num_timesteps == 12 and sorted(p.name for p in tmp_path.iterdir()) == ["DrQv2_1", "DrQv2_2"]


def test_vec_normalize():
    env = VecNormalize(DummyVecEnv([lambda: make_env("MlpPolicy")]), gamma=0.99)
    model = model_for("MlpPolicy", env=env)
    model.learn(40)
    assert model._n_updates > 0 and model.get_vec_normalize_env() is env
    assert env.obs_rms.count > 1


def test_fake_image_env():
    env = FakeImageEnv(action_dim=2, screen_height=36, screen_width=36, n_channels=3, discrete=False)
    model = model_for("CnnPolicy", env=env)  # channel-last: SB3 transposes it (VecTransposeImage)
    assert model.observation_space.shape == (3, 36, 36)
    model.learn(20)
    assert model._n_updates > 0


# ----------------------------------------------------------------------------- 7. SB3's own test bodies


def sized(policy, **kwargs):
    """``tiny(policy)`` without ``feature_dim``, for SB3's size keywords."""
    policy_kwargs = tiny(policy)
    del policy_kwargs["feature_dim"]
    return {**policy_kwargs, **kwargs}


@pytest.mark.parametrize(
    ("policy", "key"),
    [("CnnPolicy", "features_dim"), ("MlpPolicy", "features_dim"), ("MultiInputPolicy", "cnn_output_dim")],
)
def test_sb3_feature_sizes_set_the_trunks(policy, key, tmp_path):
    # SB3's test_cnn.py / test_dict_env.py: policy_kwargs=dict(features_extractor_kwargs=dict(features_dim=32)) ...
    model = DrQv2(policy, make_env(policy), **SMALL, policy_kwargs=sized(policy, features_extractor_kwargs={key: 12}))
    assert model.policy.feature_dim == 12
    for network in (model.actor, model.critic, model.critic_target):
        assert network.trunk[0].out_features == 12 and network.trunk[0].in_features == model.encoder.repr_dim
    assert model.critic.q1[0].in_features == 12 + model.action_space.shape[0]
    model.learn(20)
    assert model._n_updates > 0
    model.save(tmp_path / "model.zip")
    loaded = DrQv2.load(tmp_path / "model.zip")
    assert loaded.actor.trunk[0].out_features == 12 and params_equal(loaded, model)


def test_transplant_reads_sb3_feature_sizes(tmp_path):
    source = DrQv2(
        "CnnPolicy",
        make_env("CnnPolicy"),
        **SMALL,
        policy_kwargs=sized("CnnPolicy", features_extractor_kwargs=dict(features_dim=12)),
    )
    source.save(tmp_path / "source.zip")
    target = DrQv2(
        "CnnPolicy",
        make_env("CnnPolicy"),
        **SMALL,
        policy_kwargs=sized("CnnPolicy", feature_dim=12),
        init_from={"mlp": tmp_path / "source.zip"},
    )
    assert th.equal(target.actor.trunk[0].weight, source.actor.trunk[0].weight)
    with pytest.raises(ValueError, match="trained with feature_dim=12, this model has feature_dim=50"):
        DrQv2(
            "CnnPolicy",
            make_env("CnnPolicy"),
            **SMALL,
            policy_kwargs=sized("CnnPolicy"),
            init_from={"mlp": tmp_path / "source.zip"},
        )


def test_sb3_feature_sizes_keep_the_other_encoder_kwargs_and_refuse_two_sizes():
    kwargs = sized("CnnPolicy", encoder_kwargs={}, features_extractor_kwargs=dict(features_dim=10, channels=6))
    model = DrQv2("CnnPolicy", make_env("CnnPolicy"), **SMALL, policy_kwargs=kwargs)
    assert model.encoder.cnn1[0].out_channels == 6 and model.actor.trunk[0].out_features == 10
    same = DrQv2("CnnPolicy", make_env("CnnPolicy"), **SMALL, policy_kwargs={**kwargs, "feature_dim": 10})
    assert same.policy.feature_dim == 10
    for bad, match in [
        (dict(feature_dim=16, features_extractor_kwargs=dict(features_dim=12)), "feature_dim=16.*pass one"),
        (dict(features_extractor_kwargs=dict(features_dim=12, cnn_output_dim=8)), "pass one"),
        (dict(features_extractor_kwargs=dict(features_dim=0)), r"\['features_dim'\] must be an integer >= 1"),
    ]:
        with pytest.raises(ParameterError, match=match) as error:
            DrQv2("CnnPolicy", make_env("CnnPolicy"), **SMALL, policy_kwargs=bad)
        assert error.value.parameter == "policy_kwargs['features_extractor_kwargs']"


class FlattenBatchNormDropoutExtractor(BaseFeaturesExtractor):
    """SB3's, from tests/test_train_eval_mode.py."""

    def __init__(self, observation_space):
        super().__init__(observation_space, get_flattened_obs_dim(observation_space))
        self.flatten = nn.Flatten()
        self.batch_norm = nn.BatchNorm1d(self._features_dim)
        self.dropout = nn.Dropout(0.5)

    def forward(self, observations):
        return self.dropout(self.batch_norm(self.flatten(observations)))


def batch_norm_stats(model):
    """SB3's ``clone_sac_batch_norm_stats``: the actor's, the critic's and the target critic's extractor."""
    stats = []
    for network in (model.actor, model.critic, model.critic_target):
        batch_norm = network.features_extractor.batch_norm
        stats += [batch_norm.bias.clone(), batch_norm.running_mean.clone()]
    return stats


def batch_norm_model(**kwargs):
    policy_kwargs = dict(net_arch=[16, 16], features_extractor_class=FlattenBatchNormDropoutExtractor)
    return DrQv2(
        "MlpPolicy", "Pendulum-v1", policy_kwargs=policy_kwargs, seed=1, buffer_size=300, batch_size=8, **kwargs
    )


def test_sb3_batch_norm_collect_rollouts_changes_nothing():
    # SB3's test_offpolicy_collect_rollout_batch_norm
    model = batch_norm_model(learning_starts=10, gradient_steps=0, train_freq=1)
    before = batch_norm_stats(model)
    model.learn(total_timesteps=100)
    assert all(th.isclose(a, b).all() for a, b in zip(before, batch_norm_stats(model), strict=True))


def test_sb3_predict_with_dropout_batch_norm():
    # SB3's test_predict_with_dropout_batch_norm
    model = batch_norm_model(learning_starts=0, verbose=1)
    before = batch_norm_stats(model)
    observation = model.get_env().reset()
    first_prediction, _ = model.predict(observation, deterministic=True)
    for _ in range(5):
        prediction, _ = model.predict(observation, deterministic=True)
        np.testing.assert_allclose(first_prediction, prediction)
    assert all(th.isclose(a, b).all() for a, b in zip(before, batch_norm_stats(model), strict=True))


def test_sb3_train_with_batch_norm():
    # SB3's test_td3_train_with_batch_norm (no actor target: DrQ-v2 has none)
    model = batch_norm_model(learning_starts=0, tau=0)
    bias, running_mean, *_ = batch_norm_stats(model)
    model.learn(total_timesteps=60)
    after = batch_norm_stats(model)
    assert ~th.isclose(bias, after[0]).all() and ~th.isclose(running_mean, after[1]).all()  # trained by the critic
    # the critic and the target critic read the same extractor: its running statistics are the critic's
    assert th.equal(after[3], after[5]) and th.equal(after[1], after[3])


@pytest.mark.parametrize("policy", POLICIES)
def test_features_extractor_is_the_shared_encoder_once(policy, tmp_path):
    model = model_for(policy)
    keys = set(model.policy.state_dict())
    for network in (model.actor, model.critic, model.critic_target):
        assert network.features_extractor is model.encoder
    assert not any("features_extractor" in key for key in keys)
    assert {key.split(".")[0] for key in keys} <= {"encoder", "actor", "critic", "critic_target"}
    # each parameter in one optimizer, once
    optimized = [
        id(p) for optimizer in model.policy.optimizers for group in optimizer.param_groups for p in group["params"]
    ]
    trained = {id(p) for p in model.policy.parameters()} - {id(p) for p in model.critic_target.parameters()}
    assert len(optimized) == len(set(optimized)) and set(optimized) == trained
    assert not {id(p) for p in model.actor.parameters()} & {id(p) for p in model.encoder.parameters()}
    obs = (
        th.as_tensor(sample_obs(model, 3))
        if policy != "MultiInputPolicy"
        else {key: th.as_tensor(value) for key, value in sample_obs(model, 3).items()}
    )
    features = model.policy.extract_features(obs, model.critic.features_extractor)
    assert th.equal(features, model.encoder(obs)) and features.shape == (3, model.encoder.repr_dim)
    with pytest.raises(ValueError, match="one encoder"):
        model.policy.extract_features(obs, nn.Linear(2, 2))
    model.learn(20)
    model.save(tmp_path / "model.zip")
    loaded = DrQv2.load(tmp_path / "model.zip", env=make_env(policy))
    assert set(loaded.policy.state_dict()) == keys and params_equal(loaded, model)
    assert loaded.actor.features_extractor is loaded.encoder is loaded.critic_target.features_extractor
    loaded.reset_from_scratch()
    assert loaded.actor.features_extractor is loaded.encoder and loaded.critic.features_extractor is loaded.encoder


def test_features_extractor_of_a_users_class_is_the_users_module():
    model = batch_norm_model(learning_starts=0)
    assert isinstance(model.actor.features_extractor, FlattenBatchNormDropoutExtractor)
    assert model.actor.features_extractor is model.encoder.extractor is model.critic_target.features_extractor


class RolloutStarts(BaseCallback):
    def __init__(self):
        super().__init__()
        self.starts = []

    def _on_rollout_start(self):
        self.starts.append((self.model.num_timesteps, self.model._n_updates))

    def _on_step(self):
        return True


@pytest.mark.parametrize("policy", POLICIES)
def test_sb3_train_freq_counts_steps_of_every_env(policy):
    # SB3's test_offpolicy_multi_env: 3 steps x 2 envs collect 6 transitions, then gradient_steps updates
    env = DummyVecEnv([lambda: make_env(policy)] * 2)
    log = RolloutStarts()
    model = model_for(policy, env=env, learning_starts=6, train_freq=3)
    model.learn(total_timesteps=24, callback=log)
    assert [t for t, _ in log.starts] == [0, 6, 12, 18] and model.num_timesteps == 24
    assert [u for _, u in log.starts] == [0, 0, 1, 2] and model._n_updates == 3  # none at 6 (not > learning_starts)
    # gradient_steps=-1: as many updates as transitions collected
    model = model_for(policy, env=env, learning_starts=0, train_freq=3, gradient_steps=-1)
    model.learn(total_timesteps=3)
    assert model.logger.name_to_value["train/n_updates"] == 3 * env.num_envs
    # DrQ-v2's ratio: one update per 3 transitions summed over the envs
    model = model_for(policy, env=env, learning_starts=6, train_freq=(3, "transition"))
    log = RolloutStarts()
    model.learn(total_timesteps=24, callback=log)
    assert [t for t, _ in log.starts] == [0, 4, 6, 10, 12, 16, 18, 22] and model._n_updates == 24 // 3 - 6 // 3


def test_sb3_offpolicy_multi_env_body():
    # SB3's test_offpolicy_multi_env for TD3, as it is (Pendulum, TimeLimit 50, 2 envs)
    def make_env():
        return gym.wrappers.TimeLimit(gym.make("Pendulum-v1"), 50)

    env = make_vec_env(make_env, n_envs=2)
    kwargs = dict(action_noise=NormalActionNoise(np.zeros(1), 0.1 * np.ones(1)), batch_size=8)
    policy_kwargs = dict(net_arch=[64], n_critics=1)
    model = DrQv2("MlpPolicy", env, policy_kwargs=policy_kwargs, learning_starts=100, buffer_size=10000, verbose=0,
                  train_freq=5, **kwargs)  # fmt: skip
    model.learn(total_timesteps=150)
    assert model._n_updates == 5  # after the rounds of 10 transitions ending at 110, 120, ..., 150
    train_freq = 3
    model = DrQv2("MlpPolicy", env, policy_kwargs=policy_kwargs, learning_starts=0, buffer_size=10000, verbose=0,
                  train_freq=train_freq, gradient_steps=-1, **kwargs)  # fmt: skip
    model.learn(total_timesteps=train_freq)
    assert model.logger.name_to_value["train/n_updates"] == train_freq * env.num_envs


def test_train_freq_units_are_checked_and_saved(tmp_path):
    with pytest.raises(ParameterError, match="train_freq must be n or .*'transition'") as error:
        model_for("MlpPolicy", train_freq=(2, "transitions"))
    assert error.value.parameter == "train_freq"
    model = model_for("MlpPolicy")
    assert model.train_freq == TrainFreq(2, TRANSITION)  # the default: DrQ-v2's ratio
    model.save(tmp_path / "default.zip")
    assert DrQv2.load(tmp_path / "default.zip").train_freq == TrainFreq(2, TRANSITION)
    model = model_for("MlpPolicy", train_freq=3)
    assert model.train_freq == TrainFreq(3, TrainFrequencyUnit.STEP)
    model.save(tmp_path / "sb3.zip")
    assert DrQv2.load(tmp_path / "sb3.zip").train_freq == TrainFreq(3, TrainFrequencyUnit.STEP)
    assert model_for("MlpPolicy", train_freq=[4, "transition"]).train_freq == TrainFreq(4, TRANSITION)  # rl_zoo3's YAML
    given = TrainFreq(2, TrainFrequencyUnit.EPISODE)
    assert model_for("MlpPolicy", train_freq=given).train_freq == given


def test_train_cli_keeps_drqv2s_ratio():
    config = TrainConfig(env="walker-walk", n_envs=2, train_freq=2).resolve()
    assert drqv2_kwargs(config)["train_freq"] == (2, "transition")


@pytest.mark.parametrize("policy", POLICIES)
def test_sb3_identity_warmup_is_visible(policy, capsys):
    # SB3's test_identity.py trains TD3 400 steps with learning_starts left at its default (TD3's 100)
    model = DrQv2(policy, make_env(policy), buffer_size=500, batch_size=8, policy_kwargs=tiny(policy), verbose=1)
    assert model.learning_starts == 2000  # DrQ-v2's
    model.learn(40)
    assert model._n_updates == 0
    out = capsys.readouterr().out
    assert (
        "DrQv2: updates start after 2,000 transitions of uniform random actions (learning_starts), 2,000 from now"
        in out
    )
    model.learning_starts = 30
    model.learn(20, reset_num_timesteps=False)
    out = capsys.readouterr().out
    assert "DrQv2: updates start at transition 42 (learning_starts=30)" in out and model._n_updates > 0
    assert "updates start after" not in out  # the warm-up (30) is over at 40
    model.learn(10, reset_num_timesteps=False)
    assert "updates start" not in capsys.readouterr().out  # said once
    quiet = DrQv2(policy, make_env(policy), **SMALL, policy_kwargs=tiny(policy))
    quiet.learn(20)
    assert quiet._n_updates > 0 and capsys.readouterr().out == ""


@pytest.mark.parametrize(
    ("algorithm", "kwargs", "policy"),
    [
        ("TD3", {}, "td3.policies.TD3Policy"),
        ("SAC", {}, "sac.policies.SACPolicy"),
        ("DDPG", {}, "td3.policies.TD3Policy"),  # SB3's DDPG saves TD3's policy: told apart by its settings
        ("TD3", {"policy_delay": 1, "target_noise_clip": 0.1}, "td3.policies.TD3Policy"),
    ],
)
def test_loading_another_sb3_algorithms_zip_names_it_and_what_loads_it(tmp_path, algorithm, kwargs, policy):
    import stable_baselines3 as sb3

    env = RandomObservationEnv(spaces.Box(-1.0, 1.0, (4,), np.float32), ACTIONS)
    model = getattr(sb3, algorithm)("MlpPolicy", env, buffer_size=10, policy_kwargs=dict(net_arch=[4]), **kwargs)
    model.save(tmp_path / "other.zip")
    with pytest.raises(ParameterError) as raised:
        DrQv2.load(tmp_path / "other")  # no AttributeError from SB3's load on another policy
    message = str(raised.value)
    assert isinstance(raised.value, ValueError) and raised.value.parameter == "path" and "\n" not in message
    assert message == (
        f"path {str(tmp_path / 'other')!r} holds a {algorithm} checkpoint (policy stable_baselines3.{policy}), "
        f"not a DrQv2 one: load it with stable_baselines3.{algorithm}.load."
    )


def test_the_callers_replay_buffer_kwargs_are_not_changed_and_a_setting_of_another_buffer_is_named():
    """DrQv2 filled its defaults (n_steps, gamma, frame_stack) into the caller's dict, so that a loop reusing one dict
    trained later models with the first one's n-step returns and discount; sampling with an SB3 buffer was a raw
    TypeError."""
    shared = {}
    first = model_for("MlpPolicy", n_steps=5, gamma=0.9, replay_buffer_kwargs=shared)
    assert shared == {} and first.replay_buffer_kwargs == {"n_steps": 5, "gamma": 0.9}
    second = model_for("MlpPolicy", replay_buffer_kwargs=shared)
    assert (second.replay_buffer.n_steps, second.replay_buffer.gamma) == (3, 0.99)
    pixels = RandomObservationEnv(spaces.Box(0, 255, (9, 36, 36), np.uint8), ACTIONS)
    stacked = {"sampling": "sb3", "frame_stack": 3}
    model = model_for("CnnPolicy", env=pixels, replay_buffer_class=FrameStackReplayBuffer, replay_buffer_kwargs=stacked)
    assert stacked == {"sampling": "sb3", "frame_stack": 3} and model.replay_buffer_kwargs["n_steps"] == 3

    for policy in ("MlpPolicy", "MultiInputPolicy"):
        with pytest.raises(ParameterError, match=r"^replay_buffer_kwargs\['sampling'\] is a setting of FrameStack"):
            model_for(policy, replay_buffer_kwargs=dict(sampling="drqv2"))
    with pytest.raises(ParameterError, match=r"DictNStepReplayBuffer is the replay buffer here \(policy Multi"):
        model_for("MultiInputPolicy", replay_buffer_kwargs=dict(sampling="drqv2"))
    with pytest.raises(ParameterError, match=r"^replay_buffer_kwargs\['capacity'\] is not a keyword of NStepReplay"):
        model_for("MlpPolicy", replay_buffer_kwargs=dict(capacity=10))
    with pytest.raises(ParameterError, match=r"^replay_buffer_kwargs\['device'\] is set by the model \(device\)"):
        model_for("MlpPolicy", replay_buffer_kwargs=dict(device="cpu"))


def test_load_of_an_sb3_zip_given_as_a_file_object_names_its_algorithm(tmp_path):
    """DrQv2.load of a TD3 zip given as a file object raised a raw AttributeError: the check of a path covers
    streams (read from where the caller left them, and put back there)."""
    import io

    from stable_baselines3 import TD3

    env = make_env("MlpPolicy")
    TD3("MlpPolicy", env, buffer_size=10).save(tmp_path / "td3.zip")
    stream = io.BytesIO(b"head" + (tmp_path / "td3.zip").read_bytes())
    stream.seek(4)
    with pytest.raises(ParameterError, match=r"^path \(a BytesIO file object\) holds a TD3 checkpoint .*TD3\.load\."):
        DrQv2.load(stream)
    assert stream.tell() == 4
    with open(tmp_path / "td3.zip", "rb") as file, pytest.raises(ParameterError, match="BufferedReader file object"):
        DrQv2.load(file)
    saved = io.BytesIO()
    model_for("MlpPolicy").save(saved)
    saved.seek(0)
    assert isinstance(DrQv2.load(saved), DrQv2)
