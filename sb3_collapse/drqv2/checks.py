"""Checks of ``DrQv2``'s arguments, made before anything is built, so that a bad value fails with its name."""

from __future__ import annotations

import inspect
import io
import json
import os
import pathlib
import re
import zipfile
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
import stable_baselines3
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import NStepReplayBuffer, ReplayBuffer
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from stable_baselines3.common.type_aliases import Schedule
from torch import nn

from sb3_collapse.drqv2.replay_buffer import FrameStackReplayBuffer
from sb3_collapse.drqv2.rounds import TRAIN_FREQ_UNITS
from sb3_collapse.errors import ParameterError, SpaceError


def _integer(name: str, value: Any, minimum: int, parameter: str | None = None) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ParameterError(parameter or name, f"{name} must be an integer >= {minimum}, got {value!r}.")


def _number(name: str, value: Any, low: float, high: float = np.inf, low_open: bool = False) -> None:
    valid = isinstance(value, (int, float, np.number)) and not isinstance(value, bool) and np.isfinite(value)
    if not valid or value < low or (low_open and value == low) or value > high:
        bounds = f"{'>' if low_open else '>='} {low:g}" + ("" if high == np.inf else f" and <= {high:g}")
        raise ParameterError(name, f"{name} must be a finite number {bounds}, got {value!r}.")


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
    """:raises ParameterError: naming the first bad hyperparameter of ``DrQv2``, what it must be and what it got"""
    if not callable(learning_rate):
        _number("learning_rate", learning_rate, 0.0, low_open=True)
    _integer("buffer_size", buffer_size, 1)
    _integer("learning_starts", learning_starts, 0)
    _integer("batch_size", batch_size, 1)
    _number("tau", tau, 0.0, 1.0)
    _number("gamma", gamma, 0.0, 1.0)
    pair = list(train_freq) if isinstance(train_freq, (tuple, list)) else None  # a list from rl_zoo3's YAML
    _integer("train_freq", pair[0] if pair else train_freq, 1)
    if pair is not None and (len(pair) != 2 or getattr(pair[1], "value", pair[1]) not in TRAIN_FREQ_UNITS):
        raise ParameterError(
            "train_freq",
            "train_freq must be n or (n, 'step') (SB3's: n steps of every environment), (n, 'episode'), or "
            f"(n, 'transition') (n transitions summed over the environments, DrQ-v2's ratio), got {train_freq!r}.",
        )
    if gradient_steps != -1:
        _integer("gradient_steps", gradient_steps, 0)  # 0: collect without updating, as SB3 allows
    _integer("n_steps", n_steps, 1)
    _number("stddev_clip", stddev_clip, 0.0)
    _integer("augmentation_pad", augmentation_pad, 0)
    for name in ("feature_dim", "hidden_dim"):
        if name in (policy_kwargs or {}):
            _integer(f"policy_kwargs['{name}']", policy_kwargs[name], 1)  # type: ignore[index]
    check_policy_kwargs(policy_kwargs)  # SB3's keywords: net_arch, n_critics, share_features_extractor...
    if seed is not None:
        _integer("seed", seed, 0)
    check_device(device)
    if not isinstance(cudnn_benchmark, bool):
        raise ParameterError("cudnn_benchmark", f"cudnn_benchmark must be True or False, got {cudnn_benchmark!r}.")


def check_device(device: th.device | str, name: str = "device") -> None:
    """:raises ParameterError: for a ``device`` torch does not know, or CUDA without a GPU (``name``: the parameter)"""
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
CUDA_GRAPH_MODES = ("reduce-overhead", "max-autotune")  # replay CUDA graphs on a CUDA device


def check_compile_update(compile_update: bool | str) -> None:
    """:raises ParameterError: unless ``compile_update`` is a bool or one of :data:`COMPILE_MODES`"""
    if isinstance(compile_update, bool) or compile_update in COMPILE_MODES:
        return
    raise ParameterError(
        "compile_update",
        f"compile_update must be True, False or a torch.compile mode {COMPILE_MODES}, got {compile_update!r}.",
    )


