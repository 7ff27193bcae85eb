"""rl_zoo3 for DrQv2: ``python -m sb3_collapse.zoo {train,enjoy} --algo drqv2 ...`` (imports rl_zoo3 only then;
the launcher: :mod:`sb3_collapse.commands.zoo`)."""

from sb3_collapse.zoo.registration import ALGO_NAME, register_with_zoo

__all__ = ["ALGO_NAME", "register_with_zoo"]
