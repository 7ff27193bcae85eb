"""
The frame schedule of every periodic callback (:class:`FrameScheduleCallback`, resumable: :class:`ResumableCallback`)
and the callbacks that watch for action collapse: metrics to TensorBoard, activations to disk. See docs/monitoring.md.
"""

from __future__ import annotations

import copy
import inspect
import io
import os
import warnings
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.logger import TensorBoardOutputFormat

from sb3_collapse.baselines import collapse_model
from sb3_collapse.common.model import CollapseModel, env_action_repeat
from sb3_collapse.common.schedule import next_due
from sb3_collapse.errors import ParameterError
from sb3_collapse.monitoring.activations import Observations, collect_activations
from sb3_collapse.monitoring.health import DEFAULT_METRICS, HealthMemory, check_health_arguments, measure_health
from sb3_collapse.monitoring.metrics import DORMANT_TAU, DORMANT_TAUS, FIGURE_CORRELATION, SATURATION_LIMIT, SRANK_DELTA
from sb3_collapse.paper import PAPER, metric_tag
from sb3_collapse.protocol import COLLAPSE_METRICS_FIELDS, append_csv_rows, atomic_output


def action_repeat_of(model: BaseAlgorithm) -> int:
    """
    :param model: an SB3 algorithm
    :return: frames per agent step: ``model.action_repeat`` (a ``CollapseModel``), else its environment's, else 1
    """
    return model.action_repeat if isinstance(model, CollapseModel) else env_action_repeat(model.get_env())


def frames_of(model: BaseAlgorithm, action_repeat: int | None = None) -> int:
    """
    :param model: an SB3 algorithm
    :param action_repeat: frames per agent step, ``None`` to read it with :func:`action_repeat_of`
    :return: frames so far, ``num_timesteps x action_repeat``
    """
    return model.num_timesteps * (action_repeat_of(model) if action_repeat is None else action_repeat)


class MetricsBatchSampler:
    """
    Draws a metrics batch from a replay buffer without touching the training's random streams: stored positions
    without replacement from its own generator, read through the buffer's ``_get_samples`` with NumPy's global state
    restored after it; the stored observations, not augmented.

    :param seed: seed of the index generator (``None``: fresh entropy)
    """

    def __init__(self, seed: int | None = None) -> None:
        self.rng = np.random.default_rng(seed)

    @classmethod
    def for_model(cls, model: BaseAlgorithm, seed: int | None = None, offset: int = 1_000_003) -> MetricsBatchSampler:
        """A sampler seeded with ``seed``, else with the model's seed plus ``offset`` (neither: fresh entropy)."""
        return cls(int(model.seed) + offset if seed is None and model.seed is not None else seed)

    def sample(self, model: BaseAlgorithm, batch_size: int) -> tuple[Observations, np.ndarray] | None:
        """
        :param model: an off-policy model with a ``replay_buffer``
        :param batch_size: observations to draw
        :return: ``(observations (batch_size, ...) or a dict of them, buffer indices)``, ``None`` while fewer are stored
        """
        drawn = self.sample_transitions(model, batch_size)
        return None if drawn is None else (drawn[0].observations, drawn[1])

    def sample_transitions(self, model: BaseAlgorithm, batch_size: int) -> tuple[Any, np.ndarray] | None:
        """
        :param model: an off-policy model with a ``replay_buffer``
        :param batch_size: transitions to draw
        :return: ``(ReplayBufferSamples, buffer indices)``, or ``None`` while the buffer holds fewer transitions
        """
        buffer = getattr(model, "replay_buffer", None)
        if buffer is None:
            raise TypeError(f"{type(model).__name__} has no replay buffer to draw a metrics batch from.")
        positions = np.arange(buffer.buffer_size if buffer.full else buffer.pos)
        if getattr(buffer, "optimize_memory_usage", False) and buffer.full:  # the position at pos is not stored
            positions = positions[positions != buffer.pos]
        if len(positions) < batch_size:
            return None
        env = model.get_vec_normalize_env()
        if hasattr(buffer, "frames_stored"):  # FrameStackReplayBuffer: the (position, env) pairs whose frames remain
            pairs = np.stack(np.meshgrid(positions, np.arange(buffer.n_envs), indexing="ij"), -1).reshape(-1, 2)
            pairs = pairs[buffer.frames_stored(pairs[:, 0], pairs[:, 1])]
            if len(pairs) < batch_size:
                return None
            chosen = pairs[np.sort(self.rng.choice(len(pairs), size=batch_size, replace=False))]
            return buffer._get_samples(chosen[:, 0], env=env, env_indices=chosen[:, 1]), chosen[:, 0]
        indices = np.sort(self.rng.choice(positions, size=batch_size, replace=False))
        state = np.random.get_state()
        try:
            samples = buffer._get_samples(indices, env=env)
        finally:
            np.random.set_state(state)
        return samples, indices


