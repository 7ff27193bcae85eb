"""Layer transplants (the paper's Study 2): a new DrQv2 started from parts of saved ones, "the rest blank":
docs/algorithm.md#layer-transplants-drqv2init_from."""

from __future__ import annotations

import functools
import inspect
import io
import json
import os
import zipfile
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.save_util import json_to_data

from sb3_collapse.drqv2.checks import SB3_DATA, SB3_POLICY, read_sb3_data, split_sb3_feature_size, zip_file
from sb3_collapse.drqv2.divergence import check_finite_weights
from sb3_collapse.drqv2.encoders import PixelEncoder
from sb3_collapse.drqv2.policies import DrQv2Policy

# Group -> prefixes of the policy state_dict keys it replaces, and -> the named layers whose weights it holds.
TRANSPLANT_GROUPS: dict[str, tuple[str, ...]] = {
    "cnn": ("encoder.",),
    "mlp": ("actor.",),
    "critic": ("critic.", "critic_target."),
}
GROUP_LAYERS: dict[str, tuple[str, ...]] = {
    "cnn": ("cnn1", "cnn2", "cnn3", "cnn4"),
    "mlp": ("mlp0", "mlp1", "mlp2", "action"),
    "critic": (),
}
SOURCE_PREFIXES: dict[str, str] = {"critic_target.": "critic."}  # target prefix -> source prefix, where they differ
DRQV2_POLICY_MODULE = "sb3_collapse.drqv2.policies"  # of the policy_class saved in every DrQv2 zip
TransplantSpec = str | os.PathLike | BaseAlgorithm  # a zip saved by DrQv2.save (".zip" may be left out), or a model


@dataclass(frozen=True)
class TransplantSource:
    """A source's policy ``state_dict`` on the CPU, its :func:`policy_settings` and where it comes from."""

    description: str
    state_dict: dict[str, th.Tensor]
    settings: dict[str, Any]


def check_init_from(init_from: Mapping[str, TransplantSpec] | None) -> dict[str, TransplantSpec]:
    """:return: ``DrQv2``'s ``init_from`` checked, group -> an absolute ``Path`` or the model, in
    ``TRANSPLANT_GROUPS`` order (reads no file; ``TypeError``, ``ValueError`` or ``FileNotFoundError`` naming it)"""
    if init_from is None:
        return {}
    if not isinstance(init_from, Mapping):
        raise TypeError(
            f"init_from must be a dict of group -> source, e.g. {{'cnn': 'good.zip', 'mlp': 'bad.zip'}}, "
            f"got {type(init_from).__name__}."
        )
    unknown = [key for key in init_from if key not in TRANSPLANT_GROUPS]
    if unknown:
        raise ValueError(
            f"init_from has unknown key(s) {unknown}; the keys must be a subset of {list(TRANSPLANT_GROUPS)} "
            "('cnn': the encoder, 'mlp': the actor, 'critic': the critic and its target)."
        )
    resolved: dict[str, TransplantSpec] = {}
    for key in (key for key in TRANSPLANT_GROUPS if key in init_from):
        source = init_from[key]
        if isinstance(source, BaseAlgorithm):
            if not isinstance(source.policy, DrQv2Policy):
                raise TypeError(
                    f"init_from[{key!r}]: a {type(source).__name__} model cannot be transplanted; "
                    "give a DrQv2 model or the path of a zip saved by DrQv2.save."
                )
            resolved[key] = source
        elif isinstance(source, (str, os.PathLike)):
            resolved[key] = resolve_source_path(key, source)
        else:
            raise TypeError(
                f"init_from[{key!r}] must be the path of a zip saved by DrQv2.save or a DrQv2 model, "
                f"got {type(source).__name__}: {source!r}."
            )
    return resolved


def resolve_source_path(key: str, path: str | os.PathLike[str]) -> Path:
    """:return: the absolute path of ``path`` or ``path.zip`` (``FileNotFoundError`` naming ``init_from[key]`` if
    neither is a file)"""
    candidate = zip_file(path)
    if candidate is None:
        raise FileNotFoundError(
            f"init_from[{key!r}]: checkpoint {os.fspath(path)!r} does not exist; give the path of a zip saved by "
            "DrQv2.save (e.g. a run's final model)."
        )
    return candidate.resolve()


