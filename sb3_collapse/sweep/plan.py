"""A sweep's plan: what its pending trials will train and take (RAM, disk, time), in its dry run and settings file
(docs/sweeps.md#the-dry-run-and-its-plan)."""

from __future__ import annotations

import functools
import inspect
import os
import shutil
from collections.abc import Collection, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces

from sb3_collapse.common.schedule import due_counts
from sb3_collapse.drqv2.policies import CnnPolicy
from sb3_collapse.drqv2.replay_buffer import FrameStackReplayBuffer
from sb3_collapse.drqv2.replay_memory import bytes_per_transition, physical_memory_bytes
from sb3_collapse.envs import ensure_rendering_backend, parse_task
from sb3_collapse.errors import InputError
from sb3_collapse.protocol import CHECKPOINTS_DIR
from sb3_collapse.run.checkpoints import ResumableCheckpoints, checkpoint_frames
from sb3_collapse.run.config import TrainConfig, drqv2_kwargs
from sb3_collapse.run.snapshots import SNAPSHOT_PREFIXES
from sb3_collapse.runfolder import NOT_A_RUN, RESUMABLE, RunStatus, run_status
from sb3_collapse.sweep.runner import Attempt, trial_left_as_is
from sb3_collapse.sweep.trials import Trial, trial_config, trial_dir

TrialState = tuple[str, tuple[str, str] | None, TrainConfig, int]
"""A trial's status, why the sweep leaves it as it is (kind and line; ``None``: finished, or to train), its resolved
settings and its frames done (:func:`trial_states`)."""
KEEP = inspect.signature(ResumableCheckpoints).parameters["keep"].default  # complete checkpoints a run keeps


@functools.cache
def _action_space(task: str) -> spaces.Box:
    """The action space of ``task`` (its dm_control action spec; no rendering)."""
    ensure_rendering_backend(required=False)
    from dm_control import suite

    return spaces.Box(-1.0, 1.0, shape=suite.load(*parse_task(task)).action_spec().shape, dtype=np.float32)


@functools.cache
def _drqv2_bytes(obs_shape: tuple[int, ...], action_dim: int, policy_kwargs: tuple) -> tuple[int, int]:
    """Bytes of a DrQ-v2 model file (weights and Adam's two moments) and of its snapshot (encoder and actor weights),
    from its policy built on the meta device (no memory)."""
    obs, action = spaces.Box(0, 255, obs_shape, np.uint8), spaces.Box(-1.0, 1.0, (action_dim,), np.float32)
    with th.device("meta"):
        policy = CnnPolicy(obs, action, lambda _: 0.0, **dict(policy_kwargs), optimizer_kwargs={"fused": False})
    state = policy.state_dict()
    optimized = [p for optimizer in policy.optimizers for group in optimizer.param_groups for p in group["params"]]

    def size(tensors: Any) -> int:
        return sum(tensor.numel() * tensor.element_size() for tensor in tensors)

    snapshot = size(value for key, value in state.items() if key.startswith(SNAPSHOT_PREFIXES))
    return size(state.values()) + 2 * size(optimized), snapshot


def trial_events(config: TrainConfig) -> dict[str, int]:
    """
    :param config: a trial's resolved settings
    :return: how many of each periodic output a run of it writes from frame 0, counted by the rule of the callbacks
        that write them (:func:`~sb3_collapse.common.schedule.due_counts`): its scheduled evaluations
        (``evaluations``, the rows of its evaluation file), its snapshots (``snapshots``: one per evaluation and the
        final model's, with ``snapshots``) and its collapse checks (``collapse_checks``, each one row per tag; a
        check that finds fewer than ``collapse_metrics_batch`` transitions stored, early in a tiny run or soon after
        a reset, writes nothing, so these are the most it writes)
    """
    per_step = config.action_repeat * config.n_envs  # type: ignore[operator]  # frames an agent step adds

    def count(period: int, at_start: bool = False) -> int:
        return len(due_counts(config.frames, period, per_step, at_start)) if period > 0 else 0  # 0: none

    evaluations = count(config.eval_every_frames, at_start=True)  # type: ignore[arg-type]  # PeriodicEvaluation's
    return {
        "evaluations": evaluations,
        "snapshots": evaluations + 1 if config.snapshots else 0,  # Snapshots: after each evaluation, the final model
        "collapse_checks": count(config.collapse_metrics_every_frames),  # CollapseMetrics'
    }


