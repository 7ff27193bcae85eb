"""DrQ-v2's actor and twin critic with its encoder, as an SB3 policy (:class:`DrQv2Policy`); named layers:
docs/algorithm.md (*Named layers*)."""

from __future__ import annotations

import contextlib
import copy
import functools
import operator
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

ACTION_EPS = 1e-6  # sampled actions are clamped to [-1 + eps, 1 - eps], as DrQ-v2's TruncatedNormal


class Actor(nn.Module):
    """DrQ-v2 actor on the encoder's ``repr_dim`` features: trunk ``Linear -> LayerNorm -> Tanh`` (``mlp0``, of
    ``feature_dim``), ``Linear -> activation`` layers ``mlp1``..``mlpK`` (``net_arch``; ``None``: two of
    ``hidden_dim``) and ``Linear -> Tanh`` (``action``), the mean action; the parameters are :class:`DrQv2Policy`'s."""

    features_extractor: nn.Module | None = None  # the policy's encoder, not a submodule (expose_encoder)

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
        for index, units in enumerate(actor_critic_arch(net_arch, hidden_dim)[0], start=1):
            self.hidden_names.append(f"mlp{index}")
            layer = nn.Sequential(nn.Linear(in_dim, units), hidden_activation(activation, leaky_relu_slope))
            setattr(self, f"mlp{index}", layer)
            in_dim = units
        self.action = nn.Sequential(nn.Linear(in_dim, action_dim), nn.Tanh())

    def forward(self, features: th.Tensor) -> th.Tensor:
        """:return: the mean action ``(batch, action_dim)`` in [-1, 1] of the encoder's ``(batch, repr_dim)``"""
        h = self.trunk(features)
        for name in self.hidden_names:
            h = getattr(self, name)(h)
        return self.action(h)

    def named_layers(self) -> dict[str, nn.Module]:
        return {"mlp0": self.trunk, **{name: getattr(self, name) for name in self.hidden_names}, "action": self.action}


def sample_action(mean: th.Tensor, std: float, clip: float | None = None) -> th.Tensor:
    """:return: a sample ``(batch, action_dim)`` of DrQ-v2's ``TruncatedNormal(mean, std)``, noise clip ``clip``"""
    return noisy_action(mean, exploration_noise(mean.shape, std, clip, mean.device, mean.dtype))


def exploration_noise(
    shape: tuple[int, ...] | th.Size,
    std: float,
    clip: float | None = None,
    device: th.device | str | None = None,
    dtype: th.dtype = th.float32,
) -> th.Tensor:
    """:return: ``N(0, std)`` noise of ``shape`` on ``device`` (torch's generator), clipped to ``[-clip, clip]``"""
    eps = th.randn(shape, device=device, dtype=dtype) * std
    if clip is not None:
        eps = eps.clamp(-clip, clip)
    return eps


def noisy_action(mean: th.Tensor, eps: th.Tensor) -> th.Tensor:
    """:return: ``mean + eps`` clamped to ``[-1 + 1e-6, 1 - 1e-6]`` with a straight-through gradient (DrQ-v2's)"""
    action = mean + eps
    clamped = action.clamp(-1.0 + ACTION_EPS, 1.0 - ACTION_EPS)
    return action - action.detach() + clamped.detach()


class Critic(nn.Module):
    """DrQ-v2 twin critic: its own trunk ``Linear -> LayerNorm -> Tanh`` shared by the ``n_critics`` Q heads
    ``q1``..``qN``, each ``Linear -> activation`` per hidden layer then ``Linear(hidden -> 1)``; else :class:`Actor`."""

    features_extractor: nn.Module | None = None  # the policy's encoder, not a submodule (expose_encoder)

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
        arch = actor_critic_arch(net_arch, hidden_dim)[1]
        self.q_names = [f"q{index}" for index in range(1, n_critics + 1)]
        for name in self.q_names:
            setattr(self, name, _q_head(feature_dim + action_dim, arch, activation, leaky_relu_slope))

    def forward(self, features: th.Tensor, action: th.Tensor) -> tuple[th.Tensor, ...]:
        """:return: ``(Q1, .., QN)``, each ``(batch, 1)``, of the encoder's features and actions in [-1, 1]"""
        h_action = th.cat([self.trunk(features), action], dim=-1)
        return tuple(getattr(self, name)(h_action) for name in self.q_names)

    @property
    def q_networks(self) -> list[nn.Module]:
        """The Q heads, as SB3's ``ContinuousCritic.q_networks``."""
        return [getattr(self, name) for name in self.q_names]


