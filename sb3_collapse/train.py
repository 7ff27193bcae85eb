"""Train DrQ-v2 on a DeepMind Control task from pixels: ``python -m sb3_collapse.train --help``.

    python -m sb3_collapse.train --env walker-walk --frames 100000 --seed 0 --logdir runs/

The defaults are **per task**: every DrQ-v2 hyperparameter left out (budget, batch size, n-step, learning rate,
exploration schedule...) comes from the task's preset, :func:`sb3_collapse.presets.preset`; a value given
explicitly overrides it, and the run's settings file records every value and where it came from.

Everything a run writes goes to one folder, ``<logdir>/<task>_s<seed>`` (``_2``, ``_3``... if it holds another run),
or exactly ``--run-dir``, in the run-folder format of :mod:`sb3_collapse.protocol`: the settings (written first),
TensorBoard events and ``progress.csv`` (the SB3 logger), the evaluations, the collapse checks, the reset rule's
events, the final model (load it with ``DrQv2.load``) and the result (written last: a folder without it is an
unfinished run). A run writes checkpoints (``--checkpoint-every-frames``, and at SIGTERM or SIGINT, after which it
exits with status 75); the same command again resumes an unfinished run from its newest one, bit for bit
(:mod:`sb3_collapse.checkpoints`).

``--algorithm td3`` or ``sac`` trains SB3's own TD3 or SAC from the same pixels instead (built by
:func:`sb3_collapse.baselines.build_baseline`; the DrQ-v2-only settings are reported unused); ``--reset-rule``
applies the paper's rule, ``--intervention`` chooses what it does (:mod:`sb3_collapse.monitoring.interventions`).

``--init-cnn``, ``--init-mlp`` and ``--init-critic`` start the encoder, the actor or the critic from the weights of a
saved DrQv2 (the paper's layer transplants, ``DrQv2(init_from=...)``). Sweeps of many such runs on Ray:
``python -m sb3_collapse.sweep --help``.

Budgets are in frames, as in DrQ-v2 and the paper (frames = agent steps x action repeat); the exploration
schedule is in agent steps, as in DrQ-v2's configs. With ``--n-envs N`` (N environments in subprocesses), agent steps
are summed over the environments (transitions) everywhere: the budget, the seed frames, the schedule, ``train_freq``,
the evaluation and collapse-check periods and DrQ-v2's one update per 2 transitions mean the same as with one
environment (``docs/throughput.md``).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import functools
import json
import os
import re
import shutil
import signal
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback, CallbackList
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv, VecEnv

from sb3_collapse.backends import configure_backends
from sb3_collapse.baselines import BASELINES, DRQV2_ONLY_SETTINGS, NATURE_CNN_MIN_SIZE, build_baseline
from sb3_collapse.drqv2 import DrQv2, StddevSchedule
from sb3_collapse.drqv2.checks import check_hyperparameters
from sb3_collapse.drqv2.divergence import DivergenceError
from sb3_collapse.drqv2.encoders import ACTIVATIONS, check_activation, check_image_size
from sb3_collapse.drqv2.replay_buffer import REPLAY_SAMPLINGS
from sb3_collapse.drqv2.transplant import resolve_source_path
from sb3_collapse.envs import make_dmc_env, parse_task
from sb3_collapse.envs.dmc import check_env_arguments
from sb3_collapse.envs.rendering import ensure_rendering_backend
from sb3_collapse.envs.replay import EpisodeReplay
from sb3_collapse.errors import (
    FULL_DISK_ERRNOS,
    InputError,
    ParameterError,
    cli_message,
    report_unwritable_outputs,
    unwritable_message,
)
from sb3_collapse.monitoring import INTERVENTIONS, CollapseMetrics, CollapseReset, frames_of
from sb3_collapse.monitoring.callbacks import ResumableCallback
from sb3_collapse.monitoring.redo import PeriodicReDo
from sb3_collapse.paper import PAPER
from sb3_collapse.presets import SETTING_NAMES, TaskPreset, preset
from sb3_collapse.protocol import (
    CHECKPOINTS_DIR,
    COLLAPSE_EVENTS_CSV,
    COLLAPSE_METRICS_CSV,
    CONFIG_JSON,
    ERROR_TXT,
    EVAL_CSV,
    EVAL_FIELDS,
    EXIT_INTERRUPTED,
    FINAL_MODEL,
    FINISHED,
    LOCK_FILE,
    PROGRESS_CSV,
    RESULT_JSON,
    SNAPSHOTS_DIR,
    append_csv_rows,
    atomic_output,
    blocking_file,
    failed_before_training,
    read_settings,
    write_failure,
    write_json_atomically,
)
from sb3_collapse.run.checkpoints import (
    CheckpointError,
    LoadedCheckpoint,
    ResumableCheckpoints,
    checkpoint_learning_rates,
    load_checkpoint,
    set_aside,
)
from sb3_collapse.run.cpu_allocator import tune_cpu_allocator
from sb3_collapse.run.lock import RunLock
from sb3_collapse.run.resumed_logger import resumed_logger
from sb3_collapse.run.signals import TrainingInterrupted, stop_signals
from sb3_collapse.run.snapshots import Snapshots
from sb3_collapse.run.timing import LearnTimer, LearnTimings, TimedVecEnv

ALGORITHMS = ("drqv2", *BASELINES)
"""What ``algorithm`` trains: DrQ-v2, or SB3's TD3 or SAC (:mod:`sb3_collapse.baselines`)."""

DEFAULT_CHECKPOINT_EVERY_FRAMES = 100_000
"""Frames between two checkpoints by default: at DrQ-v2's ~100 frames/s on a V100, a stop loses at most ~17 minutes;
each checkpoint writes the model (105 MB with Adam at the default sizes) and the replay data since the previous one
(about 1.1 GB per 100,000 frames of 84x84 pixels at action repeat 2): docs/checkpoints.md."""

RESUME_FREE_SETTINGS = (
    "logdir",
    "run_name",
    "run_dir",
    "progress_bar",
    "verbose",
    "torch_threads",
    "device",
    "checkpoint_every_frames",
    "sources",
)
"""Settings that may differ between a run and its resumption (where and how it is shown, how often checkpoints are
taken; a resumption on another device or number of threads is not bit-identical, see docs/checkpoints.md)."""

PRESET, USER = "preset", "user"
"""Where a preset setting's value came from, in the run's settings file."""


