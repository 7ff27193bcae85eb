"""Gymnasium ids for the DeepMind Control Suite tasks: ``sb3_collapse/<domain>-<task>-v0``.

The task list is hard-coded so that registering the ids does not import dm_control (slow, and it
must come after the OpenGL backend is chosen, see :mod:`sb3_collapse.envs.rendering`).
"""

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

# Short domain names accepted in task names, as in DrQ-v2 ("cup_catch").
DOMAIN_ALIASES: dict[str, str] = {"cup": "ball_in_cup"}

ENV_NAMESPACE = "sb3_collapse"
ENTRY_POINT = "sb3_collapse.envs.dmc:DMCEnv"
# Module that registers the ids, preloaded by the forkserver (see ``_preload_in_forkserver``).
_REGISTERING_MODULE = "sb3_collapse.envs"


def dmc_env_id(task_id: str) -> str:
    """
    :param task_id: Task name in the ``<domain>-<task>`` form, e.g. "walker-walk".
    :return: Its Gymnasium id, e.g. "sb3_collapse/walker-walk-v0".
    """
    return f"{ENV_NAMESPACE}/{task_id}-v0"


def register_dmc_envs() -> list[str]:
    """
    Register a Gymnasium id for every DeepMind Control Suite task (idempotent).

    Ids are ``sb3_collapse/<domain>-<task>-v0`` (e.g. ``sb3_collapse/walker-walk-v0``,
    ``sb3_collapse/ball_in_cup-catch-v0``), plus aliases such as ``sb3_collapse/cup-catch-v0``.
    They build a :class:`sb3_collapse.envs.dmc.DMCEnv`; keyword arguments of ``gymnasium.make``
    (``seed``, ``action_repeat``, ``frame_stack``, ``size``, ``camera_id``, ``obs_type``) go to it.
    No ``TimeLimit`` is added: the environment truncates episodes itself at dm_control's time limit.

    Also makes the multiprocessing forkserver import ``sb3_collapse.envs``, so that
    ``SubprocVecEnv`` workers started with the (default) forkserver method know the ids.

    :return: The ids registered by this call (empty if they were all already registered).
    """
    task_ids = [f"{domain}-{task}" for domain, task in DMC_TASKS]
    aliases = [
        (f"{alias}-{task}", f"{domain}-{task}")
        for alias, domain in DOMAIN_ALIASES.items()
        for task_domain, task in DMC_TASKS
        if task_domain == domain
    ]
    registered = []
    for name, task_id in [(task_id, task_id) for task_id in task_ids] + aliases:
        env_id = dmc_env_id(name)
        if env_id in gym.registry:
            continue
        gym.register(id=env_id, entry_point=ENTRY_POINT, kwargs={"task": task_id}, max_episode_steps=None)
        registered.append(env_id)
    _preload_in_forkserver(_REGISTERING_MODULE)
    return registered


def _preload_in_forkserver(module: str) -> None:
    """
    Add a module to those the multiprocessing forkserver imports when it starts.

    ``SubprocVecEnv`` starts its workers with the forkserver method by default; they are forked from
    a fresh server process where only ``__main__`` is imported, so ``gymnasium.make("sb3_collapse/...")``
    in a worker would not find the ids unless the server imports the registering module too.
    This has no effect if the forkserver is already running (then use the ``"sb3_collapse.envs:<id>"``
    form of the id, or pass a callable building the env).

    :param module: Name of the module to import in the forkserver.
    """
    current = list(getattr(forkserver._forkserver, "_preload_modules", None) or ["__main__"])
    if module not in current:
        forkserver.set_forkserver_preload([*current, module])
