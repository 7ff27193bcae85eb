"""Networks of DrQ-v2: pixel encoder, actor and twin critic, wrapped as an SB3 policy.

The layers are named as in :data:`sb3_collapse.common.layers.LAYER_NAMES` (``cnn0``..``cnn4``, ``mlp0``..``mlp2``,
``action``; the table is there), the vocabulary shared by the callbacks, the probe and the plots.

``activation="leaky_relu"`` (policy keyword argument) replaces every ReLU of the encoder, the actor and the critic
(``cnn1``..``cnn4``, ``mlp1``, ``mlp2``, the Q heads) with a Leaky-ReLU of negative slope ``leaky_relu_slope``
(PyTorch's default 0.01): the ablation of the paper's footnote 1, "We tried substituting all the ReLU with
Leaky-ReLU (Maas et al., 2013) where the neurons cannot die, but it did not resolve action collapse." The layers keep
their names.

:meth:`DrQv2Policy.named_layers` returns, for each name, the module whose forward output *is* that
activation and whose parameters are that layer's weights (``cnn0`` has none). ``MlpPolicy`` has no
``cnnK`` layers.
"""

from __future__ import annotations

import copy
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.preprocessing import is_image_space
from stable_baselines3.common.type_aliases import PyTorchObs, Schedule
from torch import nn

from sb3_collapse.common.layers import LayerParts, reinitialize, sequential_hidden_parts
from sb3_collapse.errors import ParameterError

ACTIVATIONS = ("relu", "leaky_relu")
"""The hidden activations of the networks: ReLU (DrQ-v2's) or Leaky-ReLU (the paper's footnote 1 ablation)."""

LEAKY_RELU_SLOPE = 0.01
"""Negative slope of the Leaky-ReLU: PyTorch's default (the paper does not give one; Maas et al., 2013 used 0.01)."""

ACTION_EPS = 1e-6
"""Sampled actions are clamped to ``[-1 + eps, 1 - eps]`` as in DrQ-v2's ``TruncatedNormal``."""


def check_activation(activation: str, leaky_relu_slope: float = LEAKY_RELU_SLOPE) -> None:
    """
    :param activation: one of :data:`ACTIVATIONS`
    :param leaky_relu_slope: the Leaky-ReLU's negative slope, in (0, 1)
    :raises ParameterError: for another activation or slope
    """
    if activation not in ACTIVATIONS:
        raise ParameterError("activation", f"activation must be one of {', '.join(ACTIVATIONS)}, got {activation!r}.")
    if isinstance(leaky_relu_slope, bool) or not 0.0 < leaky_relu_slope < 1.0:
        raise ParameterError(
            "leaky_relu_slope", f"leaky_relu_slope must be in (0, 1) (0 is a ReLU), got {leaky_relu_slope!r}."
        )


def hidden_activation(activation: str = "relu", leaky_relu_slope: float = LEAKY_RELU_SLOPE) -> nn.Module:
    """
    :param activation: ``"relu"`` or ``"leaky_relu"``
    :param leaky_relu_slope: negative slope of the Leaky-ReLU
    :return: a new in-place activation module: ``nn.ReLU`` or ``nn.LeakyReLU(leaky_relu_slope)``
    """
    check_activation(activation, leaky_relu_slope)
    if activation == "leaky_relu":
        return nn.LeakyReLU(leaky_relu_slope, inplace=True)
    return nn.ReLU(inplace=True)


def weight_init(module: nn.Module) -> None:
    """
    DrQ-v2's initialization: orthogonal weights (gain 1 for Linear, sqrt(2) for Conv), zero biases.
    LayerNorm keeps PyTorch's default (unit scale, zero shift).

    :param module: module to initialize in place (use with ``Module.apply``)
    """
    if isinstance(module, nn.Linear):
        nn.init.orthogonal_(module.weight.data)
        if module.bias is not None:
            module.bias.data.fill_(0.0)
    elif isinstance(module, (nn.Conv2d, nn.ConvTranspose2d)):
        nn.init.orthogonal_(module.weight.data, nn.init.calculate_gain("relu"))
        if module.bias is not None:
            module.bias.data.fill_(0.0)


