import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from torch import nn

from sb3_collapse.common.layers import LAYER_NAMES
from sb3_collapse.drqv2.encoders import FUSED_CONV_RELU, ConvReLU
from sb3_collapse.drqv2.policies import CnnPolicy, MlpPolicy, sample_action

PIXELS = spaces.Box(0, 255, (9, 84, 84), np.uint8)
ACTIONS = spaces.Box(-1.0, 1.0, (6,), np.float32)
STATES = spaces.Box(-np.inf, np.inf, (24,), np.float32)


def _lr(_progress):
    return 1e-4


@pytest.fixture(scope="module")
def policy():
    th.manual_seed(0)
    return CnnPolicy(PIXELS, ACTIONS, _lr)


def test_encoder_architecture(policy):
    convs = [m for m in policy.encoder.modules() if isinstance(m, nn.Conv2d)]
    assert [(c.in_channels, c.out_channels, c.kernel_size, c.stride, c.padding) for c in convs] == [
        (9, 32, (3, 3), (2, 2), (0, 0)),
        (32, 32, (3, 3), (1, 1), (0, 0)),
        (32, 32, (3, 3), (1, 1), (0, 0)),
        (32, 32, (3, 3), (1, 1), (0, 0)),
    ]
    assert policy.encoder.repr_dim == 39_200
    obs = th.randint(0, 256, (2, 9, 84, 84), dtype=th.uint8)
    assert policy.encoder(obs).shape == (2, 39_200)


def test_encoder_normalizes_pixels(policy):
    out = policy.encoder.cnn0(th.tensor([[[[0, 255]]]], dtype=th.uint8))
    assert th.allclose(out.flatten(), th.tensor([-0.5, 0.5]))


def _linear_shapes(module):
    return [(m.in_features, m.out_features) for m in module.modules() if isinstance(m, nn.Linear)]


def test_actor_architecture(policy):
    actor = policy.actor
    assert _linear_shapes(actor) == [(39_200, 50), (50, 1024), (1024, 1024), (1024, 6)]
    assert isinstance(actor.trunk[1], nn.LayerNorm) and isinstance(actor.trunk[2], nn.Tanh)
    assert isinstance(actor.mlp1[1], nn.ReLU) and isinstance(actor.mlp2[1], nn.ReLU)
    assert isinstance(actor.action[1], nn.Tanh)


def test_critic_architecture(policy):
    critic = policy.critic
    assert _linear_shapes(critic.trunk) == [(39_200, 50)]
    for head in (critic.q1, critic.q2):
        assert _linear_shapes(head) == [(56, 1024), (1024, 1024), (1024, 1)]
    features = th.randn(3, 39_200)
    q1, q2 = critic(features, th.zeros(3, 6))
    assert q1.shape == q2.shape == (3, 1)


def test_target_critic_starts_equal_and_is_separate(policy):
    for (name, param), target in zip(policy.critic.named_parameters(), policy.critic_target.parameters()):
        assert th.equal(param, target), name
        assert param.data_ptr() != target.data_ptr()
        assert not target.requires_grad
    # No target encoder, no target actor.
    assert not hasattr(policy, "actor_target") and not hasattr(policy, "encoder_target")


def test_orthogonal_init_and_zero_biases(policy):
    for module in policy.modules():
        if isinstance(module, nn.Linear):
            weight = module.weight.detach()
            gram = weight @ weight.T if weight.shape[0] <= weight.shape[1] else weight.T @ weight
            assert th.allclose(gram, th.eye(gram.shape[0]), atol=1e-4)
            assert th.count_nonzero(module.bias) == 0
        elif isinstance(module, nn.Conv2d):
            weight = module.weight.detach().reshape(module.out_channels, -1)
            assert th.allclose(weight @ weight.T, 2.0 * th.eye(module.out_channels), atol=1e-4)  # gain sqrt(2)
            assert th.count_nonzero(module.bias) == 0


