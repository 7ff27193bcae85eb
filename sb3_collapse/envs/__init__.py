"""DeepMind Control Suite environments from pixels (DrQ-v2's preprocessing). Importing this registers the Gymnasium
ids ``sb3_collapse/<domain>-<task>-v0`` and imports no dm_control. See docs/environments.md."""

from sb3_collapse.envs.dmc import REWARD_INPUTS, DMCEnv, make_dmc_env, parse_task
from sb3_collapse.envs.registration import DMC_TASKS, register_dmc_envs
from sb3_collapse.envs.rendering import ensure_rendering_backend

__all__ = [
    "DMC_TASKS", "REWARD_INPUTS", "DMCEnv", "ensure_rendering_backend", "make_dmc_env", "parse_task",
    "register_dmc_envs",
]  # fmt: skip

register_dmc_envs()