def describe_source(source: TransplantSpec) -> str:
    """A plain string naming a resolved source: the path itself, or ``<in-memory DrQv2, seed 0, 120 agent steps>``."""
    if isinstance(source, BaseAlgorithm):
        return f"<in-memory {type(source).__name__}, seed {source.seed}, {source.num_timesteps} agent steps>"
    return os.fspath(source)


def load_sources(resolved: Mapping[str, TransplantSpec]) -> dict[str, TransplantSource]:
    """:return: group -> source of :func:`check_init_from`'s ``resolved``, each file read once (``ValueError`` for a
    file that is no DrQv2 zip)"""
    files: dict[str, TransplantSource] = {}
    for key, spec in resolved.items():
        if not isinstance(spec, BaseAlgorithm) and os.fspath(spec) not in files:
            files[os.fspath(spec)] = read_source_zip(key, spec)  # type: ignore[arg-type]
    return {
        key: source_from_model(spec) if isinstance(spec, BaseAlgorithm) else files[os.fspath(spec)]
        for key, spec in resolved.items()
    }


def source_from_model(model: BaseAlgorithm) -> TransplantSource:
    """:return: a copy of a DrQv2 ``model``'s policy weights on the CPU and its settings"""
    policy = model.policy  # a DrQv2Policy (check_init_from)
    state_dict = {name: value.detach().to("cpu", copy=True) for name, value in policy.state_dict().items()}
    settings = policy_settings(type(policy), model.policy_kwargs, policy.observation_space, policy.action_space)
    return TransplantSource(describe_source(model), state_dict, settings)


def read_source_zip(key: str, path: Path) -> TransplantSource:
    """The policy weights and settings of a zip saved by ``DrQv2.save``, without building a model (``ValueError``
    for anything else, naming ``init_from[key]``)."""
    where = f"init_from[{key!r}] = {os.fspath(path)!r}"
    if not zipfile.is_zipfile(path):
        raise ValueError(f"{where} is not a zip file (corrupt or truncated?); expected a zip saved by DrQv2.save.")
    with zipfile.ZipFile(path) as archive:
        missing = {SB3_DATA, SB3_POLICY} - set(archive.namelist())
        if missing:
            raise ValueError(f"{where} is a zip but not an SB3 model: it lacks {sorted(missing)}.")
        raw = _read_member(where, SB3_DATA, lambda: read_sb3_data(archive))
        module = (raw.get("policy_class") or {}).get("__module__")
        if module != DRQV2_POLICY_MODULE:
            raise ValueError(
                f"{where} is not a DrQv2 model: its policy comes from {module!r}, not {DRQV2_POLICY_MODULE!r}; "
                "transplants copy DrQv2 layers, give a zip saved by DrQv2.save."
            )
        needed = ("policy_class", "policy_kwargs", "observation_space", "action_space")
        data = _read_member(where, SB3_DATA, lambda: json_to_data(json.dumps({name: raw[name] for name in needed})))
        load = functools.partial(th.load, map_location="cpu", weights_only=True)
        state_dict = _read_member(where, SB3_POLICY, lambda: load(io.BytesIO(archive.read(SB3_POLICY))))
    policy_class = data.get("policy_class")
    if not (isinstance(policy_class, type) and issubclass(policy_class, DrQv2Policy)):
        raise ValueError(f"{where}: its policy class could not be restored as a DrQv2Policy (got {policy_class!r}).")
    if not (isinstance(state_dict, dict) and all(isinstance(v, th.Tensor) for v in state_dict.values())):
        raise ValueError(f"{where}: policy.pth is not a state_dict of tensors; is the file corrupt?")
    settings = policy_settings(
        policy_class, data.get("policy_kwargs") or {}, data.get("observation_space"), data.get("action_space")
    )
    return TransplantSource(os.fspath(path), state_dict, settings)


def _read_member(where: str, member: str, read: Callable[[], Any]) -> Any:
    """``read()``, with any failure (damaged member, bad JSON, missing entry, bad pickle) as a ``ValueError``."""
    try:
        return read()
    except Exception as error:
        reason = (str(error).strip().splitlines() or [""])[0]
        raise ValueError(
            f"{where}: its {member!r} could not be read ({type(error).__name__}: {reason[:200]}); is the file "
            "corrupt? Expected a zip saved by DrQv2.save."
        ) from error


