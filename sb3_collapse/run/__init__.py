"""One training run: its settings, run folder, runner and what it writes beside the model (docs/layout.md).

The public names below are imported from their modules at their first use, so that importing one module of this
package (as the sweep's workers and the report do) does not import the runner and its environments."""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from sb3_collapse.run.config import TrainConfig
    from sb3_collapse.run.replay_checkpoint import ReplayStore
    from sb3_collapse.run.runner import TrainResult, train
    from sb3_collapse.run.snapshots import load_snapshot
    from sb3_collapse.run.timing import LearnTimer, TimedVecEnv

_LAZY = {
    "TrainConfig": "config", "TrainResult": "runner", "train": "runner", "ReplayStore": "replay_checkpoint",
    "load_snapshot": "snapshots", "LearnTimer": "timing", "TimedVecEnv": "timing",
}  # fmt: skip
__all__ = ["LearnTimer", "ReplayStore", "TimedVecEnv", "TrainConfig", "TrainResult", "load_snapshot", "train"]


def __getattr__(name: str) -> Any:
    """:return: one of the public names, imported from its module at its first use"""
    if name in _LAZY:
        value = getattr(importlib.import_module(f"{__name__}.{_LAZY[name]}"), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