class PixelNormalization(nn.Module):
    """
    ``cnn0``: uint8 pixels to floats in [-0.5, 0.5].

    :param channels_last: return the images in ``channels_last`` memory format (faster convolutions)
    """

    def __init__(self, channels_last: bool = True) -> None:
        super().__init__()
        self.channels_last = channels_last

    def forward(self, obs: th.Tensor) -> th.Tensor:
        if self.channels_last:
            obs = obs.contiguous(memory_format=th.channels_last)
        return obs.float().div_(255.0).sub_(0.5) if obs.dtype == th.uint8 else obs.float() / 255.0 - 0.5


def _fused_conv_relu_available() -> bool:
    """Whether this torch build has oneDNN's convolution with a fused ReLU (``torch.ops.mkldnn``, CPU)."""
    try:
        return th.backends.mkldnn.is_available() and hasattr(th.ops.mkldnn, "_convolution_pointwise")
    except (AttributeError, RuntimeError):
        return False


FUSED_CONV_RELU = _fused_conv_relu_available()
"""Whether :class:`ConvReLU` runs its convolution and ReLU as one oneDNN kernel on the CPU."""


class _FusedConvReLU(th.autograd.Function):
    """``relu(conv2d(x, weight, bias))`` as one oneDNN kernel forward; backward as autograd computes it."""

    @staticmethod
    def forward(ctx: Any, x: th.Tensor, weight: th.Tensor, bias: th.Tensor, conv: nn.Conv2d) -> th.Tensor:
        args = (list(conv.padding), list(conv.stride), list(conv.dilation), conv.groups)
        y = th.ops.mkldnn._convolution_pointwise(x, weight, bias, *args, "relu", [], "")
        ctx.save_for_backward(x, weight, y)
        ctx.args = args
        return y

    @staticmethod
    def backward(ctx: Any, grad_y: th.Tensor) -> tuple[th.Tensor | None, ...]:
        x, weight, y = ctx.saved_tensors
        padding, stride, dilation, groups = ctx.args
        grad_z = th.ops.aten.threshold_backward(grad_y, y, 0)
        grads = th.ops.aten.convolution_backward(
            grad_z, x, weight, [weight.shape[0]], stride, padding, dilation, False, [0, 0], groups,
            list(ctx.needs_input_grad[:3]),
        )
        return (*grads, None)