def _constructor_default(cls: type, name: str) -> Any:
    """The default of keyword ``name`` of ``cls.__init__``, looked up along the class hierarchy."""
    for init in (klass.__dict__["__init__"] for klass in cls.__mro__ if "__init__" in klass.__dict__):
        parameter = inspect.signature(init).parameters.get(name)
        if parameter is not None and parameter.default is not inspect.Parameter.empty:
            return parameter.default
    return None


def policy_settings(
    policy_class: type[DrQv2Policy], policy_kwargs: Mapping[str, Any], observation_space: Any, action_space: Any
) -> dict[str, Any]:
    """:return: the settings that shape a DrQv2 policy's weights (``"policy"``, ``"feature_dim"``...), defaults
    filled in"""

    def kwarg(name: str) -> Any:
        return policy_kwargs[name] if name in policy_kwargs else _constructor_default(policy_class, name)

    encoder_class = kwarg("encoder_class")
    sb3_size, sb3_encoder_kwargs = split_sb3_feature_size(
        policy_kwargs.get("features_extractor_kwargs"), policy_kwargs.get("features_extractor_class")
    )
    encoder_kwargs = {**(kwarg("encoder_kwargs") or {}), **sb3_encoder_kwargs}
    pixel = isinstance(encoder_class, type) and issubclass(encoder_class, PixelEncoder)

    def encoder_kwarg(name: str) -> Any:
        if not pixel:
            return None
        return encoder_kwargs[name] if name in encoder_kwargs else _constructor_default(encoder_class, name)

    shape = getattr(observation_space, "shape", None)
    action_shape = getattr(action_space, "shape", None)
    return {
        "policy": policy_class.__name__,
        "observation shape": tuple(shape) if shape is not None else None,
        "action dimensions": int(np.prod(action_shape)) if action_shape is not None else None,
        "feature_dim": kwarg("feature_dim") if sb3_size is None else sb3_size,
        "hidden_dim": kwarg("hidden_dim"),
        "encoder channels": encoder_kwarg("channels"),
        "channels_last": encoder_kwarg("channels_last"),
    }


def target_settings(policy: DrQv2Policy) -> dict[str, Any]:
    """:func:`policy_settings` of a built policy."""
    encoder_kwargs = {**policy.encoder_kwargs}
    if isinstance(policy.encoder, PixelEncoder):
        encoder_kwargs.setdefault("channels_last", policy.encoder.channels_last)
    kwargs = {name: getattr(policy, name) for name in ("feature_dim", "hidden_dim", "encoder_class")}
    kwargs["encoder_kwargs"] = encoder_kwargs
    return policy_settings(type(policy), kwargs, policy.observation_space, policy.action_space)


SETTING_HINTS: dict[str, str] = {  # setting -> how it is set
    "policy": "CnnPolicy reads pixels, MlpPolicy state vectors",
    "observation shape": "a different frame_stack (3 channels per frame) or image size",
    "action dimensions": "a different task (action space)",
    "feature_dim": "policy_kwargs=dict(feature_dim=...)",
    "hidden_dim": "policy_kwargs=dict(hidden_dim=...)",
    "encoder channels": "policy_kwargs=dict(encoder_kwargs=dict(channels=...))",
}


def likely_cause(source: Mapping[str, Any], target: Mapping[str, Any]) -> str:
    """:return: a sentence naming the :func:`policy_settings` that differ between ``source`` and ``target``"""
    differences = [
        f"the source was trained with {name}={source[name]!r}, this model has {name}={target[name]!r}"
        + (f" ({SETTING_HINTS[name]})" if name in SETTING_HINTS else "")
        for name in SETTING_HINTS
        if source.get(name) != target.get(name)
    ]
    return "; ".join(differences) or "the networks were built differently although their recorded settings agree"


def group_keys(keys: list[str] | Mapping[str, Any], group: str) -> list[str]:
    """:return: the ``state_dict`` keys among ``keys`` that ``group`` replaces, in order"""
    return [key for key in keys if key.startswith(TRANSPLANT_GROUPS[group])]


