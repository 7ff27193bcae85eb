"""
A guard against diverging training, read where the losses are read anyway (at each log dump: no host
synchronization per update).

- A loss, or a weight, that is not finite stops training: :class:`DivergenceError` names the update and the frame.
  So does an action of the actor that is not finite (``DrQv2`` checks it on the host, before the environment gets it).
- A loss that grows by orders of magnitude over its scale at the start of training warns once: its absolute value
  above :data:`GROWTH_FACTOR` times the largest of the first :data:`REFERENCE_DUMPS` dumps (at least 1).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Iterable, Mapping

import torch as th

GROWTH_FACTOR = 1e4
"""How many times its starting scale a loss may grow before a warning (four orders of magnitude)."""

REFERENCE_DUMPS = 10
"""Log dumps whose losses set the starting scale."""


class DivergenceError(FloatingPointError):
    """Training produced a loss or a weight that is not finite; the message names the update and the frame."""


def all_finite(tensors: Iterable[th.Tensor]) -> th.Tensor:
    """
    :param tensors: e.g. a model's parameters (on one device)
    :return: a 0-d boolean tensor on their device: whether every entry of every tensor is finite (no host read)
    """
    tensors = list(tensors)
    if not tensors:
        return th.tensor(True, device="cpu")
    return th.stack(th._foreach_norm(tensors)).isfinite().all()


class DivergenceGuard:
    """
    Checks the mean losses of each log dump (see the module docstring).

    :param growth: :data:`GROWTH_FACTOR`
    :param reference_dumps: :data:`REFERENCE_DUMPS`
    """

    def __init__(self, growth: float = GROWTH_FACTOR, reference_dumps: int = REFERENCE_DUMPS) -> None:
        self.growth = growth
        self.reference_dumps = reference_dumps
        self.scale: dict[str, float] = {}
        self.dumps = 0
        self.warnings: list[str] = []
        """The warnings given, at most one per loss (for the run's summary)."""

    def check(self, losses: Mapping[str, float], weights_finite: bool, update: int, frame: int) -> None:
        """
        :param losses: loss name -> its mean since the last dump
        :param weights_finite: whether every weight is finite (:func:`all_finite`)
        :param update: the number of updates so far
        :param frame: the frame count
        :raises DivergenceError: for a loss or a weight that is not finite
        """
        for name, value in losses.items():
            if not math.isfinite(value):
                raise DivergenceError(f"training diverged: the {name} is {value} at update {update} (frame {frame:,}).")
        if not weights_finite:
            raise DivergenceError(f"training diverged: a weight is not finite after update {update} (frame {frame:,}).")
        self.dumps += 1
        for name, value in losses.items():
            if self.dumps <= self.reference_dumps:
                self.scale[name] = max(self.scale.get(name, 1.0), abs(value))
            elif abs(value) > self.growth * self.scale.get(name, 1.0) and not any(name in w for w in self.warnings):
                message = (
                    f"the {name} grew to {value:.3g} at update {update} (frame {frame:,}), over {self.growth:g} times "
                    f"its scale at the start ({self.scale.get(name, 1.0):.3g}): training may be diverging (learning "
                    "rate too high?)."
                )
                self.warnings.append(message)
                warnings.warn(f"DrQv2: {message}", RuntimeWarning, stacklevel=2)

    def state_dict(self) -> dict:
        """:return: the starting scales, the dump count and the warnings (for a run checkpoint)"""
        return {"scale": dict(self.scale), "dumps": self.dumps, "warnings": list(self.warnings)}

    def load_state_dict(self, state: Mapping) -> None:
        """:param state: a :meth:`state_dict`"""
        self.scale, self.dumps, self.warnings = dict(state["scale"]), int(state["dumps"]), list(state["warnings"])