class ConvReLU(nn.Sequential):
    """
    ``Conv2d`` then ``ReLU`` (or Leaky-ReLU): one named layer (``cnn1``..``cnn4``), whose output is the activation
    after the ReLU.

    On the CPU, for float32 inputs, the two run as one oneDNN kernel (the convolution with a fused ReLU): the same
    values as running them one after the other (tested), without a second pass over the activation. Elsewhere
    (CUDA, other dtypes, under ``torch.compile``, which fuses by itself) it is the plain ``Sequential``; with
    a Leaky-ReLU (the fused kernel is ReLU only) too.

    :param in_channels: input channels
    :param out_channels: filters
    :param stride: stride of the 3x3 convolution (no padding)
    :param fused: run the two as one kernel where possible; ``False`` runs them one after the other everywhere
    :param activation: ``"relu"`` or ``"leaky_relu"`` (:func:`hidden_activation`)
    :param leaky_relu_slope: negative slope of the Leaky-ReLU
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        stride: int,
        fused: bool = True,
        activation: str = "relu",
        leaky_relu_slope: float = LEAKY_RELU_SLOPE,
    ) -> None:
        conv = nn.Conv2d(in_channels, out_channels, 3, stride=stride)
        super().__init__(conv, hidden_activation(activation, leaky_relu_slope))
        self.fused = fused and activation == "relu"

    def forward(self, x: th.Tensor) -> th.Tensor:
        conv = self[0]
        fusable = self.fused and x.device.type == "cpu" and x.dtype == conv.weight.dtype == th.float32
        if FUSED_CONV_RELU and fusable and not th.compiler.is_compiling():
            return _FusedConvReLU.apply(x, conv.weight, conv.bias, conv)
        return super().forward(x)


class PixelEncoder(nn.Module):
    """
    DrQ-v2's convolutional encoder: ``cnn0`` normalization, then four 3x3 convolutions with 32 channels
    (stride 2, then 1, 1, 1), no padding, ReLU after each; the output is flattened.
    Initialized with :func:`weight_init` at construction.

    With ``channels_last`` (the default) the convolutions run in ``channels_last`` memory format, faster on
    CPU (oneDNN) and GPU (cuDNN), and the output is flattened in (H, W, C) order, which is free in that format;
    otherwise in DrQ-v2's (C, H, W) order. The order only permutes the inputs of the trunks' first Linear
    layers, whose orthogonal initialization is invariant to it: the learning dynamics are the same.
    The ``cnnK`` activations (module outputs) are the same tensors either way.

    :param observation_space: channel-first ``uint8`` image space, e.g. ``Box(0, 255, (9, 84, 84), uint8)``
    :param channels: number of filters of every convolution
    :param channels_last: run the convolutions in ``channels_last`` memory format
    :param fused_relu: on the CPU, run each convolution and its ReLU as one kernel (:class:`ConvReLU`, same values;
        ignored with a Leaky-ReLU)
    :param activation: ``"relu"`` (DrQ-v2's) or ``"leaky_relu"`` after each convolution
    :param leaky_relu_slope: negative slope of the Leaky-ReLU
    """

    has_cnn = True

    def __init__(
        self,
        observation_space: spaces.Space,
        channels: int = 32,
        channels_last: bool = True,
        fused_relu: bool = True,
        activation: str = "relu",
        leaky_relu_slope: float = LEAKY_RELU_SLOPE,
    ) -> None:
        super().__init__()
        check_pixel_space(observation_space)
        for name, size in zip(("height", "width"), observation_space.shape[1:]):
            check_image_size(size, f"observation {name}")
        in_channels = observation_space.shape[0]
        self.cnn0 = PixelNormalization(channels_last)
        act = dict(fused=fused_relu, activation=activation, leaky_relu_slope=leaky_relu_slope)
        self.cnn1 = ConvReLU(in_channels, channels, stride=2, **act)  # type: ignore[arg-type]
        self.cnn2 = ConvReLU(channels, channels, stride=1, **act)  # type: ignore[arg-type]
        self.cnn3 = ConvReLU(channels, channels, stride=1, **act)  # type: ignore[arg-type]
        self.cnn4 = ConvReLU(channels, channels, stride=1, **act)  # type: ignore[arg-type]
        self.apply(weight_init)
        self.channels_last = channels_last
        if channels_last:
            self.to(memory_format=th.channels_last)
        self.repr_dim = channels * int(np.prod(_conv_output_size(observation_space.shape[1:])))

    def forward(self, obs: th.Tensor) -> th.Tensor:
        h = self.cnn4(self.cnn3(self.cnn2(self.cnn1(self.cnn0(obs)))))
        if self.channels_last:
            # (H, W, C) order: a free view of channels_last memory, where (C, H, W) order needs a copy.
            return h.permute(0, 2, 3, 1).flatten(1)
        return h.flatten(1)

    def named_layers(self) -> dict[str, nn.Module]:
        return {"cnn0": self.cnn0, "cnn1": self.cnn1, "cnn2": self.cnn2, "cnn3": self.cnn3, "cnn4": self.cnn4}


class StateEncoder(nn.Module):
    """
    Identity encoder for state vectors (``MlpPolicy``): the actor and critic trunks read the state directly.

    :param observation_space: 1-d ``Box`` of floats
    :param activation: unused (no layer), accepted so that every encoder takes the policy's activation
    :param leaky_relu_slope: unused
    """

    has_cnn = False

    def __init__(
        self, observation_space: spaces.Space, activation: str = "relu", leaky_relu_slope: float = LEAKY_RELU_SLOPE
    ) -> None:
        super().__init__()
        check_state_space(observation_space)
        self.repr_dim = int(observation_space.shape[0])
        self.apply(weight_init)

    def forward(self, obs: th.Tensor) -> th.Tensor:
        return obs.float()

    def named_layers(self) -> dict[str, nn.Module]:
        return {}


class Actor(nn.Module):
    """
    DrQ-v2 actor: trunk ``Linear -> LayerNorm -> Tanh`` (``mlp0``), two ``Linear -> ReLU`` layers of
    ``hidden_dim`` units (``mlp1``, ``mlp2``) and ``Linear -> Tanh`` (``action``), the mean action.

    :param repr_dim: size of the encoder output
    :param action_dim: number of action dimensions
    :param feature_dim: size of the trunk output
    :param hidden_dim: units of the two hidden layers
    :param activation: ``"relu"`` (DrQ-v2's) or ``"leaky_relu"`` in ``mlp1`` and ``mlp2``
    :param leaky_relu_slope: negative slope of the Leaky-ReLU
    """

    def __init__(
        self,
        repr_dim: int,
        action_dim: int,
        feature_dim: int = 50,
        hidden_dim: int = 1024,
        activation: str = "relu",
        leaky_relu_slope: float = LEAKY_RELU_SLOPE,
    ) -> None:
        super().__init__()
        self.trunk = nn.Sequential(nn.Linear(repr_dim, feature_dim), nn.LayerNorm(feature_dim), nn.Tanh())
        self.mlp1 = nn.Sequential(nn.Linear(feature_dim, hidden_dim), hidden_activation(activation, leaky_relu_slope))
        self.mlp2 = nn.Sequential(nn.Linear(hidden_dim, hidden_dim), hidden_activation(activation, leaky_relu_slope))
        self.action = nn.Sequential(nn.Linear(hidden_dim, action_dim), nn.Tanh())

    def forward(self, features: th.Tensor) -> th.Tensor:
        """
        :param features: encoder output
        :return: the mean action, in [-1, 1]
        """
        return self.action(self.mlp2(self.mlp1(self.trunk(features))))

    def named_layers(self) -> dict[str, nn.Module]:
        return {"mlp0": self.trunk, "mlp1": self.mlp1, "mlp2": self.mlp2, "action": self.action}


def sample_action(mean: th.Tensor, std: float, clip: float | None = None) -> th.Tensor:
    """
    Sample of DrQ-v2's ``TruncatedNormal(mean, std)``: ``mean + eps`` with ``eps ~ N(0, std)``, ``eps``
    clipped to ``[-clip, clip]`` when ``clip`` is given, the action clamped to ``[-1 + 1e-6, 1 - 1e-6]``
    with a straight-through gradient (the gradient reaches ``mean`` even where the clamp is active).
    Equal to ``noisy_action(mean, exploration_noise(mean.shape, std, clip, mean.device))``.

    :param mean: mean action, in [-1, 1]
    :param std: standard deviation of the noise
    :param clip: noise clip, ``None`` for none
    :return: the sampled action
    """
    return noisy_action(mean, exploration_noise(mean.shape, std, clip, mean.device))


def exploration_noise(
    shape: tuple[int, ...] | th.Size, std: float, clip: float | None = None, device: th.device | str | None = None
) -> th.Tensor:
    """
    The noise ``eps`` of :func:`sample_action`, drawn from torch's global generator: ``N(0, std)``, clipped to
    ``[-clip, clip]`` when ``clip`` is given.

    :param shape: shape of the actions
    :param std: standard deviation
    :param clip: noise clip, ``None`` for none
    :param device: where the noise goes
    :return: float32 noise of that shape
    """
    eps = th.randn(shape, device=device) * std
    if clip is not None:
        eps = eps.clamp(-clip, clip)
    return eps


def noisy_action(mean: th.Tensor, eps: th.Tensor) -> th.Tensor:
    """
    ``mean + eps`` clamped to ``[-1 + 1e-6, 1 - 1e-6]`` with a straight-through gradient (the gradient reaches
    ``mean`` even where the clamp is active), as DrQ-v2's ``TruncatedNormal.sample``.

    :param mean: mean action, in [-1, 1]
    :param eps: noise, e.g. from :func:`exploration_noise`
    :return: the action
    """
    action = mean + eps
    clamped = action.clamp(-1.0 + ACTION_EPS, 1.0 - ACTION_EPS)
    return action - action.detach() + clamped.detach()


class Critic(nn.Module):
    """
    DrQ-v2 twin critic: its own trunk ``Linear -> LayerNorm -> Tanh`` shared by two Q heads, each
    ``Linear(feature + A -> hidden) -> ReLU -> Linear(hidden -> hidden) -> ReLU -> Linear(hidden -> 1)``.

    :param repr_dim: size of the encoder output
    :param action_dim: number of action dimensions
    :param feature_dim: size of the trunk output
    :param hidden_dim: units of the hidden layers
    :param activation: ``"relu"`` (DrQ-v2's) or ``"leaky_relu"`` in the Q heads
    :param leaky_relu_slope: negative slope of the Leaky-ReLU
    """

    def __init__(
        self,
        repr_dim: int,
        action_dim: int,
        feature_dim: int = 50,
        hidden_dim: int = 1024,
        activation: str = "relu",
        leaky_relu_slope: float = LEAKY_RELU_SLOPE,
    ) -> None:
        super().__init__()
        self.trunk = nn.Sequential(nn.Linear(repr_dim, feature_dim), nn.LayerNorm(feature_dim), nn.Tanh())
        self.q1 = _q_head(feature_dim + action_dim, hidden_dim, activation, leaky_relu_slope)
        self.q2 = _q_head(feature_dim + action_dim, hidden_dim, activation, leaky_relu_slope)

    def forward(self, features: th.Tensor, action: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        """
        :param features: encoder output
        :param action: actions in [-1, 1]
        :return: ``(Q1, Q2)``, each of shape ``(batch, 1)``
        """
        return self.heads(self.trunk(features), action)

    def heads(self, trunk_features: th.Tensor, action: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        """
        :param trunk_features: output of :attr:`trunk`
        :param action: actions in [-1, 1]
        :return: ``(Q1, Q2)``
        """
        h_action = th.cat([trunk_features, action], dim=-1)
        return self.q1(h_action), self.q2(h_action)


def _q_head(
    in_dim: int, hidden_dim: int, activation: str = "relu", leaky_relu_slope: float = LEAKY_RELU_SLOPE
) -> nn.Sequential:
    return nn.Sequential(
        nn.Linear(in_dim, hidden_dim),
        hidden_activation(activation, leaky_relu_slope),
        nn.Linear(hidden_dim, hidden_dim),
        hidden_activation(activation, leaky_relu_slope),
        nn.Linear(hidden_dim, 1),
    )


class DrQv2Policy(BasePolicy):
    """
    Encoder, actor, critic and target critic of DrQ-v2, with one Adam optimizer for each trained part.

    The encoder is trained by the critic loss only; the target critic (trunk and heads) is a soft copy of
    the critic; there is no target encoder and no target actor.

    :param observation_space: observation space
    :param action_space: action space, a bounded ``Box``
    :param lr_schedule: learning rate schedule (constant 1e-4 in DrQ-v2)
    :param feature_dim: size of the actor and critic trunk outputs (50; 100 for humanoid in DrQ-v2)
    :param hidden_dim: units of the hidden layers of the actor and the Q heads
    :param encoder_class: ``PixelEncoder`` (``CnnPolicy``) or ``StateEncoder`` (``MlpPolicy``)
    :param encoder_kwargs: keyword arguments of the encoder (``channels``, ``channels_last``, ``fused_relu``)
    :param optimizer_class: optimizer of the encoder, actor and critic
    :param optimizer_kwargs: its keyword arguments, learning rate excluded (Adam gets ``fused=True`` unless
        given otherwise)
    :param activation: the hidden activation of the encoder, the actor and the critic: ``"relu"`` (DrQ-v2's) or
        ``"leaky_relu"`` (the paper's footnote 1 ablation); saved with the model (``policy_kwargs``)
    :param leaky_relu_slope: negative slope of the Leaky-ReLU (:data:`LEAKY_RELU_SLOPE`, PyTorch's default 0.01)
    """

    encoder: PixelEncoder | StateEncoder
    actor: Actor
    critic: Critic
    critic_target: Critic

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Box,
        lr_schedule: Schedule,
        feature_dim: int = 50,
        hidden_dim: int = 1024,
        encoder_class: type[PixelEncoder | StateEncoder] = PixelEncoder,
        encoder_kwargs: dict[str, Any] | None = None,
        optimizer_class: type[th.optim.Optimizer] = th.optim.Adam,
        optimizer_kwargs: dict[str, Any] | None = None,
        activation: str = "relu",
        leaky_relu_slope: float = LEAKY_RELU_SLOPE,
    ) -> None:
        check_activation(activation, leaky_relu_slope)
        super().__init__(
            observation_space,
            action_space,
            optimizer_class=optimizer_class,
            optimizer_kwargs=optimizer_kwargs,
            squash_output=True,
            normalize_images=False,
        )
        check_action_space(action_space)
        self.feature_dim = feature_dim
        self.hidden_dim = hidden_dim
        self.encoder_class = encoder_class
        self.encoder_kwargs = encoder_kwargs or {}
        self.activation = activation
        self.leaky_relu_slope = leaky_relu_slope
        if optimizer_class is th.optim.Adam and "fused" not in self.optimizer_kwargs:
            # One fused kernel per step instead of a dozen per tensor: the same update (speed: benchmarks/README.md).
            self.optimizer_kwargs["fused"] = True
        self.exploration_std = 1.0
        """Standard deviation of the exploration noise of ``predict(deterministic=False)``; the algorithm
        sets it from its schedule before every action it takes."""
        self._build(lr_schedule)

    def _build(self, lr_schedule: Schedule) -> None:
        """Create fresh networks (new random weights) and fresh optimizers."""
        action_dim = int(np.prod(self.action_space.shape))
        act = {"activation": self.activation, "leaky_relu_slope": self.leaky_relu_slope}
        encoder_act = act if self.activation != "relu" else {}  # an encoder class of its own may not take them
        self.encoder = self.encoder_class(self.observation_space, **{**encoder_act, **self.encoder_kwargs})
        repr_dim = self.encoder.repr_dim
        self.actor = Actor(repr_dim, action_dim, self.feature_dim, self.hidden_dim, **act)
        self.critic = Critic(repr_dim, action_dim, self.feature_dim, self.hidden_dim, **act)
        # The encoder initializes itself (before switching to channels_last).
        for module in (self.actor, self.critic):
            module.apply(weight_init)
        self.critic_target = copy.deepcopy(self.critic)
        self.critic_target.requires_grad_(False)

        lr = lr_schedule(1)
        params = list(self.encoder.parameters())
        self.encoder.optimizer = self.optimizer_class(params, lr=lr, **self.optimizer_kwargs) if params else None
        self.actor.optimizer = self.optimizer_class(self.actor.parameters(), lr=lr, **self.optimizer_kwargs)
        self.critic.optimizer = self.optimizer_class(self.critic.parameters(), lr=lr, **self.optimizer_kwargs)

    @property
    def optimizers(self) -> list[th.optim.Optimizer]:
        """The optimizers of the encoder (pixels only), the actor and the critic."""
        optimizers = [self.encoder.optimizer, self.actor.optimizer, self.critic.optimizer]
        return [optimizer for optimizer in optimizers if optimizer is not None]

    def named_layers(self) -> dict[str, nn.Module]:
        """
        The modules that produce each named activation, input to output.

        For each name in ``cnn0``..``cnn4`` (pixel policies only), ``mlp0``, ``mlp1``, ``mlp2`` and
        ``action``, the module whose forward output is that activation (register a forward hook on it)
        and whose parameters are that layer's weights (read their gradients for the layer's gradient norm).
        ``cnn0`` is the normalization and has no parameters. Activations are those of ``encoder`` then
        ``actor``; the critic's layers are not named.

        :return: ordered mapping name -> module
        """
        return {**self.encoder.named_layers(), **self.actor.named_layers()}

    def _get_constructor_parameters(self) -> dict[str, Any]:
        return dict(
            observation_space=self.observation_space,
            action_space=self.action_space,
            feature_dim=self.feature_dim,
            hidden_dim=self.hidden_dim,
            encoder_class=self.encoder_class,
            encoder_kwargs=self.encoder_kwargs,
            optimizer_class=self.optimizer_class,
            optimizer_kwargs=self.optimizer_kwargs,
            activation=self.activation,
            leaky_relu_slope=self.leaky_relu_slope,
            lr_schedule=self._dummy_schedule,
        )

    def forward(self, observation: th.Tensor, deterministic: bool = False) -> th.Tensor:
        return self._predict(observation, deterministic=deterministic)

    def _predict(self, observation: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        mean = self.actor(self.encoder(observation))  # type: ignore[arg-type]
        if deterministic:
            return mean
        return sample_action(mean, self.exploration_std, clip=None)

    def set_training_mode(self, mode: bool) -> None:
        self.encoder.train(mode)
        self.actor.train(mode)
        self.critic.train(mode)
        self.training = mode

    def renew_networks(self, lr_schedule: Schedule) -> None:
        """
        New random weights for the encoder, actor, critic and target critic (drawn as :meth:`_build` draws them, from
        torch's global generator as it is now), copied into the existing parameter tensors, so that compiled code
        and CUDA graphs that hold them stay valid; new optimizers (empty state) over them.

        :param lr_schedule: the learning-rate schedule of the new optimizers
        """
        was_training = self.training
        kept = {name: getattr(self, name) for name in ("encoder", "actor", "critic", "critic_target")}
        self._build(lr_schedule)
        with th.no_grad():
            for name, module in kept.items():
                fresh = getattr(self, name)
                module.load_state_dict(fresh.state_dict())
                optimizer = getattr(fresh, "optimizer", None)
                if optimizer is not None:
                    module.optimizer = type(optimizer)(module.parameters(), **optimizer.defaults)
                setattr(self, name, module)
        self.set_training_mode(was_training)

    # ---------------------------------------------------------------------------- the parts the interventions act on
    # The protocol sb3_collapse.monitoring.interventions.InterventionParts (duck typed), with named_layers and optimizers.
    def initialize_weights(self, module: nn.Module) -> None:
        """
        New initial values for every parameter of ``module`` (a part of this policy), in place, from torch's global
        generator: :func:`weight_init` on Linear and Conv2d, ``reset_parameters()`` otherwise (LayerNorm: unit scale,
        zero shift).

        :param module: the module to initialize
        :raises TypeError: for a submodule with parameters and no known initializer
        """
        reinitialize(module, weight_init)

    def online_networks(self) -> dict[str, nn.Module]:
        """:return: the trained networks by name, ``encoder``, ``actor`` and ``critic`` (the encoder even without
        parameters)"""
        return {"encoder": self.encoder, "actor": self.actor, "critic": self.critic}

    def target_networks(self) -> dict[str, nn.Module]:
        """:return: the target networks by name: ``target critic``"""
        return {"target critic": self.critic_target}

    def actor_modules(self) -> list[nn.Module]:
        """:return: what a reset of the actor renews: the whole actor (the encoder is the critic's, it is kept)"""
        return [self.actor]

    def actor_mlp_modules(self) -> list[nn.Module]:
        """:return: the actor's layers after the encoder: the whole actor, as :meth:`actor_modules`"""
        return [self.actor]

    @staticmethod
    def _leaf_modules(module: nn.Module) -> list[nn.Module]:
        """The modules of ``module`` without children, in registration order (the forward order here)."""
        return [sub for sub in module.modules() if next(sub.children(), None) is None]

    def _q_heads(self) -> list[nn.Module]:
        """The critic's Q networks: its children but the trunk (the members of a ``ModuleList`` one by one)."""
        children = [child for name, child in self.critic.named_children() if name != "trunk"]
        return [head for child in children for head in (child if isinstance(child, nn.ModuleList) else [child])]

    def hidden_layer_parts(self) -> list[LayerParts]:
        """
        The hidden layers whose units ReDo may recycle: the actor's ``mlp1``, ``mlp2``... (a ``Linear`` and its
        activation, read by the next Linear; the trunk ``mlp0`` ends with LayerNorm and Tanh, it is not one), then
        each Q network's ``q<k>.mlp1``, ``q<k>.mlp2``...

        :return: the layers' parts, actor first
        """
        parts = sequential_hidden_parts("", self._leaf_modules(self.actor), first=0)
        for k, head in enumerate(self._q_heads(), start=1):
            parts += sequential_hidden_parts(f"q{k}.", self._leaf_modules(head))
        return parts

    def encoder_channel_parts(self) -> list[LayerParts]:
        """
        The convolutions of the pixel encoder as layers of channels that ReDo may recycle, ``cnn1``..``cnn4``: a
        channel's consumers are the next convolution, or for the last one the first Linear of the actor and of the
        critic, which read it at every position (in the encoder's flattening order).

        :return: the layers' parts, input to output; ``[]`` for an encoder without convolutions (``MlpPolicy``)
        """
        if not isinstance(self.encoder, PixelEncoder):
            return []
        blocks = [(name, block) for name, block in self.encoder.named_layers().items() if isinstance(block, ConvReLU)]
        trunks = tuple(next(m for m in net.modules() if isinstance(m, nn.Linear)) for net in (self.actor, self.critic))
        positions = self.encoder.repr_dim // blocks[-1][1][0].out_channels
        parts = []
        for k, (name, block) in enumerate(blocks):
            last = k == len(blocks) - 1
            consumers = trunks if last else (blocks[k + 1][1][0],)
            parts.append(
                LayerParts(name, block[0], block, consumers, positions if last else 1, self.encoder.channels_last)
            )
        return parts

    def forward_hidden(self, observations: PyTorchObs, actions: th.Tensor) -> None:
        """
        Run the layers of :meth:`hidden_layer_parts` and :meth:`encoder_channel_parts` on a batch, for hooks on their
        activations to read: the encoder, the actor on its features, the critic on its features and the actions
        (the caller sets the mode and the gradient).

        :param observations: ``(n, *obs_shape)`` observations
        :param actions: ``(n, action_dim)`` actions in [-1, 1]
        """
        features = self.encoder(observations)  # type: ignore[arg-type]
        self.actor(features)
        self.critic(features, actions)


class CnnPolicy(DrQv2Policy):
    """DrQ-v2 from pixels: channel-first ``uint8`` image observations (e.g. 9x84x84 for 3 stacked RGB frames)."""

    def __init__(self, *args: Any, encoder_class: type[PixelEncoder | StateEncoder] = PixelEncoder, **kwargs: Any):
        super().__init__(*args, encoder_class=encoder_class, **kwargs)


class MlpPolicy(DrQv2Policy):
    """DrQ-v2 from state vectors: the same actor and critic, no encoder, no augmentation."""

    def __init__(self, *args: Any, encoder_class: type[PixelEncoder | StateEncoder] = StateEncoder, **kwargs: Any):
        super().__init__(*args, encoder_class=encoder_class, **kwargs)


def check_pixel_space(observation_space: spaces.Space) -> None:
    """
    :param observation_space: space to check
    :raises ValueError: unless it is a channel-first ``uint8`` image ``Box`` (``(C, H, W)``, ``C < H, W``)
    """
    if not (
        isinstance(observation_space, spaces.Box)
        and is_image_space(observation_space, check_channels=False)
        and observation_space.shape[0] < min(observation_space.shape[1:])
    ):
        raise ValueError(
            f"CnnPolicy needs channel-first uint8 image observations of shape (channels, height, width), "
            f"such as make_dmc_env(...)'s (9, 84, 84), but got {observation_space}. "
            "Use MlpPolicy for state vectors (make_dmc_env(..., obs_type='state'))."
        )
    height, width = observation_space.shape[1:]
    if min(_conv_output_size((height, width))) < 1:
        raise ValueError(f"Images of {height}x{width} pixels are too small for the DrQ-v2 encoder (at least 15x15).")


def check_state_space(observation_space: spaces.Space) -> None:
    """
    :param observation_space: space to check
    :raises ValueError: unless it is a 1-d ``Box`` that is not an image
    """
    if isinstance(observation_space, spaces.Box) and is_image_space(observation_space, check_channels=False):
        raise ValueError(
            f"MlpPolicy takes state vectors, but the observations are images {observation_space}: use CnnPolicy."
        )
    if not (isinstance(observation_space, spaces.Box) and len(observation_space.shape) == 1):
        raise ValueError(
            f"MlpPolicy needs a 1-d Box of state features, got {observation_space}. "
            "Flatten dict observations first (gymnasium.wrappers.FlattenObservation)."
        )


def check_action_space(action_space: spaces.Space) -> None:
    """
    :param action_space: space to check
    :raises TypeError: unless it is a ``Box`` with finite bounds (DrQ-v2 is for continuous control)
    """
    if not isinstance(action_space, spaces.Box):
        raise TypeError(
            f"DrQv2 is for continuous actions (gymnasium.spaces.Box), got {type(action_space).__name__}: {action_space}."
        )
    if not (np.all(np.isfinite(action_space.low)) and np.all(np.isfinite(action_space.high))):
        raise TypeError(f"DrQv2 needs finite action bounds to rescale its tanh actions, got {action_space}.")


def _conv_output_size(image_size: tuple[int, ...]) -> tuple[int, ...]:
    """Height and width after the encoder: 3x3 stride 2 then three 3x3 stride 1, no padding."""
    return tuple((size - 3) // 2 + 1 - 6 for size in image_size)


MIN_IMAGE_SIZE = 15
"""The smallest image height and width, in pixels, that the encoder's convolutions leave at least 1x1 of."""


def check_image_size(size: int, name: str = "size") -> None:
    """
    :param size: an image height or width, in pixels
    :param name: the parameter's name, for the message
    :raises ParameterError: when the encoder's convolutions would leave nothing of it
    """
    if size < MIN_IMAGE_SIZE:
        raise ParameterError(
            name,
            f"{name} must be >= {MIN_IMAGE_SIZE} pixels (the encoder's 3x3 convolutions, the first with stride 2, "
            f"leave nothing of smaller images), got {size}.",
        )