def source_key(target_key: str) -> str:
    """The source ``state_dict`` key copied into ``target_key`` (``critic_target.X`` <- ``critic.X``)."""
    for target_prefix, source_prefix in SOURCE_PREFIXES.items():
        if target_key.startswith(target_prefix):
            return source_prefix + target_key[len(target_prefix) :]
    return target_key


def plan_transplant(policy: DrQv2Policy, sources: Mapping[str, TransplantSource]) -> dict[str, th.Tensor]:
    """:return: target ``state_dict`` key -> the source tensor to copy into it, a transplant of ``sources`` into
    ``policy`` checked (``ValueError`` for a group either lacks, other keys, shapes, dtypes or ``channels_last``, or
    source weights that are not finite)"""
    target_state = policy.state_dict()
    settings = target_settings(policy)
    plan: dict[str, th.Tensor] = {}
    for group, source in sources.items():
        if group not in TRANSPLANT_GROUPS:
            raise ValueError(f"Unknown transplant group {group!r}; expected one of {list(TRANSPLANT_GROUPS)}.")
        where = f"init_from[{group!r}] = {source.description!r}"
        targets = group_keys(target_state, group)
        if not targets:
            raise ValueError(
                f"{where}: this model ({settings['policy']}) has no {group!r} weights to replace"
                + (" (MlpPolicy has no CNN encoder)." if group == "cnn" else ".")
            )
        wanted = {source_key(key) for key in targets}
        source_prefixes = tuple({source_key(prefix) for prefix in TRANSPLANT_GROUPS[group]})
        offered = {key for key in source.state_dict if key.startswith(source_prefixes)}
        if not offered:
            raise ValueError(
                f"{where}: the source ({source.settings['policy']}) has no {group!r} weights"
                + (" (an MlpPolicy model has no CNN encoder)." if group == "cnn" else ".")
            )
        if wanted != offered:
            raise ValueError(
                f"{where}: the source's {group!r} weights are not this model's: missing in the source "
                f"{sorted(wanted - offered)}, unknown to this model {sorted(offered - wanted)}. Likely cause: "
                f"{likely_cause(source.settings, settings)}."
            )
        orders = (settings["channels_last"], source.settings["channels_last"])
        if group in ("mlp", "critic") and None not in orders and orders[0] != orders[1]:
            raise ValueError(
                f"{where}: the source's encoder was built with channels_last={source.settings['channels_last']}, "
                f"this model's with channels_last={settings['channels_last']}: the encoder's output is flattened "
                "in another order, so the transplanted trunk would read permuted features. Build this model with "
                f"policy_kwargs=dict(encoder_kwargs=dict(channels_last={source.settings['channels_last']}))."
            )
        for key in targets:
            value, expected = source.state_dict[source_key(key)], target_state[key]
            if value.shape != expected.shape:
                into = "" if source_key(key) == key else f" (copied into {key!r})"
                raise ValueError(
                    f"{where}: parameter {source_key(key)!r}{into} has shape {tuple(value.shape)} in the source and "
                    f"{tuple(expected.shape)} in this model. Likely cause: {likely_cause(source.settings, settings)}. "
                    "Build this model with the source's settings to transplant this group."
                )
            if value.dtype != expected.dtype:
                raise ValueError(
                    f"{where}: parameter {source_key(key)!r} is {value.dtype} in the source but {key!r} is "
                    f"{expected.dtype} in this model."
                )
            plan[key] = value
        check_finite_weights({source_key(key): plan[key] for key in targets}, where)  # those it copies
    return plan


def transplant(policy: DrQv2Policy, sources: Mapping[str, TransplantSource], verbose: int = 0) -> list[str]:
    """Check everything (:func:`plan_transplant`), then copy the groups' weights into ``policy``'s tensors in place
    (``verbose >= 1``: say which). :return: the ``state_dict`` keys replaced"""
    plan = plan_transplant(policy, sources)
    target_state = policy.state_dict()  # tensors share storage with the parameters
    with th.no_grad():
        for key, value in plan.items():
            target_state[key].copy_(value)
    if verbose >= 1:
        groups = ", ".join(f"{group} from {source.description}" for group, source in sources.items())
        print(f"DrQv2: transplanted {groups} ({len(plan)} tensors)")
    return list(plan)