class ResumableCallback(BaseCallback):
    """
    A callback whose state (:attr:`state_attributes`, its sampler's generator, the agent step) is saved in run
    checkpoints and with ``DrQv2.save``, and taken instead of a fresh start by the next ``learn()`` (unless that
    restarts the step count from a later state). See docs/monitoring.md#one-schedule.
    """

    state_attributes: tuple[str, ...] = ()  # the attributes that make up the state

    _pending_state: dict[str, Any] | None = None

    def init_callback(self, model: BaseAlgorithm) -> None:
        """SB3's, on ``collapse_model(model)``."""
        super().init_callback(collapse_model(model))

    def state_dict(self) -> dict[str, Any]:
        """:return: the callback's state (picklable copies)"""
        state = {name: copy.deepcopy(getattr(self, name)) for name in self.state_attributes}
        model = getattr(self, "model", None)  # set by init_callback
        if model is not None:
            state["num_timesteps"] = int(model.num_timesteps)
        sampler = getattr(self, "sampler", None)
        if isinstance(sampler, MetricsBatchSampler):
            state["sampler"] = sampler.rng.bit_generator.state
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """
        :param state: a :meth:`state_dict` taken while attached to a model, taken when the next ``learn()`` starts
        :raises ValueError: for a state that lacks one of its entries (one written by another version)
        """
        missing = [name for name in (*self.state_attributes, "num_timesteps") if name not in state]
        if missing:
            raise ValueError(
                f"{type(self).__name__}: the saved state lacks {', '.join(missing)}: it was written by another version "
                "of sb3-collapse; continue it with that version, or start a new run."
            )
        self._pending_state = state

    def get_config(self) -> dict[str, Any]:
        """:return: the constructor's arguments (the attributes of the same names), to build this callback again"""
        parameters = [name for name in inspect.signature(type(self).__init__).parameters if name != "self"]
        return {name: copy.deepcopy(getattr(self, name)) for name in parameters}

    def on_training_start(self, locals_: dict[str, Any], globals_: dict[str, Any]) -> None:
        state, self._pending_state = self._pending_state, None
        if state is not None and self.model.num_timesteps == 0 and state["num_timesteps"] > 0:
            state = None  # learn() restarted the step count: a new run, not a continuation
        if state is None:
            super().on_training_start(locals_, globals_)
            return
        self.locals, self.globals = locals_, globals_
        self.num_timesteps = self.model.num_timesteps
        for name in self.state_attributes:
            setattr(self, name, copy.deepcopy(state[name]))
        sampler = getattr(self, "sampler", None)
        if "sampler" in state and isinstance(sampler, MetricsBatchSampler):
            sampler.rng.bit_generator.state = state["sampler"]


