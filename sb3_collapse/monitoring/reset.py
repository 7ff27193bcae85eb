"""The action-collapse paper's reset rule (Section 5.2), with a choice of intervention: :class:`CollapseReset`."""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

from stable_baselines3.common.base_class import BaseAlgorithm

from sb3_collapse.common.layers import LAYER_NAMES, layer_parameters
from sb3_collapse.common.model import CollapseModel
from sb3_collapse.errors import ParameterError
from sb3_collapse.monitoring.callbacks import FrameScheduleCallback, MetricsBatchSampler
from sb3_collapse.monitoring.grad_norms import grad_norms_of
from sb3_collapse.monitoring.interventions import (
    InterventionResult,
    apply_intervention,
    check_intervention,
)
from sb3_collapse.monitoring.metrics import action_spread
from sb3_collapse.paper import PAPER
from sb3_collapse.protocol import COLLAPSE_EVENT_FIELDS


def escape_step(
    streak: int, value: float | None, threshold: float = PAPER.threshold, patience: int = PAPER.patience
) -> tuple[int, bool]:
    """
    One check of the rule's escape test, the one definition that :class:`CollapseReset` runs during training and the
    report runs over a run's logged checks (:func:`first_escape`). Section 5.2: "we choose to use the gradient norm of
    mlp1 to determine whether an agent suffers from action collapse", and "if we do not see a gradient norm larger
    than [``threshold``] of consecutive five computations every 2e5 frames, the training would be reset; once we see
    that, the training continues until the end" (defaults: :data:`sb3_collapse.paper.PAPER`).

    :param streak: consecutive healthy checks before this one
    :param value: the check's value (``None``: no value, the streak is left as it is)
    :param threshold: a value above it is healthy ("a gradient norm larger than" it)
    :param patience: consecutive healthy checks that mean an escape ("consecutive five computations")
    :return: the streak after this check (one more when ``value > threshold``, else 0) and whether it reaches
        ``patience`` (an escape)
    """
    if value is not None:
        streak = streak + 1 if value > threshold else 0
    return streak, streak >= patience


def first_escape(
    frames: Iterable[int],
    values: Iterable[float | None],
    threshold: float = PAPER.threshold,
    patience: int = PAPER.patience,
    restarts: Iterable[int] = (),
) -> int | None:
    """
    The rule's escape test (:func:`escape_step`) over a run's logged checks, in frame order: the frame of the check
    that completes the first escape, ``None`` when none does. The streak starts again after each frame of
    ``restarts`` (the rule's resets: a check at a reset's frame belongs to the window it ends, as in
    :class:`CollapseReset`, whose check runs before its reset in the same step).

    :param frames: the frame of each check, increasing
    :param values: the metric at each check (``None`` or nan: no value)
    :param threshold: a value above it is healthy
    :param patience: consecutive healthy checks that mean an escape
    :param restarts: frames after which the streak starts from 0 (a new window)
    :return: the escape's frame, or ``None``
    """
    pending, streak = sorted(restarts), 0
    for frame, value in zip(frames, values, strict=True):
        while pending and frame > pending[0]:
            pending.pop(0)
            streak = 0
        value = None if value is None or not math.isfinite(value) else float(value)
        streak, escaped = escape_step(streak, value, threshold, patience)
        if escaped:
            return int(frame)
    return None


