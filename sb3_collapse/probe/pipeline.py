"""Recording rollouts from a checkpoint (``python -m sb3_collapse.probe record``) and checking checkpoint files."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from sb3_collapse.errors import InputError
from sb3_collapse.probe.checkpoints import Checkpoint, read_saved_data
from sb3_collapse.probe.rollouts import ENV_SETTINGS, RecordOptions, Rollouts, record_rollouts, resolve_env_config

ROLLOUTS_NAME = "rollouts.npz"


def record(checkpoint: Checkpoint, options: RecordOptions, progress: bool = True) -> Rollouts:
    """Record rollouts of a checkpoint's agent (``progress``: show a progress bar)."""
    env = {key: getattr(options, key) for key in ENV_SETTINGS[1:]}
    env_config = resolve_env_config(checkpoint.env_config, task_id=options.env, **env)
    how = {key: getattr(options, key) for key in ("episodes", "seed", "deterministic", "noise_std", "max_steps")}
    metadata = {"checkpoint": str(checkpoint.path), "checkpoint_num_timesteps": checkpoint.num_timesteps}
    return record_rollouts(checkpoint.model, env_config, progress=progress, metadata=metadata, **how)


def check_checkpoint_files(paths: Sequence[str | Path], same_observations: bool = True) -> None:
    """Check, before any long work, that every path is an SB3 checkpoint of a probe-able algorithm and (with
    ``same_observations``: the same rollouts feed them all) that they take observations of one shape."""
    if not paths:
        raise InputError("Give at least one checkpoint (.zip).")
    shapes: dict[tuple, str | Path] = {}
    for path in paths:
        _, data = read_saved_data(path)
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
