"""
rl_zoo3 for DrQv2: ``python -m sb3_collapse.zoo {train,enjoy} --algo drqv2 ...`` (docs/zoo.md). Importing this
package does not import rl_zoo3 (an optional dependency: ``pip install -e '.[zoo]'`` in a clone).
"""

from sb3_collapse.zoo.launcher import main
from sb3_collapse.zoo.registration import ALGO_NAME, register_with_zoo

__all__ = ["ALGO_NAME", "main", "register_with_zoo"]
