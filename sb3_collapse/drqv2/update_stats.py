"""The statistics of the updates, summed on the device and averaged into the logger at each log dump."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch as th
from stable_baselines3.common.logger import Logger


class UpdateStats:
    """Sums of per-update statistics since the last :meth:`dump`: ``grad_norms`` (``(layers,)``) logged as
    ``train/grad_norm/<layer>``, every other (0-d) as ``train/<name>``."""

    def __init__(self) -> None:
        self.sums: dict[str, th.Tensor] = {}
        self.count = 0  # updates added since the last dump

    def add(self, **values: th.Tensor | None) -> None:
        """Add one update's statistics, name -> tensor on the model's device (``None`` skipped)."""
        for name, value in ((name, value.detach()) for name, value in values.items() if value is not None):
            self.sums[name] = self.sums[name] + value if name in self.sums else value.clone()
        self.count += 1

    def dump(self, logger: Logger, layer_names: Sequence[str]) -> dict[str, float] | None:
        """Write the means since the last dump to ``logger`` (``layer_names`` of ``grad_norms``) and start new sums.
        :return: name -> mean of every statistic but ``grad_norms``; ``None`` when no update was added"""
        if self.count == 0:
            return None
        n, sums = self.count, {name: value.cpu() for name, value in self.sums.items()}
        means = {}
        for name, value in sums.items():
            if name == "grad_norms":
                for layer, norm in zip(layer_names, (value / n).tolist()):
                    logger.record(f"train/grad_norm/{layer}", norm)
            else:
                means[name] = float(value) / n
                logger.record(f"train/{name}", means[name])
        self.sums, self.count = {}, 0
        return means

    def state_dict(self) -> dict[str, Any]:
        """:return: the sums (tensors on their device) and the count, for a run checkpoint"""
        return {"sums": dict(self.sums), "count": self.count}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """:param state: a :meth:`state_dict`, its tensors on the model's device"""
        self.sums, self.count = dict(state["sums"]), int(state["count"])
