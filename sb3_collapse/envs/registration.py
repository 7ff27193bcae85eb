"""Gymnasium ids ``sb3_collapse/<domain>-<task>-v0`` for the DeepMind Control Suite tasks, from a hard-coded task
list: registering imports no dm_control (which must come after the OpenGL backend is chosen)."""

from __future__ import annotations

from multiprocessing import forkserver

import gymnasium as gym

# (domain, task) pairs of the suite, equal to ``dm_control.suite.ALL_TASKS`` (checked by the tests).
DMC_TASKS: tuple[tuple[str, str], ...] = (
    ("acrobot", "swingup"), ("acrobot", "swingup_sparse"),
    ("ball_in_cup", "catch"),
    ("cartpole", "balance"), ("cartpole", "balance_sparse"), ("cartpole", "swingup"), ("cartpole", "swingup_sparse"),
    ("cartpole", "two_poles"), ("cartpole", "three_poles"),
    ("cheetah", "run"),
    ("dog", "stand"), ("dog", "walk"), ("dog", "trot"), ("dog", "run"), ("dog", "fetch"),
    ("finger", "spin"), ("finger", "turn_easy"), ("finger", "turn_hard"),
    ("fish", "upright"), ("fish", "swim"),
    ("hopper", "stand"), ("hopper", "hop"),
    ("humanoid", "stand"), ("humanoid", "walk"), ("humanoid", "run"), ("humanoid", "run_pure_state"),
    ("humanoid_CMU", "stand"), ("humanoid_CMU", "walk"), ("humanoid_CMU", "run"),
    ("lqr", "lqr_2_1"), ("lqr", "lqr_6_2"),
    ("manipulator", "bring_ball"), ("manipulator", "bring_peg"), ("manipulator", "insert_ball"),
    ("manipulator", "insert_peg"),
    ("pendulum", "swingup"),
    ("point_mass", "easy"), ("point_mass", "hard"),
    ("quadruped", "walk"), ("quadruped", "run"), ("quadruped", "escape"), ("quadruped", "fetch"),
    ("reacher", "easy"), ("reacher", "hard"),
    ("stacker", "stack_2"), ("stacker", "stack_4"),
    ("swimmer", "swimmer6"), ("swimmer", "swimmer15"),
    ("walker", "stand"), ("walker", "walk"), ("walker", "run"),
)  # fmt: skip

DOMAIN_ALIASES: dict[str, str] = {"cup": "ball_in_cup"}  # short domain names, as in DrQ-v2 ("cup_catch")
DOMAIN_NAMES: dict[str, str] = {**{domain: domain for domain, _ in DMC_TASKS}, **DOMAIN_ALIASES}  # name -> domain

ENTRY_POINT = "sb3_collapse.envs.dmc:DMCEnv"


def dmc_env_id(task_id: str) -> str:
    """:return: the Gymnasium id of a ``<domain>-<task>`` name, e.g. ``sb3_collapse/walker-walk-v0``"""
    return f"sb3_collapse/{task_id}-v0"


def register_dmc_envs() -> list[str]:
    """Register a Gymnasium id (no ``TimeLimit``: the env truncates itself) for every suite task and alias, and
    have the forkserver import ``sb3_collapse.envs`` for ``SubprocVecEnv``. :return: the ids new to this call"""
    registered = []
    for name, domain, task in [
        (name, d, task) for name, d in DOMAIN_NAMES.items() for d2, task in DMC_TASKS if d2 == d
    ]:
        env_id, task_id = dmc_env_id(f"{name}-{task}"), f"{domain}-{task}"
        if env_id in gym.registry:
            continue
        gym.register(id=env_id, entry_point=ENTRY_POINT, kwargs={"task": task_id}, max_episode_steps=None)
        registered.append(env_id)
    # SubprocVecEnv's forkserver workers import only __main__: the server must import the module that registers.
    current = list(getattr(forkserver._forkserver, "_preload_modules", None) or ["__main__"])
    if "sb3_collapse.envs" not in current:
        forkserver.set_forkserver_preload([*current, "sb3_collapse.envs"])
    return registered
