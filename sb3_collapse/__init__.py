"""sb3-collapse: DrQ-v2 for Stable-Baselines3 on DeepMind Control pixels, and tools to study action collapse."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from sb3_collapse.envs import make_dmc_env
from sb3_collapse.monitoring import ActivationLogger, CollapseMetrics, CollapseReset, PeriodicReDo

if TYPE_CHECKING:
    from sb3_collapse.drqv2 import DrQv2

__version__ = "0.1.0"

__all__ = [
    "ActivationLogger",
    "CollapseMetrics",
    "CollapseReset",
    "DrQv2",
    "PeriodicReDo",
    "__version__",
    "make_dmc_env",
]


def __getattr__(name: str) -> Any:
    """
    ``sb3_collapse.DrQv2``, imported at its first use: importing ``sb3_collapse.monitoring`` (which imports this
    package first) does not import the algorithm.

    :param name: the attribute
    :return: the attribute's value
    :raises AttributeError: for a name that is not one
    """
    if name == "DrQv2":
        from sb3_collapse.drqv2 import DrQv2

        globals()["DrQv2"] = DrQv2
        return DrQv2
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