class FrameScheduleCallback(ResumableCallback):
    """
    The schedule of every periodic callback: :meth:`_on_check` at the first step where the frames (or :meth:`_count`)
    reach each multiple of the period, once for a step that crosses several. See docs/monitoring.md#one-schedule.

    :param check_every_frames: frames between two checks (a subclass may name it :attr:`period_parameter`)
    :param verbose: 0 silent, 1 info
    """

    state_attributes = ("next_check", "n_checks")
    period_parameter = "check_every_frames"  # the constructor parameter, and attribute, that holds the period
    min_period = 1  # the smallest period allowed (0: no scheduled check, for a callback that also acts on demand)
    check_at_start = False  # check at the start of learn() (at a multiple of the period), not at its last step

    def __init__(self, check_every_frames: int, verbose: int = 0) -> None:
        super().__init__(verbose)
        whole = isinstance(check_every_frames, (int, np.integer)) and not isinstance(check_every_frames, bool)
        if not whole or check_every_frames < self.min_period:  # a str, nan, 2.5: refused, not a check at every step
            raise ParameterError(
                self.period_parameter,
                f"{self.period_parameter} must be {'' if whole else 'an integer '}>= {self.min_period}, got "
                f"{check_every_frames!r}.",
            )
        setattr(self, self.period_parameter, check_every_frames)
        self.next_check = 0  # the count of the next check, set when learn() starts
        self.n_checks = 0  # checks so far, all learn() calls
        self.action_repeat = 1

    @property
    def period(self) -> int:
        """Counts (frames, or updates) between two checks."""
        return getattr(self, self.period_parameter)

    def _init_callback(self) -> None:
        self.action_repeat = action_repeat_of(self.model)

    def _on_training_start(self) -> None:
        count = self._count()
        self.next_check = self._following(count - 1 if self.check_at_start else count)
        if self.check_at_start:
            self._check_if_due()

    def _following(self, count: int) -> int:
        """The first multiple of the period above ``count`` (:func:`~sb3_collapse.common.schedule.next_due`, the
        rule that the plan's counts follow too)."""
        return next_due(count, self.period) if self.period else 0

    @property
    def frames(self) -> int:
        """Frames so far."""
        return frames_of(self.model, self.action_repeat)

    def _count(self) -> int:
        return self.frames

    def _on_step(self) -> bool:
        if self.check_at_start and self._at_budget_end():
            return True  # the last step of learn(), before its updates
        return self._check_if_due()

    def _at_budget_end(self) -> bool:
        """Whether this step is the last of the ``learn()`` call (its ``total_timesteps``), or after it."""
        return self.num_timesteps >= (self.locals.get("total_timesteps") or float("inf"))

    def _check_if_due(self) -> bool:
        count = self._count()
        if not self.period or count < self.next_check:
            return True
        self.next_check = self._following(count)
        self.n_checks += 1
        return self._on_check(count) is not False

    def _on_check(self, count: int) -> bool | None:
        """A check at ``count`` (frames, or what :meth:`_count` counts); ``False`` stops ``learn()``."""
        raise NotImplementedError

    def _batch_activations(self, layers: Iterable[str] | None, **kwargs: Any) -> tuple[dict, np.ndarray] | None:
        """``layers``' activations on a new metrics batch of ``self.batch_size``, its indices; ``None`` while fewer."""
        assert self.sampler is not None, "The callback is not initialized: pass it to learn() first."
        batch = self.sampler.sample(self.model, self.batch_size)
        return None if batch is None else (collect_activations(self.model, batch[0], layers=layers, **kwargs), batch[1])

    def _log(self, frames: int, values: Mapping[str, float]) -> None:
        """Record ``values`` (tag -> value) and ``time/frames``, then dump them at the model's agent step."""
        for tag, value in {**values, "time/frames": frames}.items():
            self.logger.record(tag, value)
        self.logger.dump(self.model.num_timesteps)

    @staticmethod
    def _append_rows(path: Path | None, fields: Sequence[str], *rows: Sequence[Any]) -> None:
        """Append ``rows`` (values in the order of ``fields``) to the CSV file ``path``, if any, its header first."""
        if path is not None:
            append_csv_rows(path, fields, [dict(zip(fields, row, strict=True)) for row in rows])


