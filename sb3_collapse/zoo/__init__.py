"""
rl_zoo3 for DrQv2: ``python -m sb3_collapse.zoo train --algo drqv2 --env sb3_collapse/walker-walk-v0
-conf zoo_configs/drqv2.yml``, and the same with ``enjoy``.

rl_zoo3 has no plugin mechanism: :func:`register_with_zoo` adds DrQv2 to its algorithm table and registers the
DeepMind Control ids, and :class:`~sb3_collapse.zoo.experiment.ZooExperimentManager` (used by the launcher) gives
the evaluation env the training env's pixel settings and refuses settings that would break pixel observations.
Importing this package does not import rl_zoo3 (an optional dependency: ``pip install -e '.[zoo]'`` in a clone).
"""

from sb3_collapse.zoo.launcher import main
from sb3_collapse.zoo.registration import ALGO_NAME, register_with_zoo

__all__ = ["ALGO_NAME", "main", "register_with_zoo"]
