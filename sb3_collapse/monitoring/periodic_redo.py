"""ReDo as Sokar et al. run it, every ``F`` updates for the whole run: :class:`PeriodicReDo`."""

from __future__ import annotations

import os
from pathlib import Path

from sb3_collapse.monitoring.callbacks import FrameScheduleCallback, MetricsBatchSampler, frames_of
from sb3_collapse.monitoring.interventions import REDO_EVERY_UPDATES, InterventionResult, intervention_parts, redo
from sb3_collapse.monitoring.metrics import DORMANT_TAU


class PeriodicReDo(FrameScheduleCallback):
    """
    ReDo (Sokar et al., ICML 2023) as its authors run it: :func:`~sb3_collapse.monitoring.interventions.redo` each
    time ``model.n_updates`` reaches a multiple of ``every_updates``, the whole run; :attr:`history` holds ``(updates,
    frame, units_recycled)`` per recycling. See docs/interventions.md#redo-every-f-updates-periodicredo.

    :param every_updates: ``F``, the updates between two recyclings
    :param tau: the dormancy threshold, relative to the layer's mean
    :param batch_size: stored transitions of the batch the activations are measured on (fewer: nothing recycled)
    :param conv_channels: recycle the channels of DrQ-v2's convolutions too
    :param events_path: CSV file that each recycling appends a row to, columns :attr:`EVENT_FIELDS` (``None``: none)
    :param verbose: 0 silent, 1 prints each recycling
    """

    EVENT_FIELDS = ("frame", "step", "updates", "units_recycled", "units_total", "detail")
    period_parameter = "every_updates"
    state_attributes = (*FrameScheduleCallback.state_attributes, "history")

    def __init__(
        self,
        every_updates: int = REDO_EVERY_UPDATES,
        tau: float = DORMANT_TAU,
        batch_size: int = 512,
        conv_channels: bool = True,
        events_path: str | os.PathLike | None = None,
        verbose: int = 0,
    ) -> None:
        if isinstance(every_updates, bool) or not isinstance(every_updates, int) or every_updates < 1:
            raise ValueError(f"every_updates must be an integer >= 1, got {every_updates!r}.")
        super().__init__(every_updates, verbose)
        if not tau >= 0:
            raise ValueError(f"tau must be >= 0, got {tau}.")
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}.")
        self.tau = tau
        self.batch_size = batch_size
        self.conv_channels = conv_channels
        self.events_path = None if events_path is None else Path(events_path)
        self.sampler: MetricsBatchSampler | None = None
        self.history: list[tuple[int, int, int]] = []
        self.results: list[InterventionResult] = []  # each recycling of this process, not saved with the state

    @property
    def recycles(self) -> int:
        """Recyclings so far (all ``learn()`` calls)."""
        return len(self.history)

    def _init_callback(self) -> None:
        super()._init_callback()
        intervention_parts(self.model)  # a TypeError for a model the interventions do not support
        self.sampler = MetricsBatchSampler.for_model(self.model, offset=2_000_003)
        self._append_rows(self.events_path, self.EVENT_FIELDS)

    def _on_training_start(self) -> None:
        super()._on_training_start()
        if self.num_timesteps == 0:  # a new run
            self.history = []

    def _count(self) -> int:
        return self.model.n_updates

    def _on_check(self, count: int) -> None:
        self.recycle(count)

    def recycle(self, updates: int) -> None:
        """
        Recycle the dormant units now.

        :param updates: the model's update count, for the record
        """
        result = redo(
            self.model, tau=self.tau, batch_size=self.batch_size, sampler=self.sampler, conv_channels=self.conv_channels
        )
        frames = frames_of(self.model)
        recycled = int(result.scalars["units_recycled"])
        self.results.append(result)
        self.history.append((updates, frames, recycled))
        row = (frames, self.model.num_timesteps, updates, recycled, int(result.scalars["units_total"]), result.detail)
        self._append_rows(self.events_path, self.EVENT_FIELDS, row)
        if self.verbose >= 1:
            print(f"PeriodicReDo: update {updates}, frame {frames}: {result.detail}")
        scalars = {"redo/units_recycled": recycled, "redo/units_total": result.scalars["units_total"]}
        self._log(frames, {**scalars, "redo/recycles": self.recycles})
