"""sb3-collapse: DrQ-v2 for Stable-Baselines3 on DeepMind Control pixels, and tools to study action collapse."""

from sb3_collapse.drqv2 import DrQv2
from sb3_collapse.envs import make_dmc_env
from sb3_collapse.monitoring import ActivationLogger, CollapseMetrics, CollapseReset, PeriodicReDo

__version__ = "0.1.0"

__all__ = [
    "ActivationLogger", "CollapseMetrics", "CollapseReset", "DrQv2", "PeriodicReDo", "__version__", "make_dmc_env"
]