def trial_bytes(config: TrainConfig) -> dict[str, int | None]:
    """
    :param config: a trial's resolved settings
    :return: bytes of its replay buffer in RAM once full (``replay_ram``), of its checkpoints folder at its peak
        (``checkpoints_peak``: the replay chunks of :data:`KEEP` checkpoints and the one being written, and their
        model files), of its snapshots (``snapshots``) and of its final model file (``model``; ``None``, and not in
        ``checkpoints_peak``, for td3 and sac)
    """
    obs = spaces.Box(0, 255, (3 * config.frame_stack, config.size, config.size), np.uint8)  # type: ignore[operator]
    action = _action_space(config.env)
    stacked = FrameStackReplayBuffer if config.frame_stack > 1 else None  # type: ignore[operator]
    buffer = (stacked, {"frame_stack": config.frame_stack}, config.buffer_size, obs, action, config.n_envs)
    per_transition = bytes_per_transition(*buffer)  # type: ignore[arg-type]
    between = config.checkpoint_every_frames // config.action_repeat  # type: ignore[operator]  # agent steps
    chunks = per_transition * min(config.buffer_size + KEEP * between, config.agent_steps)  # type: ignore[operator]
    model = snapshot = None
    if config.algorithm == "drqv2":
        policy_kwargs = tuple(sorted(drqv2_kwargs(config)["policy_kwargs"].items()))
        model, snapshot = _drqv2_bytes(obs.shape, int(np.prod(action.shape)), policy_kwargs)
    snapshots = snapshot * trial_events(config)["snapshots"] if snapshot is not None else 0
    return {
        "replay_ram": round(per_transition * config.buffer_size),  # type: ignore[operator]
        "checkpoints_peak": round(chunks) + (KEEP + 1) * (model or 0),
        "snapshots": snapshots,
        "model": model,
    }


def _group(trial: Trial) -> str:
    """The trials of one task and variant share their settings: ``"walker-walk/drqv2"``."""
    return f"{trial.task}/{trial.variant}"


def free_bytes(out: str | os.PathLike) -> int:
    """:return: the free bytes of the filesystem holding ``out`` (of its nearest existing parent: it may not exist)"""
    path = Path(out).absolute()
    while not path.exists() and path != path.parent:
        path = path.parent
    return shutil.disk_usage(path).free


def _trial_disk(sizes: Mapping[str, int | None]) -> int:
    """Bytes one trial writes at most: its checkpoints at their peak, its snapshots and its final model."""
    return (sizes["checkpoints_peak"] or 0) + (sizes["snapshots"] or 0) + (sizes["model"] or 0)


