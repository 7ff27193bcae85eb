"""Make DrQv2 and the DeepMind Control ids known to rl_zoo3."""

from __future__ import annotations

from types import ModuleType

from sb3_collapse.errors import MissingDependencyError

ALGO_NAME = "drqv2"
"""Name of DrQv2 in rl_zoo3's algorithm table (``--algo drqv2``)."""

INSTALL_HINT = "pip install -e '.[zoo]' in a clone of sb3-collapse"


def import_rl_zoo3() -> ModuleType:
    """
    :return: the ``rl_zoo3`` package
    :raises MissingDependencyError: if it (or a package it needs) cannot be imported, saying how to install it
    """
    try:
        import rl_zoo3
        import rl_zoo3.utils  # the algorithm table
    except ImportError as error:
        missing = f" (missing module: {error.name})" if error.name else ""
        raise MissingDependencyError(f"rl_zoo3 cannot be imported{missing}: {INSTALL_HINT}") from error
    return rl_zoo3


def register_with_zoo() -> None:
    """
    Add DrQv2 to rl_zoo3's algorithm table (``rl_zoo3.utils.ALGOS``) as ``"drqv2"`` and register the
    ``sb3_collapse/<domain>-<task>-v0`` Gymnasium ids (idempotent; docs/zoo.md).

    :raises MissingDependencyError: if rl_zoo3 is not installed
    """
    import_rl_zoo3()
    from rl_zoo3.utils import ALGOS

    import sb3_collapse.envs  # noqa: F401  (registers the ids)
    from sb3_collapse.drqv2 import DrQv2

    ALGOS[ALGO_NAME] = DrQv2
