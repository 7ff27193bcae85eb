"""Networks of DrQ-v2: pixel encoder, actor and twin critic, wrapped as an SB3 policy (:class:`DrQv2Policy`).

The layers are named as in :data:`sb3_collapse.common.layers.LAYER_NAMES` (``cnn0``..``cnn4``, ``mlp0``..``mlp2``,
``action``), the vocabulary shared by the callbacks, the probe and the plots: :meth:`DrQv2Policy.named_layers`.
The names under ``net_arch``, ``MultiInputPolicy`` and a user's features extractor (*Named layers*):
docs/algorithm.md#the-algorithm-sb3_collapsedrqv2; ``activation="leaky_relu"``:
docs/interventions.md#the-leaky-relu-ablation.
"""

from __future__ import annotations

import contextlib
import copy
from collections.abc import Iterable, Iterator, Sequence
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from stable_baselines3.common.type_aliases import PyTorchObs, Schedule
from torch import nn
from torch.nn import functional as F

from sb3_collapse.common.layers import LayerParts, reinitialize, sequential_hidden_parts
from sb3_collapse.drqv2.checks import (
    ACTIVATION_FNS,
    actor_critic_arch,
    check_action_space,
    check_policy_kwargs,
    split_sb3_feature_size,
)
from sb3_collapse.drqv2.encoders import (
    LEAKY_RELU_SLOPE,
    ConvReLU,
    DictEncoder,
    FeaturesExtractorEncoder,
    PixelEncoder,
    StateEncoder,
    check_activation,
    hidden_activation,
    weight_init,
)

ACTION_EPS = 1e-6
"""Sampled actions are clamped to ``[-1 + eps, 1 - eps]`` as in DrQ-v2's ``TruncatedNormal``."""


def hidden_layers(net_arch: Sequence[int] | None, hidden_dim: int) -> list[int]:
    """
    :param net_arch: SB3's ``net_arch`` of a network (units of each hidden layer), ``None`` for DrQ-v2's
    :param hidden_dim: the units of DrQ-v2's two hidden layers, used when ``net_arch`` is ``None``
    :return: the units of each hidden layer
    """
    return [hidden_dim, hidden_dim] if net_arch is None else [int(units) for units in net_arch]


class Actor(nn.Module):
    """
    DrQ-v2 actor: trunk ``Linear -> LayerNorm -> Tanh`` (``mlp0``), two ``Linear -> ReLU`` layers of
    ``hidden_dim`` units (``mlp1``, ``mlp2``) and ``Linear -> Tanh`` (``action``), the mean action.

    With SB3's ``net_arch`` (a list of units), one ``Linear -> ReLU`` layer per entry, named ``mlp1``, ``mlp2``, ...
    ``mlpK`` in order (``net_arch=[]``: the ``action`` head reads the trunk directly).

    :param repr_dim: size of the encoder output
    :param action_dim: number of action dimensions
    :param feature_dim: size of the trunk output
    :param hidden_dim: units of the two hidden layers (when ``net_arch`` is ``None``)
    :param activation: ``"relu"`` (DrQ-v2's) or ``"leaky_relu"`` in the hidden layers
    :param leaky_relu_slope: negative slope of the Leaky-ReLU
    :param net_arch: units of each hidden layer; ``None``: ``[hidden_dim, hidden_dim]`` (DrQ-v2's)
    """

    features_extractor: nn.Module | None = None
    """SB3's name for the encoder whose features this network reads (:func:`expose_encoder`): the policy's, shared,
    not a submodule of this network; ``None`` for a network built alone."""

    def __init__(
        self,
        repr_dim: int,
        action_dim: int,
        feature_dim: int = 50,
        hidden_dim: int = 1024,
        activation: str = "relu",
        leaky_relu_slope: float = LEAKY_RELU_SLOPE,
        net_arch: Sequence[int] | None = None,
    ) -> None:
        super().__init__()
        self.trunk = nn.Sequential(nn.Linear(repr_dim, feature_dim), nn.LayerNorm(feature_dim), nn.Tanh())
        self.hidden_names: list[str] = []
        in_dim = feature_dim
        for index, units in enumerate(hidden_layers(net_arch, hidden_dim), start=1):
            name = f"mlp{index}"
            setattr(
                self, name, nn.Sequential(nn.Linear(in_dim, units), hidden_activation(activation, leaky_relu_slope))
            )
            self.hidden_names.append(name)
            in_dim = units
        self.action = nn.Sequential(nn.Linear(in_dim, action_dim), nn.Tanh())

    def forward(self, features: th.Tensor) -> th.Tensor:
        """
        :param features: encoder output
        :return: the mean action, in [-1, 1]
        """
        h = self.trunk(features)
        for name in self.hidden_names:
            h = getattr(self, name)(h)
        return self.action(h)

    def named_layers(self) -> dict[str, nn.Module]:
        return {"mlp0": self.trunk, **{name: getattr(self, name) for name in self.hidden_names}, "action": self.action}


