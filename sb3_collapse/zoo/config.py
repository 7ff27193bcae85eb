"""
``zoo_configs/drqv2.yml``, generated from the preset table (:mod:`sb3_collapse.presets`) so that the two cannot drift:

    python -m sb3_collapse.zoo.config zoo_configs/drqv2.yml   # rewrite the file
    python -m sb3_collapse.zoo.config --check zoo_configs/drqv2.yml   # exit 1 if it is not up to date

A test checks that the file in the repository is :func:`render_zoo_config`'s output.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import yaml

from sb3_collapse.envs.registration import DOMAIN_ALIASES, dmc_env_id
from sb3_collapse.presets import PRESETS, TaskPreset

HEADER = """\
# DrQ-v2's published hyperparameters for the DeepMind Control pixel tasks, as rl_zoo3 hyperparameters of
# sb3_collapse.DrQv2, keyed by the Gymnasium ids that `import sb3_collapse.envs` registers.
#
#   python -m sb3_collapse.zoo train --algo drqv2 --env sb3_collapse/walker-walk-v0 -conf zoo_configs/drqv2.yml
#
# GENERATED from the preset table sb3_collapse/presets.py (DrQ-v2's cfgs/config.yaml and cfgs/task/*.yaml,
# facebookresearch/drqv2, MIT) by `python -m sb3_collapse.zoo.config zoo_configs/drqv2.yml`: do not edit it by
# hand, a test checks that it is up to date.
#
# Units. SB3 and rl_zoo3 count AGENT STEPS (one env.step, i.e. `action_repeat` simulator frames); DrQ-v2 and the
# action-collapse paper count FRAMES = agent steps x action_repeat. So:
#   n_timesteps      agent steps: DrQ-v2's num_train_frames / action_repeat (1.1M frames -> 550,000)
#   learning_starts  agent steps of uniform random actions: num_seed_frames / action_repeat
#   buffer_size      transitions (one per agent step): DrQ-v2's replay_buffer_size, capped at n_timesteps (a larger
#                    buffer is never filled). DrQv2's FrameStackReplayBuffer stores each 3x84x84 frame once,
#                    ~21.5 KB per transition (reserved lazily, filled as training goes)
#   train_freq       agent steps between two updates (update_every_steps), one gradient step each
#   n_steps          n-step return length, in agent steps (nstep)
#   stddev_schedule  exploration std, durations in AGENT STEPS, exactly DrQ-v2's string
#   replay_buffer_kwargs.sampling  drqv2: DrQ-v2's replay sampling (finished episodes only, no n-step return
#                    started in an episode's last n-1 steps)
#   rl_zoo3's --eval-freq is in agent steps too: the launcher's default is DrQ-v2's eval_every_frames / 2, with
#   DrQ-v2's num_eval_episodes.
#
# env_kwargs go to the training env AND to the evaluation env (the launcher makes rl_zoo3 pass them to both).
# Never use rl_zoo3's `frame_stack` hyperparameter (VecFrameStack) nor `normalize` with DrQv2: the env stacks the
# frames itself and the launcher refuses both. The collapse callbacks and the paper's reset rule are the launcher's
# --collapse-metrics and --reset-rule switches.
"""


def zoo_hyperparameters(task_preset: TaskPreset, size: int = 84) -> dict[str, Any]:
    """
    :param task_preset: a task's preset
    :param size: image height and width, in pixels (DrQ-v2's 84)
    :return: the rl_zoo3 hyperparameters of DrQv2 for the task, counts in agent steps
    """
    steps = task_preset.frames // task_preset.action_repeat
    return {
        "policy": "CnnPolicy",
        "env_kwargs": {
            "action_repeat": task_preset.action_repeat,
            "frame_stack": task_preset.frame_stack,
            "size": size,
        },
        "n_timesteps": steps,
        "learning_starts": task_preset.seed_frames // task_preset.action_repeat,
        "buffer_size": min(task_preset.buffer_size, steps),
        "batch_size": task_preset.batch_size,
        "learning_rate": task_preset.learning_rate,
        "n_steps": task_preset.n_steps,
        "gamma": task_preset.gamma,
        "tau": task_preset.tau,
        "train_freq": task_preset.train_freq,
        "gradient_steps": 1,
        "stddev_schedule": task_preset.stddev_schedule,
        "stddev_clip": task_preset.stddev_clip,
        "augmentation_pad": task_preset.augmentation_pad,
        "replay_buffer_kwargs": {"sampling": task_preset.replay_sampling},
        "policy_kwargs": f"dict(feature_dim={task_preset.feature_dim}, hidden_dim={task_preset.hidden_dim})",
    }


def zoo_env_ids(task: str) -> list[str]:
    """
    :param task: a task, ``<domain>-<task>``
    :return: its Gymnasium ids: the registered one, and DrQ-v2's alias where there is one (``cup-catch``)
    """
    domain, name = task.split("-", 1)
    aliases = [alias for alias, target in DOMAIN_ALIASES.items() if target == domain]
    return [dmc_env_id(task)] + [dmc_env_id(f"{alias}-{name}") for alias in aliases]


def render_zoo_config() -> str:
    """
    :return: the text of ``zoo_configs/drqv2.yml``: one entry per preset of :data:`~sb3_collapse.presets.PRESETS`
        (and per alias id), by tier
    """
    parts = [HEADER]
    for tier in ("easy", "medium", "hard"):
        presets = [task_preset for task_preset in PRESETS.values() if task_preset.tier == tier]
        frames = presets[0].frames
        parts.append(f"\n# {tier} tasks: {frames:,} frames\n")
        for task_preset in presets:
            entries = {env_id: zoo_hyperparameters(task_preset) for env_id in zoo_env_ids(task_preset.task)}
            parts.append(yaml.safe_dump(entries, sort_keys=False, default_flow_style=None, width=120))
    return "".join(parts)


def main(argv: list[str] | None = None) -> int:
    """
    :param argv: command-line arguments (``sys.argv[1:]`` when ``None``)
    :return: 0, or 1 when ``--check`` finds the file out of date
    """
    parser = argparse.ArgumentParser(
        prog="python -m sb3_collapse.zoo.config", description="Write zoo_configs/drqv2.yml from the preset table."
    )
    parser.add_argument("path", help="the YAML file to write (or check)")
    parser.add_argument("--check", action="store_true", help="only check that the file is up to date")
    args = parser.parse_args(argv)
    text, path = render_zoo_config(), Path(args.path)
    if args.check:
        if not path.is_file() or path.read_text() != text:
            print(f"{path} is not up to date: run python -m sb3_collapse.zoo.config {path}", file=sys.stderr)
            return 1
        return 0
    path.write_text(text)
    print(f"wrote {path} ({len(PRESETS)} tasks)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
