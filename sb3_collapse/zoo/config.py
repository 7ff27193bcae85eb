"""``zoo_configs/drqv2.yml``, generated from the preset table: ``python -m sb3_collapse.zoo.config [--check] PATH``
(needs pyyaml, which the ``zoo`` extra installs)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from sb3_collapse.envs.registration import DOMAIN_ALIASES, dmc_env_id
from sb3_collapse.errors import MissingDependencyError
from sb3_collapse.presets import PRESETS, TaskPreset

HEADER = """\
# DrQ-v2's published hyperparameters for the DeepMind Control pixel tasks, as rl_zoo3 hyperparameters of
# sb3_collapse.DrQv2, keyed by the Gymnasium ids that `import sb3_collapse.envs` registers.
#
#   python -m sb3_collapse.zoo train --algo drqv2 --env sb3_collapse/walker-walk-v0 -conf zoo_configs/drqv2.yml
#
# GENERATED from the preset table sb3_collapse/presets.py by `python -m sb3_collapse.zoo.config
# zoo_configs/drqv2.yml`: do not edit it by hand, a test checks that it is up to date.
# Counts are in AGENT STEPS (frames / action_repeat); each key's unit: zoo_configs/README.md. Never use rl_zoo3's
# `frame_stack` hyperparameter nor `normalize` with DrQv2 (the launcher refuses both): docs/zoo.md.
"""


def _zoo_hyperparameters(task_preset: TaskPreset, size: int = 84) -> dict[str, Any]:
    """The rl_zoo3 hyperparameters of DrQv2 for a task's preset, counts in agent steps, ``size`` in pixels."""
    p, steps = task_preset, task_preset.frames // task_preset.action_repeat
    return {
        "policy": "CnnPolicy",
        "env_kwargs": {"action_repeat": p.action_repeat, "frame_stack": p.frame_stack, "size": size},
        "n_timesteps": steps, "learning_starts": p.seed_frames // p.action_repeat,
        "buffer_size": min(p.buffer_size, steps), "batch_size": p.batch_size, "learning_rate": p.learning_rate,
        "n_steps": p.n_steps, "gamma": p.gamma, "tau": p.tau, "train_freq": p.train_freq, "gradient_steps": 1,
        "stddev_schedule": p.stddev_schedule, "stddev_clip": p.stddev_clip, "augmentation_pad": p.augmentation_pad,
        "replay_buffer_kwargs": {"sampling": p.replay_sampling},
        "policy_kwargs": f"dict(feature_dim={p.feature_dim}, hidden_dim={p.hidden_dim})",
    }  # fmt: skip


def _zoo_env_ids(task: str) -> list[str]:
    """The Gymnasium ids of ``task``: the registered one, and DrQ-v2's alias where there is one (``cup-catch``)."""
    domain, name = task.split("-", 1)
    aliases = [alias for alias, target in DOMAIN_ALIASES.items() if target == domain]
    return [dmc_env_id(task)] + [dmc_env_id(f"{alias}-{name}") for alias in aliases]


def render_zoo_config() -> str:
    """The text of ``zoo_configs/drqv2.yml``: an entry per preset (and per alias id), by tier.

    :raises MissingDependencyError: without pyyaml"""
    try:
        import yaml
    except ImportError as error:
        raise MissingDependencyError("pyyaml cannot be imported: pip install -e '.[zoo]' (or pyyaml)") from error
    parts = [HEADER]
    for tier in ("easy", "medium", "hard"):
        presets = [task_preset for task_preset in PRESETS.values() if task_preset.tier == tier]
        frames = presets[0].frames
        parts.append(f"\n# {tier} tasks: {frames:,} frames\n")
        for task_preset in presets:
            entries = {env_id: _zoo_hyperparameters(task_preset) for env_id in _zoo_env_ids(task_preset.task)}
            parts.append(yaml.safe_dump(entries, sort_keys=False, default_flow_style=None, width=120))
    return "".join(parts)


def main(argv: list[str] | None = None) -> int:
    """:return: 0, or 1 when ``--check`` finds the file out of date"""
    parser = argparse.ArgumentParser(
        prog="python -m sb3_collapse.zoo.config", description="Write zoo_configs/drqv2.yml from the preset table."
    )
    parser.add_argument("path", help="the YAML file to write (or check)")
    parser.add_argument("--check", action="store_true", help="only check that the file is up to date")
    args = parser.parse_args(argv)
    try:
        text, path = render_zoo_config(), Path(args.path)
    except MissingDependencyError as error:
        print(f"error: {error}", file=sys.stderr)
        return 1
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
