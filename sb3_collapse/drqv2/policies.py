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

With SB3's ``net_arch`` (``policy_kwargs=dict(net_arch=[...])``), the actor's hidden layers are ``mlp1``..``mlpK``, one
per entry (``mlp1`` and ``mlp2`` stay the first two hidden ReLU outputs; ``net_arch=[]`` has none). ``MultiInputPolicy``
names its image key's encoder ``cnn0``..``cnn4`` (``cnn1.<key>``... with several image keys); a user's
``features_extractor_class`` has no named layers. SB3's other policy keywords: see :class:`DrQv2Policy`.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.preprocessing import get_flattened_obs_dim, is_image_space, preprocess_obs
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from stable_baselines3.common.type_aliases import PyTorchObs, Schedule
from torch import nn
from torch.nn import functional as F

from sb3_collapse.common.layers import LayerParts, reinitialize, sequential_hidden_parts
from sb3_collapse.drqv2.augmentation import random_shift
from sb3_collapse.errors import ParameterError, SpaceError

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
    ``cnn0``: uint8 pixels to floats in [-0.5, 0.5] (DrQ-v2's ``obs / 255 - 0.5``).

    :param channels_last: return the images in ``channels_last`` memory format (faster convolutions)
    :param normalize_images: ``False``: the images are already normalized (SB3's ``normalize_images=False``), they
        are only converted to float
    """

    def __init__(self, channels_last: bool = True, normalize_images: bool = True) -> None:
        super().__init__()
        self.channels_last = channels_last
        self.normalize_images = normalize_images

    def forward(self, obs: th.Tensor) -> th.Tensor:
        if self.channels_last:
            obs = obs.contiguous(memory_format=th.channels_last)
        if not self.normalize_images:
            return obs.float()
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
    :param normalize_images: ``True``: ``uint8`` images, ``cnn0`` computes ``obs / 255 - 0.5``; ``False`` (SB3's
        keyword): images already normalized, any float ``Box`` of shape ``(channels, height, width)``, taken as they
        are
    """

    has_cnn = True
    """Random-shift augmentation applies to the observations (they are images)."""

    def __init__(
        self,
        observation_space: spaces.Space,
        channels: int = 32,
        channels_last: bool = True,
        fused_relu: bool = True,
        activation: str = "relu",
        leaky_relu_slope: float = LEAKY_RELU_SLOPE,
        normalize_images: bool = True,
    ) -> None:
        super().__init__()
        check_pixel_space(observation_space, normalize_images)
        for name, size in zip(("height", "width"), observation_space.shape[1:]):
            check_image_size(size, f"observation {name}")
        in_channels = observation_space.shape[0]
        self.cnn0 = PixelNormalization(channels_last, normalize_images)
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

    def augment(self, obs: th.Tensor, pad: int, shifts: th.Tensor) -> th.Tensor:
        """
        :param obs: a batch of images
        :param pad: random-shift padding in pixels
        :param shifts: the offsets of :func:`~sb3_collapse.drqv2.augmentation.draw_shifts`
        :return: the shifted images, in the memory format the convolutions take (no copy in ``cnn0``)
        """
        return random_shift(obs, pad, shifts, self.channels_last)


class StateEncoder(nn.Module):
    """
    Identity encoder for state vectors (``MlpPolicy``): the actor and critic trunks read the state directly.

    Observations go through SB3's ``preprocess_obs`` and are flattened, as SB3's ``FlattenExtractor`` does: a
    ``Box`` as floats, ``Discrete`` and ``MultiDiscrete`` one-hot encoded, ``MultiBinary`` as floats.

    :param observation_space: a ``Box`` that is not an image (any shape, flattened), ``Discrete``, ``MultiDiscrete``
        or ``MultiBinary``
    :param activation: unused (no layer), accepted so that every encoder takes the policy's activation
    :param leaky_relu_slope: unused
    :param normalize_images: unused (no image), accepted as SB3's policies accept it
    """

    has_cnn = False

    def __init__(
        self,
        observation_space: spaces.Space,
        activation: str = "relu",
        leaky_relu_slope: float = LEAKY_RELU_SLOPE,
        normalize_images: bool = True,
    ) -> None:
        super().__init__()
        check_state_space(observation_space)
        self.observation_space = observation_space
        self.repr_dim = int(get_flattened_obs_dim(observation_space))
        self.apply(weight_init)

    def forward(self, obs: th.Tensor) -> th.Tensor:
        if isinstance(self.observation_space, spaces.Box):
            return obs.float().flatten(1)
        return preprocess_obs(obs, self.observation_space).flatten(1)  # type: ignore[union-attr]

    def named_layers(self) -> dict[str, nn.Module]:
        return {}


def _image_keys(observation_space: spaces.Dict, normalize_images: bool) -> list[str]:
    """The keys of a ``Dict`` space whose spaces are channel-first images (uint8, or any float with
    ``normalize_images=False``)."""
    return [
        key
        for key, space in observation_space.spaces.items()
        if is_image_space(space, check_channels=False, normalized_image=not normalize_images)
        and space.shape[0] < min(space.shape[1:])
    ]


def _shift_images(obs: Any, pad: int, shifts: th.Tensor, image_keys: Sequence[str] | None) -> Any:
    """Random shift of the images of ``obs``: the tensor itself (``image_keys=None``) or its ``image_keys``."""
    if image_keys is None:
        return random_shift(obs, pad, shifts)
    return {key: random_shift(value, pad, shifts) if key in image_keys else value for key, value in obs.items()}


class DictEncoder(nn.Module):
    """
    Encoder of ``spaces.Dict`` observations (``MultiInputPolicy``), as visual RL with proprioception does: DrQ-v2's
    :class:`PixelEncoder` on each image key (a channel-first ``uint8`` ``Box``; any float ``Box`` of 3 dimensions
    with ``normalize_images=False``), every other key through SB3's ``preprocess_obs`` (one-hot for discrete
    spaces), flattened; all concatenated, the image features first (in the space's key order), then the others.

    Random-shift augmentation applies to the image keys only; a sample's image keys share one shift.

    Named layers: with one image key, its encoder's ``cnn0``..``cnn4``; with several, ``cnn0.<key>``..
    ``cnn4.<key>`` for each key; none without an image key.

    :param observation_space: a ``spaces.Dict`` of ``Box``, ``Discrete``, ``MultiDiscrete`` or ``MultiBinary``
    :param activation: ``"relu"`` (DrQ-v2's) or ``"leaky_relu"`` in the pixel encoders
    :param leaky_relu_slope: negative slope of the Leaky-ReLU
    :param normalize_images: as :class:`PixelEncoder`'s
    :param encoder_kwargs: keyword arguments of each :class:`PixelEncoder` (``channels``, ``channels_last``,
        ``fused_relu``)
    """

    def __init__(
        self,
        observation_space: spaces.Space,
        activation: str = "relu",
        leaky_relu_slope: float = LEAKY_RELU_SLOPE,
        normalize_images: bool = True,
        **encoder_kwargs: Any,
    ) -> None:
        super().__init__()
        if not isinstance(observation_space, spaces.Dict):
            raise SpaceError(
                "policy",
                f"MultiInputPolicy takes dict observations (gymnasium.spaces.Dict), got {observation_space}: use "
                "CnnPolicy for images, MlpPolicy for state vectors.",
            )
        self.observation_space = observation_space
        self.image_keys = _image_keys(observation_space, normalize_images)
        self.vector_keys = [key for key in observation_space.spaces if key not in self.image_keys]
        for key in self.vector_keys:
            check_state_space(observation_space[key], f"MultiInputPolicy's key {key!r}")
        kwargs = dict(activation=activation, leaky_relu_slope=leaky_relu_slope, normalize_images=normalize_images)
        self.pixel_encoders = nn.ModuleDict(
            {key: PixelEncoder(observation_space[key], **{**kwargs, **encoder_kwargs}) for key in self.image_keys}
        )
        self.has_cnn = bool(self.image_keys)
        self.repr_dim = sum(encoder.repr_dim for encoder in self.pixel_encoders.values()) + sum(
            get_flattened_obs_dim(observation_space[key]) for key in self.vector_keys
        )

    def forward(self, obs: dict[str, th.Tensor]) -> th.Tensor:
        features = [self.pixel_encoders[key](obs[key]) for key in self.image_keys]
        for key in self.vector_keys:
            features.append(preprocess_obs(obs[key], self.observation_space[key]).float().flatten(1))  # type: ignore[union-attr]
        return th.cat(features, dim=1)

    def augment(self, obs: dict[str, th.Tensor], pad: int, shifts: th.Tensor) -> dict[str, th.Tensor]:
        """
        :param obs: a batch of dict observations
        :param pad: random-shift padding in pixels
        :param shifts: the offsets of :func:`~sb3_collapse.drqv2.augmentation.draw_shifts`, one per sample
        :return: the observations, their image keys shifted
        """
        return {
            key: self.pixel_encoders[key].augment(value, pad, shifts) if key in self.image_keys else value
            for key, value in obs.items()
        }

    def named_layers(self) -> dict[str, nn.Module]:
        if len(self.image_keys) == 1:
            return self.pixel_encoders[self.image_keys[0]].named_layers()
        return {
            f"{name}.{key}": module
            for key in self.image_keys
            for name, module in self.pixel_encoders[key].named_layers().items()
        }


class FeaturesExtractorEncoder(nn.Module):
    """
    A user's SB3 features extractor (``policy_kwargs=dict(features_extractor_class=...)``) in place of DrQ-v2's
    encoder: the observations go through SB3's ``preprocess_obs`` (images divided by 255 unless
    ``normalize_images=False``, discrete spaces one-hot encoded), then the extractor, as in SB3's policies. It is
    shared by the actor and the critic and trained by the critic loss only, as DrQ-v2's encoder.

    Random-shift augmentation applies to image observations (a channel-first image ``Box``, or the image keys of a
    ``Dict``), before the extractor. The extractor keeps its own initialization; it has no named layers.

    :param observation_space: the observation space
    :param features_extractor_class: a ``BaseFeaturesExtractor`` subclass
    :param features_extractor_kwargs: its keyword arguments
    :param normalize_images: SB3's: divide images by 255
    """

    def __init__(
        self,
        observation_space: spaces.Space,
        features_extractor_class: type[BaseFeaturesExtractor],
        features_extractor_kwargs: Mapping[str, Any] | None = None,
        normalize_images: bool = True,
    ) -> None:
        super().__init__()
        if not (
            isinstance(features_extractor_class, type) and issubclass(features_extractor_class, BaseFeaturesExtractor)
        ):
            raise ParameterError(
                "policy_kwargs['features_extractor_class']",
                "policy_kwargs['features_extractor_class'] must be a subclass of SB3's BaseFeaturesExtractor "
                f"(stable_baselines3.common.torch_layers), got {features_extractor_class!r}.",
            )
        self.observation_space = observation_space
        self.normalize_images = normalize_images
        self.extractor = features_extractor_class(observation_space, **(features_extractor_kwargs or {}))
        self.repr_dim = int(self.extractor.features_dim)
        self.image_keys: list[str] | None = None
        if isinstance(observation_space, spaces.Dict):
            self.image_keys = _image_keys(observation_space, normalize_images)
            self.has_cnn = bool(self.image_keys)
        else:
            self.has_cnn = is_image_space(observation_space, normalized_image=not normalize_images) and (
                observation_space.shape[0] < min(observation_space.shape[1:])  # channel-first
            )

    def forward(self, obs: PyTorchObs) -> th.Tensor:
        return self.extractor(preprocess_obs(obs, self.observation_space, self.normalize_images))

    def augment(self, obs: PyTorchObs, pad: int, shifts: th.Tensor) -> PyTorchObs:
        """
        :param obs: a batch of observations
        :param pad: random-shift padding in pixels
        :param shifts: the offsets of :func:`~sb3_collapse.drqv2.augmentation.draw_shifts`, one per sample
        :return: the observations, their images shifted
        """
        return _shift_images(obs, pad, shifts, self.image_keys)

    def named_layers(self) -> dict[str, nn.Module]:
        return {}


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


def _q_head(
    in_dim: int, net_arch: Sequence[int], activation: str = "relu", leaky_relu_slope: float = LEAKY_RELU_SLOPE
) -> nn.Sequential:
    layers: list[nn.Module] = []
    for units in net_arch:
        layers += [nn.Linear(in_dim, units), hidden_activation(activation, leaky_relu_slope)]
        in_dim = units
    return nn.Sequential(*layers, nn.Linear(in_dim, 1))


class DrQv2Policy(BasePolicy):
    """
    Encoder, actor, critic and target critic of DrQ-v2, with one Adam optimizer for each trained part.

    The encoder is trained by the critic loss only; the target critic (trunk and heads) is a soft copy of
    the critic; there is no target encoder and no target actor.

    SB3's policy keywords (those of TD3's ``TD3Policy``) mean what they mean there; see ``docs/algorithm.md``.

    :param observation_space: observation space
    :param action_space: action space, a bounded ``Box``
    :param lr_schedule: learning rate schedule (constant 1e-4 in DrQ-v2)
    :param feature_dim: size of the actor and critic trunk outputs (50; 100 for humanoid in DrQ-v2)
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
    :param features_extractor_class: SB3's: a ``BaseFeaturesExtractor`` subclass used in place of DrQ-v2's
        encoder (:class:`FeaturesExtractorEncoder`), shared by the actor and the critic and trained by the critic
        loss; ``None``: DrQ-v2's encoder (``encoder_class``)
    :param features_extractor_kwargs: its keyword arguments; without ``features_extractor_class``, those of DrQ-v2's
        encoder (as ``encoder_kwargs``)
    :param normalize_images: SB3's: ``True`` divides ``uint8`` images by 255 (DrQ-v2's encoder: ``obs / 255 - 0.5``);
        ``False`` takes images already normalized (float ``Box`` observations) as they are
    :param share_features_extractor: SB3's: ``True``, DrQ-v2's only setting (one encoder for the actor and the
        critic, trained by the critic loss only, as TD3's ``share_features_extractor=True``); ``False`` is refused
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
        self.feature_dim = feature_dim
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
        if features_extractor_class is None and features_extractor_kwargs:
            self.encoder_kwargs = {**self.encoder_kwargs, **features_extractor_kwargs}  # DrQ-v2's encoder's
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
            net_arch=self.net_arch,
            features_extractor_class=self.features_extractor_class,
            features_extractor_kwargs=self.features_extractor_kwargs,
            normalize_images=self.normalize_images,
            share_features_extractor=self.share_features_extractor,
            n_critics=self.n_critics,
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


ACTIVATION_FNS: dict[type[nn.Module], str] = {nn.ReLU: "relu", nn.LeakyReLU: "leaky_relu"}
"""SB3's ``activation_fn`` values DrQv2 takes, and the ``activation`` each means."""


def actor_critic_arch(
    net_arch: list[int] | dict[str, list[int]] | None, hidden_dim: int
) -> tuple[list[int], list[int]]:
    """
    SB3's ``get_actor_critic_arch`` with DrQ-v2's default.

    :param net_arch: a list of units (actor and each Q head), ``dict(pi=[...], qf=[...])``, or ``None``
    :param hidden_dim: the units of DrQ-v2's two hidden layers, for ``None``
    :return: the hidden layers of the actor and of each Q head
    """
    if net_arch is None:
        return [hidden_dim, hidden_dim], [hidden_dim, hidden_dim]
    if isinstance(net_arch, Mapping):
        return [int(units) for units in net_arch["pi"]], [int(units) for units in net_arch["qf"]]
    return [int(units) for units in net_arch], [int(units) for units in net_arch]


def check_policy_kwargs(policy_kwargs: Mapping[str, Any] | None) -> None:
    """
    Check the SB3 keywords of ``policy_kwargs`` (``DrQv2``'s constructor and ``check_hyperparameters`` call it, before
    anything is built).

    :param policy_kwargs: the ``policy_kwargs`` of ``DrQv2``
    :raises ParameterError: naming the first bad keyword (``policy_kwargs['net_arch']``), what it must be and what
        to pass instead
    """
    kwargs = dict(policy_kwargs or {})

    def name(key: str) -> str:
        return f"policy_kwargs['{key}']"

    def units(key: str, value: Any) -> None:
        if not isinstance(value, (list, tuple)) or any(
            isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1 for n in value
        ):
            raise ParameterError(
                name("net_arch"),
                f"{key} must be a list of layer sizes (integers >= 1), e.g. [1024, 1024] (DrQ-v2's), got {value!r}.",
            )

    net_arch = kwargs.get("net_arch")
    if isinstance(net_arch, Mapping):
        if set(net_arch) != {"pi", "qf"}:
            raise ParameterError(
                name("net_arch"),
                "policy_kwargs['net_arch'] as a dict takes the keys 'pi' (actor) and 'qf' (each Q head), both, as SB3's "
                f"TD3; got {sorted(net_arch)}. Pass e.g. dict(pi=[1024, 1024], qf=[1024, 1024]), or one list for both.",
            )
        for key in ("pi", "qf"):
            units(f"policy_kwargs['net_arch']['{key}']", net_arch[key])
    elif net_arch is not None:
        units("policy_kwargs['net_arch']", net_arch)
    if net_arch is not None and kwargs.get("hidden_dim", 1024) != 1024:
        raise ParameterError(
            name("net_arch"),
            f"policy_kwargs gives both net_arch={net_arch!r} and hidden_dim={kwargs['hidden_dim']!r}: pass one "
            "(hidden_dim=h is net_arch=[h, h]).",
        )
    n_critics = kwargs.get("n_critics", 2)
    if isinstance(n_critics, bool) or not isinstance(n_critics, (int, np.integer)) or n_critics < 1:
        raise ParameterError(
            name("n_critics"), f"policy_kwargs['n_critics'] must be an integer >= 1, got {n_critics!r}."
        )
    if kwargs.get("share_features_extractor", True) is not True:
        raise ParameterError(
            name("share_features_extractor"),
            "DrQ-v2 has one encoder, shared by the actor and the critic and trained by the critic loss only (SB3's "
            "share_features_extractor=True); a separate actor encoder trained by the actor loss "
            "(share_features_extractor=False, TD3's default) is another algorithm. Leave share_features_extractor out "
            f"or pass True; got {kwargs['share_features_extractor']!r}.",
        )
    activation_fn = kwargs.get("activation_fn")
    if activation_fn is not None:
        if activation_fn not in ACTIVATION_FNS:
            raise ParameterError(
                name("activation_fn"),
                f"policy_kwargs['activation_fn'] must be torch.nn.ReLU (DrQ-v2's) or torch.nn.LeakyReLU (with "
                f"leaky_relu_slope), got {activation_fn!r}.",
            )
        if kwargs.get("activation", "relu") not in ("relu", ACTIVATION_FNS[activation_fn]):
            raise ParameterError(
                name("activation_fn"),
                f"policy_kwargs gives activation_fn={activation_fn.__name__} and activation={kwargs['activation']!r}: "
                "pass one.",
            )
    extractor = kwargs.get("features_extractor_class")
    if extractor is not None and not (isinstance(extractor, type) and issubclass(extractor, BaseFeaturesExtractor)):
        raise ParameterError(
            name("features_extractor_class"),
            "policy_kwargs['features_extractor_class'] must be a subclass of SB3's BaseFeaturesExtractor "
            f"(stable_baselines3.common.torch_layers), got {extractor!r}.",
        )
    if extractor is None and kwargs.get("features_extractor_kwargs") and kwargs.get("encoder_kwargs"):
        raise ParameterError(
            name("features_extractor_kwargs"),
            "without features_extractor_class, features_extractor_kwargs are the keyword arguments of DrQ-v2's encoder, "
            "as encoder_kwargs: pass one of them.",
        )


def check_pixel_space(observation_space: spaces.Space, normalize_images: bool = True) -> None:
    """
    :param observation_space: space to check
    :param normalize_images: ``False``: any float ``Box`` of 3 dimensions is an image (already normalized)
    :raises SpaceError: unless it is a channel-first image ``Box`` (``(C, H, W)``, ``C < H, W``), ``uint8`` in
        [0, 255] unless ``normalize_images=False``
    """
    if not (
        isinstance(observation_space, spaces.Box)
        and is_image_space(observation_space, check_channels=False, normalized_image=not normalize_images)
        and observation_space.shape[0] < min(observation_space.shape[1:])
    ):
        raise SpaceError(
            "policy",
            f"CnnPolicy needs channel-first uint8 image observations of shape (channels, height, width), "
            f"such as make_dmc_env(...)'s (9, 84, 84), but got {observation_space}. "
            "Use MlpPolicy for state vectors (make_dmc_env(..., obs_type='state')), MultiInputPolicy for dict "
            "observations, and policy_kwargs=dict(normalize_images=False) for float images already normalized.",
        )
    height, width = observation_space.shape[1:]
    if min(_conv_output_size((height, width))) < 1:
        raise SpaceError(
            "env", f"Images of {height}x{width} pixels are too small for the DrQ-v2 encoder (at least 15x15)."
        )


STATE_SPACES = (spaces.Box, spaces.Discrete, spaces.MultiDiscrete, spaces.MultiBinary)
"""The observation spaces of ``MlpPolicy`` (and of the non-image keys of ``MultiInputPolicy``)."""


def check_state_space(observation_space: spaces.Space, where: str = "MlpPolicy") -> None:
    """
    :param observation_space: space to check
    :param where: who takes it, for the message
    :raises SpaceError: unless it is a ``Box`` that is not an image (flattened), ``Discrete``, ``MultiDiscrete`` or
        ``MultiBinary``
    """
    if isinstance(observation_space, spaces.Box) and is_image_space(observation_space, check_channels=False):
        raise SpaceError(
            "policy",
            f"{where} takes state vectors, but the observations are images {observation_space}: use CnnPolicy.",
        )
    if isinstance(observation_space, spaces.Dict):
        raise SpaceError(
            "policy",
            f"{where} takes state vectors, got dict observations {observation_space}: use MultiInputPolicy "
            "(images through DrQ-v2's encoder, the other keys concatenated), or flatten them "
            "(gymnasium.wrappers.FlattenObservation).",
        )
    if not isinstance(observation_space, STATE_SPACES):
        raise SpaceError(
            "policy",
            f"{where} needs a Box, Discrete, MultiDiscrete or MultiBinary observation space, got {observation_space}.",
        )


def check_action_space(action_space: spaces.Space) -> None:
    """
    :param action_space: space to check
    :raises SpaceError: unless it is a ``Box`` with finite bounds (DrQ-v2 is for continuous control); also a
        ``TypeError`` and an ``AssertionError`` (what SB3 raises for an unsupported action space)
    """
    if not isinstance(action_space, spaces.Box):
        raise SpaceError(
            "env",
            f"DrQv2 is for continuous actions (gymnasium.spaces.Box), got {type(action_space).__name__}: {action_space}.",
        )
    if not (np.all(np.isfinite(action_space.low)) and np.all(np.isfinite(action_space.high))):
        raise SpaceError("env", f"DrQv2 needs finite action bounds to rescale its tanh actions, got {action_space}.")


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
