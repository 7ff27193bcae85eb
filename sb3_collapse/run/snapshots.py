"""Snapshots: a run's encoder and actor saved at every evaluation (an SB3 zip without critic, optimizers or replay
buffer), the weights the probe and the report's fixed-set figures read. See docs/figures.md."""

from __future__ import annotations

import json
import os
import zipfile
from pathlib import Path
from typing import Any

import torch as th
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.save_util import load_from_zip_file, save_to_zip_file

from sb3_collapse.drqv2.transplant import GROUP_LAYERS, TRANSPLANT_GROUPS
from sb3_collapse.monitoring.callbacks import frames_of
from sb3_collapse.protocol import SNAPSHOT_FILE, atomic_output

SNAPSHOT_GROUPS = ("cnn", "mlp")  # the transplant groups a snapshot holds: the encoder and the actor
SNAPSHOT_PREFIXES = tuple(prefix for group in SNAPSHOT_GROUPS for prefix in TRANSPLANT_GROUPS[group])
MARKER = "snapshot.json"
"""The zip member that marks a snapshot: ``{"groups", "layers", "num_timesteps", "frames"}``."""


def save_snapshot(model: Any, path: str | os.PathLike) -> Path:
    """Save the encoder and actor of a DrQv2 ``model`` with the settings SB3 saves, atomically, into the zip ``path``
    (its folder created); return it. :raises TypeError: for a model without a DrQ-v2 encoder and actor."""
    state_dict = model.policy.state_dict()
    kept = {key: value.detach().cpu() for key, value in state_dict.items() if key.startswith(SNAPSHOT_PREFIXES)}
    if not all(any(key.startswith(prefix) for key in kept) for prefix in SNAPSHOT_PREFIXES):
        raise TypeError(
            f"model must be a DrQv2 model (policy entries {', '.join(SNAPSHOT_PREFIXES)}), got {type(model).__name__}."
        )
    # The settings, as BaseAlgorithm.save keeps them: the attributes minus the excluded ones and the torch objects.
    data = model.__dict__.copy()
    excluded = set(model._excluded_save_params())
    state_dicts, torch_variables = model._get_torch_save_params()
    excluded.update(name.split(".")[0] for name in state_dicts + torch_variables)
    for name in excluded:
        data.pop(name, None)
    marker = {
        "groups": list(SNAPSHOT_GROUPS),
        "layers": [layer for group in SNAPSHOT_GROUPS for layer in GROUP_LAYERS[group]],
        "num_timesteps": int(model.num_timesteps),
        "frames": frames_of(model),
    }
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_output(path) as temporary:
        save_to_zip_file(temporary, data=data, params={"policy": kept})
        with zipfile.ZipFile(temporary, "a") as archive:
            archive.writestr(MARKER, json.dumps(marker))
    return path


def is_snapshot(path: str | os.PathLike) -> bool:
    """:return: whether ``path`` is a zip with a snapshot's marker (:data:`MARKER`)"""
    try:
        with zipfile.ZipFile(path) as archive:
            return MARKER in archive.namelist()
    except (OSError, zipfile.BadZipFile):
        return False


def load_snapshot(path: str | os.PathLike, device: th.device | str = "cpu", **kwargs: Any) -> Any:
    """
    Load a snapshot into a DrQv2 model (without environment) for inference; its critic is random, not to be used.

    :param path: the zip
    :param device: where the networks go
    :param kwargs: saved attributes to override (e.g. ``buffer_size`` for a small replay buffer)
    :return: the model
    :raises ValueError: for a zip that is not a snapshot or lacks encoder or actor entries
    """
    from sb3_collapse.drqv2.drqv2 import DrQv2  # lazy: only loading builds a model

    if not is_snapshot(path):
        raise ValueError(f"{path} is not a snapshot (no {MARKER}); load a full checkpoint with DrQv2.load.")
    data, params, _ = load_from_zip_file(path, device=device)
    model = DrQv2(policy=data["policy_class"], env=None, device=device, _init_setup_model=False)
    model.__dict__.update(data)
    model.__dict__.update(kwargs)
    model._setup_model()
    missing, unexpected = model.policy.load_state_dict(params["policy"], strict=False)
    lacking = [key for key in missing if key.startswith(SNAPSHOT_PREFIXES)]
    if lacking or unexpected:
        raise ValueError(
            f"{path}: the encoder and actor do not match the saved settings (missing {lacking[:3]}, unexpected "
            f"{list(unexpected)[:3]}); was the file written by another version?"
        )
    model.policy.set_training_mode(False)
    return model


class Snapshots(BaseCallback):
    """
    Save a snapshot (:func:`save_snapshot`, ``<folder>/snapshot_<frames, 10 digits>_frames.zip``) each time it is
    called: ``PeriodicEvaluation(callback_after_eval=Snapshots(folder))`` takes one at every evaluation.

    :param folder: where the zips go
    :param verbose: 0 silent, 1 a line per snapshot
    """

    def __init__(self, folder: str | os.PathLike, verbose: int = 0) -> None:
        super().__init__(verbose)
        self.folder = Path(folder)
        self.saved: list[Path] = []  # the zips written by this process, in order

    def _on_step(self) -> bool:
        self.save()
        return True

    def save(self) -> Path:
        """:return: the zip of the model's encoder and actor, saved now"""
        path = save_snapshot(self.model, self.folder / SNAPSHOT_FILE.format(frames=frames_of(self.model)))
        self.saved.append(path)
        if self.verbose >= 1:
            print(f"Snapshots: saved {path}")
        return path
