"""Checks of ``DrQv2``'s arguments, made before anything is built, so that a bad value fails with its name."""

from __future__ import annotations

import os
import pathlib
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
import torch as th
from stable_baselines3.common.type_aliases import Schedule

from sb3_collapse.drqv2.policies import check_policy_kwargs
from sb3_collapse.drqv2.rounds import TRAIN_FREQ_UNITS
from sb3_collapse.errors import ParameterError


def check_hyperparameters(
    *,
    learning_rate: float | Schedule = 1e-4,
    buffer_size: int = 1,
    learning_starts: int = 0,
    batch_size: int = 1,
    tau: float = 0.01,
    gamma: float = 0.99,
    train_freq: int | tuple[int, str] = 1,
    gradient_steps: int = 1,
    n_steps: int = 1,
    stddev_clip: float = 0.3,
    augmentation_pad: int = 0,
    policy_kwargs: Mapping[str, Any] | None = None,
    seed: int | None = None,
    device: th.device | str = "auto",
    cudnn_benchmark: bool = False,
) -> None:
    """
    Check :class:`DrQv2`'s hyperparameters (the constructor calls it; ``TrainConfig.validate`` too, before a run
    folder is created), so that a bad value fails before anything is built, with its name.

    :raises ParameterError: naming the first bad parameter, what it must be and what it got
    """

    def integer(name: str, value: Any, minimum: int) -> None:
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
            raise ParameterError(name, f"{name} must be an integer >= {minimum}, got {value!r}.")

    def number(name: str, value: Any, low: float, high: float = np.inf, low_open: bool = False) -> None:
        valid = isinstance(value, (int, float, np.number)) and not isinstance(value, bool) and np.isfinite(value)
        if not valid or value < low or (low_open and value == low) or value > high:
            bounds = f"{'>' if low_open else '>='} {low:g}" + ("" if high == np.inf else f" and <= {high:g}")
            raise ParameterError(name, f"{name} must be a finite number {bounds}, got {value!r}.")

    if not callable(learning_rate):
        number("learning_rate", learning_rate, 0.0, low_open=True)
    integer("buffer_size", buffer_size, 1)
    integer("learning_starts", learning_starts, 0)
    integer("batch_size", batch_size, 1)
    number("tau", tau, 0.0, 1.0)
    number("gamma", gamma, 0.0, 1.0)
    pair = list(train_freq) if isinstance(train_freq, (tuple, list)) else None  # a list from rl_zoo3's YAML
    integer("train_freq", pair[0] if pair else train_freq, 1)
    if pair is not None and (len(pair) != 2 or getattr(pair[1], "value", pair[1]) not in TRAIN_FREQ_UNITS):
        raise ParameterError(
            "train_freq",
            "train_freq must be n or (n, 'step') (SB3's: n steps of every environment), (n, 'episode'), or "
            f"(n, 'transition') (n transitions summed over the environments, DrQ-v2's ratio), got {train_freq!r}.",
        )
    if gradient_steps != -1:
        integer("gradient_steps", gradient_steps, 0)  # 0: collect without updating, as SB3 allows
    integer("n_steps", n_steps, 1)
    number("stddev_clip", stddev_clip, 0.0)
    integer("augmentation_pad", augmentation_pad, 0)
    for name in ("feature_dim", "hidden_dim"):
        if name in (policy_kwargs or {}):
            integer(f"policy_kwargs['{name}']", policy_kwargs[name], 1)  # type: ignore[index]
    check_policy_kwargs(policy_kwargs)  # SB3's keywords: net_arch, n_critics, share_features_extractor...
    if seed is not None:
        integer("seed", seed, 0)
    check_device(device)
    if not isinstance(cudnn_benchmark, bool):
        raise ParameterError("cudnn_benchmark", f"cudnn_benchmark must be True or False, got {cudnn_benchmark!r}.")


