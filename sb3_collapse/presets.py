"""
DrQ-v2's published per-task hyperparameters for the DeepMind Control pixel tasks (facebookresearch/drqv2, MIT:
``cfgs/config.yaml``, ``cfgs/task/*.yaml``), the defaults of the train CLI, the sweep and ``zoo_configs/drqv2.yml``.
Units and the table: docs/presets.md.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any

from sb3_collapse.envs.dmc import parse_task


@dataclass(frozen=True)
class TaskPreset:
    """
    DrQ-v2's settings for one task.

    :param task: the task, ``<domain>-<task>``
    :param tier: DrQ-v2's difficulty tier, ``"easy"``, ``"medium"`` or ``"hard"``
    :param from_drqv2: whether DrQ-v2 published a config for this task (``False``: the easy tier's settings)
    :param frames: training budget, in frames (``num_train_frames``)
    :param action_repeat: frames per agent step
    :param frame_stack: stacked RGB frames per observation
    :param seed_frames: frames of uniform random actions before the first update (``num_seed_frames``)
    :param batch_size: minibatch size
    :param buffer_size: replay capacity, in transitions (``replay_buffer_size``)
    :param learning_rate: Adam learning rate (``lr``)
    :param n_steps: n-step return length, in agent steps (``nstep``)
    :param feature_dim: trunk size of the actor and the critic
    :param hidden_dim: hidden units of the actor's ``mlp1``, ``mlp2`` and of the Q heads
    :param stddev_schedule: exploration std schedule, durations in agent steps
    :param stddev_clip: clip of the exploration noise in the updates
    :param tau: soft-update coefficient of the target critic (``critic_target_tau``)
    :param gamma: discount factor (``discount``)
    :param train_freq: agent steps between two updates (``update_every_steps``)
    :param augmentation_pad: random-shift padding, in pixels (``RandomShiftsAug(pad=4)``)
    :param eval_every_frames: frames between two evaluations
    :param eval_episodes: episodes per evaluation (``num_eval_episodes``)
    :param replay_sampling: ``"drqv2"``: DrQ-v2's replay sampling (:class:`~sb3_collapse.drqv2.FrameStackReplayBuffer`)
    """

    task: str
    tier: str
    from_drqv2: bool
    frames: int
    action_repeat: int = 2
    frame_stack: int = 3
    seed_frames: int = 4000
    batch_size: int = 256
    buffer_size: int = 1_000_000
    learning_rate: float = 1e-4
    n_steps: int = 3
    feature_dim: int = 50
    hidden_dim: int = 1024
    stddev_schedule: str = "linear(1.0,0.1,100000)"
    stddev_clip: float = 0.3
    tau: float = 0.01
    gamma: float = 0.99
    train_freq: int = 2
    augmentation_pad: int = 4
    eval_every_frames: int = 10_000
    eval_episodes: int = 10
    replay_sampling: str = "drqv2"

    def settings(self) -> dict[str, Any]:
        """The hyperparameters, by name (every field but ``task``, ``tier`` and ``from_drqv2``)."""
        return {name: getattr(self, name) for name in SETTING_NAMES}


SETTING_NAMES: tuple[str, ...] = tuple(
    field.name for field in dataclasses.fields(TaskPreset) if field.name not in ("task", "tier", "from_drqv2")
)
"""The hyperparameters a preset sets, in table order."""

TIERS: Mapping[str, Mapping[str, Any]] = MappingProxyType(
    {
        "easy": {"frames": 1_100_000, "stddev_schedule": "linear(1.0,0.1,100000)"},
        "medium": {"frames": 3_100_000, "stddev_schedule": "linear(1.0,0.1,500000)"},
        "hard": {"frames": 30_100_000, "stddev_schedule": "linear(1.0,0.1,2000000)"},
    }
)
"""DrQ-v2's ``cfgs/task/{easy,medium,hard}.yaml``."""

WALKER = {"n_steps": 1, "batch_size": 512}
HUMANOID = {"learning_rate": 8e-5, "feature_dim": 100}

_DRQV2_TASKS: dict[str, tuple[str, dict[str, Any]]] = {
    "walker-walk": ("easy", WALKER), "walker-stand": ("easy", WALKER), "hopper-stand": ("easy", {}),
    "finger-spin": ("easy", {}), "cartpole-balance": ("easy", {}), "cartpole-balance_sparse": ("easy", {}),
    "cartpole-swingup": ("easy", {}), "ball_in_cup-catch": ("easy", {}), "pendulum-swingup": ("easy", {}),
    "walker-run": ("medium", WALKER), "hopper-hop": ("medium", {}), "cheetah-run": ("medium", {}),
    "quadruped-walk": ("medium", {}), "quadruped-run": ("medium", {"buffer_size": 100_000}),
    "acrobot-swingup": ("medium", {}), "cartpole-swingup_sparse": ("medium", {}), "finger-turn_easy": ("medium", {}),
    "finger-turn_hard": ("medium", {}), "reacher-easy": ("medium", {}), "reacher-hard": ("medium", {}),
    "humanoid-stand": ("hard", HUMANOID), "humanoid-walk": ("hard", HUMANOID), "humanoid-run": ("hard", HUMANOID),
}  # fmt: skip

FALLBACK_TIER = "easy"
"""The tier of a suite task that DrQ-v2 published no config for."""

PRESETS: Mapping[str, TaskPreset] = MappingProxyType(
    {
        task: TaskPreset(task=task, tier=tier, from_drqv2=True, **{**TIERS[tier], **overrides})
        for task, (tier, overrides) in _DRQV2_TASKS.items()
    }
)
"""Task (``<domain>-<task>``) -> DrQ-v2's preset, for the 23 suite tasks of DrQ-v2's ``cfgs/task/``."""


def preset(task: str) -> TaskPreset:
    """
    :param task: a DeepMind Control suite task, in any form :func:`~sb3_collapse.envs.parse_task` accepts
    :return: DrQ-v2's preset; for a task DrQ-v2 did not run, the easy tier's settings with ``from_drqv2=False``
    :raises ValueError: for a name that is not a suite task
    """
    domain, name = parse_task(task)
    task_id = f"{domain}-{name}"
    if task_id in PRESETS:
        return PRESETS[task_id]
    return TaskPreset(task=task_id, tier=FALLBACK_TIER, from_drqv2=False, **TIERS[FALLBACK_TIER])
