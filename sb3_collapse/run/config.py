"""The settings of one training run, :class:`TrainConfig`, each declared once with :func:`setting`; the flags, help
and docs tables generated from them: :mod:`sb3_collapse.run.settings`. Units: docs/throughput.md#units."""

from __future__ import annotations

import dataclasses
import inspect
import operator
from dataclasses import dataclass
from typing import Any

from sb3_collapse.baselines import BASELINES, NATURE_CNN_MIN_SIZE
from sb3_collapse.drqv2 import StddevSchedule
from sb3_collapse.drqv2.checks import check_hyperparameters
from sb3_collapse.drqv2.encoders import ACTIVATIONS, check_image_size
from sb3_collapse.drqv2.replay_buffer import REPLAY_SAMPLINGS
from sb3_collapse.drqv2.transplant import resolve_source_path
from sb3_collapse.envs.dmc import check_env_arguments
from sb3_collapse.errors import ParameterError
from sb3_collapse.monitoring import INTERVENTIONS, CollapseReset
from sb3_collapse.paper import PAPER
from sb3_collapse.presets import SETTING_NAMES, TaskPreset, preset
from sb3_collapse.protocol import SNAPSHOTS_DIR

ALGORITHMS = ("drqv2", *BASELINES)
"""What ``algorithm`` trains: DrQ-v2, or SB3's TD3 or SAC (:mod:`sb3_collapse.baselines`)."""

RESUME_FREE_SETTINGS = ("logdir", "run_name", "run_dir", "progress_bar", "verbose", "torch_threads", "device")
RESUME_FREE_SETTINGS += ("checkpoint_every_frames", "sources")
"""Settings that may differ between a run and its resumption (docs/checkpoints.md)."""

PRESET, USER = "preset", "user"
"""Where a preset setting's value came from, in the run's settings file."""

TRAINING, RUN = "training", "run"
"""A setting's flag (``cli``): ``TRAINING``, of the train CLI and the sweep; ``RUN``, of the train CLI only."""

UNITS = ("frames", "agent steps", "transitions", "pixels", "episodes", "updates", "observations", "evaluations", "GB")
UNITS += ("percent", None)
"""The units a setting may count in (``None``: not a count)."""


def setting(
    default: Any = None,
    *,
    help: str,
    unit: str | None,
    preset: bool = False,
    cli: str | None = TRAINING,
    flag: str | None = None,
    choices: tuple[str, ...] | None = None,
    minimum: float | None = None,
    maximum: float | None = None,
    above: float | None = None,
    zero_means: str | None = None,
    nargs: int | str | None = None,
    metavar: str | tuple[str, ...] | None = None,
    required: bool = False,
    default_factory: Any = dataclasses.MISSING,
) -> Any:
    """
    A setting of a command line, declared once as a dataclass field (see :mod:`sb3_collapse.run.settings`).

    :param default: the default value (``None`` for a preset setting: the task's preset fills it)
    :param help: one sentence; other settings named in backticks (`` `reset_rule` ``) show as their flags
    :param unit: what it counts in, one of :data:`UNITS`
    :param preset: whether the task's preset fills it (one of :data:`~sb3_collapse.presets.SETTING_NAMES`)
    :param cli: :data:`TRAINING`, :data:`RUN` or ``None`` (no flag)
    :param flag: the flag, when not ``--<name>`` (``--no-<name>`` when on by default); no dashes: a positional
    :param choices: the values it takes (each value, with ``nargs``)
    :param minimum: the smallest value it takes
    :param maximum: the largest value it takes
    :param above: a bound its values must exceed
    :param zero_means: what ``0`` means, for a setting with ``minimum=0``
    :param nargs: how many values the flag takes (``argparse``'s ``nargs``; the bounds hold for each)
    :param metavar: the names of its values in the help
    :param required: whether the command line needs it
    :param default_factory: instead of ``default``, for a mutable default
    :return: the dataclass field
    """
    if unit not in UNITS:
        raise ParameterError("unit", f"unit must be one of {UNITS}, got {unit!r}.")
    metadata = {key: value for key, value in locals().items() if key not in ("default", "default_factory")}
    if default_factory is not dataclasses.MISSING:
        return dataclasses.field(default_factory=default_factory, metadata=metadata)
    return dataclasses.field(default=default, metadata=metadata)