def sweep_plan(
    configs: Mapping[Trial, TrainConfig],
    done_frames: Mapping[Trial, int],
    cpus_per_trial: float = 1,
    gpus_per_trial: float = 0,
    frames_per_second: float | None = None,
    out: str | os.PathLike | None = None,
) -> dict[str, Any]:
    """
    :param configs: the resolved settings of every trial that will hold files (finished or to train)
    :param done_frames: the trials to train (pending) -> the frames their newest checkpoint holds (0 without one)
    :param cpus_per_trial: CPUs per trial
    :param gpus_per_trial: GPUs per trial
    :param frames_per_second: one trial's training frames per second (measured), for the time estimate
    :param out: the sweep folder, for the free space of its disk (``out_free_bytes``; ``None``: not measured)
    :return: the plan (the sweep settings file's ``plan``): frames, agent steps and updates to train, bytes and
        :func:`trial_events` (``events``) per (task, variant), the disk the sweep holds at the end, the disk its
        pending trials write at most (``disk_needed_bytes``: their final models and snapshots, and the checkpoints
        of those at once; ``largest_trial_disk_bytes``: one trial's), this machine's RAM/CPUs/GPUs and the trials it
        runs at once,
        and the reset rule's window of each (task, variant) that runs it (``reset_window_frames``: the task's
        exploration end unless given)
    """
    frames = steps = updates = 0
    for trial, done in done_frames.items():
        config = configs[trial]
        repeat = config.action_repeat
        frames += config.frames - done  # type: ignore[operator]
        steps += config.agent_steps - done // repeat  # type: ignore[operator]
        start = max(done // repeat, config.seed_frames // repeat)  # type: ignore[operator]  # no update in the warm-up
        every = config.train_freq if config.algorithm == "drqv2" else 1  # agent steps per update (SB3's: 1)
        updates += max(0, config.agent_steps - start) // every  # type: ignore[operator]
    groups = {_group(trial): trial_bytes(config) for trial, config in configs.items()}
    events = {_group(trial): trial_events(config) for trial, config in configs.items()}
    pending = [groups[_group(trial)] for trial in done_frames]
    at_end = sum(groups[_group(trial)]["snapshots"] + (groups[_group(trial)]["model"] or 0) for trial in configs)
    node = {"ram_bytes": physical_memory_bytes(), "cpus": os.cpu_count() or 1, "gpus": th.cuda.device_count()}
    largest = max((sizes["replay_ram"] for sizes in pending), default=0)
    limits = {"ram": node["ram_bytes"] // largest if largest else len(pending)}
    limits["cpus"] = int(node["cpus"] // cpus_per_trial)
    if gpus_per_trial > 0:
        limits["gpus"] = int(node["gpus"] // gpus_per_trial)
    at_once = min(len(pending), *limits.values())
    peaks = sorted((sizes["checkpoints_peak"] for sizes in pending), reverse=True)  # removed as each trial finishes
    needed = sum(sizes["snapshots"] + (sizes["model"] or 0) for sizes in pending) + sum(peaks[:at_once])
    hours = frames / (frames_per_second * at_once) / 3600 if frames_per_second and at_once else None
    return {
        "trials_pending": len(done_frames), "frames": frames, "agent_steps": steps, "updates": updates,
        "bytes": groups, "events": events, "disk_at_end_bytes": at_end, "node": node,
        "largest_replay_ram_bytes": largest,
        "trials_at_once": at_once, "limits": limits, "frames_per_second": frames_per_second, "hours": hours,
        "disk_needed_bytes": needed, "largest_trial_disk_bytes": max(map(_trial_disk, pending), default=0),
        "out_free_bytes": None if out is None else free_bytes(out),
        "reset_window_frames": {_group(t): c.reset_window_frames for t, c in configs.items() if c.reset_rule},
    }  # fmt: skip


def trial_states(
    trials: Sequence[Trial],
    out: str | Path,
    training: Mapping[str, Any],
    checkpoints: Mapping,
    snapshot_variants: Collection[str] | None = None,
) -> dict[Trial, TrialState]:
    """Trial -> its status, why the sweep leaves it as it is (:func:`~sb3_collapse.sweep.runner.trial_left_as_is`:
    kind and line; ``None``: finished, or trained), its resolved settings (:func:`~sb3_collapse.sweep.trials.
    trial_config`'s, ``snapshot_variants`` included) and the frames done (the budget when finished, the newest
    checkpoint's when unfinished, else 0)."""
    states = {}
    for trial in trials:
        folder = trial_dir(out, trial)
        status = str(run_status(folder) or NOT_A_RUN)
        reason = None if status == RunStatus.FINISHED else trial_left_as_is(folder)
        config = trial_config(trial, out, training, checkpoints, snapshot_variants=snapshot_variants)
        done = checkpoint_frames(folder / CHECKPOINTS_DIR) if status in RESUMABLE else None
        states[trial] = (status, reason, config, config.frames if status == RunStatus.FINISHED else done or 0)
    return states


def states_plan(
    states: Mapping[Trial, TrialState],
    cpus_per_trial: float = 1,
    gpus_per_trial: float = 0,
    frames_per_second: float | None = None,
    out: str | os.PathLike | None = None,
) -> dict[str, Any]:
    """
    :func:`sweep_plan` of the trials of ``states`` (:func:`trial_states`): every trial that holds files but the
    damaged ones (those in use by another process count, though not trained now); the finished ones hold their
    outputs, the others are to train from their frames done.
    """
    configs = {trial: state[2] for trial, state in states.items() if state[1] is None or state[1][0] == Attempt.IN_USE}
    done = {trial: state[3] for trial, state in states.items() if state[1] is None and state[0] != RunStatus.FINISHED}
    return sweep_plan(configs, done, cpus_per_trial, gpus_per_trial, frames_per_second, out)


def check_node(plan: Mapping[str, Any]) -> None:
    """An ``InputError`` when this machine's RAM cannot hold one pending trial's replay buffer."""
    ram, largest = plan["node"]["ram_bytes"], plan["largest_replay_ram_bytes"]
    if largest > ram:
        raise InputError(
            f"this machine has {ram / 1e9:,.1f} GB of RAM, less than one trial's replay buffer ({largest / 1e9:,.1f} "
            "GB once full): pass a smaller `buffer_size` or run on a larger machine; nothing was written.",
            parameter="buffer_size",
        )


def check_disk(plan: Mapping[str, Any]) -> str | None:
    """
    The plan's disk against the free space at ``out`` (``out_free_bytes``), as :func:`check_node` checks the RAM.

    :return: a warning line when the pending trials may write more than is free (the trials that meet the full disk
        fail with their checkpoints intact, and resume at a rerun once there is space), ``None`` when it fits
    :raises InputError: naming ``out``, when one trial's outputs alone do not fit (none could finish)
    """
    free, needed, largest = plan["out_free_bytes"], plan["disk_needed_bytes"], plan["largest_trial_disk_bytes"]
    if free is None or needed <= free:
        return None
    free_text, at_once = size_text(free), plan["trials_at_once"]
    if largest > free:
        raise InputError(
            f"out: its disk has {free_text} free, less than one trial writes ({size_text(largest)}: its checkpoints "
            "at their peak, snapshots and final model): free space or give `out` on a larger disk (or pass a smaller "
            "`buffer_size`); nothing was written.",
            parameter="out",
        )
    return (
        f"the {plan['trials_pending']} trials to train write up to {size_text(needed)} ({at_once} at once) and the "
        f"disk of `out` has {free_text} free: the trials that meet a full disk fail with their checkpoints intact; "
        "free space, then run the same command again to resume them."
    )


def size_text(nbytes: float | None) -> str:
    """``nbytes`` for a person: in GB with 2 decimals from 1e9 bytes, else in MB with 1 (``"-"`` for ``None``)."""
    if nbytes is None:
        return "-"
    return f"{nbytes / 1e9:,.2f} GB" if nbytes >= 1e9 else f"{nbytes / 1e6:,.1f} MB"
