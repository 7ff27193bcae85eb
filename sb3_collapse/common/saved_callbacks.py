"""A callback's state, saved and put back by one pair of functions for run checkpoints and for the constructor's
callbacks that ``DrQv2.save`` keeps and ``DrQv2.load`` builds again. See docs/checkpoints.md."""

from __future__ import annotations

import importlib
import warnings
from collections.abc import Iterable
from typing import Any, Protocol, runtime_checkable

from stable_baselines3.common.callbacks import BaseCallback

CallbackStates = list[tuple[str, "dict[str, Any] | None"]]
"""``(class name, state)`` of each callback that carries a state, in order (:func:`callback_states`)."""


@runtime_checkable
class StatefulCallback(Protocol):
    """A callback whose state can be saved and put back."""

    def state_dict(self) -> dict[str, Any]:
        """:return: the state, picklable"""

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """:param state: a :meth:`state_dict`, taken when the next ``learn()`` starts"""


@runtime_checkable
class SavableCallback(StatefulCallback, Protocol):
    """A callback that can also be built again with its settings."""

    def get_config(self) -> dict[str, Any]:
        """:return: the constructor's keyword arguments"""


def callback_states(callbacks: Iterable[BaseCallback]) -> CallbackStates:
    """:return: the class name and ``state_dict()`` of each :class:`StatefulCallback` among ``callbacks``, in order
    (``None`` for one never attached to a model)"""
    return [
        (type(callback).__name__, callback.state_dict() if getattr(callback, "model", None) is not None else None)
        for callback in callbacks
        if isinstance(callback, StatefulCallback)
    ]


def load_callback_states(callbacks: Iterable[BaseCallback], states: CallbackStates) -> None:
    """Give each :class:`StatefulCallback` among ``callbacks`` its state in ``states`` (:func:`callback_states`'s),
    taken at its next ``learn()``; ``ValueError`` when the callbacks are not those saved."""
    stateful = [callback for callback in callbacks if isinstance(callback, StatefulCallback)]
    names, saved_names = [type(callback).__name__ for callback in stateful], [name for name, _ in states]
    if names != saved_names:
        raise ValueError(f"the callbacks saved are {saved_names}, these are {names}: use the settings that saved them.")
    for callback, (_, state) in zip(stateful, states):
        if state is not None:
            callback.load_state_dict(state)


def saved_callbacks(callback: BaseCallback | list[BaseCallback] | None) -> dict[str, Any]:
    """:return: what ``DrQv2.save`` keeps of a constructor's ``callback``: ``specs``, each one's class
    (``"module:QualName"``) and ``config`` (``get_config()`` or ``None``), and the ``states`` of those with one"""
    callbacks = callback if isinstance(callback, list) else [callback] if callback is not None else []
    specs = [{"class": f"{type(item).__module__}:{type(item).__qualname__}", "config": None} for item in callbacks]
    for item, spec in zip(callbacks, specs):
        if isinstance(item, SavableCallback):
            try:
                spec["config"] = item.get_config()
            except AttributeError:  # a constructor argument that is not kept as an attribute of the same name
                pass
    savable = [item for item, spec in zip(callbacks, specs) if spec["config"] is not None]
    return {"specs": specs, "states": callback_states(savable)}


def restore_callbacks(saved: dict[str, Any], caller: str) -> BaseCallback | list[BaseCallback] | None:
    """:return: the callbacks of :func:`saved_callbacks`'s ``saved``, built again with their states (one, a list or
    ``None``); a warning from ``caller`` (``"DrQv2.load"``) names those that were not saved"""
    built, lost = [], []
    for spec in saved["specs"]:
        module, _, name = spec["class"].partition(":")
        if spec["config"] is None:
            lost.append(name)
        else:
            built.append(getattr(importlib.import_module(module), name)(**spec["config"]))
    load_callback_states(built, saved["states"])
    if lost:
        warnings.warn(
            f"{caller}: the constructor callback(s) {', '.join(lost)} could not be saved and are not restored; "
            f"pass them again: {caller}(path, callback=[...]).",
            stacklevel=3,
        )
    return built[0] if len(built) == 1 else built or None