def compile_mode(compile_update: bool | str, device: th.device) -> str:
    """:return: the ``torch.compile`` mode of ``compile_update``: for ``True``, ``"reduce-overhead"`` on CUDA and
    ``"default"`` elsewhere"""
    default = "reduce-overhead" if device.type == "cuda" else "default"
    return compile_update if isinstance(compile_update, str) else default


def check_load_arguments(path: Any, kwargs: Mapping[str, Any], name: str = "DrQv2.load") -> None:
    """Check ``load``'s ``path`` and ``kwargs`` before SB3 reads anything (``name``: the caller): ``TypeError`` for
    ``init_from``, ``FileNotFoundError`` without the file, ``ParameterError`` for a zip of one of SB3's algorithms (a
    path, or a file object: read from its position, then put back there)."""
    if "init_from" in kwargs:
        raise TypeError(
            f"{name} does not transplant layers (init_from): it restores the saved weights. Build a new "
            "model with DrQv2(policy, env, init_from={...}) to start from the layers of saved models."
        )
    if isinstance(path, (str, os.PathLike)):
        found = zip_file(path)
        if found is None:
            suffix = pathlib.Path(path).suffix
            tried = f"{os.fspath(path)!r}" + ("" if suffix == ".zip" else f" (nor {os.fspath(path) + '.zip'!r})")
            raise FileNotFoundError(f"{name}: no model file {tried}; give the path of a zip saved by DrQv2.save.")
        saved, shown = saved_sb3_algorithm(found), f"path {os.fspath(path)!r}"
    elif isinstance(path, io.IOBase) and path.readable() and path.seekable():
        start = path.tell()
        try:
            saved = saved_sb3_algorithm(path)
        finally:
            path.seek(start)  # SB3's load reads the zip from where the caller left the stream
        shown = f"path (a {type(path).__name__} file object)"
    else:
        return
    if saved is not None:
        algorithm, policy = saved
        loader = f"stable_baselines3.{algorithm}.load" if algorithm else "the SB3 algorithm that saved it"
        raise ParameterError(
            "path",
            f"{shown} holds a {algorithm or 'Stable-Baselines3'} checkpoint (policy {policy}), not a DrQv2 one: load "
            f"it with {loader}.",
        )


def zip_file(path: str | os.PathLike[str]) -> pathlib.Path | None:
    """:return: ``path``, or ``path.zip`` where ``path`` has no ``.zip`` suffix (as SB3's ``load``), if a file"""
    given = pathlib.Path(path)
    zipped = given.with_name(given.name + ".zip")
    return given if given.is_file() else zipped if given.suffix != ".zip" and zipped.is_file() else None


SB3_DATA, SB3_POLICY = "data", "policy.pth"  # members of a zip of SB3's save: settings and spaces as JSON, weights


def read_sb3_data(archive: zipfile.ZipFile) -> dict[str, Any]:
    """
    The one reader of an SB3 zip's :data:`SB3_DATA` member: the algorithm's settings, its policy's class and its
    spaces, as SB3's ``save`` wrote them (each class or space a JSON object of its ``__module__`` and a serialization;
    ``stable_baselines3.common.save_util.json_to_data`` rebuilds them).

    :param archive: the open zip
    :return: the member's JSON object
    :raises KeyError: without the member; ``ValueError`` (``json.JSONDecodeError``, ``UnicodeDecodeError``) when it is
        not a JSON object
    """
    data = json.loads(archive.read(SB3_DATA))
    if not isinstance(data, dict):
        raise ValueError(f"expected a JSON object, got {type(data).__name__}")
    return data


