"""DrQ-v2's per-task hyperparameters on DeepMind Control pixels (facebookresearch/drqv2, MIT: ``cfgs/config.yaml``,
``cfgs/task/*.yaml``): the defaults of the train CLI, the sweep and ``zoo_configs/drqv2.yml``. See docs/presets.md."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any

from sb3_collapse.drqv2.schedules import StddevSchedule
from sb3_collapse.envs.dmc import parse_task
from sb3_collapse.paper import PAPER


@dataclass(frozen=True)
class TaskPreset:
    """DrQ-v2's settings for one task: each hyperparameter is the ``TrainConfig`` setting of the same name
    (docs/presets.md); the comments name DrQ-v2's config keys.

    :param task: the task, ``<domain>-<task>``
    :param tier: DrQ-v2's difficulty tier, ``"easy"``, ``"medium"`` or ``"hard"``
    :param from_drqv2: whether DrQ-v2 published a config for this task (``False``: the easy tier's settings)
    """

    task: str
    tier: str
    from_drqv2: bool
    frames: int  # num_train_frames
    action_repeat: int = 2
    frame_stack: int = 3
    seed_frames: int = 4000  # num_seed_frames
    batch_size: int = 256
    buffer_size: int = 1_000_000  # replay_buffer_size, in transitions
    learning_rate: float = 1e-4  # lr
    n_steps: int = 3  # nstep, in agent steps
    feature_dim: int = 50
    hidden_dim: int = 1024
    stddev_schedule: str = "linear(1.0,0.1,100000)"  # durations in agent steps
    stddev_clip: float = 0.3
    tau: float = 0.01  # critic_target_tau
    gamma: float = 0.99  # discount
    train_freq: int = 2  # update_every_steps
    augmentation_pad: int = 4  # RandomShiftsAug(pad=4)
    eval_every_frames: int = 10_000
    eval_episodes: int = 10  # num_eval_episodes
    replay_sampling: str = "drqv2"  # finished episodes only (sb3_collapse.drqv2.FrameStackReplayBuffer)

    def settings(self) -> dict[str, Any]:
        """The hyperparameters, by name (every field but ``task``, ``tier`` and ``from_drqv2``)."""
        return {name: getattr(self, name) for name in SETTING_NAMES}

    def env_kwargs(self) -> dict[str, Any]:
        """:return: the keyword arguments of ``make_dmc_env(task, ...)`` that this preset sets (``action_repeat``,
        ``frame_stack``)"""
        return dict(action_repeat=self.action_repeat, frame_stack=self.frame_stack)

    def drqv2_kwargs(self, frames: int | None = None, **kwargs: Any) -> dict[str, Any]:
        """
        The keyword arguments of ``DrQv2(policy, env, ...)`` that the train command gives a run of this preset, so
        that a library run and the command's are the same configuration::

            task = preset("walker-walk")
            env = make_dmc_env(task.task, seed=0, **task.env_kwargs())
            model = DrQv2("CnnPolicy", env, seed=0, **task.drqv2_kwargs())
            model.learn(task.frames // task.action_repeat)  # SB3 counts agent steps

        :param frames: the run's budget, in frames (default: the preset's ``frames``): the replay buffer is capped at
            its agent steps, as the train command caps it (a larger buffer is never filled)
        :param kwargs: keyword arguments of ``DrQv2`` given over the preset's (``seed``, ``device``, ``callback``...)
        :return: the keyword arguments (``learning_starts`` and ``buffer_size`` in agent steps)
        """
        settings = self.settings()
        steps = max(1, (self.frames if frames is None else frames) // self.action_repeat)
        settings["buffer_size"] = min(self.buffer_size, steps)
        return drqv2_kwargs_of(settings) | kwargs


def drqv2_kwargs_of(settings: Mapping[str, Any]) -> dict[str, Any]:
    """
    :param settings: a value for each of :data:`SETTING_NAMES` (a preset's, or a run's resolved settings)
    :return: the keyword arguments of ``DrQv2(policy, env, ...)`` they make: DrQ-v2's update ratio with any number of
        environments (``train_freq`` counted in transitions), ``learning_starts`` = ``seed_frames // action_repeat``
    """
    same = ("learning_rate", "buffer_size", "batch_size", "gamma", "tau", "n_steps", "stddev_schedule", "stddev_clip")
    return {name: settings[name] for name in (*same, "augmentation_pad")} | dict(
        learning_starts=settings["seed_frames"] // settings["action_repeat"],
        train_freq=(settings["train_freq"], "transition"),
        replay_buffer_kwargs=dict(sampling=settings["replay_sampling"]),
        policy_kwargs=dict(feature_dim=settings["feature_dim"], hidden_dim=settings["hidden_dim"]),
    )


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

FALLBACK_TIER = "easy"  # of a suite task DrQ-v2 published no config for

PRESETS: Mapping[str, TaskPreset] = MappingProxyType(
    {
        task: TaskPreset(task=task, tier=tier, from_drqv2=True, **{**TIERS[tier], **overrides})
        for task, (tier, overrides) in _DRQV2_TASKS.items()
    }
)
"""Task (``<domain>-<task>``) -> DrQ-v2's preset, for the 23 suite tasks of DrQ-v2's ``cfgs/task/``."""


def preset(task: str) -> TaskPreset:
    """:return: DrQ-v2's preset of a suite ``task`` (any form ``parse_task`` takes; ``ValueError`` for another); for a
    task DrQ-v2 did not run, the easy tier's settings with ``from_drqv2=False``"""
    domain, name = parse_task(task)
    task_id = f"{domain}-{name}"
    if task_id in PRESETS:
        return PRESETS[task_id]
    return TaskPreset(task=task_id, tier=FALLBACK_TIER, from_drqv2=False, **TIERS[FALLBACK_TIER])


def reset_window_frames(task: str, stddev_schedule: str | None = None, action_repeat: int | None = None) -> int:
    """
    The reset rule's default window, Proposition 1's m: "m is the frames where the exploration decreases to the
    smallest" (Section 5.2; "DrQ-v2 uses an exploration noise that decreases with training steps, which becomes the
    smallest (but not zero) when x = 20", Observation 3): the agent step at which ``stddev_schedule`` reaches its
    final value, times ``action_repeat``. The easy tasks' ``linear(1.0,0.1,100000)`` at action repeat 2 gives the
    paper's 200,000 frames; the medium tier's 1,000,000, the hard tier's 4,000,000.

    :param task: the task, whose preset gives what is not passed
    :param stddev_schedule: the run's exploration schedule, durations in agent steps (``None``: the preset's)
    :param action_repeat: the run's frames per agent step (``None``: the preset's)
    :return: the window in frames; the paper's 200,000 (:data:`~sb3_collapse.paper.PAPER`) for a schedule that does
        not decay (a constant)
    :raises ValueError: for an unknown task or a malformed schedule
    """
    task_preset = preset(task)
    schedule = StddevSchedule(task_preset.stddev_schedule if stddev_schedule is None else stddev_schedule)
    repeat = task_preset.action_repeat if action_repeat is None else action_repeat
    end = schedule.end_step
    return PAPER.window_frames if not end else end * repeat
