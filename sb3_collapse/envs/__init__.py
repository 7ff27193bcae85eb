"""DeepMind Control Suite environments for pixel-based RL (DrQ-v2 preprocessing).

Importing this module registers the Gymnasium ids ``sb3_collapse/<domain>-<task>-v0``
(e.g. ``sb3_collapse/walker-walk-v0``). It does not import dm_control or mujoco: they are
imported when the first environment is built, after a headless OpenGL backend is chosen
(see :func:`ensure_rendering_backend`; the backend is also chosen if dm_control or mujoco is
imported directly after this module).
"""

from sb3_collapse.envs.dmc import DMCEnv, make_dmc_env, parse_task
from sb3_collapse.envs.registration import DMC_TASKS, register_dmc_envs
from sb3_collapse.envs.rendering import RenderingBackendError, ensure_rendering_backend, install_import_hook

__all__ = [
    "DMC_TASKS",
    "DMCEnv",
    "RenderingBackendError",
    "ensure_rendering_backend",
    "make_dmc_env",
    "parse_task",
    "register_dmc_envs",
]

register_dmc_envs()
install_import_hook()