def check_device(device: th.device | str, name: str = "device") -> None:
    """
    :param device: a torch device, or ``"auto"``
    :param name: the parameter's name, for the message
    :raises ParameterError: for a device torch does not know, or CUDA without a GPU (instead of SB3's silent
        fallback to the CPU)
    """
    if device == "auto":
        return
    try:
        parsed = th.device(device)
    except (RuntimeError, TypeError) as error:
        message = f"{name} must be 'auto', 'cpu', 'cuda', 'cuda:N'..., got {device!r} ({error})."
        raise ParameterError(name, message) from None
    if parsed.type == "cuda" and not th.cuda.is_available():
        raise ParameterError(
            name,
            f"{name}={str(device)!r} asks for a CUDA GPU, but torch sees none (torch.cuda.is_available() is False): "
            "use device='cpu' or 'auto', or a CUDA build of torch on a machine with a GPU.",
        )


COMPILE_MODES = ("default", "reduce-overhead", "max-autotune", "max-autotune-no-cudagraphs")
"""The ``torch.compile`` modes that ``compile_update`` takes."""

CUDA_GRAPH_MODES = ("reduce-overhead", "max-autotune")
"""The modes among them that replay CUDA graphs on a CUDA device."""


def check_compile_update(compile_update: bool | str) -> None:
    """
    :param compile_update: the ``compile_update`` argument of ``DrQv2``
    :raises ParameterError: unless it is a bool or one of :data:`COMPILE_MODES`
    """
    if isinstance(compile_update, bool) or compile_update in COMPILE_MODES:
        return
    raise ParameterError(
        "compile_update",
        f"compile_update must be True, False or a torch.compile mode {COMPILE_MODES}, got {compile_update!r}.",
    )


def compile_mode(compile_update: bool | str, device: th.device) -> str:
    """
    :param compile_update: ``True`` or a mode (see ``DrQv2``)
    :param device: the model's device
    :return: the ``torch.compile`` mode: the given one, or for ``True`` ``"reduce-overhead"`` (CUDA graphs) on CUDA
        and ``"default"`` elsewhere
    """
    if isinstance(compile_update, str):
        return compile_update
    return "reduce-overhead" if device.type == "cuda" else "default"


def check_load_arguments(path: Any, kwargs: Mapping[str, Any], name: str = "DrQv2.load") -> None:
    """
    :param path: the path given to ``load`` (a file object is not checked)
    :param kwargs: the attributes it overrides
    :param name: the caller, for the messages
    :raises TypeError: for ``init_from``: loading restores the saved weights, it does not transplant
    :raises FileNotFoundError: when neither ``path`` nor ``path.zip`` is a file, naming the path given (SB3 would
        name ``path.zip``)
    """
    if "init_from" in kwargs:
        raise TypeError(
            f"{name} does not transplant layers (init_from): it restores the saved weights. Build a new "
            "model with DrQv2(policy, env, init_from={...}) to start from the layers of saved models."
        )
    if isinstance(path, (str, os.PathLike)):
        given = pathlib.Path(path)
        zipped = given.with_name(given.name + ".zip")
        if not given.is_file() and not (given.suffix != ".zip" and zipped.is_file()):
            tried = f"{os.fspath(path)!r}" + ("" if given.suffix == ".zip" else f" (nor {os.fspath(zipped)!r})")
            raise FileNotFoundError(f"{name}: no model file {tried}; give the path of a zip saved by DrQv2.save.")


def compile_losses(critic_loss: Callable, actor_loss: Callable, compile_update: bool | str, device: th.device) -> tuple:
    """
    :param critic_loss: ``DrQv2._critic_loss``
    :param actor_loss: ``DrQv2._actor_loss``
    :param compile_update: ``DrQv2``'s argument (``False``: the functions as they are)
    :param device: the model's device
    :return: the two functions, ``torch.compile``-d in :func:`compile_mode` with static shapes (the batch size is fixed
        during training: another batch size compiles its own code)
    """
    if not compile_update:
        return critic_loss, actor_loss
    mode = compile_mode(compile_update, device)
    return th.compile(critic_loss, mode=mode, dynamic=False), th.compile(actor_loss, mode=mode, dynamic=False)


def uses_cuda_graphs(compile_update: bool | str, device: th.device) -> bool:
    """:return: whether the compiled update replays CUDA graphs (each update then starts a new graph step)"""
    return bool(compile_update) and device.type == "cuda" and compile_mode(compile_update, device) in CUDA_GRAPH_MODES
