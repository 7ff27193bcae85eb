"""A guard against diverging training, read at each log dump (no host synchronization per update):
docs/algorithm.md#divergence-guard."""

from __future__ import annotations

import math
import warnings
from collections.abc import Iterable, Mapping
from typing import Any

import torch as th

from sb3_collapse.errors import DivergenceError, InputError

GROWTH_FACTOR = 1e4  # times its starting scale a loss may grow before a warning
REFERENCE_DUMPS = 10  # log dumps whose losses set the starting scale
VALUE_BOUND_FACTOR = 100.0  # times the bound its rewards allow a loss may reach before a warning


def all_finite(tensors: Iterable[th.Tensor]) -> th.Tensor:
    """:return: a 0-d boolean tensor on the ``tensors``' device: whether every entry of every tensor is finite"""
    tensors = list(tensors)
    return th.stack(th._foreach_norm(tensors)).isfinite().all() if tensors else th.tensor(True, device="cpu")


def first_non_finite(tensors: Mapping[str, Any]) -> str | None:
    """:return: the name of the first floating-point tensor of ``tensors`` (a ``state_dict``; other values skipped)
    holding a NaN or an infinity, ``None`` when there is none (one host synchronization for them all)"""
    names = [name for name, value in tensors.items() if isinstance(value, th.Tensor) and value.is_floating_point()]
    if not names:
        return None
    device = tensors[names[0]].device  # a state_dict on one device: no copy
    finite = th.stack([tensors[name].isfinite().all().to(device) for name in names]).cpu()
    return None if bool(finite.all()) else names[int((~finite).nonzero()[0])]


def check_finite_weights(tensors: Mapping[str, Any], where: str) -> None:
    """Refuse the weights ``tensors`` (a ``state_dict``) read from ``where`` (a file, in the caller's words) when one
    is not finite: a diverged model gives meaningless actions (or none MuJoCo accepts) and probes.

    :raises InputError: naming ``where`` and the first non-finite tensor
    """
    name = first_non_finite(tensors)
    if name is not None:
        value = tensors[name]
        count = int((~value.isfinite()).sum())
        raise InputError(
            f"{where} holds weights that are not finite: {name!r} has {count:,} NaN or infinite value(s) of "
            f"{value.numel():,} (a diverged model); give a checkpoint saved before it diverged."
        )


class DivergenceGuard:
    """Checks the mean losses of each log dump; ``growth``: :data:`GROWTH_FACTOR`, ``reference_dumps``:
    :data:`REFERENCE_DUMPS`."""

    def __init__(self, growth: float = GROWTH_FACTOR, reference_dumps: int = REFERENCE_DUMPS) -> None:
        self.growth = growth
        self.reference_dumps = reference_dumps
        self.scale: dict[str, float] = {}
        self.max_reward = 1.0
        self.dumps = 0
        self.warnings: list[str] = []  # at most one per loss, for the run's summary

    def check_dump(
        self, means: Mapping[str, float], weights_finite: bool, update: int, frame: int, gamma: float, logger: Any
    ) -> None:
        """:meth:`check` the means of a log dump (``UpdateStats.dump``'s), and log ``train/divergence_warnings`` when
        this dump gave a new warning."""
        given = len(self.warnings)
        losses = {name: means[name] for name in ("critic_loss", "actor_loss", "batch_reward") if name in means}
        self.check(losses, weights_finite, update, frame, gamma=gamma)
        if len(self.warnings) > given:
            logger.record("train/divergence_warnings", len(self.warnings))

    def check(
        self, losses: Mapping[str, float], weights_finite: bool, update: int, frame: int, gamma: float | None = None
    ) -> None:
        """Check the ``losses`` (mean since the last dump: ``critic_loss``, ``actor_loss``, ``batch_reward``) at
        ``update`` and ``frame``: ``DivergenceError`` for a loss or a weight that is not finite, a warning for a loss
        far over its scale at the start or over what the rewards and ``gamma`` allow (``None``: no such bound)."""
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