class CollapseMetrics(FrameScheduleCallback):
    """
    Logs the collapse metrics of every named layer (tags: docs/monitoring.md) on a metrics batch of replay
    observations every ``check_every_frames`` (while enough are stored), measured by :func:`measure_health`; the last
    values in :attr:`last_metrics`. With a TensorBoard logger, it writes a custom-scalars layout into the run's folder
    (docs/monitoring.md#dashboard).

    :param check_every_frames: frames between two checks
    :param batch_size: observations of the metrics batch
    :param layers: the named layers to measure, ``None`` for all (``cnn0`` .. ``action``)
    :param tau: threshold of the dormant ratio
    :param delta: threshold of the effective rank
    :param saturation_limit: ``|a|`` above which an action component counts as saturated
    :param forward_batch_size: observations per forward pass
    :param seed: seed of the batch's indices; ``None``: derived from the model's seed
    :param csv_path: CSV file that each check appends a row per tag to (``None``: none)
    :param verbose: 0 silent, 1 prints a line per check
    :param metrics: which, of ``HEALTH_METRICS`` (``sb3_collapse.monitoring.health``); ``None``: ``DEFAULT_METRICS``,
        the tags logged by default
    :param networks: which, of ``"actor"`` and ``"critic"`` (the critic's layers ``q1.mlp0``.., ``q1``..)
    :param taus: thresholds of the ``dormant_ratios`` metric, a tag ``dormant_ratio_tau<tau>`` each
    :param dashboard: write the TensorBoard custom-scalars layout, once per run folder
    """

    state_attributes = (*FrameScheduleCallback.state_attributes, "last_metrics")
    # Not in the saved state (a state written before them stays readable): the memory of the dormant units and of
    # the weights at the last reset starts again when a resumed run's learn() starts.

    def __init__(
        self,
        check_every_frames: int = PAPER.check_every_frames,
        batch_size: int = 512,
        layers: Iterable[str] | None = None,
        tau: float = DORMANT_TAU,
        delta: float = SRANK_DELTA,
        saturation_limit: float = SATURATION_LIMIT,
        forward_batch_size: int = 256,
        seed: int | None = None,
        csv_path: str | os.PathLike | None = None,
        verbose: int = 0,
        metrics: Iterable[str] | None = None,
        networks: Iterable[str] = ("actor",),
        taus: Sequence[float] = DORMANT_TAUS,
        dashboard: bool = True,
    ) -> None:
        super().__init__(check_every_frames, verbose)
        self.metrics = None if metrics is None else list(metrics)
        self.networks = list(networks)
        self.taus = list(taus)
        check_health_arguments(self.measured, self.networks, self.taus)
        if batch_size < 2:
            raise ValueError(f"batch_size must be >= 2 observations (correlations need pairs), got {batch_size}.")
        self.batch_size = batch_size
        self.layers = None if layers is None else list(layers)
        self.tau = tau
        self.delta = delta
        self.saturation_limit = saturation_limit
        self.forward_batch_size = forward_batch_size
        self.seed = seed
        self.csv_path = None if csv_path is None else Path(csv_path)
        self.dashboard = dashboard
        self.sampler: MetricsBatchSampler | None = None
        self.last_metrics: dict[str, float] = {}
        self.memory = HealthMemory()  # the dormant units of the last check, the weights at the last reset
        self._memory_step: int | None = None  # the model's reset_step when the memory was started
        self._dashboard_folders: set[str] = set()

    @property
    def measured(self) -> tuple[str, ...]:
        """The metrics measured: :attr:`metrics`, else ``DEFAULT_METRICS``."""
        return DEFAULT_METRICS if self.metrics is None else tuple(self.metrics)

    def _init_callback(self) -> None:
        super()._init_callback()
        self.sampler = MetricsBatchSampler.for_model(self.model, self.seed)
        self._append_rows(self.csv_path, COLLAPSE_METRICS_FIELDS)
        if self.dashboard:
            self._write_dashboard()

    def _write_dashboard(self) -> None:
        """The custom-scalars layout, into the folder of each TensorBoard output of the logger not written yet."""
        for output in self.logger.output_formats:
            writer = getattr(output, "writer", None)
            if (
                isinstance(output, TensorBoardOutputFormat)
                and writer is not None
                and writer.log_dir not in self._dashboard_folders
            ):
                writer.add_custom_scalars(dashboard_layout(self.measured, self.networks))
                writer.flush()
                self._dashboard_folders.add(writer.log_dir)

    def _on_step(self) -> bool:
        # A reset from scratch (model.reset_step moves): the weights now are the reference of weight_change, and the
        # dormant units of the old networks are forgotten; read at each step, so before any update of the new ones.
        reset_step = getattr(self.model, "reset_step", 0)
        if self._memory_step != reset_step:
            self._memory_step = reset_step
            self.memory = HealthMemory()
            if "weight_change" in self.measured:
                self.memory.remember_weights(self.model, self.networks)
        return super()._on_step()

    def compute(self) -> dict[str, float] | None:
        """:return: every metric on a new metrics batch, not logged: tag -> value (``None`` while too few are stored)"""
        assert self.sampler is not None, "The callback is not initialized: pass it to learn() first."
        batch = self.sampler.sample(self.model, self.batch_size)
        if batch is None:
            return None
        return measure_health(
            self.model,
            batch[0],
            self.measured,
            self.networks,
            self.layers,
            tau=self.tau,
            taus=self.taus,
            delta=self.delta,
            saturation_limit=self.saturation_limit,
            batch_size=self.forward_batch_size,
            device=self.model.device,
            memory=self.memory,
        )

    def _on_check(self, frames: int) -> None:
        values = self.compute()
        if values is None:
            if self.verbose >= 1:
                print(f"CollapseMetrics: frame {frames} skipped, fewer than {self.batch_size} transitions stored")
            return
        self.last_metrics = values
        self._log(frames, values)
        rows = [(frames, self.num_timesteps, tag, value) for tag, value in values.items()]
        self._append_rows(self.csv_path, COLLAPSE_METRICS_FIELDS, *rows)
        if self.verbose >= 1:
            shown = (metric_tag(PAPER.layer, ""), "collapse/action_std")
            summary = ", ".join(f"{k}={v:.4g}" for k, v in values.items() if k.startswith(shown))
            print(f"CollapseMetrics at frame {frames}: {summary}")


