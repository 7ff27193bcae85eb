"""sb3-collapse: DrQ-v2 for Stable-Baselines3 on DeepMind Control pixels, and tools to study action collapse."""

import importlib
from typing import Any

from sb3_collapse.drqv2 import DrQv2
from sb3_collapse.envs import make_dmc_env  # registers the sb3_collapse/<domain>-<task>-v0 Gymnasium ids

__version__ = "0.1.0"

_MONITORING = ("ActivationLogger", "CollapseMetrics", "CollapseReset", "PeriodicReDo")
"""Imported from ``sb3_collapse.monitoring`` when first used: importing the algorithm does not import them."""

__all__ = ["ActivationLogger", "CollapseMetrics", "CollapseReset", "DrQv2", "PeriodicReDo", "__version__", "make_dmc_env"]


def __getattr__(name: str) -> Any:
    if name in _MONITORING:
        value = getattr(importlib.import_module("sb3_collapse.monitoring"), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'sb3_collapse' has no attribute {name!r}")