class CollapseReset(FrameScheduleCallback):
    """
    The paper's rule (Section 5.2, defaults :data:`sb3_collapse.paper.PAPER`): "if we do not see a gradient norm
    larger than [``threshold``] of consecutive five computations every 2e5 frames, the training would be reset", or
    another ``intervention``, on a DrQv2, TD3, DDPG or SAC model; no intervention at or after the last frame of
    ``learn()``. Rule and logs: docs/monitoring.md#the-rule, docs/interventions.md#what-is-logged.

    :param window_frames: frames after the start or the last reset within which the agent must escape
    :param check_every_frames: frames between two checks of the metric
    :param threshold: a value above it is healthy (the paper's gradient-norm threshold)
    :param patience: consecutive healthy checks that mean an escape
    :param layer: the named layer whose gradient norm is read, for ``metric="grad_norm"``
    :param max_resets: the most resets in one run, ``None`` for no limit
    :param metric: ``"grad_norm"`` (the paper's), ``"action_std"`` (a metrics batch's action spread), ``model -> float``
    :param batch_size: replay observations of the batch of ``metric="action_std"`` and ``intervention="redo"``
    :param events_path: CSV file that each intervention and the escape append a row to (``None``: none)
    :param intervention: what a window without escape ends with, a key of ``INTERVENTIONS`` (``"reset"``: the paper's)
    :param intervention_kwargs: the intervention's own parameters, e.g. ``{"tau": 0.1}`` for ``"redo"``
    :param verbose: 0 silent, 1 prints each intervention and the escape
    """

    EVENT_FIELDS = COLLAPSE_EVENT_FIELDS
    state_attributes = (
        *FrameScheduleCallback.state_attributes,
        "window_start_frame",
        "streak",
        "resets",
        "reset_frames",
        "interventions",
        "escaped",
        "escape_frame",
        "history",
    )

    def __init__(
        self,
        window_frames: int = PAPER.window_frames,
        check_every_frames: int = PAPER.check_every_frames,
        threshold: float = PAPER.threshold,
        patience: int = PAPER.patience,
        layer: str = PAPER.layer,
        max_resets: int | None = None,
        metric: str | Callable[[BaseAlgorithm], float | None] = "grad_norm",
        batch_size: int = 512,
        events_path: str | os.PathLike | None = None,
        intervention: str = "reset",
        intervention_kwargs: dict[str, Any] | None = None,
        verbose: int = 0,
    ) -> None:
        super().__init__(check_every_frames, verbose)
        if window_frames < 1:
            raise ValueError(f"window_frames must be >= 1 frame, got {window_frames}.")
        if patience < 1:
            raise ValueError(f"patience must be >= 1 check, got {patience}.")
        if max_resets is not None and max_resets < 0:
            raise ValueError(f"max_resets must be >= 0 or None, got {max_resets}.")
        if not (callable(metric) or metric in ("grad_norm", "action_std")):
            raise ValueError(f"metric must be 'grad_norm', 'action_std' or a callable model -> float, got {metric!r}.")
        if isinstance(threshold, bool) or not isinstance(threshold, (int, float)) or not math.isfinite(threshold):
            raise ParameterError("threshold", f"threshold must be a finite number, got {threshold!r}.")
        if threshold < 0 and metric in ("grad_norm", "action_std"):
            raise ParameterError(
                "threshold",
                f"threshold must be >= 0 for metric={metric!r} (a norm or a spread is never negative, so every check "
                f"would be healthy), got {threshold}.",
            )
        if metric == "grad_norm" and layer not in LAYER_NAMES:
            raise ParameterError("layer", f"layer must be one of {', '.join(LAYER_NAMES)}, got {layer!r}.")
        check_intervention(intervention)
        self.intervention = intervention
        self.intervention_kwargs = dict(intervention_kwargs or {})
        self.window_frames = window_frames
        self.threshold = threshold
        self.patience = patience
        self.layer = layer
        self.max_resets = max_resets
        self.metric = metric
        self.batch_size = batch_size
        self.events_path = None if events_path is None else Path(events_path)
        self.sampler: MetricsBatchSampler | None = None
        self._reset_state(window_start_frame=0)

    def _reset_state(self, window_start_frame: int) -> None:
        self.window_start_frame = window_start_frame
        self.streak = 0
        self.resets = 0
        self.reset_frames: list[int] = []
        self.interventions: list[InterventionResult] = []
        self.escaped = False
        self.escape_frame: int | None = None
        self.history: list[tuple[int, float | None]] = []

    def _init_callback(self) -> None:
        super()._init_callback()
        try:
            check_intervention(self.intervention, self.model)
        except TypeError as error:
            raise TypeError(f"CollapseReset: {error} Use CollapseMetrics to only watch the metrics.") from None
        if self.metric == "grad_norm":
            names = list(layer_parameters(self.model))
            if self.layer not in names:
                raise ValueError(f"layer={self.layer!r} has no parameters in this model; choose one of {names}.")
        self.sampler = MetricsBatchSampler.for_model(self.model)
        self._append_rows(self.events_path, self.EVENT_FIELDS)

    def _write_event(self, frames: int, event: str, detail: str = "") -> None:
        row = (frames, self.num_timesteps, event, self.resets, self.intervention, detail)
        self._append_rows(self.events_path, self.EVENT_FIELDS, row)

    def _on_training_start(self) -> None:
        super()._on_training_start()
        if self.num_timesteps == 0:  # a new run (learn() with reset_num_timesteps=True)
            self._reset_state(window_start_frame=0)
        elif self.resets == 0 and self.window_start_frame == 0:
            # A loaded model that was reset in an earlier process: its window starts at its last reset.
            reset_step = self.model.reset_step if isinstance(self.model, CollapseModel) else 0
            self.window_start_frame = reset_step * self.action_repeat

    def read_metric(self) -> float | None:
        """:return: the health value of the model now (see ``metric``), ``None`` when there is none"""
        if callable(self.metric):
            value = self.metric(self.model)
            return None if value is None else float(value)
        if self.metric == "grad_norm":
            return grad_norms_of(self.model).get(self.layer)
        drawn = self._batch_activations(["action"], device=self.model.device)
        return None if drawn is None else action_spread(drawn[0]["action"])

    def _on_step(self) -> bool:
        super()._on_step()  # runs _on_check at check frames
        frames = self.frames
        if not self.escaped and frames - self.window_start_frame >= self.window_frames:
            if self._at_budget_end():
                pass  # the window ends with the budget: nothing trains after it, so no reset
            elif self.max_resets is None or self.resets < self.max_resets:
                self._reset(frames)
            else:
                self.window_start_frame = frames  # no reset left: the next window only re-arms the test
        return True

    def _on_check(self, frames: int) -> None:
        if self.escaped:
            return
        value = self.read_metric()
        self.history.append((frames, value))
        self.streak, escaped = escape_step(self.streak, value, self.threshold, self.patience)
        if value is not None:
            self.logger.record("collapse/reset_rule/value", value)
            self.logger.record("collapse/reset_rule/threshold", self.threshold)  # beside it on the dashboard
        if escaped:
            self.escaped = True
            self.escape_frame = frames
            self.logger.record("collapse/escape_frame", frames)
            self._write_event(frames, "escape")
            if self.verbose >= 1:
                print(f"CollapseReset: escaped action collapse at frame {frames} ({self.resets} resets)")
        self._record(frames)

    def _reset(self, frames: int) -> None:
        kwargs = self.intervention_kwargs
        if self.intervention == "redo":  # on the rule's metrics batch
            kwargs = {"batch_size": self.batch_size, "sampler": self.sampler, **kwargs}
        result = apply_intervention(self.model, self.intervention, **kwargs)
        self.interventions.append(result)
        self.resets += 1
        self.reset_frames.append(frames)
        self.window_start_frame = frames
        self.streak = 0
        self._write_event(frames, "reset", result.detail)
        if self.verbose >= 1:
            print(
                f"CollapseReset: no escape within {self.window_frames} frames, {self.intervention} at frame {frames}: "
                f"{result.detail}"
            )
        self.logger.record("collapse/reset_frame", frames)
        for key, value in result.scalars.items():
            self.logger.record(f"collapse/intervention/{key}", value)
        self._record(frames)

    def _record(self, frames: int) -> None:
        rule = {"collapse/reset_rule/streak": self.streak, "collapse/resets": self.resets}
        self._log(frames, {**rule, "collapse/escaped": int(self.escaped)})