def sample_action(mean: th.Tensor, std: float, clip: float | None = None) -> th.Tensor:
    """
    Sample of DrQ-v2's ``TruncatedNormal(mean, std)``: ``mean + eps`` with ``eps ~ N(0, std)``, ``eps``
    clipped to ``[-clip, clip]`` when ``clip`` is given, the action clamped to ``[-1 + 1e-6, 1 - 1e-6]``
    with a straight-through gradient (the gradient reaches ``mean`` even where the clamp is active).
    Equal to ``noisy_action(mean, exploration_noise(mean.shape, std, clip, mean.device, mean.dtype))``.

    :param mean: mean action, in [-1, 1]
    :param std: standard deviation of the noise
    :param clip: noise clip, ``None`` for none
    :return: the sampled action
    """
    return noisy_action(mean, exploration_noise(mean.shape, std, clip, mean.device, mean.dtype))


def exploration_noise(
    shape: tuple[int, ...] | th.Size,
    std: float,
    clip: float | None = None,
    device: th.device | str | None = None,
    dtype: th.dtype = th.float32,
) -> th.Tensor:
    """
    The noise ``eps`` of :func:`sample_action`, drawn from torch's global generator: ``N(0, std)``, clipped to
    ``[-clip, clip]`` when ``clip`` is given.

    :param shape: shape of the actions
    :param std: standard deviation
    :param clip: noise clip, ``None`` for none
    :param device: where the noise goes
    :param dtype: its dtype (the actions'; float32 whatever torch's default dtype)
    :return: noise of that shape
    """
    eps = th.randn(shape, device=device, dtype=dtype) * std
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

    With SB3's ``n_critics``, ``n_critics`` heads ``q1``..``qN``; with its ``net_arch`` (a list of units), one
    ``Linear -> ReLU`` per entry in each head.

    :param repr_dim: size of the encoder output
    :param action_dim: number of action dimensions
    :param feature_dim: size of the trunk output
    :param hidden_dim: units of the hidden layers (when ``net_arch`` is ``None``)
    :param activation: ``"relu"`` (DrQ-v2's) or ``"leaky_relu"`` in the Q heads
    :param leaky_relu_slope: negative slope of the Leaky-ReLU
    :param net_arch: units of each hidden layer of a head; ``None``: ``[hidden_dim, hidden_dim]`` (DrQ-v2's)
    :param n_critics: number of Q heads (DrQ-v2's 2)
    """

    features_extractor: nn.Module | None = None
    """SB3's name for the encoder whose features this network reads (:func:`expose_encoder`): the policy's, shared,
    not a submodule of this network; ``None`` for a network built alone."""

    def __init__(
        self,
        repr_dim: int,
        action_dim: int,
        feature_dim: int = 50,
        hidden_dim: int = 1024,
        activation: str = "relu",
        leaky_relu_slope: float = LEAKY_RELU_SLOPE,
        net_arch: Sequence[int] | None = None,
        n_critics: int = 2,
    ) -> None:
        super().__init__()
        self.trunk = nn.Sequential(nn.Linear(repr_dim, feature_dim), nn.LayerNorm(feature_dim), nn.Tanh())
        arch = hidden_layers(net_arch, hidden_dim)
        self.q_names = [f"q{index}" for index in range(1, n_critics + 1)]
        for name in self.q_names:
            setattr(self, name, _q_head(feature_dim + action_dim, arch, activation, leaky_relu_slope))

    def forward(self, features: th.Tensor, action: th.Tensor) -> tuple[th.Tensor, ...]:
        """
        :param features: encoder output
        :param action: actions in [-1, 1]
        :return: ``(Q1, Q2)`` (``n_critics`` values), each of shape ``(batch, 1)``
        """
        return self.heads(self.trunk(features), action)

    def heads(self, trunk_features: th.Tensor, action: th.Tensor) -> tuple[th.Tensor, ...]:
        """
        :param trunk_features: output of :attr:`trunk`
        :param action: actions in [-1, 1]
        :return: ``(Q1, Q2)`` (``n_critics`` values)
        """
        h_action = th.cat([trunk_features, action], dim=-1)
        return tuple(getattr(self, name)(h_action) for name in self.q_names)

    @property
    def q_networks(self) -> list[nn.Module]:
        """The Q heads, as SB3's ``ContinuousCritic.q_networks``."""
        return [getattr(self, name) for name in self.q_names]


def min_q(q_values: Sequence[th.Tensor]) -> th.Tensor:
    """
    :param q_values: the critic's ``(Q1, ..., QN)``
    :return: their element-wise minimum (``th.min(Q1, Q2)`` for DrQ-v2's two, ``Q1`` for one)
    """
    minimum = q_values[0]
    for q in q_values[1:]:
        minimum = th.min(minimum, q)
    return minimum


def critic_mse(q_values: Sequence[th.Tensor], target_q: th.Tensor) -> th.Tensor:
    """
    :param q_values: the critic's ``(Q1, ..., QN)``
    :param target_q: the target
    :return: ``MSE(Q1, y) + ... + MSE(QN, y)``
    """
    loss = F.mse_loss(q_values[0], target_q)
    for q in q_values[1:]:
        loss = loss + F.mse_loss(q, target_q)
    return loss


def soft_update(params: Iterable[th.Tensor], target_params: Iterable[th.Tensor], tau: float) -> None:
    """
    SB3's ``polyak_update`` (``target = target * (1 - tau) + tau * param``, in place, the same values) in two
    ``torch._foreach`` calls instead of two per tensor.

    :param params: parameters of the trained network
    :param target_params: parameters of its target network, updated in place
    :param tau: soft update coefficient
    """
    targets = list(target_params)
    with th.no_grad():
        th._foreach_mul_(targets, 1 - tau)
        th._foreach_add_(targets, list(params), alpha=tau)


@contextlib.contextmanager
def frozen(module: nn.Module) -> Iterator[None]:
    """Parameters of ``module`` with ``requires_grad=False`` inside the block (those that required it before, after)."""
    params = [param for param in module.parameters() if param.requires_grad]
    for param in params:
        param.requires_grad_(False)
    try:
        yield
    finally:
        for param in params:
            param.requires_grad_(True)


def _q_head(
    in_dim: int, net_arch: Sequence[int], activation: str = "relu", leaky_relu_slope: float = LEAKY_RELU_SLOPE
) -> nn.Sequential:
    layers: list[nn.Module] = []
    for units in net_arch:
        layers += [nn.Linear(in_dim, units), hidden_activation(activation, leaky_relu_slope)]
        in_dim = units
    return nn.Sequential(*layers, nn.Linear(in_dim, 1))


def expose_encoder(encoder: nn.Module, *networks: nn.Module) -> None:
    """
    SB3's ``features_extractor`` on each network (``model.actor.features_extractor``, the critic's, the target
    critic's, which DrQ-v2 runs on the online encoder's features): the policy's encoder, or a user's
    ``BaseFeaturesExtractor`` itself (the ``extractor`` of :class:`FeaturesExtractorEncoder`). A reference, not a
    submodule: the encoder's parameters are in ``state_dict()``, the optimizers and the saved zip once, under
    ``encoder.``, and ``networks``' ``parameters()``, ``apply()`` and ``train()`` do not reach them.

    :param encoder: the policy's encoder
    :param networks: the networks that read its features
    """
    extractor = encoder.extractor if isinstance(encoder, FeaturesExtractorEncoder) else encoder
    for network in networks:
        network.__dict__["features_extractor"] = extractor  # nn.Module.__setattr__ would register it


class DrQv2Policy(BasePolicy):
    """
    Encoder, actor, critic and target critic of DrQ-v2, with one Adam optimizer for each trained part.

    The encoder is trained by the critic loss only; the target critic (trunk and heads) is a soft copy of
    the critic; there is no target encoder and no target actor.

    SB3's policy keywords (those of TD3's ``TD3Policy``) mean what they mean there; what DrQ-v2 makes of each:
    docs/algorithm.md#sb3s-keywords-code-written-for-td3-runs-with-drqv2.

    :param observation_space: observation space
    :param action_space: action space, a bounded ``Box``
    :param lr_schedule: learning rate schedule (constant 1e-4 in DrQ-v2)
    :param feature_dim: size of the actor and critic trunk outputs (50; 100 for humanoid in DrQ-v2); SB3's
        ``features_extractor_kwargs=dict(features_dim=...)`` (or ``cnn_output_dim``) sets it too
    :param hidden_dim: units of the two hidden layers of the actor and of each Q head (when ``net_arch`` is
        ``None``)
    :param encoder_class: ``PixelEncoder`` (``CnnPolicy``), ``StateEncoder`` (``MlpPolicy``) or ``DictEncoder``
        (``MultiInputPolicy``)
    :param encoder_kwargs: keyword arguments of the encoder (``channels``, ``channels_last``, ``fused_relu``)
    :param optimizer_class: optimizer of the encoder, actor and critic
    :param optimizer_kwargs: its keyword arguments, learning rate excluded (Adam gets ``fused=True`` unless
        given otherwise)
    :param activation: the hidden activation of the encoder, the actor and the critic: ``"relu"`` (DrQ-v2's) or
        ``"leaky_relu"`` (the paper's footnote 1 ablation); saved with the model (``policy_kwargs``)
    :param leaky_relu_slope: negative slope of the Leaky-ReLU (:data:`LEAKY_RELU_SLOPE`, PyTorch's default 0.01)
    :param net_arch: SB3's: the hidden layers of the actor and of each Q head, a list of units for both or
        ``dict(pi=[...], qf=[...])``; ``None``: ``[hidden_dim, hidden_dim]`` for both (DrQ-v2's ``[1024, 1024]``).
        The actor's hidden layers are named ``mlp1``..``mlpK`` (``K = len(pi)``)
    :param activation_fn: SB3's: ``nn.ReLU`` (DrQ-v2's) or ``nn.LeakyReLU`` (``activation="leaky_relu"``); ``None``
        leaves ``activation`` as given
    :param features_extractor_class: SB3's: a ``BaseFeaturesExtractor`` subclass in place of DrQ-v2's encoder
        (:class:`FeaturesExtractorEncoder`); ``None``: DrQ-v2's encoder (``encoder_class``)
    :param features_extractor_kwargs: its keyword arguments; without ``features_extractor_class``, those of DrQ-v2's
        encoder, but ``features_dim`` and ``cnn_output_dim`` set ``feature_dim`` (``checks.SB3_FEATURE_SIZES``)
    :param normalize_images: SB3's: ``True`` divides ``uint8`` images by 255 (DrQ-v2's encoder: ``obs / 255 - 0.5``);
        ``False`` takes images already normalized (float ``Box`` observations) as they are
    :param share_features_extractor: SB3's: ``True`` only (one encoder, trained by the critic loss); ``False`` is
        refused
    :param n_critics: SB3's: number of Q heads (DrQ-v2's 2); the targets and the actor loss take their minimum
    """

    encoder: PixelEncoder | StateEncoder | DictEncoder | FeaturesExtractorEncoder
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
        encoder_class: type[nn.Module] = PixelEncoder,
        encoder_kwargs: dict[str, Any] | None = None,
        optimizer_class: type[th.optim.Optimizer] = th.optim.Adam,
        optimizer_kwargs: dict[str, Any] | None = None,
        activation: str = "relu",
        leaky_relu_slope: float = LEAKY_RELU_SLOPE,
        net_arch: list[int] | dict[str, list[int]] | None = None,
        activation_fn: type[nn.Module] | None = None,
        features_extractor_class: type[BaseFeaturesExtractor] | None = None,
        features_extractor_kwargs: dict[str, Any] | None = None,
        normalize_images: bool = True,
        share_features_extractor: bool = True,
        n_critics: int = 2,
    ) -> None:
        check_policy_kwargs(
            dict(
                feature_dim=feature_dim,
                hidden_dim=hidden_dim,
                net_arch=net_arch,
                activation=activation,
                activation_fn=activation_fn,
                features_extractor_class=features_extractor_class,
                encoder_kwargs=encoder_kwargs,
                features_extractor_kwargs=features_extractor_kwargs,
                share_features_extractor=share_features_extractor,
                n_critics=n_critics,
            )
        )
        if activation_fn is not None:
            activation = ACTIVATION_FNS[activation_fn]
        check_activation(activation, leaky_relu_slope)
        super().__init__(
            observation_space,
            action_space,
            optimizer_class=optimizer_class,
            optimizer_kwargs=optimizer_kwargs,
            squash_output=True,
            normalize_images=normalize_images,
        )
        check_action_space(action_space)
        sb3_size, drqv2_encoder_kwargs = split_sb3_feature_size(features_extractor_kwargs, features_extractor_class)
        self.feature_dim = feature_dim if sb3_size is None else sb3_size
        self.hidden_dim = hidden_dim
        self.net_arch = net_arch
        self.actor_arch, self.critic_arch = actor_critic_arch(net_arch, hidden_dim)
        self.n_critics = n_critics
        self.share_features_extractor = share_features_extractor
        self.activation_fn = activation_fn
        self.features_extractor_class = features_extractor_class
        self.features_extractor_kwargs = features_extractor_kwargs or {}
        self.encoder_class = encoder_class
        self.encoder_kwargs = encoder_kwargs or {}
        if drqv2_encoder_kwargs:
            self.encoder_kwargs = {**self.encoder_kwargs, **drqv2_encoder_kwargs}  # DrQ-v2's encoder's
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
        if self.features_extractor_class is not None:
            self.encoder = FeaturesExtractorEncoder(
                self.observation_space,
                self.features_extractor_class,
                self.features_extractor_kwargs,
                self.normalize_images,
            )
        else:
            # An encoder class of its own may not take these: passed only when they differ from the defaults.
            encoder_act = act if self.activation != "relu" else {}
            normalize = {} if self.normalize_images else {"normalize_images": False}
            self.encoder = self.encoder_class(
                self.observation_space, **{**encoder_act, **normalize, **self.encoder_kwargs}
            )
        repr_dim = self.encoder.repr_dim
        self.actor = Actor(repr_dim, action_dim, self.feature_dim, self.hidden_dim, **act, net_arch=self.actor_arch)
        self.critic = Critic(
            repr_dim,
            action_dim,
            self.feature_dim,
            self.hidden_dim,
            **act,
            net_arch=self.critic_arch,
            n_critics=self.n_critics,
        )
        # The encoder initializes itself (before switching to channels_last).
        for module in (self.actor, self.critic):
            module.apply(weight_init)
        for module in (self.encoder, self.actor, self.critic):
            module.float()  # SB3's observations and replay samples are float32, whatever torch's default dtype
        self.critic_target = copy.deepcopy(self.critic)
        self.critic_target.requires_grad_(False)
        expose_encoder(self.encoder, self.actor, self.critic, self.critic_target)

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
            net_arch=self.net_arch,
            features_extractor_class=self.features_extractor_class,
            features_extractor_kwargs=self.features_extractor_kwargs,
            normalize_images=self.normalize_images,
            share_features_extractor=self.share_features_extractor,
            n_critics=self.n_critics,
            lr_schedule=self._dummy_schedule,
        )

    def extract_features(  # type: ignore[override]
        self, obs: PyTorchObs, features_extractor: nn.Module | None = None
    ) -> th.Tensor:
        """
        SB3's: the features that the actor and the critic read, from the one encoder they share (DrQ-v2's normalizes
        the pixels itself in ``cnn0``; a user's extractor gets SB3's ``preprocess_obs`` first).

        :param obs: observations
        :param features_extractor: ``None``, or a network's ``features_extractor`` (the actor's, the critic's and the
            target critic's are this encoder)
        :return: ``(n, repr_dim)`` features
        :raises ValueError: for another module
        """
        if features_extractor is not None and features_extractor is not self.actor.features_extractor:
            raise ValueError(
                "DrQv2Policy has one encoder, model.actor.features_extractor (the critic's and the target critic's "
                f"too); got another module, {type(features_extractor).__name__}."
            )
        return self.encoder(obs)  # type: ignore[arg-type]

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
    # The protocol sb3_collapse.monitoring.interventions.InterventionParts (duck typed), with named_layers and
    # optimizers.
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

    def feature_readers(self) -> list[nn.Module]:
        """
        The networks that read the encoder's features: every network of :meth:`online_networks` and
        :meth:`target_networks` but the encoder (the actor, the critic, and the target critic, which DrQ-v2 runs on
        the online encoder's features). The consumers of the encoder's last layer are read from this list, so a
        network added to either is not missed when ReDo recycles a channel.

        :return: the networks, in the order of those two methods
        """
        networks = {**self.online_networks(), **self.target_networks()}
        return [network for network in networks.values() if network is not self.encoder]

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
        channel's consumers are the next convolution, or for the last one the first Linear of each network of
        :meth:`feature_readers` (actor, critic, target critic), which read it at every position (in the encoder's
        flattening order).

        :return: the layers' parts, input to output; ``[]`` for an encoder without convolutions (``MlpPolicy``)
        """
        if not isinstance(self.encoder, PixelEncoder):
            return []
        blocks = [(name, block) for name, block in self.encoder.named_layers().items() if isinstance(block, ConvReLU)]
        trunks = tuple(next(m for m in net.modules() if isinstance(m, nn.Linear)) for net in self.feature_readers())
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

    def __init__(self, *args: Any, encoder_class: type[nn.Module] = PixelEncoder, **kwargs: Any):
        super().__init__(*args, encoder_class=encoder_class, **kwargs)


class MlpPolicy(DrQv2Policy):
    """DrQ-v2 from state vectors: the same actor and critic, no encoder, no augmentation."""

    def __init__(self, *args: Any, encoder_class: type[nn.Module] = StateEncoder, **kwargs: Any):
        super().__init__(*args, encoder_class=encoder_class, **kwargs)


class MultiInputPolicy(DrQv2Policy):
    """
    DrQ-v2 from dict observations (:class:`DictEncoder`): DrQ-v2's encoder on the image keys, the other keys (e.g.
    proprioception) flattened and concatenated to the image features; the augmentation shifts the images only.
    """

    def __init__(self, *args: Any, encoder_class: type[nn.Module] = DictEncoder, **kwargs: Any):
        super().__init__(*args, encoder_class=encoder_class, **kwargs)
