"""
A guard against diverging training, read where the losses are read anyway (at each log dump: no host
synchronization per update).

- A loss, or a weight, that is not finite stops training: :class:`DivergenceError` names the update and the frame.
  So does an action of the actor that is not finite (``DrQv2`` checks it on the host, before the environment gets it).
- A loss that grows by orders of magnitude warns once (per loss): its absolute value above :data:`GROWTH_FACTOR`
  times the largest of the first :data:`REFERENCE_DUMPS` dumps (at least 1), or, for a run that diverges from its
  first updates, above :data:`VALUE_BOUND_FACTOR` times what its rewards allow: with ``r`` the largest mean batch
  reward seen (n-step rewards, at least 1) and ``Q = r / (1 - gamma)`` the largest plausible value, ``Q^2`` for the
  critic loss (a squared error of values) and ``Q`` for the actor loss (minus a value).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Iterable, Mapping
from typing import Any

import torch as th

from sb3_collapse.errors import DivergenceError

GROWTH_FACTOR = 1e4
"""How many times its starting scale a loss may grow before a warning (four orders of magnitude)."""

REFERENCE_DUMPS = 10
"""Log dumps whose losses set the starting scale."""

VALUE_BOUND_FACTOR = 100.0
"""How many times the bound its rewards allow a loss may reach before a warning."""


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
        self.max_reward = 1.0
        self.dumps = 0
        self.warnings: list[str] = []
        """The warnings given, at most one per loss (for the run's summary)."""

    def check_dump(
        self, means: Mapping[str, float], weights_finite: bool, update: int, frame: int, gamma: float, logger: Any
    ) -> None:
        """
        :meth:`check` the means of a log dump (``UpdateStats.dump``: the losses and the batch reward are read), and
        record the number of warnings in ``logger`` (``train/divergence_warnings``) when this dump gave a new one.

        :raises DivergenceError: as :meth:`check`
        """
        given = len(self.warnings)
        losses = {name: means[name] for name in ("critic_loss", "actor_loss", "batch_reward") if name in means}
        self.check(losses, weights_finite, update, frame, gamma=gamma)
        if len(self.warnings) > given:
            logger.record("train/divergence_warnings", len(self.warnings))

    def check(
        self,
        losses: Mapping[str, float],
        weights_finite: bool,
        update: int,
        frame: int,
        gamma: float | None = None,
    ) -> None:
        """
        :param losses: name -> mean since the last dump: ``critic_loss``, ``actor_loss`` and ``batch_reward`` (the
            mean reward of the sampled transitions, not checked, kept for the bound on the values)
        :param weights_finite: whether every weight is finite (:func:`all_finite`)
        :param update: the number of updates so far
        :param frame: the frame count
        :param gamma: the discount, for the bound on the values; ``None``: no such bound
        :raises DivergenceError: for a loss or a weight that is not finite
        """
        losses = dict(losses)
        reward = losses.pop("batch_reward", None)
        if reward is not None and math.isfinite(reward):
            self.max_reward = max(self.max_reward, abs(reward))
        value_bound = None if gamma is None else self.max_reward / max(1.0 - gamma, 1e-6)
        for name, value in losses.items():
            if not math.isfinite(value):
                raise DivergenceError(f"training diverged: the {name} is {value} at update {update} (frame {frame:,}).")
        if not weights_finite:
            raise DivergenceError(f"training diverged: a weight is not finite after update {update} (frame {frame:,}).")
        self.dumps += 1
        for name, value in losses.items():
            if any(w.startswith(f"the {name} ") for w in self.warnings):
                continue
            bound = None if value_bound is None else value_bound**2 if name == "critic_loss" else value_bound
            if bound is not None and abs(value) > VALUE_BOUND_FACTOR * bound:
                reason = f"over {VALUE_BOUND_FACTOR:g} times what the rewards allow ({bound:.3g})"
            elif self.dumps > self.reference_dumps and abs(value) > self.growth * self.scale.get(name, 1.0):
                reason = f"over {self.growth:g} times its scale at the start ({self.scale.get(name, 1.0):.3g})"
            else:
                if self.dumps <= self.reference_dumps:
                    self.scale[name] = max(self.scale.get(name, 1.0), abs(value))
                continue
            message = (
                f"the {name} is {value:.3g} at update {update} (frame {frame:,}), {reason}: training may be diverging "
                "(learning rate too high?)."
            )
            self.warnings.append(message)
            warnings.warn(f"DrQv2: {message}", RuntimeWarning, stacklevel=2)
