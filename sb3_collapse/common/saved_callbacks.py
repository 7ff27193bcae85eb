"""
Callbacks saved with a model: what ``DrQv2.save`` keeps of the constructor's callbacks, and how ``DrQv2.load`` builds
them again.

A callback can be saved when it provides ``get_config()`` (its constructor's arguments), ``state_dict()`` and
``load_state_dict(state)`` (:class:`SavableCallback`), as ``sb3_collapse.monitoring``'s resumable callbacks
(``CollapseReset``, ``CollapseMetrics``...) do. Any other callback is recorded by its class name only, so that
``load`` can say which ones the user must pass again.
"""

from __future__ import annotations

import importlib
import warnings
from collections.abc import Sequence
from typing import Any, Protocol, runtime_checkable

from stable_baselines3.common.callbacks import BaseCallback


@runtime_checkable
class SavableCallback(Protocol):
    """A callback that can be built again with its settings and its state."""

    def get_config(self) -> dict[str, Any]:
        """:return: the constructor's keyword arguments"""

    def state_dict(self) -> dict[str, Any]:
        """:return: the state, picklable"""

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """:param state: a :meth:`state_dict`, taken when the next ``learn()`` starts"""


def callback_spec(callback: BaseCallback) -> dict[str, Any]:
    """
    :param callback: a callback given to a model's constructor
    :return: its class (``"module:QualName"``) and, for a :class:`SavableCallback`, its constructor's arguments and
        its state (``None`` before it was attached to a model); ``supported: False`` for another callback
    """
    kind = f"{type(callback).__module__}:{type(callback).__qualname__}"
    if not isinstance(callback, SavableCallback):
        return {"class": kind, "supported": False}
    try:
        config = callback.get_config()
    except AttributeError:  # a constructor argument that is not kept as an attribute of the same name
        return {"class": kind, "supported": False}
    state = callback.state_dict() if getattr(callback, "model", None) is not None else None
    return {"class": kind, "supported": True, "config": config, "state": state}


def callback_from_spec(spec: dict[str, Any]) -> BaseCallback | None:
    """
    :param spec: a :func:`callback_spec`
    :return: the callback built again, holding the saved state for its next ``learn()``; ``None`` for an
        unsupported one
    """
    if not spec.get("supported"):
        return None
    module, _, name = spec["class"].partition(":")
    callback = getattr(importlib.import_module(module), name)(**spec["config"])
    if spec["state"] is not None:
        callback.load_state_dict(spec["state"])
    return callback


def callback_specs(callback: BaseCallback | list[BaseCallback] | None) -> list[dict[str, Any]]:
    """
    :param callback: a model's constructor callback(s)
    :return: the :func:`callback_spec` of each
    """
    callbacks = callback if isinstance(callback, list) else [callback] if callback is not None else []
    return [callback_spec(item) for item in callbacks]


def callbacks_from_specs(specs: Sequence[dict[str, Any]]) -> tuple[BaseCallback | list[BaseCallback] | None, list[str]]:
    """
    :param specs: :func:`callback_specs` of a saved model
    :return: the callbacks built again (one, a list, or ``None``, as a constructor takes them) and the class names of
        those that could not be saved
    """
    built = [callback_from_spec(spec) for spec in specs]
    lost = [spec["class"].rpartition(":")[2] for spec, callback in zip(specs, built) if callback is None]
    kept = [callback for callback in built if callback is not None]
    return (kept[0] if len(kept) == 1 else kept or None), lost


def restore_callbacks(specs: Sequence[dict[str, Any]], caller: str) -> BaseCallback | list[BaseCallback] | None:
    """
    The callbacks of a loaded model, built again; a warning names those that could not be saved.

    :param specs: :func:`callback_specs` of the saved model
    :param caller: what loads the model, for the warning (``"DrQv2.load"``)
    :return: the callbacks (one, a list, or ``None``, as a constructor takes them)
    """
    callbacks, lost = callbacks_from_specs(specs)
    if lost:
        warnings.warn(
            f"{caller}: the constructor callback(s) {', '.join(lost)} could not be saved and are not restored; "
            f"pass them again: {caller}(path, callback=[...]).",
            stacklevel=3,
        )
    return callbacks