def saved_sb3_algorithm(path: pathlib.Path | io.IOBase) -> tuple[str | None, str] | None:
    """:return: ``(algorithm or None, policy class)`` read from the ``data`` of a zip (a path or a seekable file object,
    read from its position) saved by one of SB3's algorithms; ``None`` for another policy or an unreadable file"""
    try:
        with zipfile.ZipFile(path) as archive:
            data = read_sb3_data(archive)
        module = str(data["policy_class"]["__module__"])
        init = re.search(r"<function (\w+)\.__init__", str(data["policy_class"].get("__init__", "")))
    except (OSError, KeyError, TypeError, ValueError, zipfile.BadZipFile):
        return None
    if not module.startswith("stable_baselines3."):
        return None
    policy = f"{module}.{init.group(1) if init else '?'}"
    algorithm = module.split(".")[1].upper()
    if algorithm == "TD3" and data.get("policy_delay") == 1 and data.get("target_noise_clip") == 0.0:
        algorithm = "DDPG"  # SB3's DDPG is TD3 with these settings, and saves TD3's policies
    return (algorithm if hasattr(stable_baselines3, algorithm) else None), policy


_SB3_BUFFER_ARGUMENTS = {  # what SB3 passes to every replay buffer itself -> where it comes from
    "self": "", "buffer_size": "buffer_size", "observation_space": "the env", "action_space": "the env",
    "device": "device", "n_envs": "the env", "optimize_memory_usage": "optimize_memory_usage",
}  # fmt: skip


def _keywords(replay_buffer_class: type) -> set[str] | None:
    """:return: the keyword arguments ``replay_buffer_class`` takes (its ``__init__``'s and those it passes on with
    ``**kwargs`` to a base class), ``None`` when some ``**kwargs`` go further"""
    names: set[str] = set()
    for cls in replay_buffer_class.__mro__:
        if "__init__" not in vars(cls):
            continue
        parameters = inspect.signature(cls.__init__).parameters.values()
        names |= {p.name for p in parameters if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)}
        if not any(p.kind == p.VAR_KEYWORD for p in parameters):
            return names
    return None


def check_replay_buffer_kwargs(
    replay_buffer_class: type[ReplayBuffer] | None, replay_buffer_kwargs: Mapping[str, Any], policy_class: type
) -> None:
    """
    :param replay_buffer_class: the replay buffer ``DrQv2`` chose (``None``: SB3's ``NStepReplayBuffer`` or
        ``ReplayBuffer``, as SB3 chooses)
    :param replay_buffer_kwargs: its keyword arguments
    :param policy_class: the model's policy, for the message
    :raises ParameterError: naming ``replay_buffer_kwargs['<key>']`` for a keyword that buffer does not take (SB3
        would raise a bare ``TypeError`` as it builds it); ``sampling``, ``frame_stack`` and ``min_episode_length``
        are ``FrameStackReplayBuffer``'s (docs/algorithm.md)
    """
    buffer = replay_buffer_class or NStepReplayBuffer
    taken = _keywords(buffer)
    if taken is None:
        return
    taken -= set(_SB3_BUFFER_ARGUMENTS)
    frame_stack_only = (_keywords(FrameStackReplayBuffer) or set()) - taken - set(_SB3_BUFFER_ARGUMENTS)
    for key in replay_buffer_kwargs:
        if key in taken:
            continue
        here = f"the replay buffer here (policy {policy_class.__name__})"
        if key in _SB3_BUFFER_ARGUMENTS:
            message = f"is set by the model ({_SB3_BUFFER_ARGUMENTS[key]}): leave it out."
        elif key in frame_stack_only:
            message = (
                "is a setting of FrameStackReplayBuffer, the buffer of CnnPolicy on a frame-stacked pixel env (or "
                f"replay_buffer_class=FrameStackReplayBuffer), and {buffer.__name__} is {here}, which samples as SB3 "
                "does: leave it out (docs/algorithm.md)."
            )
        else:
            message = f"is not a keyword of {buffer.__name__}, {here}: it takes {', '.join(sorted(taken))}."
        raise ParameterError("replay_buffer_kwargs", f"replay_buffer_kwargs[{key!r}] {message}")


