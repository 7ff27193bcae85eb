"""The encoders of DrQ-v2's policies (pixels, state vectors, dict observations, a user's SB3 features extractor),
the hidden activation, DrQ-v2's weight initialization and the checks of observation spaces."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.preprocessing import get_flattened_obs_dim, is_image_space, preprocess_obs
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from stable_baselines3.common.type_aliases import PyTorchObs
from torch import nn

from sb3_collapse.drqv2.augmentation import random_shift
from sb3_collapse.errors import ParameterError, SpaceError

ACTIVATIONS = ("relu", "leaky_relu")  # ReLU (DrQ-v2's) or Leaky-ReLU (the paper's footnote 1 ablation)
LEAKY_RELU_SLOPE = 0.01  # PyTorch's default: the paper gives none (docs/interventions.md)


def check_activation(activation: str, leaky_relu_slope: float = LEAKY_RELU_SLOPE) -> None:
    """:raises ParameterError: unless ``activation`` is one of :data:`ACTIVATIONS` and ``leaky_relu_slope`` in (0, 1)"""
    if activation not in ACTIVATIONS:
        raise ParameterError("activation", f"activation must be one of {', '.join(ACTIVATIONS)}, got {activation!r}.")
    if isinstance(leaky_relu_slope, bool) or not 0.0 < leaky_relu_slope < 1.0:
        raise ParameterError(
            "leaky_relu_slope", f"leaky_relu_slope must be in (0, 1) (0 is a ReLU), got {leaky_relu_slope!r}."
        )


def hidden_activation(activation: str = "relu", leaky_relu_slope: float = LEAKY_RELU_SLOPE) -> nn.Module:
    """:return: a new in-place ``nn.ReLU`` or ``nn.LeakyReLU(leaky_relu_slope)`` for ``activation``"""
    check_activation(activation, leaky_relu_slope)
    return nn.LeakyReLU(leaky_relu_slope, inplace=True) if activation == "leaky_relu" else nn.ReLU(inplace=True)


def weight_init(module: nn.Module) -> None:
    """DrQ-v2's initialization of ``module`` in place (``Module.apply``): orthogonal weights (gain 1 for Linear,
    sqrt(2) for Conv), zero biases."""
    if isinstance(module, (nn.Linear, nn.Conv2d, nn.ConvTranspose2d)):
        gain = 1.0 if isinstance(module, nn.Linear) else nn.init.calculate_gain("relu")
        nn.init.orthogonal_(module.weight.data, gain)
        if module.bias is not None:
            module.bias.data.fill_(0.0)


class PixelNormalization(nn.Module):
    """``cnn0``: uint8 pixels to floats in [-0.5, 0.5] (DrQ-v2's ``obs / 255 - 0.5``), in ``channels_last`` memory
    format; with ``normalize_images=False`` only converted to float."""

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


try:  # whether this torch has oneDNN's convolution with a fused ReLU: ConvReLU runs as one kernel on the CPU
    FUSED_CONV_RELU = th.backends.mkldnn.is_available() and hasattr(th.ops.mkldnn, "_convolution_pointwise")
except (AttributeError, RuntimeError):
    FUSED_CONV_RELU = False


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
        )  # fmt: skip
        return (*grads, None)


class ConvReLU(nn.Sequential):
    """``Conv2d(in_channels, out_channels, 3, stride)`` then the ``activation``, one named layer (``cnn1``..``cnn4``);
    with ``fused``, one oneDNN kernel on the CPU with the same values (docs/algorithm.md)."""

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
        fused = FUSED_CONV_RELU and fusable and not th.compiler.is_compiling()
        return _FusedConvReLU.apply(x, conv.weight, conv.bias, conv) if fused else super().forward(x)


class PixelEncoder(nn.Module):
    """
    DrQ-v2's convolutional encoder of channel-first ``uint8`` images: ``cnn0`` normalization, four 3x3 convolutions
    (stride 2, 1, 1, 1), no padding, the ``activation`` after each, flattened ((H, W, C) with ``channels_last``).

    :param channels: number of filters of every convolution
    :param channels_last: run the convolutions in ``channels_last`` memory format
    :param fused_relu: on the CPU, run each convolution and its ReLU as one kernel (:class:`ConvReLU`)
    :param normalize_images: ``False`` (SB3's keyword): float images already normalized, taken as they are
    """

    has_cnn = True  # random-shift augmentation applies

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
        check_pixel_space(observation_space, normalize_images)  # images of at least MIN_IMAGE_SIZE pixels
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
        return h.permute(0, 2, 3, 1).flatten(1) if self.channels_last else h.flatten(1)  # (H, W, C): a free view

    def named_layers(self) -> dict[str, nn.Module]:
        return {"cnn0": self.cnn0, "cnn1": self.cnn1, "cnn2": self.cnn2, "cnn3": self.cnn3, "cnn4": self.cnn4}

    def augment(self, obs: th.Tensor, pad: int, shifts: th.Tensor) -> th.Tensor:
        """:return: ``obs`` shifted by ``shifts`` (:func:`draw_shifts`'s) after padding ``pad`` pixels, in the
        memory format the convolutions take"""
        return random_shift(obs, pad, shifts, self.channels_last)


class StateEncoder(nn.Module):
    """Identity encoder of ``MlpPolicy``: SB3's ``preprocess_obs``, flattened (as SB3's ``FlattenExtractor``); it
    takes the other encoders' ``activation``, ``leaky_relu_slope`` and ``normalize_images`` and ignores them."""

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

    def forward(self, obs: th.Tensor) -> th.Tensor:
        box = isinstance(self.observation_space, spaces.Box)
        return obs.float().flatten(1) if box else preprocess_obs(obs, self.observation_space).flatten(1)  # type: ignore[union-attr]

    def named_layers(self) -> dict[str, nn.Module]:
        return {}


def _channel_first_image(space: spaces.Space, normalize_images: bool, check_channels: bool = False) -> bool:
    """Whether ``space`` is an image ``Box`` ``(C, H, W)`` with ``C < H, W`` (``uint8`` unless ``normalize_images``)."""
    image = is_image_space(space, check_channels=check_channels, normalized_image=not normalize_images)
    return image and space.shape[0] < min(space.shape[1:])  # type: ignore[index]


def _image_keys(observation_space: spaces.Dict, normalize_images: bool) -> list[str]:
    """The keys of a ``Dict`` space whose spaces are channel-first images."""
    return [key for key, space in observation_space.spaces.items() if _channel_first_image(space, normalize_images)]


class DictEncoder(nn.Module):
    """Encoder of ``spaces.Dict`` observations (``MultiInputPolicy``): a :class:`PixelEncoder` (``encoder_kwargs``)
    on each image key, the other keys through SB3's ``preprocess_obs``, flattened; concatenated, images first."""

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
        images = [self.pixel_encoders[key](obs[key]) for key in self.image_keys]
        vectors = [preprocess_obs(obs[key], self.observation_space[key]).float().flatten(1) for key in self.vector_keys]  # type: ignore[union-attr]
        return th.cat(images + vectors, dim=1)

    def augment(self, obs: dict[str, th.Tensor], pad: int, shifts: th.Tensor) -> dict[str, th.Tensor]:
        """:return: ``obs`` with its image keys shifted (:meth:`PixelEncoder.augment`)"""
        return {
            key: self.pixel_encoders[key].augment(value, pad, shifts) if key in self.image_keys else value
            for key, value in obs.items()
        }

    def named_layers(self) -> dict[str, nn.Module]:
        layers = {key: self.pixel_encoders[key].named_layers() for key in self.image_keys}
        if len(layers) == 1:
            return next(iter(layers.values()))
        return {f"{name}.{key}": module for key, named in layers.items() for name, module in named.items()}


class FeaturesExtractorEncoder(nn.Module):
    """A user's SB3 ``features_extractor_class`` (with ``features_extractor_kwargs``) in place of DrQ-v2's encoder,
    after SB3's ``preprocess_obs``; trained by the critic loss only, on shifted images; no named layers."""

    def __init__(
        self,
        observation_space: spaces.Space,
        features_extractor_class: type[BaseFeaturesExtractor],
        features_extractor_kwargs: Mapping[str, Any] | None = None,
        normalize_images: bool = True,
    ) -> None:
        super().__init__()
        self.observation_space = observation_space
        self.normalize_images = normalize_images
        self.extractor = features_extractor_class(observation_space, **(features_extractor_kwargs or {}))
        self.repr_dim = int(self.extractor.features_dim)
        self.image_keys: list[str] | None = None
        if isinstance(observation_space, spaces.Dict):
            self.image_keys = _image_keys(observation_space, normalize_images)
            self.has_cnn = bool(self.image_keys)
        else:
            self.has_cnn = _channel_first_image(observation_space, normalize_images, check_channels=True)

    def forward(self, obs: PyTorchObs) -> th.Tensor:
        return self.extractor(preprocess_obs(obs, self.observation_space, self.normalize_images))

    def augment(self, obs: PyTorchObs, pad: int, shifts: th.Tensor) -> PyTorchObs:
        """:return: ``obs`` with its images shifted (:meth:`PixelEncoder.augment`)"""
        if self.image_keys is None:
            return random_shift(obs, pad, shifts)  # type: ignore[arg-type]
        return {k: random_shift(v, pad, shifts) if k in self.image_keys else v for k, v in obs.items()}  # type: ignore[union-attr]

    def named_layers(self) -> dict[str, nn.Module]:
        return {}


def check_pixel_space(observation_space: spaces.Space, normalize_images: bool = True) -> None:
    """:raises SpaceError: unless ``observation_space`` is a channel-first image ``Box`` (``uint8`` unless
    ``normalize_images=False``)"""
    if not _channel_first_image(observation_space, normalize_images):
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
            "env",
            f"Images of {height}x{width} pixels are too small for the DrQ-v2 encoder (at least "
            f"{MIN_IMAGE_SIZE}x{MIN_IMAGE_SIZE}).",
        )


STATE_SPACES = (spaces.Box, spaces.Discrete, spaces.MultiDiscrete, spaces.MultiBinary)  # MlpPolicy's


def check_state_space(observation_space: spaces.Space, where: str = "MlpPolicy") -> None:
    """:raises SpaceError: unless ``observation_space`` is one of :data:`STATE_SPACES` and no image (``where``
    takes it)"""
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


def _conv_output_size(image_size: tuple[int, ...]) -> tuple[int, ...]:
    """Height and width after the encoder: 3x3 stride 2 then three 3x3 stride 1, no padding."""
    return tuple((size - 3) // 2 + 1 - 6 for size in image_size)


MIN_IMAGE_SIZE = 15  # pixels: the smallest height and width the convolutions leave 1x1 of


def check_image_size(size: int, name: str = "size") -> None:
    """:raises ParameterError: when the convolutions would leave nothing of an image ``size`` pixels high or wide"""
    if size < MIN_IMAGE_SIZE:
        raise ParameterError(
            name,
            f"{name} must be >= {MIN_IMAGE_SIZE} pixels (the encoder's 3x3 convolutions, the first with stride 2, "
            f"leave nothing of smaller images), got {size}.",
        )