@dataclass
class TrainConfig:
    """
    Settings of one training run (:func:`sb3_collapse.run.runner.train`), listed in ``docs/presets.md``. The DrQ-v2
    hyperparameters default to ``None``: :meth:`resolve` takes them from ``preset(env)``.
    """

    env: str = setting("walker-walk", help="dm_control task: walker-walk, cartpole-swingup, ...", unit=None, cli=RUN)
    frames: int | None = setting(
        help="training budget, in frames (easy tasks 1.1M, medium 3.1M, hard 30.1M)",
        unit="frames",
        preset=True,
        minimum=1,
    )
    seed: int = setting(0, help="random seed (environment, networks, exploration)", unit=None, cli=RUN)
    logdir: str = setting("runs", help="parent folder of the run folder <task>_s<seed>", unit=None, cli=RUN)
    run_name: str | None = setting(help="name of the run folder instead of <task>_s<seed>", unit=None, cli=RUN)
    run_dir: str | None = setting(
        help="the exact run folder (new, or an unfinished run to resume) instead of `logdir`/`run_name`",
        unit=None,
        cli=RUN,
    )
    action_repeat: int | None = setting(help="frames per agent step", unit="frames", preset=True)
    frame_stack: int | None = setting(help="stacked RGB frames per observation", unit=None, preset=True)
    size: int = setting(84, help="image height and width, in pixels", unit="pixels")
    eval_every_frames: int | None = setting(
        help="frames between evaluations of the deterministic policy, from frame 0, none at the budget's end",
        unit="frames",
        preset=True,
        minimum=0,
        zero_means="no evaluation",
    )
    eval_episodes: int | None = setting(
        help="episodes per evaluation, on an evaluation environment seeded with `seed`",
        unit="episodes",
        preset=True,
        minimum=0,
    )
    checkpoint_every_frames: int = setting(
        100_000,
        help="frames between two checkpoints, to resume the run (a SIGTERM or SIGINT writes one too)",
        unit="frames",
        minimum=0,
        zero_means="only at a signal",
    )
    seed_frames: int | None = setting(
        help="frames of uniformly random actions before the first update", unit="frames", preset=True, minimum=0
    )
    batch_size: int | None = setting(
        help="minibatch size of each update (walker tasks 512, others 256)", unit=None, preset=True
    )
    buffer_size: int | None = setting(
        help="replay capacity; the preset's is capped at the run's agent steps", unit="transitions", preset=True
    )
    learning_rate: float | None = setting(
        help="Adam learning rate (humanoid 8e-5, others 1e-4)", unit=None, preset=True, flag="--lr"
    )
    n_steps: int | None = setting(
        help="n-step return length (walker tasks 1, others 3)", unit="agent steps", preset=True
    )
    feature_dim: int | None = setting(
        help="actor and critic trunk size (humanoid 100, others 50)", unit=None, preset=True
    )
    hidden_dim: int | None = setting(help="hidden units of the actor and the Q heads", unit=None, preset=True)
    stddev_schedule: str | None = setting(
        help="exploration std: a float, linear(init,final,duration) or step_linear(...)",
        unit="agent steps",
        preset=True,
    )
    stddev_clip: float | None = setting(help="clip of the exploration noise in the updates", unit=None, preset=True)
    tau: float | None = setting(help="soft-update coefficient of the target critic", unit=None, preset=True)
    gamma: float | None = setting(help="discount factor", unit=None, preset=True)
    train_freq: int | None = setting(
        help="agent steps (summed over the environments) per update", unit="agent steps", preset=True
    )
    augmentation_pad: int | None = setting(
        help="random-shift padding, in pixels (0: no augmentation)", unit="pixels", preset=True
    )
    replay_sampling: str | None = setting(
        help="drqv2: finished episodes only, no n-step return started in an episode's last n-1 steps (DrQ-v2's); "
        "sb3: the episode in progress too, returns truncated at the time limit (SB3's)",
        unit=None,
        preset=True,
        choices=REPLAY_SAMPLINGS,
    )
    collapse_metrics_every_frames: int = setting(
        PAPER.check_every_frames,
        help="frames between two checks of the collapse metrics of every named layer (the paper's)",
        unit="frames",
        minimum=0,
        zero_means="no checks",
    )
    collapse_metrics_batch: int = setting(
        512, help="replay observations per collapse-metrics check", unit="observations", minimum=2
    )
    algorithm: str = setting(
        "drqv2",
        help="drqv2, or SB3's td3 or sac with DrQ-v2's network sizes (docs/interventions.md)",
        unit=None,
        cli=RUN,
        choices=ALGORITHMS,
    )
    reset_rule: bool = setting(
        False,
        help="reset from scratch when the agent has not escaped action collapse within each window (the paper's rule)",
        unit=None,
        cli=RUN,
    )
    intervention: str | None = setting(
        help="what the reset rule does instead of a reset from scratch (needs `reset_rule`; docs/interventions.md)",
        unit=None,
        cli=RUN,
        choices=tuple(INTERVENTIONS),
    )
    reset_window_frames: int = setting(
        PAPER.window_frames, help="the reset rule's window, in frames (the paper's by default)", unit="frames"
    )
    activation: str = setting(
        "relu",
        help="hidden activation of DrQ-v2's networks: relu, or leaky_relu of slope 0.01 (the paper's footnote 1)",
        unit=None,
        cli=RUN,
        choices=ACTIVATIONS,
    )
    redo_every_updates: int = setting(
        0,
        help="recycle the dormant units every this many updates, as ReDo does (PeriodicReDo, docs/interventions.md)",
        unit="updates",
        cli=RUN,
        minimum=0,
        zero_means="no ReDo",
    )
    init_cnn: str | None = setting(
        help="start the encoder (cnn1..cnn4) from this DrQv2 checkpoint (zip; the paper's layer transplants); "
        "default: random",
        unit=None,
        cli=RUN,
    )
    init_mlp: str | None = setting(
        help="start the actor (mlp0..action) from this DrQv2 checkpoint (zip); default: random", unit=None, cli=RUN
    )
    init_critic: str | None = setting(
        help="start the critic and its target from this DrQv2 checkpoint (zip); default: random", unit=None, cli=RUN
    )
    n_envs: int = setting(
        1,
        help="training environments (subprocesses when > 1; frames summed over them; docs/throughput.md)",
        unit=None,
        minimum=1,
    )
    step_envs_during_updates: bool = setting(
        False, help="step the environments while the learner updates (DrQ-v2's reference order)", unit=None
    )
    compile_update: bool = setting(
        False,
        help="compile the update with torch.compile (CUDA graphs on CUDA); about a minute at the first update",
        unit=None,
    )
    tf32: bool = setting(True, help="let float32 matmuls use TensorFloat-32 on CUDA GPUs that have it", unit=None)
    deterministic: bool = setting(
        False,
        help="reproducible CUDA kernels: no cuDNN autotuner, deterministic algorithms (slower on a GPU)",
        unit=None,
    )
    snapshots: bool = setting(
        False,
        help=f"save the encoder and actor at every evaluation and at the end into <run>/{SNAPSHOTS_DIR}/ (Figure 2)",
        unit=None,
    )
    device: str = setting("auto", help="auto, cpu, cuda, cuda:1, ...", unit=None, cli=RUN)
    torch_threads: int | None = setting(
        help="threads of torch's CPU operations; default: torch's", unit=None, cli=RUN, minimum=1
    )
    progress_bar: bool = setting(True, help="show a progress bar", unit=None, cli=RUN)
    verbose: int = setting(0, help="SB3 verbosity (0: silent, 1: SB3's log tables)", unit=None)
    variant: str | None = setting(
        help="name of the variant; default: <algorithm>[+<intervention>] (drqv2+reset with the reset rule)",
        unit=None,
        cli=None,
    )
    transplant: dict[str, str] | None = setting(  # noqa: RUF009 - setting() returns a dataclass field
        help="the sweep's names of the initial weights ({cnn: blank | good | bad, ...}); default: none",
        unit=None,
        cli=None,
    )
    sources: dict[str, str] = setting(  # noqa: RUF009 - setting() returns a dataclass field
        help='for each preset setting, "preset" or "user"; filled by resolve()',
        unit=None,
        cli=None,
        default_factory=dict,
    )

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
        :return: a new config with every preset setting left at ``None`` taken from the task's preset, and
            :attr:`sources` filled in; the preset's ``buffer_size`` is capped at the run's agent steps
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
        Check every setting before anything is built or written, each by the code that owns it (the run folder:
        :func:`~sb3_collapse.run.folder.check_run_folder`).

        :raises ParameterError: with a message naming the bad setting
        """
        config = self if self.resolved else self.resolve()
        for field in dataclasses.fields(config):
            problem = declared_problem(field, getattr(config, field.name), integer=True)
            if problem is not None:
                raise ParameterError(field.name, f"{field.name} {problem}")
        # A budget counts whole agent steps (frames // action_repeat); the preset's replay buffer is capped there.
        steps, needed = config.frames // config.action_repeat, 1  # type: ignore[operator]
        if config.algorithm == "drqv2" and config.sources.get("buffer_size") == PRESET:
            needed = config.n_steps * config.n_envs  # type: ignore[operator]
        if steps < needed:
            why = f"; the replay buffer they cap needs n_steps={config.n_steps} per environment" if needed > 1 else ""
            raise ParameterError(
                "frames",
                f"frames must be >= {needed * config.action_repeat}: a budget counts whole agent steps of "  # type: ignore[operator]
                f"action_repeat={config.action_repeat} frames{why}; got {config.frames}.",
            )
        if config.intervention is not None and not config.reset_rule:
            raise ParameterError(
                "intervention", f"intervention={config.intervention!r} is what the reset rule does: set reset_rule."
            )
        if config.snapshots and (config.algorithm != "drqv2" or config.eval_every_frames == 0):
            raise ParameterError(
                "snapshots",
                "snapshots are saved at every evaluation of a DrQ-v2 run: they need algorithm='drqv2' and "
                f"eval_every_frames > 0 (got algorithm={config.algorithm!r}, "
                f"eval_every_frames={config.eval_every_frames}).",
            )
        if config.algorithm != "drqv2":
            _check_drqv2_only(config)
        if config.eval_every_frames > 0 and config.eval_episodes < 1:  # type: ignore[operator]
            raise ParameterError(
                "eval_episodes", "eval_episodes must be >= 1 when evaluating (or set eval_every_frames=0)."
            )
        owners = (("stddev_schedule", StddevSchedule), ("reset_window_frames", CollapseReset))
        for name, owner in owners:
            try:
                owner(getattr(config, name))
            except ValueError as error:
                raise ParameterError(name, f"{name}: {error}") from None
        check_env_arguments(**env_kwargs(config))
        check_image_size(config.size)
        checked = inspect.signature(check_hyperparameters).parameters
        check_hyperparameters(**{name: value for name, value in drqv2_kwargs(config).items() if name in checked})
        for group, path in config.init_from.items():
            try:
                resolve_source_path(group, path)
            except FileNotFoundError as error:
                raise ParameterError(f"init_{group}", f"init_{group}: {error}") from None

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
        """:return: the run's settings file: every setting (resolved), ``variant``, ``preset`` and ``sources``"""
        config = self if self.resolved else self.resolve()
        task = config.preset
        preset_record = {"task": task.task, "tier": task.tier, "from_drqv2": task.from_drqv2}
        return {**dataclasses.asdict(config), "variant": config.variant_name, "preset": preset_record}