FIGURE4_PANELS = (
    ("numerical_rank", "numerical rank"),
    (FIGURE_CORRELATION, "correlation"),
    ("dead_units", "dead units"),
    ("grad_norm", "gradient norm"),
)
"""The paper's Figure 4 columns, metric -> title, as the dashboard groups them (the actor's ``mlp1``, ``mlp2``..)."""


def dashboard_layout(metrics: Iterable[str] = DEFAULT_METRICS, networks: Iterable[str] = ("actor",)) -> dict:
    """
    The TensorBoard custom-scalars layout of the tags :class:`CollapseMetrics` logs (and :class:`CollapseReset`'s),
    for ``SummaryWriter.add_custom_scalars``: category -> chart title -> ``["Multiline", [tag regexes]]``.

    :param metrics: the metrics measured (a chart of each, every layer a line, in the "all layers" category)
    :param networks: the networks measured (the critic's Q values get charts of their own)
    :return: ``collapse: Figure 4`` (the paper's four panels, a line per hidden layer ``mlp1``, ``mlp2``.., and the
        actions' spread), ``collapse: reset rule`` (its value against its threshold, resets and escape), then
        ``collapse: critic`` and ``collapse: all layers``
    """
    metrics, networks = list(metrics), list(networks)
    hidden = r"^collapse/mlp[1-9][0-9]*/{}$"
    figure4 = {title: ["Multiline", [hidden.format(metric)]] for metric, title in FIGURE4_PANELS if metric in metrics}
    if "action_std" in metrics:
        figure4["action spread"] = ["Multiline", [r"^collapse/action_std$"]]
    layout = {
        "collapse: Figure 4": figure4,
        "collapse: reset rule": {
            "rule value against its threshold": [
                "Multiline",
                [r"^collapse/reset_rule/value$", r"^collapse/reset_rule/threshold$"],
            ],
            "resets and escape": ["Multiline", [r"^collapse/resets$", r"^collapse/escaped$"]],
        },
    }
    if "critic" in networks:
        layout["collapse: critic"] = {
            f"Q {stat[2:]} (Q(s, mu(s)))": ["Multiline", [rf"^collapse/q[0-9]+/{stat}$"]]
            for stat in ("q_mean", "q_std")
            if stat in metrics
        }
    tags = {"action_std": r"^collapse/action_std$", "action_saturation": r"^collapse/action_saturation$"}
    tags["dormant_ratios"] = r"^collapse/[^/]+/dormant_ratio_tau.*$"
    layout["collapse: all layers"] = {
        metric: ["Multiline", [tags.get(metric, rf"^collapse/[^/]+/{metric}$")]]
        for metric in metrics
        if metric not in ("q_mean", "q_std")
    }
    return {category: charts for category, charts in layout.items() if charts}