def compile_losses(critic_loss: Callable, actor_loss: Callable, compile_update: bool | str, device: th.device) -> tuple:
    """:return: ``DrQv2``'s two loss functions, ``torch.compile``-d in :func:`compile_mode` with static shapes (as
    they are for ``compile_update=False``)"""
    if not compile_update:
        return critic_loss, actor_loss
    mode = compile_mode(compile_update, device)
    return th.compile(critic_loss, mode=mode, dynamic=False), th.compile(actor_loss, mode=mode, dynamic=False)


def uses_cuda_graphs(compile_update: bool | str, device: th.device) -> bool:
    """:return: whether the compiled update replays CUDA graphs (each update then starts a new graph step)"""
    return bool(compile_update) and device.type == "cuda" and compile_mode(compile_update, device) in CUDA_GRAPH_MODES


SB3_FEATURE_SIZES = ("features_dim", "cnn_output_dim")  # SB3's features_extractor_kwargs that set feature_dim


def split_sb3_feature_size(
    features_extractor_kwargs: Mapping[str, Any] | None, features_extractor_class: type | None = None
) -> tuple[int | None, dict[str, Any]]:
    """:return: the ``feature_dim`` given by :data:`SB3_FEATURE_SIZES` (or ``None``) and the other keyword arguments,
    for DrQ-v2's encoder (``None, {}`` with a ``features_extractor_class``)"""
    kwargs = dict(features_extractor_kwargs or {})
    if features_extractor_class is not None:
        return None, {}
    sizes = [kwargs.pop(key) for key in SB3_FEATURE_SIZES if key in kwargs]
    return (sizes[0] if sizes else None), kwargs


ACTIVATION_FNS: dict[type[nn.Module], str] = {nn.ReLU: "relu", nn.LeakyReLU: "leaky_relu"}  # SB3's -> activation


def actor_critic_arch(
    net_arch: list[int] | dict[str, list[int]] | None, hidden_dim: int
) -> tuple[list[int], list[int]]:
    """SB3's ``get_actor_critic_arch`` of ``net_arch``, DrQ-v2's two layers of ``hidden_dim`` for ``None``."""
    pi, qf = (net_arch["pi"], net_arch["qf"]) if isinstance(net_arch, Mapping) else (net_arch, net_arch)
    return tuple([hidden_dim, hidden_dim] if arch is None else [int(units) for units in arch] for arch in (pi, qf))  # type: ignore[return-value]