@dataclass
class TrainConfig:
    """
    Settings of one training run. Frame counts include the action repeat; ``stddev_schedule``, ``n_steps`` and
    ``train_freq`` are in agent steps, ``buffer_size`` in transitions.

    **Per-task defaults.** Every DrQ-v2 hyperparameter (the fields of :class:`~sb3_collapse.presets.TaskPreset`:
    ``frames``, ``action_repeat``, ``frame_stack``, ``seed_frames``, ``batch_size``, ``buffer_size``,
    ``learning_rate``, ``n_steps``, ``feature_dim``, ``hidden_dim``, ``stddev_schedule``, ``stddev_clip``, ``tau``,
    ``gamma``, ``train_freq``, ``augmentation_pad``, ``eval_every_frames``, ``eval_episodes``, ``replay_sampling``)
    defaults to ``None``: :meth:`resolve` takes it from ``preset(env)``. A value given explicitly overrides the
    preset; :attr:`sources` says, for each of them, ``"preset"`` or ``"user"``. The preset's ``buffer_size`` is
    capped at the run's agent steps (a larger buffer is never filled).

    :param env: dm_control task, e.g. ``"walker-walk"``
    :param frames: training budget, in frames
    :param seed: random seed (environment, networks, exploration)
    :param logdir: parent folder of the run folder
    :param run_name: name of the run folder; ``<task>_s<seed>`` by default
    :param run_dir: the exact run folder, instead of ``<logdir>/<run_name>`` (created; it must not exist or be
        empty); ``None``: a new folder under ``logdir``
    :param action_repeat: frames per agent step
    :param frame_stack: stacked RGB frames per observation
    :param size: image height and width, in pixels
    :param eval_every_frames: frames between evaluations (and one at frame 0, none at the budget's end:
        :func:`~sb3_collapse.paper.evaluation_schedule`; the saved final model is evaluated apart); ``0``
        disables evaluation
    :param eval_episodes: episodes per evaluation (deterministic policy), on an evaluation environment seeded with
        ``seed``, as the reference seeds its own (the same seed as the training environment)
    :param checkpoint_every_frames: frames between two checkpoints of the run, to resume it (:mod:`sb3_collapse.checkpoints`;
        a SIGTERM or SIGINT writes one too); ``0``: only at a signal. Deleted when the run finishes
    :param seed_frames: frames of uniformly random actions before the first update
    :param batch_size: minibatch size
    :param buffer_size: replay capacity, in transitions
    :param learning_rate: Adam learning rate
    :param n_steps: n-step return length, in agent steps
    :param feature_dim: actor and critic trunk size
    :param hidden_dim: hidden units of the actor and the Q heads
    :param stddev_schedule: exploration std schedule, durations in agent steps
    :param stddev_clip: noise clip in the updates
    :param tau: soft-update coefficient of the target critic
    :param gamma: discount factor
    :param train_freq: agent steps (summed over the environments) per update
    :param augmentation_pad: random-shift padding, in pixels
    :param replay_sampling: ``"drqv2"`` (DrQ-v2's: finished episodes only, no n-step return started in an episode's
        last ``n_steps - 1`` steps) or ``"sb3"`` (SB3's: the episode in progress too, returns truncated at the time
        limit), see :class:`~sb3_collapse.drqv2.FrameStackReplayBuffer`
    :param collapse_metrics_every_frames: frames between two ``CollapseMetrics`` checks (collapse metrics of every
        named layer to TensorBoard); ``0`` disables them
    :param collapse_metrics_batch: observations of the replay buffer in each ``CollapseMetrics`` metrics batch
    :param algorithm: ``"drqv2"``, or SB3's ``"td3"`` or ``"sac"`` from the same pixels, with DrQ-v2's network sizes
        (:func:`sb3_collapse.baselines.build_baseline`; they do not use the DrQ-v2-only settings
        :data:`sb3_collapse.baselines.DRQV2_ONLY_SETTINGS`, nor layer transplants)
    :param reset_rule: apply the paper's reset-from-scratch rule (``CollapseReset``)
    :param intervention: what the reset rule does at the end of a window without escape (``"reset"``,
        ``"reset_actor"``, ``"reset_mlp"``, ``"redo"``, ``"shrink_perturb"``, see
        :mod:`sb3_collapse.monitoring.interventions`); ``None``: ``"reset"``, the paper's. Needs ``reset_rule``
    :param reset_window_frames: frames the agent has to escape collapse before a reset (the rule's window)
    :param activation: hidden activation of DrQ-v2's encoder, actor and critic: ``"relu"`` (DrQ-v2's) or
        ``"leaky_relu"`` (negative slope 0.01, the paper's footnote 1 ablation); DrQ-v2 only
    :param redo_every_updates: recycle the dormant units every this many updates for the whole run (ReDo as Sokar et
        al. run it, :class:`~sb3_collapse.monitoring.redo.PeriodicReDo`, DrQ-v2's convolution channels included);
        ``0``: never
    :param init_cnn: checkpoint (``DrQv2.save`` zip) whose encoder (``cnn1``..``cnn4``) the model starts from;
        ``None``: random (see ``DrQv2``'s ``init_from``, the paper's layer transplants)
    :param init_mlp: checkpoint whose actor (``mlp0``, ``mlp1``, ``mlp2``, ``action``) the model starts from
    :param init_critic: checkpoint whose critic (and target critic) the model starts from
    :param n_envs: training environments; more than one (or ``step_envs_during_updates``) runs them in subprocesses
        (``SubprocVecEnv``, seeds ``seed``, ``seed + 1``...). Agent steps are then summed over them (transitions): the
        frame counts, ``stddev_schedule`` and ``train_freq`` mean the same as with one, and DrQ-v2 keeps one update
        per ``train_freq`` transitions (see ``DrQv2``); the evaluation environment stays single
    :param step_envs_during_updates: step the environments while the learner updates (``DrQv2``'s option of that name:
        a one-round policy lag, DrQ-v2's reference order); runs the environments in subprocesses even when ``n_envs`` is 1
    :param compile_update: compile the update with ``torch.compile`` (``DrQv2``'s ``compile_update=True``: CUDA graphs on
        CUDA)
    :param snapshots: save the encoder and actor (about 13 MB) at every evaluation and at the end into
        ``snapshots/`` of the run folder, for ``python -m sb3_collapse.probe`` (the paper's Figure 2);
        DrQ-v2 only, needs evaluations
    :param tf32: let float32 matmuls and convolutions use TensorFloat-32 on CUDA GPUs that have it
        (:func:`~sb3_collapse.backends.configure_backends`; nothing changes on the CPU)
    :param deterministic: reproducible CUDA kernels: cuDNN's autotuner off, deterministic algorithms where torch has
        them (:func:`~sb3_collapse.backends.configure_backends`); slower on a GPU, nothing changes on the CPU
    :param device: ``"auto"``, ``"cpu"``, ``"cuda"``...
    :param torch_threads: threads of torch's CPU operations (``torch.set_num_threads``); ``None``: torch's default
    :param progress_bar: show a progress bar
    :param verbose: SB3 verbosity (0: silent, 1: log tables)
    :param variant: name of the variant in the settings and the result; ``None``: ``<algorithm>+<intervention>``
        with the reset rule (``"drqv2+reset"``), else ``<algorithm>`` (``"drqv2"``)
    :param transplant: the sources of the initial weights, as the sweep's transplant grid names them
        (``{"cnn": "blank" | "good" | "bad", "mlp": ...}``), recorded in the settings; ``None``: not a grid cell
    """

    env: str = "walker-walk"
    frames: int | None = None
    seed: int = 0
    logdir: str = "runs"
    run_name: str | None = None
    run_dir: str | None = None
    action_repeat: int | None = None
    frame_stack: int | None = None
    size: int = 84
    eval_every_frames: int | None = None
    eval_episodes: int | None = None
    checkpoint_every_frames: int = DEFAULT_CHECKPOINT_EVERY_FRAMES
    seed_frames: int | None = None
    batch_size: int | None = None
    buffer_size: int | None = None
    learning_rate: float | None = None
    n_steps: int | None = None
    feature_dim: int | None = None
    hidden_dim: int | None = None
    stddev_schedule: str | None = None
    stddev_clip: float | None = None
    tau: float | None = None
    gamma: float | None = None
    train_freq: int | None = None
    augmentation_pad: int | None = None
    replay_sampling: str | None = None
    collapse_metrics_every_frames: int = PAPER.check_every_frames
    collapse_metrics_batch: int = 512
    algorithm: str = "drqv2"
    reset_rule: bool = False
    intervention: str | None = None
    reset_window_frames: int = PAPER.window_frames
    activation: str = "relu"
    redo_every_updates: int = 0
    init_cnn: str | None = None
    init_mlp: str | None = None
    init_critic: str | None = None
    n_envs: int = 1
    step_envs_during_updates: bool = False
    compile_update: bool = False
    tf32: bool = True
    deterministic: bool = False
    snapshots: bool = False
    device: str = "auto"
    torch_threads: int | None = None
    progress_bar: bool = True
    verbose: int = 0
    variant: str | None = None
    transplant: dict[str, str] | None = None
    sources: dict[str, str] = dataclasses.field(default_factory=dict)
    """For each preset setting, ``"preset"`` or ``"user"``; filled by :meth:`resolve`."""

    @property
    def preset(self) -> TaskPreset:
        """DrQ-v2's preset of :attr:`env`."""
        return preset(self.env)

    @property
    def resolved(self) -> bool:
        """Whether every preset setting has a value (:meth:`resolve` was called)."""
        return all(getattr(self, name) is not None for name in SETTING_NAMES)

    def resolve(self) -> TrainConfig:
        """
        These settings with every preset setting left at ``None`` taken from the task's preset, and
        :attr:`sources` filled in.

        :return: a new, resolved config (this one is not changed)
        :raises ParameterError: for an unknown task (``env``)
        """
        try:
            task_preset = self.preset
        except ValueError as error:
            raise ParameterError("env", f"env: {error}") from None
        values: dict[str, Any] = {}
        sources: dict[str, str] = {}
        for name in SETTING_NAMES:
            value = getattr(self, name)
            sources[name] = self.sources.get(name, USER if value is not None else PRESET)
            values[name] = getattr(task_preset, name) if value is None else value
        if sources["buffer_size"] == PRESET:  # a larger buffer is never filled
            steps = max(1, values["frames"] // max(1, values["action_repeat"]))
            values["buffer_size"] = min(values["buffer_size"], steps)
        return dataclasses.replace(self, **values, sources=sources)

    def validate(self) -> None:
        """
        Check every setting that can be checked before anything is built or written (preset settings are checked
        as resolved). Each value is checked where it is owned: the env's settings by ``make_dmc_env``'s check, the
        algorithm's by ``DrQv2``'s, the callbacks' by their constructors; the run's own here.

        :raises ParameterError: with a message naming the bad setting
        """
        config = self if self.resolved else self.resolve()
        if config.algorithm not in ALGORITHMS:
            raise ParameterError(
                "algorithm", f"algorithm must be one of {', '.join(ALGORITHMS)}, got {config.algorithm!r}."
            )
        if config.intervention is not None:
            if config.intervention not in INTERVENTIONS:
                raise ParameterError(
                    "intervention",
                    f"intervention must be one of {', '.join(INTERVENTIONS)}, got {config.intervention!r}.",
                )
            if not config.reset_rule:
                raise ParameterError(
                    "intervention", f"intervention={config.intervention!r} is what the reset rule does: set reset_rule."
                )
        check_activation(config.activation)
        if config.algorithm != "drqv2" and config.activation != "relu":
            raise ParameterError(
                "activation",
                f"activation={config.activation!r} is a DrQ-v2 option; algorithm={config.algorithm!r} "
                "keeps SB3's ReLU networks.",
            )
        if isinstance(config.redo_every_updates, bool) or config.redo_every_updates < 0:
            raise ParameterError(
                "redo_every_updates", f"redo_every_updates must be >= 0 (0: no ReDo), got {config.redo_every_updates}."
            )
        if config.algorithm in BASELINES and config.size < NATURE_CNN_MIN_SIZE:
            raise ParameterError(
                "size",
                f"size must be >= {NATURE_CNN_MIN_SIZE} pixels for algorithm={config.algorithm!r} (SB3's NatureCNN), "
                f"got {config.size}.",
            )
        if config.algorithm != "drqv2":
            for name, default in (("n_envs", 1), ("step_envs_during_updates", False), ("compile_update", False)):
                if getattr(config, name) != default:
                    raise ParameterError(
                        name,
                        f"{name}={getattr(config, name)!r} is a DrQv2 option (docs/throughput.md); algorithm="
                        f"{config.algorithm!r} trains with one environment and SB3's loop: leave it at {default!r}.",
                    )
        if config.snapshots and (config.algorithm != "drqv2" or config.eval_every_frames == 0):
            raise ParameterError(
                "snapshots",
                "snapshots are saved at every evaluation of a DrQ-v2 run: they need algorithm='drqv2' and "
                f"eval_every_frames > 0 (got algorithm={config.algorithm!r}, eval_every_frames={config.eval_every_frames}).",
            )
        if config.algorithm != "drqv2" and config.init_from:
            raise ParameterError(
                f"init_{next(iter(config.init_from))}",
                f"init_{next(iter(config.init_from))}: layer transplants are for DrQ-v2 checkpoints; "
                f"algorithm={config.algorithm!r} cannot start from them.",
            )
        try:
            StddevSchedule(config.stddev_schedule)  # type: ignore[arg-type]
        except ValueError as error:
            raise ParameterError("stddev_schedule", f"stddev_schedule: {error}") from None
        check_env_arguments(config.action_repeat, config.frame_stack, config.size)  # type: ignore[arg-type]
        check_image_size(config.size)
        if config.frames < 1:  # type: ignore[operator]
            raise ParameterError("frames", f"frames must be >= 1, got {config.frames}.")
        for name in (
            "eval_every_frames",
            "eval_episodes",
            "checkpoint_every_frames",
            "seed_frames",
            "collapse_metrics_every_frames",
        ):
            if getattr(config, name) < 0:
                raise ParameterError(name, f"{name} must be >= 0, got {getattr(config, name)}.")
        if config.eval_every_frames > 0 and config.eval_episodes < 1:
            raise ParameterError(
                "eval_episodes", "eval_episodes must be >= 1 when evaluating (or set eval_every_frames=0)."
            )
        if config.replay_sampling not in REPLAY_SAMPLINGS:
            raise ParameterError(
                "replay_sampling",
                f"replay_sampling must be one of {', '.join(REPLAY_SAMPLINGS)}, got {config.replay_sampling!r}.",
            )
        check_hyperparameters(
            learning_rate=config.learning_rate,  # type: ignore[arg-type]
            buffer_size=config.buffer_size,  # type: ignore[arg-type]
            batch_size=config.batch_size,  # type: ignore[arg-type]
            tau=config.tau,  # type: ignore[arg-type]
            gamma=config.gamma,  # type: ignore[arg-type]
            train_freq=config.train_freq,  # type: ignore[arg-type]
            n_steps=config.n_steps,  # type: ignore[arg-type]
            stddev_clip=config.stddev_clip,  # type: ignore[arg-type]
            augmentation_pad=config.augmentation_pad,  # type: ignore[arg-type]
            policy_kwargs=dict(
                feature_dim=config.feature_dim, hidden_dim=config.hidden_dim, activation=config.activation
            ),
            seed=config.seed,
            device=config.device,
        )
        for name, build in (
            ("collapse_metrics_batch", lambda: CollapseMetrics(batch_size=config.collapse_metrics_batch)),
            ("reset_window_frames", lambda: CollapseReset(config.reset_window_frames)),
        ):
            try:
                build()
            except ValueError as error:
                raise ParameterError(name, f"{name}: {error}") from None
        if config.torch_threads is not None and config.torch_threads < 1:
            raise ParameterError("torch_threads", f"torch_threads must be >= 1, got {config.torch_threads}.")
        if isinstance(config.n_envs, bool) or not isinstance(config.n_envs, int) or config.n_envs < 1:
            raise ParameterError("n_envs", f"n_envs must be an integer >= 1, got {config.n_envs!r}.")
        for group, path in config.init_from.items():
            try:
                resolve_source_path(group, path)
            except FileNotFoundError as error:
                raise ParameterError(f"init_{group}", f"init_{group}: {error}") from None
        if config.run_dir is not None:
            state = run_folder_state(Path(config.run_dir))
            if state == FOREIGN:
                raise ParameterError(
                    "run_dir",
                    f"run_dir {config.run_dir} exists and is not an empty folder (nor the folder of a run): remove it "
                    "or choose another.",
                )
            if state == FINISHED_RUN:
                raise ParameterError(
                    "run_dir", f"run_dir {config.run_dir} holds a finished run ({RESULT_JSON}): choose another folder."
                )
        logdir = Path(config.logdir)
        blocking = blocking_file(logdir)
        if blocking is not None:
            raise ParameterError("logdir", f"logdir {logdir}: {blocking} is a file, not a folder.")

    @property
    def agent_steps(self) -> int:
        """Training budget in agent steps, summed over the environments (transitions), of the resolved settings."""
        config = self if self.resolved else self.resolve()
        return max(1, config.frames // config.action_repeat)  # type: ignore[operator]

    @property
    def init_from(self) -> dict[str, str]:
        """The ``init_from`` argument of ``DrQv2``: group (``cnn``, ``mlp``, ``critic``) -> checkpoint path."""
        paths = {"cnn": self.init_cnn, "mlp": self.init_mlp, "critic": self.init_critic}
        return {group: path for group, path in paths.items() if path is not None}

    @property
    def variant_name(self) -> str:
        """:attr:`variant`, or the name of the plain variant these settings run."""
        if self.variant is not None:
            return self.variant
        base = self.algorithm + ("-leaky" if self.activation == "leaky_relu" else "")
        if self.reset_rule:
            return f"{base}+{self.intervention or 'reset'}"
        return f"{base}+redo_periodic" if self.redo_every_updates > 0 else base

    def record(self) -> dict[str, Any]:
        """
        The content of the run's settings file: every setting (resolved), ``variant``, ``preset`` (the task's
        preset: ``task``, ``tier``, ``from_drqv2``) and ``sources`` (preset setting -> ``"preset"`` or ``"user"``).
        """
        config = self if self.resolved else self.resolve()
        task_preset = config.preset
        return {
            **dataclasses.asdict(config),
            "variant": config.variant_name,
            "preset": {"task": task_preset.task, "tier": task_preset.tier, "from_drqv2": task_preset.from_drqv2},
        }


class PeriodicEvaluation(ResumableCallback):
    """
    Deterministic evaluation at frame 0 and every ``every_frames`` frames, logged to TensorBoard
    (``eval/mean_reward``, ``eval/std_reward``) and appended to a CSV as soon as it is done: the scheduled
    evaluations (:func:`~sb3_collapse.paper.evaluation_schedule`), as in the reference's ``train.py``, where the
    paper's statistics come from.

    Not at the last step of ``learn()`` (the reference does not evaluate there either; there, SB3 calls the callbacks
    before that step's updates). :func:`train` evaluates the saved final model after ``learn()`` with
    :meth:`evaluate_saved_model`: that evaluation is labelled apart (TensorBoard ``eval_saved_model/...``, the result
    file's ``saved_model_eval``), neither in the CSV nor in :attr:`rows`.

    :param eval_env: evaluation environment (same pixel settings as the training one)
    :param every_frames: frames between evaluations
    :param episodes: episodes per evaluation
    :param csv_path: CSV file with the columns :data:`~sb3_collapse.protocol.EVAL_FIELDS`
    """

    state_attributes = ("next_eval_frame", "rows")

    def __init__(self, eval_env: Any, every_frames: int, episodes: int, csv_path: Path) -> None:
        super().__init__()
        self.eval_env = eval_env
        self.every_frames = every_frames
        self.episodes = episodes
        self.csv_path = csv_path
        self.start_time = time.time()
        self.next_eval_frame = 0
        self.rows: list[dict[str, float]] = []

    def _frames(self) -> int:
        return frames_of(self.model)

    def _on_training_start(self) -> None:
        self.next_eval_frame = self._frames()
        self._maybe_evaluate()

    def _on_step(self) -> bool:
        if self.model.num_timesteps < getattr(self.model, "_total_timesteps", float("inf")):
            self._maybe_evaluate()
        return True

    def _maybe_evaluate(self) -> None:
        if self._frames() >= self.next_eval_frame:
            self.evaluate()
            while self.next_eval_frame <= self._frames():
                self.next_eval_frame += self.every_frames

    def _run_episodes(self, prefix: str) -> dict[str, float]:
        """Evaluate now and log the result under ``<prefix>/...``; return the row (keys :data:`EVAL_FIELDS`)."""
        rewards, _ = evaluate_policy(
            self.model, self.eval_env, n_eval_episodes=self.episodes, deterministic=True, return_episode_rewards=True
        )
        row = {
            "frame": self._frames(),
            "step": self.model.num_timesteps,
            "mean_reward": float(np.mean(rewards)),
            "std_reward": float(np.std(rewards)),
            "episodes": len(rewards),
            "wall_time_s": round(time.time() - self.start_time, 1),
        }
        self.logger.record(f"{prefix}/mean_reward", row["mean_reward"])
        self.logger.record(f"{prefix}/std_reward", row["std_reward"])
        self.logger.record(f"{prefix}/frames", row["frame"])
        self.logger.dump(step=self.model.num_timesteps)
        return row

    def evaluate(self) -> dict[str, float]:
        """A scheduled evaluation: evaluate now, log the result and append it to the CSV; return the CSV row."""
        row = self._run_episodes("eval")
        append_csv_rows(self.csv_path, EVAL_FIELDS, [row])
        self.rows.append(row)
        return row

    def evaluate_saved_model(self) -> dict[str, float]:
        """
        Evaluate the final model (after ``learn()``), logged as ``eval_saved_model/...``; not a scheduled evaluation:
        not in the CSV, not in :attr:`rows`.

        :return: the row (keys :data:`~sb3_collapse.protocol.EVAL_FIELDS`)
        """
        return self._run_episodes("eval_saved_model")


@dataclass
class TrainResult:
    """
    :param run_dir: folder of the run
    :param model_path: the final checkpoint
    :param evaluations: one dict per scheduled evaluation (``frame``, ``step``, ``mean_reward``, ...)
    :param summary: the content of the result file (see :func:`run_summary`)
    :param saved_model_evaluation: the evaluation of the saved final model (same keys; ``None`` without
        evaluations), not one of ``evaluations``
    """

    run_dir: Path
    model_path: Path
    evaluations: list[dict[str, float]]
    summary: dict[str, Any] = dataclasses.field(default_factory=dict)
    saved_model_evaluation: dict[str, float] | None = None


def run_summary(
    config: TrainConfig,
    task_id: str,
    model: BaseAlgorithm,
    evaluations: list[dict[str, float]],
    reset_rule: CollapseReset | None,
    wall_time_s: float,
    resumes: int = 0,
    saved_model_eval: dict[str, float] | None = None,
    timings: LearnTimings | None = None,
) -> dict[str, Any]:
    """
    The content of the run's result file (keys :data:`~sb3_collapse.protocol.RESULT_KEYS`): ``status``
    (:data:`~sb3_collapse.protocol.FINISHED`), ``task``, ``variant``, ``seed``, ``frames`` (frames
    trained, action repeat included), ``agent_steps``, ``final_eval`` (``frame``, ``mean_reward``, ``std_reward``
    of the last scheduled evaluation, the one the paper's success/failure classes read; ``None`` without evaluation),
    ``saved_model_eval`` (the same keys and ``episodes`` for the evaluation of the saved final model, at the run's
    last frame, outside the schedule and the statistics; ``None`` without it), ``resets`` (resets of the reset rule),
    ``reset_frames`` (their frames), ``escaped`` (whether the rule saw an escape from action collapse; ``None`` without the rule),
    ``escape_frame`` (``None`` without escape), ``wall_time_s`` (seconds of the whole run, over all its processes),
    ``timings`` (where the time of ``learn()`` went: ``LearnTimings.as_dict()``, see :mod:`sb3_collapse.run.timing`,
    of the last process only when the run was resumed; ``None`` for SB3's TD3 and SAC) and ``resumes`` (times the run
    was resumed from a checkpoint).

    :param config: the run's settings
    :param task_id: the task, ``<domain>-<task>``
    :param model: the trained model
    :param evaluations: the evaluation rows
    :param reset_rule: the run's reset-rule callback, ``None`` without the rule
    :param wall_time_s: seconds the run took
    :param resumes: times the run was resumed from a checkpoint
    :param saved_model_eval: the evaluation of the saved final model (``PeriodicEvaluation.evaluate_saved_model``)
    :param timings: the time split of the run's ``learn()`` (:class:`~sb3_collapse.run.timing.LearnTimer`)
    :return: the summary, JSON-serializable
    """
    last = evaluations[-1] if evaluations else None
    saved = None
    if saved_model_eval is not None:
        saved = {key: saved_model_eval[key] for key in ("frame", "mean_reward", "std_reward", "episodes")}
        saved["frame"], saved["episodes"] = int(saved["frame"]), int(saved["episodes"])
    return {
        "status": FINISHED,
        "task": task_id,
        "variant": config.variant_name,
        "seed": config.seed,
        "frames": int(frames_of(model)),
        "agent_steps": int(model.num_timesteps),
        "final_eval": None
        if last is None
        else {"frame": int(last["frame"]), "mean_reward": last["mean_reward"], "std_reward": last["std_reward"]},
        "saved_model_eval": saved,
        "resets": 0 if reset_rule is None else reset_rule.resets,
        "reset_frames": [] if reset_rule is None else [int(frame) for frame in reset_rule.reset_frames],
        "escaped": None if reset_rule is None else bool(reset_rule.escaped),
        "escape_frame": None if reset_rule is None or reset_rule.escape_frame is None else int(reset_rule.escape_frame),
        "wall_time_s": round(wall_time_s, 2),
        "timings": None if timings is None else timings.as_dict(),
        "resumes": resumes,
        "divergence_warnings": list(model.divergence_guard.warnings) if isinstance(model, DrQv2) else [],
    }


NEW_RUN, UNFINISHED_RUN, FINISHED_RUN, FOREIGN = "new", "unfinished", "finished", "foreign"
"""What a folder holds, for a run that wants it (:func:`run_folder_state`)."""


def run_folder_state(path: Path) -> str:
    """
    :param path: a run folder (or where one would go)
    :return: :data:`NEW_RUN` (missing, empty, or a run that failed before training: a new run may take it),
        :data:`UNFINISHED_RUN` (the settings file and no result: a run to resume from its checkpoints),
        :data:`FINISHED_RUN` (a result file) or :data:`FOREIGN` (anything else: not for a run)
    """
    if not path.exists():
        return NEW_RUN
    if not path.is_dir():
        return FOREIGN
    if not any(entry.name != LOCK_FILE for entry in path.iterdir()) or failed_before_training(path):
        return NEW_RUN
    if (path / RESULT_JSON).exists():
        return FINISHED_RUN
    return UNFINISHED_RUN if (path / CONFIG_JSON).is_file() else FOREIGN


def settings_differences(saved: dict[str, Any], config: TrainConfig) -> list[str]:
    """
    :param saved: the settings file of a run folder
    :param config: the settings of a run that wants to resume it
    :return: one line per setting that differs (those of :data:`RESUME_FREE_SETTINGS` may), empty when the run
        can resume it
    """
    current = json.loads(json.dumps(config.record()))
    # A setting added after the run folder was written: the run had its default.
    defaults = json.loads(json.dumps(dataclasses.asdict(TrainConfig())))
    saved = {**{name: defaults[name] for name in defaults if name not in saved and name not in SETTING_NAMES}, **saved}
    return [
        f"`{name}={current.get(name)}` (the run folder has {saved.get(name)!r})"
        for name in sorted(set(saved) | set(current))
        if name not in RESUME_FREE_SETTINGS and saved.get(name) != current.get(name)
    ]


def optimizer_differences(checkpoint: Path, config: TrainConfig) -> list[str]:
    """
    :param checkpoint: the folder of the checkpoint a run would resume from
    :param config: the settings of the run
    :return: one line per optimizer setting of the checkpoint (the learning rate of each optimizer) that is not the
        run's: a settings file edited after the checkpoint was written would change the run mid-run
    """
    rates = sorted({rate for group in checkpoint_learning_rates(checkpoint).values() for rate in group})
    if not rates or rates == [config.learning_rate]:
        return []
    trained = ", ".join(f"{rate:g}" for rate in rates)
    return [f"`learning_rate={config.learning_rate}` (its checkpoint {checkpoint.name} trained with {trained})"]


def _saved_settings(run_dir: Path) -> dict[str, Any]:
    try:
        return read_settings(run_dir / CONFIG_JSON)
    except (OSError, ValueError) as error:
        raise ParameterError("run_dir", f"run_dir {run_dir}: its {CONFIG_JSON} cannot be read ({error}).") from None


def _new_run_dir(logdir: Path, name: str, config: TrainConfig) -> Path:
    """
    The first of ``<logdir>/<name>``, ``<name>_2``, ``<name>_3``... that can take this run: a new folder, or the
    folder of an unfinished run with the same settings (resumed).
    """
    run_dir, index = logdir / name, 1
    while True:
        state = run_folder_state(run_dir)
        if state == NEW_RUN:
            return run_dir
        if state == UNFINISHED_RUN:
            differences = settings_differences(_saved_settings(run_dir), config)
            if not differences:
                return run_dir
            print(f"{run_dir} holds an unfinished run with other settings ({'; '.join(differences)}): not resuming it.")
        index += 1
        run_dir = logdir / f"{name}_{index}"


def _empty_run_dir(run_dir: Path) -> None:
    """Delete what a run folder holds, but the lock file (held by this process)."""
    for path in run_dir.iterdir():
        if path.name != LOCK_FILE:
            shutil.rmtree(path) if path.is_dir() else path.unlink()


def _open_run_dir(run_dir: Path, config: TrainConfig) -> LoadedCheckpoint | None:
    """
    With the run folder locked: a new run writes its settings; an unfinished run with the same settings is resumed
    from its newest readable checkpoint (damaged newer ones are reported), or restarted without one.

    :return: the checkpoint to resume from, ``None`` for a run from frame 0
    :raises ParameterError: for a folder with a finished run, another run's settings or other content
    """
    state = run_folder_state(run_dir)
    if state in (FINISHED_RUN, FOREIGN):
        raise ParameterError(
            "run_dir", f"run_dir {run_dir} holds a finished run or other files: choose another folder."
        )
    if state == UNFINISHED_RUN:
        differences = settings_differences(_saved_settings(run_dir), config)
        if differences:
            raise ParameterError(
                "run_dir",
                f"run_dir {run_dir} holds an unfinished run with other settings: {'; '.join(differences)}. Run it "
                "with its own settings to resume it, or train into another folder.",
            )
        checkpoint = load_checkpoint(run_dir / CHECKPOINTS_DIR)
        skipped = [] if checkpoint is None else checkpoint.skipped
        for folder, reason in skipped:  # kept aside under another name, never read again
            print(f"Checkpoint {folder} is damaged ({reason}): falling back to the one before.")
            set_aside(folder)
        if checkpoint is not None:
            differences = optimizer_differences(checkpoint.folder, config)
            if differences:  # the settings file was edited: the run would change its settings mid-run
                raise ParameterError(
                    "run_dir",
                    f"run_dir {run_dir} holds an unfinished run with other settings: {'; '.join(differences)}. Run "
                    f"it with the settings it trained with (and its {CONFIG_JSON} as it wrote it) to resume it, or "
                    "train into another folder.",
                )
            error_file = run_dir / ERROR_TXT
            if error_file.is_file():  # kept with the checkpoints, out of the way of the sweep's status
                first = error_file.read_text().splitlines()[:1]
                print(f"The previous attempt {first[0] if first else 'failed'}; resuming.")
                error_file.replace(run_dir / CHECKPOINTS_DIR / f"error_{time.strftime('%Y%m%d-%H%M%S')}.txt")
            print(f"Resuming {run_dir} from its checkpoint at frame {checkpoint.frames:,} ({checkpoint.folder.name}).")
            return checkpoint
        print(f"{run_dir} holds an unfinished run without a readable checkpoint: restarting it from frame 0.")
    _empty_run_dir(run_dir)
    write_json_atomically(run_dir / CONFIG_JSON, config.record())
    return None


def train(config: TrainConfig) -> TrainResult:
    """
    Train DrQ-v2 as ``config`` says (preset settings left at ``None`` come from the task's preset), evaluating and
    logging on the way, and save the final model.

    Everything that can fail on bad input (the settings, the initial weights of ``init_*``, the environments, the
    model and its replay buffer) is checked or built **before** the run folder is created. A failure after it
    marks the folder as failed (the error file, with the agent step it failed at; see
    :func:`~sb3_collapse.protocol.write_failure`) and is raised again; a folder that failed before its first agent
    step holds no training and is reused by the next run.

    **Resuming.** The folder of an unfinished run with the same settings (but those of :data:`RESUME_FREE_SETTINGS`)
    is resumed from its newest readable checkpoint (:mod:`sb3_collapse.checkpoints`), or restarted from frame 0
    without one; with other settings it is refused (an explicit ``run_dir``) or passed over for ``<name>_2``... The
    folder is locked while the run trains into it (a second process is refused). A SIGTERM or SIGINT writes a
    checkpoint and raises :class:`~sb3_collapse.checkpoints.TrainingInterrupted`; the checkpoints are deleted once
    the run has finished.

    The model that is saved is the model of the last evaluation: the reset rule never resets at the budget's end
    (see :class:`~sb3_collapse.CollapseReset`), and the budget's last frames are evaluated after ``learn()`` when
    the periodic evaluation did not fall on them.

    :param config: the run's settings
    :return: where things were written, and the evaluations
    :raises InputError: for bad input (a ``ParameterError`` for a bad setting), before anything is written; a
        ``RunFolderLocked`` when another process trains into the folder
    :raises TrainingInterrupted: after a SIGTERM or SIGINT, once the checkpoint is written
    :raises CheckpointError: when a checkpoint cannot be written (a full disk): the previous one is intact
    """
    start_time = time.time()
    config = config.resolve()
    config.validate()
    domain, task = parse_task(config.env)
    task_id = f"{domain}-{task}"
    env_kwargs = dict(action_repeat=config.action_repeat, frame_stack=config.frame_stack, size=config.size)
    if config.torch_threads is not None:
        th.set_num_threads(config.torch_threads)
    configure_backends(tf32=config.tf32, deterministic=config.deterministic)

    try:
        env, eval_env, model = _build(config, task_id, env_kwargs)
    except InputError:
        raise
    except (ValueError, TypeError, MemoryError, FileNotFoundError) as error:  # bad input: nothing written yet
        raise InputError(str(error)) from error

    if config.run_dir is not None:
        run_dir = Path(config.run_dir)
    else:
        run_dir = _new_run_dir(Path(config.logdir), config.run_name or f"{task_id}_s{config.seed}", config)
    with contextlib.ExitStack() as stack:
        try:
            run_dir.mkdir(parents=True, exist_ok=True)
            stack.enter_context(RunLock(run_dir))
        except OSError as error:  # a read-only or full disk, no permission: nothing was written
            message = unwritable_message(error)
            if message is None:
                raise
            raise InputError(f"run folder: {message}") from None
        checkpoint = _open_run_dir(run_dir, config)
        try:
            result = _train_into(
                config, task_id, run_dir, model, env, eval_env, config.agent_steps, start_time, checkpoint
            )
            (run_dir / LOCK_FILE).unlink(missing_ok=True)  # finished: no process may take the folder any more
            return result
        except TrainingInterrupted:
            raise
        except BaseException as error:
            write_failure(run_dir, model.num_timesteps, frames_of(model), error)
            raise


def _monitored_dmc_env(task_id: str, seed: int, env_kwargs: dict[str, Any]) -> EpisodeReplay:
    """The env of a run: ``Monitor``-ed, and recording its episode for the checkpoints (``EpisodeReplay``)."""
    return EpisodeReplay(Monitor(make_dmc_env(task_id, seed=seed, **env_kwargs)))


def _subprocess_env(task_id: str, seed: int, env_kwargs: dict[str, Any]) -> EpisodeReplay:
    """:func:`_monitored_dmc_env` in a worker of ``SubprocVecEnv``, deaf to SIGINT and SIGTERM: the main process
    answers them with a checkpoint, which needs its workers alive."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    return _monitored_dmc_env(task_id, seed, env_kwargs)


def _training_env(config: TrainConfig, task_id: str, env_kwargs: dict[str, Any]) -> EpisodeReplay | SubprocVecEnv:
    """One ``Monitor``-ed env in this process, or ``n_envs`` of them in subprocesses (seeds ``seed``, ``seed + 1``...)."""
    if config.n_envs == 1 and not config.step_envs_during_updates:
        return _monitored_dmc_env(task_id, config.seed, env_kwargs)
    ensure_rendering_backend()  # checked once here, inherited by the subprocesses
    factories = [functools.partial(_subprocess_env, task_id, config.seed + i, env_kwargs) for i in range(config.n_envs)]
    return SubprocVecEnv(factories)


def _build(
    config: TrainConfig, task_id: str, env_kwargs: dict[str, Any]
) -> tuple[EpisodeReplay | VecEnv, EpisodeReplay | None, BaseAlgorithm]:
    """The training env(s), the evaluation env (``None`` without evaluations) and the model of :func:`train`."""
    env = _training_env(config, task_id, env_kwargs)
    eval_env = None
    if config.eval_every_frames > 0:  # seeded as the reference's (dmc.make(..., cfg.seed), as the training env)
        eval_env = _monitored_dmc_env(task_id, config.seed, env_kwargs)
    model: BaseAlgorithm
    if config.algorithm != "drqv2":  # SB3's TD3 or SAC from the same pixels
        model = build_baseline(
            config.algorithm,
            env,
            learning_rate=config.learning_rate,  # type: ignore[arg-type]
            buffer_size=config.buffer_size,  # type: ignore[arg-type]
            learning_starts=config.seed_frames // config.action_repeat,  # type: ignore[operator]
            batch_size=config.batch_size,  # type: ignore[arg-type]
            feature_dim=config.feature_dim,  # type: ignore[arg-type]
            hidden_dim=config.hidden_dim,  # type: ignore[arg-type]
            gamma=config.gamma,  # type: ignore[arg-type]
            frame_stack=config.frame_stack,
            seed=config.seed,
            device=config.device,
            verbose=config.verbose,
        )
    else:
        single = env
        env = TimedVecEnv(single if isinstance(single, VecEnv) else DummyVecEnv([lambda: single]))
        model = DrQv2(
            "CnnPolicy",
            env,
            learning_rate=config.learning_rate,
            buffer_size=config.buffer_size,
            learning_starts=config.seed_frames // config.action_repeat,
            batch_size=config.batch_size,
            tau=config.tau,
            gamma=config.gamma,
            train_freq=config.train_freq,
            n_steps=config.n_steps,
            stddev_schedule=config.stddev_schedule,
            stddev_clip=config.stddev_clip,
            augmentation_pad=config.augmentation_pad,
            replay_buffer_kwargs=dict(sampling=config.replay_sampling),
            policy_kwargs=dict(
                feature_dim=config.feature_dim, hidden_dim=config.hidden_dim, activation=config.activation
            ),
            seed=config.seed,
            device=config.device,
            verbose=config.verbose,
            init_from=config.init_from or None,
            step_envs_during_updates=config.step_envs_during_updates,
            compile_update=config.compile_update,
        )
        if model.device.type == "cpu":
            tune_cpu_allocator()  # a process-wide setting: glibc keeps the update's freed buffers for reuse
    return env, eval_env, model


def _train_into(
    config: TrainConfig,
    task_id: str,
    run_dir: Path,
    model: BaseAlgorithm,
    env: EpisodeReplay | VecEnv,
    eval_env: EpisodeReplay | None,
    steps: int,
    start_time: float,
    checkpoint: LoadedCheckpoint | None = None,
) -> TrainResult:
    """:func:`train` once the model is built and the run folder holds the settings (or a checkpoint to resume)."""

    callbacks: list[BaseCallback] = []
    evaluation = None
    if eval_env is not None:
        evaluation = PeriodicEvaluation(eval_env, config.eval_every_frames, config.eval_episodes, run_dir / EVAL_CSV)
        callbacks.append(evaluation)
    snapshots = None
    if config.snapshots:
        snapshots = Snapshots(config.eval_every_frames, run_dir / SNAPSHOTS_DIR)
        callbacks.append(snapshots)
    if config.collapse_metrics_every_frames > 0:
        metrics = CollapseMetrics(
            config.collapse_metrics_every_frames,
            batch_size=config.collapse_metrics_batch,
            csv_path=run_dir / COLLAPSE_METRICS_CSV,
        )
        callbacks.append(metrics)
    reset_rule = None
    if config.reset_rule:
        reset_rule = CollapseReset(
            config.reset_window_frames,
            check_every_frames=min(PAPER.check_every_frames, config.reset_window_frames),
            batch_size=config.collapse_metrics_batch,
            events_path=run_dir / COLLAPSE_EVENTS_CSV,
            intervention=config.intervention or "reset",
            verbose=1,
        )
        callbacks.append(reset_rule)
    if config.redo_every_updates > 0:
        callbacks.append(PeriodicReDo(config.redo_every_updates, batch_size=config.collapse_metrics_batch))

    earlier_s, resumes = 0.0, 0  # seconds and resumptions of the earlier processes of this run
    checkpoints = ResumableCheckpoints(
        run_dir / CHECKPOINTS_DIR,
        config.checkpoint_every_frames,
        callbacks=callbacks,
        eval_env=eval_env,
        csv_files=[run_dir / name for name in (PROGRESS_CSV, EVAL_CSV, COLLAPSE_METRICS_CSV, COLLAPSE_EVENTS_CSV)],
        extra_state=lambda: {"elapsed_s": earlier_s + time.time() - start_time, "resumes": resumes},
        verbose=1,
    )
    checkpoints.init_callback(model)
    if checkpoint is not None:
        checkpoint, notes = checkpoints.resume(checkpoint)
        for note in notes:
            print(f"Note: {note}")
        earlier_s, resumes = checkpoint.state["extra"]["elapsed_s"], checkpoint.state["extra"]["resumes"] + 1
        if evaluation is not None:
            evaluation.start_time = start_time - earlier_s
    callbacks.append(checkpoints)
    timer = LearnTimer(env if isinstance(env, TimedVecEnv) else None)
    formats = ["stdout", "csv", "tensorboard"] if config.verbose else ["csv", "tensorboard"]
    model.set_logger(resumed_logger(run_dir, formats, checkpoint))

    user = sorted(name for name, source in config.sources.items() if source == USER)
    task_preset = config.preset
    origin = (
        f"DrQ-v2's {task_preset.tier} preset"
        if task_preset.from_drqv2
        else (f"the {task_preset.tier} tier (DrQ-v2 published no config for {task_id})")
    )
    if config.algorithm == "drqv2":
        algorithm = "DrQ-v2"
        details = (
            f"{config.n_steps}-step returns, lr {config.learning_rate:g}, {config.replay_sampling} replay sampling"
        )
    else:
        algorithm = f"SB3's {type(model).__name__}"
        details = f"lr {config.learning_rate:g}; DrQ-v2-only settings not used: {', '.join(DRQV2_ONLY_SETTINGS)}"
    rule = f", reset rule: {config.intervention or 'reset'}" if config.reset_rule else ""
    if config.frames % config.action_repeat:  # type: ignore[operator]
        print(
            f"Note: the budget of {config.frames:,} frames is not a multiple of the action repeat "
            f"{config.action_repeat}: the run trains {steps * config.action_repeat:,} frames ({steps:,} agent steps).",
            flush=True,
        )
    print(
        f"{algorithm} on {task_id} from pixels{rule}: {config.frames:,} frames = {steps:,} agent steps "
        f"(action repeat {config.action_repeat}{f', summed over {config.n_envs} envs' if config.n_envs > 1 else ''}), "
        f"seed {config.seed}, device {model.device}.\n"
        f"Settings: {origin}" + (f", overridden: {', '.join(user)}" if user else "") + f" (batch {config.batch_size}, "
        f"{details}).\n"
        f"Writing to {run_dir} (tensorboard --logdir {run_dir if config.run_dir else config.logdir})",
        flush=True,
    )
    try:
        with stop_signals(checkpoints):
            model.learn(
                steps - model.num_timesteps,
                callback=CallbackList([*callbacks, timer]),  # the timer last: the rest counts as overhead
                log_interval=1,
                progress_bar=config.progress_bar,
                reset_num_timesteps=checkpoint is None,
            )
    except TrainingInterrupted:
        model.logger.close()
        env.close()
        raise
    except DivergenceError as error:
        model.logger.close()
        env.close()
        kept = checkpoints.last_checkpoint
        where = (
            f"its last checkpoint, {kept}, holds the weights before it"
            if kept is not None
            else "no checkpoint was written"
        )
        raise DivergenceError(f"{error} The run stops; {where}. Try a smaller --lr in another run folder.") from None
    except OSError as error:  # the run folder became read-only, or full, while training (a log, a file of a callback)
        if unwritable_message(error) is None:
            raise
        with contextlib.suppress(OSError):  # closing flushes, into the same folder
            model.logger.close()
        env.close()
        raise CheckpointError(stopped_writing_message(error, frames_of(model), checkpoints.last_checkpoint)) from None
    model_path = run_dir / FINAL_MODEL
    try:
        with atomic_output(model_path) as temporary:
            model.save(temporary)
        saved_model_eval = None
        if evaluation is not None:  # the saved model, outside the schedule (labelled apart, not in the evaluation file)
            saved_model_eval = evaluation.evaluate_saved_model()
        if snapshots is not None:
            snapshots.save()  # the final model's, next to its evaluation (once per frame)
        model.logger.close()
        env.close()
        evaluations = evaluation.rows if evaluation is not None else []
        if evaluations:
            last = evaluations[-1]
            print(
                f"Last scheduled evaluation at frame {last['frame']:,}: {last['mean_reward']:.1f} +- "
                f"{last['std_reward']:.1f}"
            )
        if saved_model_eval is not None:
            print(
                f"Saved final model at frame {saved_model_eval['frame']:,} (outside the schedule): "
                f"{saved_model_eval['mean_reward']:.1f} +- {saved_model_eval['std_reward']:.1f}"
            )
        wall_time_s = earlier_s + time.time() - start_time
        timings = timer.timings if isinstance(model, DrQv2) else None
        summary = run_summary(
            config, task_id, model, evaluations, reset_rule, wall_time_s, resumes, saved_model_eval, timings
        )
        write_json_atomically(run_dir / RESULT_JSON, summary)  # last: it marks the run as finished
    except OSError as error:
        message = unwritable_message(error)
        if message is None:
            raise
        model.logger.close()  # closing again is harmless where the failure came after these
        env.close()
        kept = checkpoints.last_checkpoint
        resume = f"it resumes from the checkpoint {kept.name}, which is intact" if kept else "it restarts the run"
        raise CheckpointError(f"{message} The run's final outputs are not written; {resume}.") from None
    shutil.rmtree(run_dir / CHECKPOINTS_DIR, ignore_errors=True)  # the run is over: its checkpoints are of no use
    print(f"Saved {model_path}")
    return TrainResult(
        run_dir=run_dir,
        model_path=model_path,
        evaluations=evaluations,
        summary=summary,
        saved_model_evaluation=saved_model_eval,
    )


def stopped_writing_message(error: OSError, frame: int, kept: Path | None) -> str:
    """
    :param error: a write that failed while the run trained (:func:`~sb3_collapse.errors.unwritable_message`)
    :param frame: the frame the run had reached
    :param kept: its last checkpoint, ``None`` without one
    :return: one line: what could not be written and why, and how the run continues
    """
    where = error.filename if error.filename is not None else "a file of the run folder"
    fix = "free space" if error.errno in FULL_DISK_ERRNOS else "make the folder writable again"
    resume = f"it resumes from the checkpoint {kept.name}, which is intact" if kept is not None else "it restarts"
    return (
        f"could not write {where} ({os.strerror(error.errno)}) at frame {frame:,}: the run stops. {fix.capitalize()}, "
        f"then run the same command again: {resume}."
    )


PRESET_HELP = "default: the task's DrQ-v2 preset (sb3_collapse.presets.preset(TASK), table in docs/presets.md)"


def training_arguments() -> argparse.ArgumentParser:
    """
    The training flags shared by ``python -m sb3_collapse.train`` and the sweep (``argparse`` parent, no
    ``--help``): every :class:`TrainConfig` setting that is the same for all the runs of a sweep. The run's task,
    seed, folder, device, reset rule and initial weights are flags of the train CLI only (the sweep sets them
    per trial). The flags of preset settings default to ``None``: the task's preset.
    """
    d = TrainConfig()
    p = argparse.ArgumentParser(add_help=False)
    g = p.add_argument_group(f"DrQ-v2 settings, per task ({PRESET_HELP})")
    g.add_argument("--frames", type=int, help="training budget, in frames (easy tasks 1.1M, medium 3.1M, hard 30.1M)")
    g.add_argument("--action-repeat", type=int, help="frames per agent step")
    g.add_argument("--frame-stack", type=int, help="stacked RGB frames per observation")
    g.add_argument("--seed-frames", type=int, help="frames of uniformly random actions before learning starts")
    g.add_argument("--batch-size", type=int, help="minibatch size of each update (walker tasks 512, others 256)")
    g.add_argument(
        "--buffer-size",
        type=int,
        help="replay capacity, in transitions (agent steps); the preset's is capped at the run's agent steps",
    )
    g.add_argument("--lr", dest="learning_rate", type=float, help="Adam learning rate (humanoid 8e-5, others 1e-4)")
    g.add_argument("--n-steps", type=int, help="n-step return length, in agent steps (walker tasks 1, others 3)")
    g.add_argument("--feature-dim", type=int, help="actor and critic trunk size (humanoid 100, others 50)")
    g.add_argument("--hidden-dim", type=int, help="hidden units of the actor and Q heads")
    g.add_argument(
        "--stddev-schedule",
        help="exploration std: a float, linear(init,final,duration) or step_linear(...), durations in agent steps",
    )
    g.add_argument("--stddev-clip", type=float, help="clip of the exploration noise in the updates")
    g.add_argument("--tau", type=float, help="soft-update coefficient of the target critic")
    g.add_argument("--gamma", type=float, help="discount factor")
    g.add_argument("--train-freq", type=int, help="agent steps (summed over the environments) per update")
    g.add_argument("--augmentation-pad", type=int, help="random-shift padding, in pixels (0: no augmentation)")
    g.add_argument(
        "--eval-every-frames", type=int, help="frames between evaluations, also one at frame 0; 0 disables them"
    )
    g.add_argument("--eval-episodes", type=int, help="episodes per evaluation (deterministic policy)")
    g.add_argument(
        "--replay-sampling",
        choices=REPLAY_SAMPLINGS,
        help="drqv2: finished episodes only, no n-step return started in an episode's last n-1 steps (DrQ-v2's); sb3: the episode in progress too, returns truncated at the time limit (SB3's)",
    )
    g = p.add_argument_group("other training settings")
    g.add_argument("--size", type=int, default=d.size, help="image height and width, in pixels (default: %(default)s)")
    g.add_argument(
        "--checkpoint-every-frames",
        type=int,
        default=d.checkpoint_every_frames,
        help="frames between intermediate checkpoints; 0: final checkpoint only (default: %(default)s)",
    )
    g.add_argument(
        "--snapshots",
        action="store_true",
        help=f"save the encoder and actor (about 13 MB at 84x84) at every evaluation and at the end into <run>/{SNAPSHOTS_DIR}/, for python -m sb3_collapse.probe sweep (Figure 2); DrQ-v2 only",
    )
    g.add_argument(
        "--collapse-metrics-every-frames",
        type=int,
        default=d.collapse_metrics_every_frames,
        help="frames between two checks of the collapse metrics (TensorBoard collapse/..., collapse metrics CSV); 0 disables them (default: the paper's, %(default)s)",
    )
    g.add_argument(
        "--collapse-metrics-batch",
        type=int,
        default=d.collapse_metrics_batch,
        help="replay observations per collapse-metrics check (default: %(default)s)",
    )
    g.add_argument(
        "--reset-window-frames",
        type=int,
        default=d.reset_window_frames,
        help="the reset rule's window, in frames (default: the paper's, %(default)s)",
    )
    g.add_argument(
        "--n-envs",
        type=int,
        default=d.n_envs,
        help="training environments (in subprocesses when more than 1); frames and agent steps are summed over them, with one update per 2 transitions as with one (default: %(default)s)",
    )
    g.add_argument(
        "--step-envs-during-updates",
        action="store_true",
        help="step the environments (in subprocesses) while the learner updates: the actions of that step come from the weights before the updates (DrQ-v2's reference order)",
    )
    g.add_argument(
        "--no-tf32",
        dest="tf32",
        action="store_false",
        help="IEEE float32 matmuls and convolutions on CUDA instead of TensorFloat-32 (on by default for GPUs that have it; no effect on the CPU)",
    )
    g.add_argument(
        "--deterministic",
        action="store_true",
        help="reproducible CUDA kernels: cuDNN's autotuner off, deterministic algorithms where torch has them (slower on a GPU; the CPU is deterministic anyway)",
    )
    g.add_argument(
        "--compile-update",
        action="store_true",
        help="compile the update with torch.compile (CUDA graphs on CUDA); compilation takes about a minute at the first update on a CPU",
    )
    g.add_argument("--verbose", type=int, default=d.verbose, help="1: print SB3's log tables (default: %(default)s)")
    return p


def training_settings(parsed: argparse.Namespace) -> dict[str, Any]:
    """
    :param parsed: arguments parsed by a parser with :func:`training_arguments` as a parent
    :return: the :class:`TrainConfig` fields of :func:`training_arguments`, by field name (``None`` for a preset
        setting not given)
    """
    names = [action.dest for action in training_arguments()._actions if action.dest != "help"]
    return {name: getattr(parsed, name) for name in names}


def build_parser() -> argparse.ArgumentParser:
    """The command line of ``python -m sb3_collapse.train``, one flag per :class:`TrainConfig` field."""
    d = TrainConfig()
    p = argparse.ArgumentParser(
        prog="python -m sb3_collapse.train",
        description="Train DrQ-v2 from pixels on a DeepMind Control task, with periodic evaluation, "
        "TensorBoard logs and a final checkpoint. Frames = agent steps x action repeat. The DrQ-v2 settings "
        "default to the task's preset (DrQ-v2's published per-task config: sb3_collapse.presets.preset(TASK), "
        f"docs/presets.md); a flag overrides it, and {CONFIG_JSON} records every value and where it came from.",
        parents=[training_arguments()],
    )
    g = p.add_argument_group("this run")
    g.add_argument(
        "--env",
        default=d.env,
        help="dm_control task: walker-walk, cartpole-swingup, quadruped-run, ... (default: %(default)s)",
    )
    g.add_argument("--seed", type=int, default=d.seed, help="random seed (default: %(default)s)")
    g.add_argument(
        "--logdir", default=d.logdir, help="parent folder of the run folder <task>_s<seed> (default: %(default)s)"
    )
    g.add_argument("--run-name", default=d.run_name, help="run folder name instead of <task>_s<seed>")
    g.add_argument(
        "--run-dir", default=d.run_dir, help="the exact run folder (new or empty), instead of --logdir/--run-name"
    )
    g.add_argument(
        "--algorithm",
        choices=ALGORITHMS,
        default=d.algorithm,
        help="drqv2, or SB3's td3 or sac from the same pixels with DrQ-v2's network sizes (docs/interventions.md) (default: %(default)s)",
    )
    g.add_argument(
        "--reset-rule",
        action="store_true",
        help="reset training from scratch when the agent has not escaped action collapse within each window (the paper's rule)",
    )
    g.add_argument(
        "--activation",
        choices=ACTIVATIONS,
        default=d.activation,
        help="hidden activation of DrQ-v2's encoder, actor and critic: relu, or leaky_relu with negative slope 0.01 (the paper's footnote 1 ablation) (default: %(default)s)",
    )
    g.add_argument(
        "--redo-every-updates",
        type=int,
        default=d.redo_every_updates,
        help="recycle the dormant units (convolution channels included) every N updates for the whole run, as ReDo does (Sokar et al., 2023; docs/interventions.md); 0: never (default: %(default)s)",
    )
    g.add_argument(
        "--intervention",
        choices=tuple(INTERVENTIONS),
        help="what the reset rule does instead of a reset from scratch (with --reset-rule; docs/interventions.md)",
    )
    g.add_argument(
        "--init-cnn", default=d.init_cnn, help="start the encoder from this DrQv2 checkpoint (zip); default: random"
    )
    g.add_argument(
        "--init-mlp",
        default=d.init_mlp,
        help="start the actor (mlp0..action) from this DrQv2 checkpoint (zip); default: random",
    )
    g.add_argument(
        "--init-critic",
        default=d.init_critic,
        help="start the critic from this DrQv2 checkpoint (zip); default: random",
    )
    g.add_argument("--device", default=d.device, help="auto, cpu, cuda, cuda:1, ... (default: %(default)s)")
    g.add_argument(
        "--torch-threads", type=int, default=d.torch_threads, help="threads of torch's CPU operations; default: torch's"
    )
    g.add_argument("--no-progress-bar", dest="progress_bar", action="store_false", help="hide the progress bar")
    g.add_argument(
        "--show-settings", action="store_true", help="print the resolved settings (and where each came from) and exit"
    )
    return p


@report_unwritable_outputs
def main(argv: list[str] | None = None) -> int:
    """
    :param argv: command-line arguments (``sys.argv[1:]`` when ``None``)
    :return: exit status
    """
    parser = build_parser()
    arguments = vars(parser.parse_args(argv))
    show = arguments.pop("show_settings")
    try:
        config = TrainConfig(**arguments).resolve()
        config.validate()
    except ValueError as error:
        parser.error(cli_message(error, parser))
    if show:
        flags = {action.dest: action.option_strings[0] for action in parser._actions if action.option_strings}
        for name, value in config.record().items():
            source = config.sources.get(name)
            print(f"{flags.get(name, name):<32} {value!r}" + (f"  ({source})" if source else ""))
        return 0
    try:
        train(config)
    except InputError as error:  # raised before training: nothing was written
        parser.error(re.sub(r"init_from\['(\w+)'\]", r"--init-\1", cli_message(error, parser)))
    except (CheckpointError, DivergenceError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 1
    except TrainingInterrupted as error:
        print(
            f"Stopped by {error.signal_name} after the checkpoint {error.checkpoint}: run the same command again to "
            f"resume (exit status {EXIT_INTERRUPTED}).",
            file=sys.stderr,
        )
        return EXIT_INTERRUPTED
    return 0


if __name__ == "__main__":
    sys.exit(main())