def test_optimizers_cover_each_part_once(policy):
    assert policy.encoder.optimizer.param_groups[0]["lr"] == 1e-4
    encoder_params = {id(p) for p in policy.encoder.parameters()}
    actor_params = {id(p) for p in policy.actor.parameters()}
    critic_params = {id(p) for p in policy.critic.parameters()}
    assert {id(p) for g in policy.encoder.optimizer.param_groups for p in g["params"]} == encoder_params
    assert {id(p) for g in policy.actor.optimizer.param_groups for p in g["params"]} == actor_params
    assert {id(p) for g in policy.critic.optimizer.param_groups for p in g["params"]} == critic_params


def test_named_layers_outputs(policy):
    layers = policy.named_layers()
    assert tuple(layers) == LAYER_NAMES
    outputs = {}
    handles = [
        m.register_forward_hook(lambda m, i, o, n=n: outputs.__setitem__(n, o.detach().clone()))
        for n, m in layers.items()
    ]
    obs = th.randint(0, 256, (4, 9, 84, 84), dtype=th.uint8)
    with th.no_grad():
        action = policy._predict(obs, deterministic=True)
    for handle in handles:
        handle.remove()
    shapes = {name: tuple(out.shape) for name, out in outputs.items()}
    assert shapes == {
        "cnn0": (4, 9, 84, 84),
        "cnn1": (4, 32, 41, 41),
        "cnn2": (4, 32, 39, 39),
        "cnn3": (4, 32, 37, 37),
        "cnn4": (4, 32, 35, 35),
        "mlp0": (4, 50),
        "mlp1": (4, 1024),
        "mlp2": (4, 1024),
        "action": (4, 6),
    }
    assert th.equal(outputs["action"], action)
    assert (outputs["mlp1"] >= 0).all() and (outputs["cnn4"] >= 0).all()
    assert list(layers["cnn0"].parameters()) == []


def test_deterministic_prediction_is_tanh_mean(policy):
    obs = th.randint(0, 256, (3, 9, 84, 84), dtype=th.uint8)
    with th.no_grad():
        features = policy.encoder(obs)
        h = policy.actor.mlp2(policy.actor.mlp1(policy.actor.trunk(features)))
        expected = th.tanh(policy.actor.action[0](h))
        assert th.allclose(policy._predict(obs, deterministic=True), expected, atol=1e-6)


def test_sample_action_noise_and_clip():
    th.manual_seed(0)
    mean = th.zeros(10_000, 2)
    assert sample_action(mean, std=0.1).std().item() == pytest.approx(0.1, rel=0.05)
    unclipped = sample_action(mean, std=1.0)
    assert unclipped.abs().max() < 1.0  # clamped to (-1, 1)
    assert unclipped.abs().max() > 0.99  # but the noise itself is not clipped
    clipped = sample_action(mean, std=1.0, clip=0.3)
    assert clipped.abs().max() <= 0.3 + 1e-6
    # Straight-through clamp: the gradient reaches the mean even at the bound.
    mean = th.full((4, 1), 0.99, requires_grad=True)
    sample_action(mean, std=1.0, clip=0.3).sum().backward()
    assert th.equal(mean.grad, th.ones_like(mean))


def test_mlp_policy_has_no_cnn():
    policy = MlpPolicy(STATES, ACTIONS, _lr)
    assert tuple(policy.named_layers()) == ("mlp0", "mlp1", "mlp2", "action")
    assert _linear_shapes(policy.actor)[0] == (24, 50)
    assert policy.encoder.optimizer is None
    assert policy._predict(th.zeros(2, 24), deterministic=True).shape == (2, 6)


def test_policy_kwargs_dims():
    policy = MlpPolicy(STATES, ACTIONS, _lr, feature_dim=100, hidden_dim=64)
    assert _linear_shapes(policy.actor) == [(24, 100), (100, 64), (64, 64), (64, 6)]