def check_policy_kwargs(policy_kwargs: Mapping[str, Any] | None) -> None:
    """:raises ParameterError: naming the first bad SB3 keyword of ``policy_kwargs`` and what to pass instead"""
    kwargs = dict(policy_kwargs or {})

    def fail(key: str, message: str) -> None:
        raise ParameterError(f"policy_kwargs['{key}']", message)

    def units(key: str, value: Any) -> None:
        if not isinstance(value, (list, tuple)) or any(
            isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1 for n in value
        ):
            fail("net_arch", f"{key} must be a list of layer sizes (integers >= 1), e.g. [1024, 1024], got {value!r}.")

    net_arch = kwargs.get("net_arch")
    if isinstance(net_arch, Mapping):
        if set(net_arch) != {"pi", "qf"}:
            fail(
                "net_arch",
                "policy_kwargs['net_arch'] as a dict takes the keys 'pi' (actor) and 'qf' (each Q head), as SB3's TD3, "
                f"got {sorted(net_arch)}: pass e.g. dict(pi=[1024, 1024], qf=[1024, 1024]), or one list for both.",
            )
        for key in ("pi", "qf"):
            units(f"policy_kwargs['net_arch']['{key}']", net_arch[key])
    elif net_arch is not None:
        units("policy_kwargs['net_arch']", net_arch)
    if net_arch is not None and kwargs.get("hidden_dim", 1024) != 1024:
        fail(
            "net_arch",
            f"policy_kwargs gives both net_arch={net_arch!r} and hidden_dim={kwargs['hidden_dim']!r}: pass one "
            "(hidden_dim=h is net_arch=[h, h]).",
        )
    _integer("policy_kwargs['n_critics']", kwargs.get("n_critics", 2), 1)
    if kwargs.get("share_features_extractor", True) is not True:
        fail(
            "share_features_extractor",
            "DrQ-v2 has one encoder, shared by the actor and the critic and trained by the critic loss only (SB3's "
            "share_features_extractor=True; False, TD3's default, is another algorithm): leave it out or pass True, "
            f"got {kwargs['share_features_extractor']!r}.",
        )
    activation_fn = kwargs.get("activation_fn")
    if activation_fn is not None and activation_fn not in ACTIVATION_FNS:
        fail(
            "activation_fn",
            "policy_kwargs['activation_fn'] must be torch.nn.ReLU (DrQ-v2's) or torch.nn.LeakyReLU (with "
            f"leaky_relu_slope), got {activation_fn!r}.",
        )
    if activation_fn is not None and kwargs.get("activation", "relu") not in ("relu", ACTIVATION_FNS[activation_fn]):
        fail(
            "activation_fn",
            f"policy_kwargs gives activation_fn={activation_fn.__name__} and activation={kwargs['activation']!r}: "
            "pass one.",
        )
    extractor = kwargs.get("features_extractor_class")
    if extractor is not None and not (isinstance(extractor, type) and issubclass(extractor, BaseFeaturesExtractor)):
        fail(
            "features_extractor_class",
            "policy_kwargs['features_extractor_class'] must be a subclass of SB3's BaseFeaturesExtractor "
            f"(stable_baselines3.common.torch_layers), got {extractor!r}.",
        )
    extractor_kwargs = kwargs.get("features_extractor_kwargs") or {}
    sizes = {key: extractor_kwargs[key] for key in SB3_FEATURE_SIZES if key in extractor_kwargs}
    if extractor is None and sizes:
        for key, value in sizes.items():
            name = f"policy_kwargs['features_extractor_kwargs']['{key}']"
            _integer(name, value, 1, "policy_kwargs['features_extractor_kwargs']")
        given = {**sizes, **({"feature_dim": kwargs["feature_dim"]} if kwargs.get("feature_dim", 50) != 50 else {})}
        if len(set(given.values())) > 1:
            fail(
                "features_extractor_kwargs",
                f"policy_kwargs gives {', '.join(f'{key}={value!r}' for key, value in given.items())}: with DrQ-v2's "
                "encoder they are all the output size of the actor's and the critic's trunks (feature_dim): pass one.",
            )
    if extractor is None and split_sb3_feature_size(extractor_kwargs)[1] and kwargs.get("encoder_kwargs"):
        fail(
            "features_extractor_kwargs",
            "without features_extractor_class, features_extractor_kwargs (but features_dim and cnn_output_dim, "
            "the trunks' feature_dim) are the keyword arguments of DrQ-v2's encoder, as encoder_kwargs: pass one of "
            "them.",
        )


def check_action_space(action_space: spaces.Space) -> None:
    """:raises SpaceError: unless ``action_space`` is a ``Box`` with finite bounds"""
    if not isinstance(action_space, spaces.Box):
        raise SpaceError(
            "env",
            f"DrQv2 is for continuous actions (gymnasium.spaces.Box), got {type(action_space).__name__}: "
            f"{action_space}.",
        )
    if not (np.all(np.isfinite(action_space.low)) and np.all(np.isfinite(action_space.high))):
        raise SpaceError("env", f"DrQv2 needs finite action bounds to rescale its tanh actions, got {action_space}.")
