"""DeepMind Control Suite environments for pixel-based RL (DrQ-v2 preprocessing).

Importing this module registers the Gymnasium ids ``sb3_collapse/<domain>-<task>-v0``
(e.g. ``sb3_collapse/walker-walk-v0``). It imports neither dm_control nor mujoco and sets no ``MUJOCO_GL``:
building an environment first chooses a headless OpenGL backend (:func:`ensure_rendering_backend`), then imports
dm_control. Code that imports dm_control itself calls :func:`ensure_rendering_backend` first.
"""

from sb3_collapse.envs.dmc import DMCEnv, make_dmc_env, parse_task
from sb3_collapse.envs.registration import DMC_TASKS, register_dmc_envs
from sb3_collapse.envs.rendering import ensure_rendering_backend

__all__ = [
    "DMC_TASKS",
    "DMCEnv",
    "ensure_rendering_backend",
    "make_dmc_env",
    "parse_task",
    "register_dmc_envs",
]

register_dmc_envs()