def test_cnn_policy_rejects_state_vectors():
    with pytest.raises(ValueError, match="CnnPolicy needs channel-first uint8 image"):
        CnnPolicy(STATES, ACTIONS, _lr)
    with pytest.raises(ValueError, match="CnnPolicy needs channel-first uint8 image"):
        CnnPolicy(spaces.Box(0, 255, (84, 84, 9), np.uint8), ACTIONS, _lr)


def test_mlp_policy_rejects_images():
    with pytest.raises(ValueError, match="use CnnPolicy"):
        MlpPolicy(PIXELS, ACTIONS, _lr)


def test_rejects_discrete_actions():
    with pytest.raises(TypeError, match="continuous actions"):
        MlpPolicy(STATES, spaces.Discrete(3), _lr)


def test_policy_save_load(tmp_path):
    policy = CnnPolicy(
        spaces.Box(0, 255, (9, 32, 32), np.uint8), spaces.Box(-1, 1, (2,), np.float32), _lr, hidden_dim=16
    )
    policy.save(tmp_path / "policy.pth")
    loaded = CnnPolicy.load(tmp_path / "policy.pth")
    obs = th.randint(0, 256, (3, 9, 32, 32), dtype=th.uint8)
    assert th.equal(policy._predict(obs, deterministic=True), loaded._predict(obs, deterministic=True))
    assert loaded.hidden_dim == 16


@pytest.mark.skipif(not FUSED_CONV_RELU, reason="this torch build has no oneDNN convolution with a fused ReLU")
@pytest.mark.parametrize("memory_format", [th.channels_last, th.contiguous_format])
@pytest.mark.parametrize("input_grad", [False, True])
def test_fused_conv_relu_equals_conv_then_relu(memory_format, input_grad):
    """The fused kernel gives the values and gradients of Conv2d then ReLU, exactly (this machine, these threads)."""
    th.manual_seed(0)
    fused, plain = ConvReLU(9, 32, stride=2), ConvReLU(9, 32, stride=2, fused=False)
    plain.load_state_dict(fused.state_dict())
    for layer in (fused, plain):
        layer.to(memory_format=memory_format)
    x = th.randn(4, 9, 30, 30).contiguous(memory_format=memory_format)
    outputs, grads = [], []
    for layer in (fused, plain):
        xi = x.clone().requires_grad_(input_grad)
        y = layer(xi)
        assert (type(y.grad_fn).__name__ == "_FusedConvReLUBackward") == layer.fused
        y.backward(th.linspace(-1, 1, y.numel()).view_as(y))
        outputs.append(y.detach())
        grads.append([xi.grad, layer[0].weight.grad, layer[0].bias.grad])
    assert (outputs[0] > 0).any() and (outputs[0] == 0).any()  # the ReLU is active somewhere, and not everywhere
    assert th.equal(outputs[0], outputs[1])
    for fused_grad, plain_grad in zip(*grads):
        assert (fused_grad is None) == (plain_grad is None) == (not input_grad and fused_grad is grads[0][0])
        if plain_grad is not None:
            assert th.equal(fused_grad, plain_grad)
    with th.no_grad():
        assert th.equal(fused(x), plain(x))


def test_encoder_named_layers_fire_their_hooks_with_the_fused_kernel(policy):
    seen = {}

    def hook(name):
        def record(_module, _args, output):
            seen[name] = tuple(output.shape)

        return record

    handles = [module.register_forward_hook(hook(name)) for name, module in policy.encoder.named_layers().items()]
    try:
        policy.encoder(th.randint(0, 256, (2, 9, 84, 84), dtype=th.uint8))
    finally:
        for handle in handles:
            handle.remove()
    assert seen == {"cnn0": (2, 9, 84, 84), "cnn1": (2, 32, 41, 41), "cnn2": (2, 32, 39, 39),
                    "cnn3": (2, 32, 37, 37), "cnn4": (2, 32, 35, 35)}
