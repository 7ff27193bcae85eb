"""Load SB3 checkpoints to probe: DrQv2, and SB3's TD3 (also DDPG's checkpoints) and SAC."""

from __future__ import annotations

import io
import itertools
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch as th
from stable_baselines3 import SAC, TD3
from stable_baselines3.common.base_class import BaseAlgorithm

from sb3_collapse.drqv2 import DrQv2
from sb3_collapse.drqv2.checks import SB3_DATA, SB3_POLICY, read_sb3_data
from sb3_collapse.drqv2.divergence import check_finite_weights
from sb3_collapse.errors import InputError, LayerMappingError
from sb3_collapse.monitoring import layer_taps
from sb3_collapse.monitoring.callbacks import action_repeat_of
from sb3_collapse.protocol import FINAL_MODEL, SNAPSHOTS_DIR, snapshot_files
from sb3_collapse.run.snapshots import is_snapshot, load_snapshot
from sb3_collapse.runfolder import RunStatus, run_status, trial_folders

ALGORITHMS: dict[str, type[BaseAlgorithm]] = {
    "sb3_collapse.drqv2.policies": DrQv2,
    "stable_baselines3.td3.policies": TD3,  # DDPG saves TD3's policy; its actor loads the same way
    "stable_baselines3.sac.policies": SAC,
}
"""Module of the saved ``policy_class`` -> algorithm class that loads the checkpoint."""


@dataclass
class Checkpoint:
    """
    :param path: the zip file
    :param model: the algorithm, on the requested device, with a tiny replay buffer
    :param algorithm: its class name
    :param num_timesteps: training progress, in agent steps
    :param action_repeat: frames per agent step
    :param label: its name in the outputs (``None``: the file name without ``.zip``)
    """

    path: Path
    model: BaseAlgorithm
    algorithm: str
    num_timesteps: int
    action_repeat: int
    label: str | None = None

    @property
    def name(self) -> str:
        """Its name in the outputs: ``label``, or the file name without ``.zip``."""
        return self.label or self.path.name.removesuffix(".zip")

    @property
    def frames(self) -> int:
        """Training progress in frames: ``num_timesteps x action_repeat``."""
        return self.num_timesteps * self.action_repeat

    @property
    def env_config(self) -> dict[str, Any] | None:
        """The ``make_dmc_env`` settings saved with a DrQv2 checkpoint, else ``None``."""
        return getattr(self.model, "env_config", None)


def read_saved_data(path: str | Path) -> tuple[type[BaseAlgorithm], dict[str, Any]]:
    """:return: the algorithm class that loads the SB3 zip ``path`` and its ``data`` JSON; :raises InputError: for
    anything else (a folder, a missing file, an algorithm whose actor has no named layers, weights not finite)"""
    path = Path(path)
    if path.is_dir():
        raise InputError(_folder_message(path))
    if not path.is_file():
        raise InputError(f"Checkpoint {path} does not exist.")
    if not zipfile.is_zipfile(path):
        raise InputError(f"{path} is not a zip file; expected an SB3 checkpoint saved with `model.save(...)`.")
    with zipfile.ZipFile(path) as archive:
        missing = {SB3_DATA, SB3_POLICY} - set(archive.namelist())
        if missing:
            raise InputError(f"{path} is a zip but not an SB3 model: it lacks {sorted(missing)}.")
        try:
            data = read_sb3_data(archive)
        except ValueError as error:  # bad JSON, or not an object
            raise InputError(f"{path}: SB3's `data` entry is not valid JSON ({error}).") from error
        try:
            weights = th.load(io.BytesIO(archive.read(SB3_POLICY)), map_location="cpu", weights_only=True)
        except Exception as error:  # any failure to unpickle: a damaged member
            raise InputError(f"{path}: its policy.pth cannot be read ({type(error).__name__}: {error}).") from error
    check_finite_weights(weights if isinstance(weights, dict) else {}, str(path))
    module = (data.get("policy_class") or {}).get("__module__")
    if module not in ALGORITHMS:
        raise InputError(
            f"{path}: cannot probe a model whose policy comes from {module!r}; named layers are defined for "
            "DrQv2 (sb3_collapse) and SB3's TD3, DDPG and SAC."
        )
    return ALGORITHMS[module], data


def _folder_message(path: Path) -> str:
    """What to give instead of a folder where a checkpoint file is expected (a sweep or run folder, or another)."""
    trials = trial_folders(path)
    if trials:
        return (
            f"{path} is a sweep folder, not a checkpoint: probe its trials with `python -m sb3_collapse.probe sweep "
            f"{path} --task {trials[0][0]}`, or give a trial's model, e.g. {trials[0][3] / FINAL_MODEL}."
        )
    models = [str(p) for p in (path / FINAL_MODEL,) if p.is_file()]
    models += [f"{path / SNAPSHOTS_DIR}/*.zip"] if snapshot_files(path) else []
    if models or run_status(path) not in (None, RunStatus.NEW):
        give = f"its model, {' or '.join(models)}." if models else "a model file (it has none yet)."
        return f"{path} is a run folder, not a checkpoint: give {give}"
    zips = sorted(path.glob("*.zip"))
    return f"{path} is a folder, not a checkpoint: give an SB3 .zip" + (f", e.g. {zips[0]}." if zips else ".")


def load_checkpoint(path: str | Path, device: th.device | str = "cpu") -> Checkpoint:
    """
    Load a checkpoint for probing and check that its layers can be named.

    :param path: an SB3 zip of DrQv2, TD3, DDPG or SAC, or a DrQv2 snapshot (encoder and actor only)
    :param device: where the networks go
    :return: the loaded checkpoint
    :raises InputError: for a file that is not an SB3 model of these, fails to load or whose layers cannot be named
    """
    path = Path(path)
    algorithm, _ = read_saved_data(path)
    try:  # a small replay buffer (room for any n-step window), never filled
        load = load_snapshot if is_snapshot(path) else algorithm.load
        model = load(path, device=device, buffer_size=64)
    except Exception as error:
        raise InputError(f"{path}: {algorithm.__name__}.load failed ({type(error).__name__}: {error}).") from error
    try:
        layer_taps(model)
    except LayerMappingError as error:
        raise InputError(f"{path}: {error}") from error
    return Checkpoint(path, model, algorithm.__name__, int(model.num_timesteps), action_repeat_of(model))


def checkpoint_labels(paths: list[str | Path]) -> list[str]:
    """:return: the checkpoints' names in the outputs: the file name without ``.zip``, with as many parent folders as
    it takes to tell them apart (``run1/model`` and ``run2/model``); :raises InputError: for a file given twice"""
    resolved = [Path(path).resolve() for path in paths]
    if len(set(resolved)) != len(resolved):
        raise InputError("The same checkpoint is given twice.")
    for depth in itertools.count(1):
        labels = [
            "/".join((path.with_suffix("") if path.suffix == ".zip" else path).parts[-depth:]) for path in resolved
        ]
        if len(set(labels)) == len(labels):
            return labels
