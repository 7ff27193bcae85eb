"""Make DrQv2 and the DeepMind Control ids known to rl_zoo3."""

from __future__ import annotations

from sb3_collapse.errors import MissingDependencyError

ALGO_NAME = "drqv2"  # DrQv2's name in rl_zoo3's algorithm table (--algo drqv2)


def register_with_zoo() -> None:
    """
    Add DrQv2 to rl_zoo3's algorithm table as ``"drqv2"`` and register the ``sb3_collapse/<domain>-<task>-v0`` ids
    (idempotent); a ``MissingDependencyError`` saying how to install rl_zoo3 when it cannot be imported.
    """
    try:
        import rl_zoo3  # noqa: F401  (the package first: its submodule may be imported already)
        from rl_zoo3.utils import ALGOS
    except ImportError as error:
        missing = f" (missing module: {error.name})" if error.name else ""
        raise MissingDependencyError(
            f"rl_zoo3 cannot be imported{missing}: pip install -e '.[zoo]' in a clone of sb3-collapse"
        ) from error

    import sb3_collapse.envs  # noqa: F401  (registers the ids)
    from sb3_collapse.drqv2 import DrQv2

    ALGOS[ALGO_NAME] = DrQv2