def declared_problem(field: dataclasses.Field, value: Any, integer: bool) -> str | None:
    """
    :param field: a field declared with :func:`setting`
    :param value: one of its values (``None`` passes)
    :param integer: whether the field holds integers
    :return: what is wrong with the value against the field's ``choices`` and bounds (``"must be >= 1, got 0."``),
        ``None`` when nothing is
    """
    metadata = field.metadata
    if value is None:
        return None
    if metadata["choices"] is not None and value not in metadata["choices"]:
        return f"must be one of {', '.join(metadata['choices'])}, got {value!r}."
    zero = f" (0: {metadata['zero_means']})" if metadata["zero_means"] else ""
    for key, sign, holds in (
        ("minimum", ">=", operator.ge),
        ("maximum", "<=", operator.le),
        ("above", ">", operator.gt),
    ):
        if metadata[key] is None:
            continue
        if isinstance(value, bool) or not isinstance(value, int if integer else (int, float)):
            return f"must be {'an integer' if integer else 'a number'} {sign} {metadata[key]}{zero}, got {value!r}."
        if not holds(value, metadata[key]):
            return f"must be {sign} {metadata[key]}{zero}, got {value}."
    return None


def _check_drqv2_only(config: TrainConfig) -> None:
    """Refuse DrQ-v2's own options for SB3's TD3 or SAC (``config.algorithm``)."""
    algorithm = config.algorithm
    if config.activation != "relu":
        raise ParameterError(
            "activation",
            f"activation={config.activation!r} is a DrQ-v2 option; algorithm={algorithm!r} keeps SB3's ReLU networks.",
        )
    if config.size < NATURE_CNN_MIN_SIZE:
        raise ParameterError(
            "size",
            f"size must be >= {NATURE_CNN_MIN_SIZE} pixels for algorithm={algorithm!r} (SB3's NatureCNN), "
            f"got {config.size}.",
        )
    for name, default in (("n_envs", 1), ("step_envs_during_updates", False), ("compile_update", False)):
        if getattr(config, name) != default:
            raise ParameterError(
                name,
                f"{name}={getattr(config, name)!r} is a DrQv2 option (docs/throughput.md); algorithm="
                f"{algorithm!r} trains with one environment and SB3's loop: leave it at {default!r}.",
            )
    if config.init_from:
        group = next(iter(config.init_from))
        raise ParameterError(
            f"init_{group}",
            f"init_{group}: layer transplants are for DrQ-v2 checkpoints; algorithm={algorithm!r} cannot start "
            "from them.",
        )


