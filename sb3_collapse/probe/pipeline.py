"""Recording rollouts from a checkpoint (``python -m sb3_collapse.probe record``) and checking checkpoint files."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from stable_baselines3.common.utils import get_device

from sb3_collapse.drqv2.checks import check_device
from sb3_collapse.errors import InputError
from sb3_collapse.probe.checkpoints import Checkpoint, identify_algorithm, load_checkpoint, read_saved_data
from sb3_collapse.probe.rollouts import (
    ENV_SETTINGS,
    Rollouts,
    check_record_arguments,
    record_rollouts,
    resolve_env_config,
)
from sb3_collapse.run.config import setting

ROLLOUTS_NAME = "rollouts.npz"


@dataclass
class RecordOptions:
    """How to record rollouts, each option declared with its flag of ``python -m sb3_collapse.probe``
    (:func:`setting`); ``None`` ones come from the checkpoint, else ``make_dmc_env``'s defaults."""

    env: str | None = setting(help="dm_control task, e.g. walker-walk; default: the checkpoint's", unit=None)
    episodes: int = setting(20, help="episodes to record", unit="episodes", minimum=1)
    max_steps: int | None = setting(
        help="cap on agent steps per episode; default: the task's time limit (500 agent steps for walker at action "
        "repeat 2)",
        unit="agent steps",
        minimum=1,
    )
    seed: int = setting(0, help="seed of the env's initial states and the action noise", unit=None)
    deterministic: bool = setting(
        True,
        help="use the policy's deterministic action (off: sample its own exploration)",
        unit=None,
        flag="--stochastic",
    )
    noise_std: float = setting(
        0.0, help="std of Gaussian noise added to each action (actions in [-1, 1])", unit=None, minimum=0
    )
    action_repeat: int | None = setting(help="frames per agent step", unit="frames", minimum=1)
    frame_stack: int | None = setting(help="stacked RGB frames per observation", unit=None, minimum=1)
    size: int | None = setting(help="image height and width", unit="pixels", minimum=1)
    camera_id: int | None = setting(help="camera of the renders", unit=None)

    def check(self) -> None:
        """:raises InputError: for a bad option, before anything is loaded or recorded"""
        check_record_arguments(self.episodes, self.max_steps, self.noise_std)


def record(checkpoint: Checkpoint, options: RecordOptions, progress: bool = True) -> Rollouts:
    """
    Record rollouts of a checkpoint's agent.

    :param checkpoint: the agent
    :param options: what to record
    :param progress: show a progress bar
    :return: the rollouts
    """
    env = {key: getattr(options, key) for key in ENV_SETTINGS[1:]}
    env_config = resolve_env_config(checkpoint.env_config, task_id=options.env, **env)
    how = {key: getattr(options, key) for key in ("episodes", "seed", "deterministic", "noise_std", "max_steps")}
    metadata = {"checkpoint": str(checkpoint.path), "checkpoint_num_timesteps": checkpoint.num_timesteps}
    return record_rollouts(checkpoint.model, env_config, progress=progress, metadata=metadata, **how)


def record_to_file(
    checkpoint_path: str | Path,
    out: str | Path,
    options: RecordOptions,
    overwrite: bool = False,
    device: str = "auto",
    progress: bool = True,
) -> Path:
    """
    ``python -m sb3_collapse.probe record``: record rollouts and save them (atomically).

    :param checkpoint_path: the agent's checkpoint
    :param out: the ``.npz`` to write
    :param options: what to record
    :param overwrite: replace an existing file
    :param device: where the networks run
    :param progress: show a progress bar
    :return: the file written
    :raises InputError: for bad input
    """
    out = Path(out)
    if out.is_dir():
        raise InputError(f"out {out} is a folder; give the path of the .npz file to write.", parameter="out")
    if out.exists() and not overwrite:
        raise InputError(f"{out} exists: pass `overwrite=True` or another `out`.", parameter="out")
    options.check()
    check_device(device)
    checkpoint = load_checkpoint(checkpoint_path, device=get_device(device))
    rollouts = record(checkpoint, options, progress)
    path, task = rollouts.save(out), rollouts.env_config["task_id"]
    print(f"Saved {len(rollouts)} agent steps of {rollouts.n_episodes} episodes of {task} to {path}")
    return path


def check_checkpoint_files(paths: Sequence[str | Path], same_observations: bool = True) -> None:
    """
    Check, before any long work, that every path is an SB3 checkpoint of a probe-able algorithm, and (the same
    rollouts feed them all) that they all take observations of one shape.

    :param paths: the checkpoints
    :param same_observations: check that they all take observations of one shape
    :raises InputError: naming the first bad file, or two checkpoints whose observations differ
    """
    if not paths:
        raise InputError("Give at least one checkpoint (.zip).")
    shapes: dict[tuple, str | Path] = {}
    for path in paths:
        data = read_saved_data(path)
        identify_algorithm(data, path)
        shape = (data.get("observation_space") or {}).get("_shape")
        if shape is not None:
            shapes.setdefault(tuple(shape), path)
    if same_observations and len(shapes) > 1:
        (first, first_path), (other, other_path) = list(shapes.items())[:2]
        raise InputError(
            f"{first_path} takes observations of shape {first} and {other_path} of shape {other}: the probe feeds "
            "every checkpoint the same rollouts, so probe checkpoints of another image size or frame stack in a run "
            "of their own.",
            parameter="checkpoints",
        )