def min_q(q_values: Sequence[th.Tensor]) -> th.Tensor:
    """:return: the element-wise minimum of the critic's ``(Q1, ..., QN)``"""
    return functools.reduce(th.min, q_values)


def critic_mse(q_values: Sequence[th.Tensor], target_q: th.Tensor) -> th.Tensor:
    """:return: ``MSE(Q1, y) + ... + MSE(QN, y)`` of the critic's ``q_values`` and the target ``y``"""
    return functools.reduce(operator.add, [F.mse_loss(q, target_q) for q in q_values])


def soft_update(params: Iterable[th.Tensor], target_params: Iterable[th.Tensor], tau: float) -> None:
    """SB3's ``polyak_update`` of ``target_params`` towards ``params`` by ``tau``, in two ``torch._foreach`` calls."""
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
    """Set SB3's ``features_extractor`` of each of ``networks`` to ``encoder`` (a user's extractor itself), not as a
    submodule: the encoder's parameters stay once in ``state_dict()``."""
    extractor = encoder.extractor if isinstance(encoder, FeaturesExtractorEncoder) else encoder
    for network in networks:
        network.__dict__["features_extractor"] = extractor  # nn.Module.__setattr__ would register it


class DrQv2Policy(BasePolicy):
    """
    Encoder, actor, critic and target critic of DrQ-v2, one Adam optimizer for each trained part; the encoder is
    trained by the critic loss only. SB3's keywords: docs/algorithm.md (*SB3's keywords*).

    :param observation_space: observation space
    :param action_space: action space, a bounded ``Box``
    :param lr_schedule: learning rate schedule
    :param feature_dim: size of the actor and critic trunk outputs (DrQ-v2's 50)
    :param hidden_dim: units of the two hidden layers of the actor and of each Q head (when ``net_arch`` is ``None``)
    :param encoder_class: ``PixelEncoder``, ``StateEncoder`` or ``DictEncoder``
    :param encoder_kwargs: keyword arguments of the encoder (``channels``, ``channels_last``, ``fused_relu``)
    :param optimizer_class: optimizer of the encoder, actor and critic
    :param optimizer_kwargs: its keyword arguments, learning rate excluded (Adam gets ``fused=True`` by default)
    :param activation: hidden activation of all networks: ``"relu"`` (DrQ-v2's) or ``"leaky_relu"``
    :param leaky_relu_slope: negative slope of the Leaky-ReLU
    :param net_arch: SB3's: hidden layers of the actor and each Q head, a list or ``dict(pi=[...], qf=[...])``
    :param activation_fn: SB3's: ``nn.ReLU`` or ``nn.LeakyReLU``; ``None`` leaves ``activation`` as given
    :param features_extractor_class: SB3's: a ``BaseFeaturesExtractor`` subclass in place of DrQ-v2's encoder
    :param features_extractor_kwargs: its keyword arguments (``features_dim``/``cnn_output_dim``: ``feature_dim``)
    :param normalize_images: SB3's: ``False`` takes float images already normalized
    :param share_features_extractor: SB3's: ``True`` only (one encoder)
    :param n_critics: SB3's: number of Q heads (DrQ-v2's 2)
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
        check_policy_kwargs(dict(
            feature_dim=feature_dim, hidden_dim=hidden_dim, net_arch=net_arch, activation=activation,
            activation_fn=activation_fn, features_extractor_class=features_extractor_class,
            encoder_kwargs=encoder_kwargs, features_extractor_kwargs=features_extractor_kwargs,
            share_features_extractor=share_features_extractor, n_critics=n_critics,
        ))  # fmt: skip
        if activation_fn is not None:
            activation = ACTIVATION_FNS[activation_fn]
        check_activation(activation, leaky_relu_slope)
        super().__init__(
            observation_space, action_space, optimizer_class=optimizer_class, optimizer_kwargs=optimizer_kwargs,
            squash_output=True, normalize_images=normalize_images,
        )  # fmt: skip
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
        self.encoder_kwargs = {**(encoder_kwargs or {}), **drqv2_encoder_kwargs}  # and SB3's for DrQ-v2's encoder
        self.activation = activation
        self.leaky_relu_slope = leaky_relu_slope
        if optimizer_class is th.optim.Adam and "fused" not in self.optimizer_kwargs:
            self.optimizer_kwargs["fused"] = True  # one kernel per step, the same update
        self.exploration_std = 1.0  # of predict(deterministic=False); the algorithm sets it from its schedule
        self._build(lr_schedule)

    def _build(self, lr_schedule: Schedule) -> None:
        """Create fresh networks (new random weights) and fresh optimizers."""
        action_dim = int(np.prod(self.action_space.shape))
        act = {"activation": self.activation, "leaky_relu_slope": self.leaky_relu_slope}
        if self.features_extractor_class is not None:
            self.encoder = FeaturesExtractorEncoder(
                self.observation_space, self.features_extractor_class, self.features_extractor_kwargs,
                self.normalize_images,
            )  # fmt: skip
        else:
            # An encoder class of its own may not take these: passed only when they differ from the defaults.
            encoder_act = act if self.activation != "relu" else {}
            normalize = {} if self.normalize_images else {"normalize_images": False}
            self.encoder = self.encoder_class(
                self.observation_space, **{**encoder_act, **normalize, **self.encoder_kwargs}
            )
        repr_dim = self.encoder.repr_dim
        self.actor = Actor(repr_dim, action_dim, self.feature_dim, self.hidden_dim, **act, net_arch=self.actor_arch)
        arch = dict(net_arch=self.critic_arch, n_critics=self.n_critics)
        self.critic = Critic(repr_dim, action_dim, self.feature_dim, self.hidden_dim, **act, **arch)  # type: ignore[arg-type]
        for module in (self.actor, self.critic):
            module.apply(weight_init)  # the encoder initializes itself (before switching to channels_last)
        for module in (self.encoder, self.actor, self.critic):
            module.float()  # SB3's observations and replay samples are float32, whatever torch's default dtype
        self.critic_target = copy.deepcopy(self.critic)
        self.critic_target.requires_grad_(False)
        expose_encoder(self.encoder, self.actor, self.critic, self.critic_target)

        lr = lr_schedule(1)
        params = list(self.encoder.parameters())
        self.encoder.optimizer = self.optimizer_class(params, lr=lr, **self.optimizer_kwargs) if params else None
        for module in (self.actor, self.critic):
            module.optimizer = self.optimizer_class(module.parameters(), lr=lr, **self.optimizer_kwargs)

    @property
    def optimizers(self) -> list[th.optim.Optimizer]:
        """The optimizers of the encoder (pixels only), the actor and the critic."""
        optimizers = [self.encoder.optimizer, self.actor.optimizer, self.critic.optimizer]
        return [optimizer for optimizer in optimizers if optimizer is not None]

    def named_layers(self) -> dict[str, nn.Module]:
        """:return: name (``cnn0``..``cnn4``, ``mlp0``..``action``) -> the module whose output is that activation and
        whose parameters are that layer's, input to output (the encoder's, then the actor's)"""
        return {**self.encoder.named_layers(), **self.actor.named_layers()}

    def _get_constructor_parameters(self) -> dict[str, Any]:
        names = (
            "observation_space", "action_space", "feature_dim", "hidden_dim", "encoder_class", "encoder_kwargs",
            "optimizer_class", "optimizer_kwargs", "activation", "leaky_relu_slope", "net_arch",
            "features_extractor_class", "features_extractor_kwargs", "normalize_images", "share_features_extractor",
            "n_critics",
        )  # fmt: skip
        return {**{name: getattr(self, name) for name in names}, "lr_schedule": self._dummy_schedule}

    def extract_features(  # type: ignore[override]
        self, obs: PyTorchObs, features_extractor: nn.Module | None = None
    ) -> th.Tensor:
        """SB3's: the ``(n, repr_dim)`` features of the one encoder (every network's ``features_extractor``; another
        module raises ``ValueError``)."""
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
        return mean if deterministic else sample_action(mean, self.exploration_std, clip=None)

    def set_training_mode(self, mode: bool) -> None:
        for module in (self.encoder, self.actor, self.critic):
            module.train(mode)
        self.training = mode

    def renew_networks(self, lr_schedule: Schedule) -> None:
        """New random weights (as :meth:`_build` draws them) copied into the existing parameters, so that compiled code
        stays valid, and new optimizers over them with ``lr_schedule``."""
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

    # The parts the interventions act on: sb3_collapse.monitoring.interventions.InterventionParts (duck typed).
    def initialize_weights(self, module: nn.Module) -> None:
        """New initial values for every parameter of ``module`` (a part of this policy), in place."""
        reinitialize(module, weight_init)

    def online_networks(self) -> dict[str, nn.Module]:
        """:return: the trained networks by name: ``encoder``, ``actor`` and ``critic``"""
        return {"encoder": self.encoder, "actor": self.actor, "critic": self.critic}

    def target_networks(self) -> dict[str, nn.Module]:
        """:return: the target networks by name: ``target critic``"""
        return {"target critic": self.critic_target}

    def feature_readers(self) -> list[nn.Module]:
        """:return: the networks that read the encoder's features: those of :meth:`online_networks` and
        :meth:`target_networks` but the encoder"""
        networks = {**self.online_networks(), **self.target_networks()}
        return [network for network in networks.values() if network is not self.encoder]

    def actor_modules(self) -> list[nn.Module]:
        """:return: what a reset of the actor renews: the whole actor (the encoder is the critic's, it is kept)"""
        return [self.actor]

    def actor_mlp_modules(self) -> list[nn.Module]:
        """:return: the actor's layers after the encoder: the whole actor"""
        return [self.actor]

    def hidden_layer_parts(self) -> list[LayerParts]:
        """:return: the hidden layers whose units ReDo may recycle: the actor's ``mlp1``.. (not the trunk ``mlp0``),
        then each Q network's ``q<k>.mlp1``.."""

        def leaves(module: nn.Module) -> list[nn.Module]:  # in registration order, the forward order here
            return [sub for sub in module.modules() if next(sub.children(), None) is None]

        parts = sequential_hidden_parts("", leaves(self.actor), first=0)
        for k, head in enumerate(self.critic.q_networks, start=1):
            parts += sequential_hidden_parts(f"q{k}.", leaves(head))
        return parts

    def encoder_channel_parts(self) -> list[LayerParts]:
        """:return: ``cnn1``..``cnn4`` as layers of channels ReDo may recycle, read by the next convolution or, for the
        last, by the first Linear of each of :meth:`feature_readers`; ``[]`` without convolutions"""
        if not isinstance(self.encoder, PixelEncoder):
            return []
        blocks = [(name, block) for name, block in self.encoder.named_layers().items() if isinstance(block, ConvReLU)]
        trunks = tuple(next(m for m in net.modules() if isinstance(m, nn.Linear)) for net in self.feature_readers())
        positions = self.encoder.repr_dim // blocks[-1][1][0].out_channels
        channels_last, last = self.encoder.channels_last, len(blocks) - 1
        return [
            LayerParts(name, block[0], block, trunks if k == last else (blocks[k + 1][1][0],),
                       positions if k == last else 1, channels_last)
            for k, (name, block) in enumerate(blocks)
        ]  # fmt: skip

    def forward_hidden(self, observations: PyTorchObs, actions: th.Tensor) -> None:
        """Run the encoder, the actor and the critic on ``(n, *obs_shape)`` observations and ``(n, action_dim)``
        actions, for hooks on their activations to read."""
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
    """DrQ-v2 from dict observations (:class:`DictEncoder`): the image keys encoded, the others concatenated."""

    def __init__(self, *args: Any, encoder_class: type[nn.Module] = DictEncoder, **kwargs: Any):
        super().__init__(*args, encoder_class=encoder_class, **kwargs)