class ActivationLogger(FrameScheduleCallback):
    """
    Saves the named activations of a metrics batch every ``every_frames``: ``<path>/activations_<agent step, 10
    digits>.npz``, one float32 ``(batch_size, *shape)`` array per layer, ``step``, ``frames``, ``indices`` (buffer
    positions) and ``layers``; a file that would take the total over ``max_bytes`` stops the saves, with a warning.

    :param every_frames: frames between two saves
    :param path: folder of the files (created if needed)
    :param batch_size: observations of the metrics batch
    :param layers: names to save; ``None``: ``mlp0``, ``mlp1``, ``mlp2``, ``action``
    :param max_bytes: the most bytes all the files of this callback may take
    :param seed: seed of the batch's indices; ``None``: derived from the model's seed
    :param verbose: 0 silent, 1 prints a line per file
    """

    period_parameter = "every_frames"
    state_attributes = (*FrameScheduleCallback.state_attributes, "bytes_written", "stopped")

    def __init__(
        self,
        every_frames: int,
        path: str | os.PathLike,
        batch_size: int = 512,
        layers: Iterable[str] | None = None,
        max_bytes: int = 1_000_000_000,
        seed: int | None = None,
        verbose: int = 0,
    ) -> None:
        super().__init__(every_frames, verbose)
        if max_bytes <= 0:
            raise ValueError(f"max_bytes must be > 0, got {max_bytes}.")
        self.path = Path(path)
        self.batch_size = batch_size
        self.layers = list(("mlp0", "mlp1", "mlp2", "action") if layers is None else layers)
        self.max_bytes = max_bytes
        self.seed = seed
        self.sampler: MetricsBatchSampler | None = None
        self.bytes_written = 0
        self.saved: list[Path] = []
        self.stopped = False

    def _init_callback(self) -> None:
        super()._init_callback()
        self.path.mkdir(parents=True, exist_ok=True)
        self.sampler = MetricsBatchSampler.for_model(self.model, self.seed)

    def _on_check(self, frames: int) -> None:
        if self.stopped:
            return
        drawn = self._batch_activations(self.layers)
        if drawn is None:
            return
        activations, indices = drawn
        arrays = {name: value.numpy() for name, value in activations.items()}
        content = io.BytesIO()
        layers = np.array(list(arrays))
        np.savez_compressed(content, **arrays, step=self.num_timesteps, frames=frames, indices=indices, layers=layers)
        size = content.getbuffer().nbytes
        if self.bytes_written + size > self.max_bytes:
            self.stopped = True
            warnings.warn(
                f"ActivationLogger: the activations at frame {frames} ({size / 1e6:.1f} MB) would take {self.path} "
                f"over max_bytes={self.max_bytes:_}; no more files are saved in this run (pass a larger max_bytes, "
                "fewer layers or a larger every_frames).",
                stacklevel=2,
            )
            return
        target = self.path / f"activations_{self.num_timesteps:010d}.npz"
        with atomic_output(target) as temporary:
            temporary.write_bytes(content.getvalue())
        self.bytes_written += size
        self.saved.append(target)
        if self.verbose >= 1:
            print(f"ActivationLogger: {target} ({size / 1e6:.1f} MB)")
