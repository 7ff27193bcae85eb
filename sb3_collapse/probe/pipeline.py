"""Recording rollouts from a checkpoint (``python -m sb3_collapse.probe record``) and checking checkpoint files."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import torch as th

from sb3_collapse.errors import InputError
from sb3_collapse.probe.checkpoints import Checkpoint, load_checkpoint, read_saved_data
from sb3_collapse.probe.rollouts import (
    ENV_SETTINGS,
    RecordOptions,
    Rollouts,
    pool_rollouts,
    record_rollouts,
    resolve_env_config,
)

ROLLOUTS_NAME = "rollouts.npz"


def summary_head(command: Sequence[str] | None, settings: Any = None) -> dict[str, Any]:
    """
    The first keys of the summary that a probe's output folder gets last (:data:`~sb3_collapse.protocol.
    PROBE_SUMMARY_JSON`, the health's file too).

    :param command: the command line (``None`` from the library)
    :param settings: the settings dataclass of the probe, if any
    :return: ``complete`` (true: the summary is written last, so that one that exists marks its folder complete),
        ``created`` (UTC, to the second), ``command`` and, given ``settings``, ``settings`` (tuples as JSON lists)
    """
    head: dict[str, Any] = {
        "complete": True,
        "created": datetime.now(UTC).isoformat(timespec="seconds"),
        "command": list(command) if command is not None else None,
    }
    if settings is not None:
        head["settings"] = {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(settings).items()}
    return head


def record(checkpoint: Checkpoint, options: RecordOptions, progress: bool = True) -> Rollouts:
    """Record rollouts of a checkpoint's agent (``progress``: show a progress bar)."""
    env = {key: getattr(options, key) for key in ENV_SETTINGS[1:]}
    env_config = resolve_env_config(checkpoint.env_config, task_id=options.env, **env)
    how = {key: getattr(options, key) for key in ("episodes", "seed", "deterministic", "noise_std", "max_steps")}
    metadata = {"checkpoint": str(checkpoint.path), "checkpoint_num_timesteps": checkpoint.num_timesteps}
    return record_rollouts(checkpoint.model, env_config, progress=progress, metadata=metadata, **how)


def record_agents(
    sources: Sequence[str | Path], options: RecordOptions, device: th.device, progress: bool = True
) -> Rollouts:
    """
    Record rollouts of each agent in turn (its checkpoint loaded, recorded, freed) and pool them
    (:func:`pool_rollouts`): agent ``rank`` records ``options.shares()[rank]`` episodes with seed ``options.seed +
    rank`` (distinct initial states); one source records as :func:`record` does.

    :param sources: the agents' checkpoints, ``options.pool_agents`` of them
    :param options: what to record (``episodes`` in all)
    :param device: where the networks run
    :param progress: show a progress bar per agent
    :return: the rollouts
    :raises InputError: when the number of ``sources`` is not ``options.pool_agents``
    """
    if len(sources) != options.pool_agents:
        raise InputError(
            f"pool_agents={options.pool_agents} but {len(sources)} agent(s) to record from.", parameter="pool_agents"
        )
    parts = []
    for rank, (source, episodes) in enumerate(zip(sources, options.shares())):
        checkpoint = load_checkpoint(source, device=device)
        parts.append(
            record(checkpoint, dataclasses.replace(options, episodes=episodes, seed=options.seed + rank), progress)
        )
        del checkpoint
    return parts[0] if len(parts) == 1 else pool_rollouts(parts)


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
