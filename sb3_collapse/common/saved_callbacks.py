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
    """
    :param callbacks: callbacks, in the order they run
    :return: the class name and the ``state_dict()`` of each :class:`StatefulCallback` among them (the state ``None``
        for one never attached to a model: it has nothing to continue)
    """
    return [
        (type(callback).__name__, callback.state_dict() if getattr(callback, "model", None) is not None else None)
        for callback in callbacks
        if isinstance(callback, StatefulCallback)
    ]


def load_callback_states(callbacks: Iterable[BaseCallback], states: CallbackStates) -> None:
    """
    Give each :class:`StatefulCallback` among ``callbacks`` its saved state (taken at its next ``learn()``).

    :param callbacks: callbacks, in the order they run
    :param states: :func:`callback_states` of the same callbacks
    :raises ValueError: when the callbacks are not those saved (their classes, in order)
    """
    stateful = [callback for callback in callbacks if isinstance(callback, StatefulCallback)]
    names, saved_names = [type(callback).__name__ for callback in stateful], [name for name, _ in states]
    if names != saved_names:
        raise ValueError(f"the callbacks saved are {saved_names}, these are {names}: use the settings that saved them.")
    for callback, (_, state) in zip(stateful, states):
        if state is not None:
            callback.load_state_dict(state)


def saved_callbacks(callback: BaseCallback | list[BaseCallback] | None) -> dict[str, Any]:
    """
    :param callback: a model's constructor callback(s)
    :return: what ``DrQv2.save`` keeps: ``specs``, each one's class (``"module:QualName"``) and ``config`` (a
        :class:`SavableCallback`'s ``get_config()``, else ``None``); ``states``, those with a ``config``'s states
    """
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
    """
    The callbacks of a loaded model, built again with their states; a warning names those that were not saved.

    :param saved: :func:`saved_callbacks` of the saved model
    :param caller: what loads the model, for the warning (``"DrQv2.load"``)
    :return: the callbacks (one, a list, or ``None``, as a constructor takes them)
    """
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
