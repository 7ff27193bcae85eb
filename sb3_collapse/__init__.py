"""sb3-collapse: DrQ-v2 for Stable-Baselines3 on DeepMind Control pixels, and tools to study action collapse."""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from sb3_collapse.envs import make_dmc_env  # registers the sb3_collapse/<domain>-<task>-v0 Gymnasium ids

if TYPE_CHECKING:
    from sb3_collapse.drqv2 import DrQv2
    from sb3_collapse.monitoring import ActivationLogger, CollapseMetrics, CollapseReset, PeriodicReDo

__version__ = "0.1.0"

# Imported at first use: the algorithm and the monitoring callbacks do not import each other.
_LAZY = {"DrQv2": "sb3_collapse.drqv2"} | {
    name: "sb3_collapse.monitoring" for name in ("ActivationLogger", "CollapseMetrics", "CollapseReset", "PeriodicReDo")
}
__all__ = [
    "ActivationLogger", "CollapseMetrics", "CollapseReset", "DrQv2", "PeriodicReDo", "__version__", "make_dmc_env"
]  # fmt: skip


def __getattr__(name: str) -> Any:
    """:return: one of the :data:`_LAZY` names, imported from its package at its first use"""
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