def env_kwargs(config: TrainConfig) -> dict[str, Any]:
    """:return: the pixel settings of ``make_dmc_env`` (``action_repeat``, ``frame_stack``, ``size``) of ``config``"""
    return dict(action_repeat=config.action_repeat, frame_stack=config.frame_stack, size=config.size)


def _model_kwargs(config: TrainConfig) -> dict[str, Any]:
    """The keyword arguments that ``DrQv2`` and SB3's TD3 and SAC share, of resolved settings."""
    learning_starts = config.seed_frames // config.action_repeat  # type: ignore[operator]
    return dict(
        learning_rate=config.learning_rate, buffer_size=config.buffer_size, learning_starts=learning_starts,
        batch_size=config.batch_size, gamma=config.gamma, seed=config.seed, device=config.device,
        verbose=config.verbose,
    )  # fmt: skip


def drqv2_kwargs(config: TrainConfig) -> dict[str, Any]:
    """:return: the keyword arguments of ``DrQv2(policy, env, ...)`` for these resolved settings"""
    return dict(
        _model_kwargs(config),
        tau=config.tau,
        train_freq=(config.train_freq, "transition"),  # DrQ-v2's ratio with any number of environments
        n_steps=config.n_steps,
        stddev_schedule=config.stddev_schedule,
        stddev_clip=config.stddev_clip,
        augmentation_pad=config.augmentation_pad,
        replay_buffer_kwargs=dict(sampling=config.replay_sampling),
        policy_kwargs=dict(feature_dim=config.feature_dim, hidden_dim=config.hidden_dim, activation=config.activation),
        init_from=config.init_from or None,
        step_envs_during_updates=config.step_envs_during_updates,
        compile_update=config.compile_update,
    )


def baseline_kwargs(config: TrainConfig) -> dict[str, Any]:
    """:return: the keyword arguments of :func:`~sb3_collapse.baselines.build_baseline` after the algorithm and the
    env, for these resolved settings (``algorithm`` one of :data:`~sb3_collapse.baselines.BASELINES`)"""
    sizes = dict(feature_dim=config.feature_dim, hidden_dim=config.hidden_dim, frame_stack=config.frame_stack)
    return dict(_model_kwargs(config), **sizes)
