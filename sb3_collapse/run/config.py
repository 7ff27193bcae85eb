"""The settings of one training run, :class:`TrainConfig`, each declared once with :func:`setting`; the flags, help
and docs tables generated from them: :mod:`sb3_collapse.commands.cli`. Units: docs/throughput.md#units."""

from __future__ import annotations

import ast
import dataclasses
import inspect
import itertools
import math
import operator
import textwrap
import types
from dataclasses import dataclass
from typing import Any

from sb3_collapse.baselines import NATURE_CNN_MIN_SIZE
from sb3_collapse.drqv2 import StddevSchedule
from sb3_collapse.drqv2.checks import check_hyperparameters
from sb3_collapse.drqv2.encoders import ACTIVATIONS, check_image_size
from sb3_collapse.drqv2.replay_buffer import REPLAY_SAMPLINGS
from sb3_collapse.drqv2.transplant import resolve_source_path
from sb3_collapse.envs.dmc import check_env_arguments
from sb3_collapse.errors import ParameterError
from sb3_collapse.monitoring import INTERVENTIONS, CollapseReset
from sb3_collapse.paper import PAPER
from sb3_collapse.presets import SETTING_NAMES, TaskPreset, drqv2_kwargs_of, preset, reset_window_frames
from sb3_collapse.protocol import SNAPSHOTS_DIR
from sb3_collapse.run.variants import ALGORITHMS, variant_name

RESUME_FREE_SETTINGS = ("logdir", "run_name", "run_dir", "progress_bar", "verbose", "torch_threads", "device")
RESUME_FREE_SETTINGS += ("checkpoint_every_frames", "sources")
"""Settings that may differ between a run and its resumption (docs/checkpoints.md)."""

PRESET, USER = "preset", "user"  # where a preset setting's value came from, in the run's settings file

TRAINING, RUN = "training", "run"  # a setting's ``cli``: flag of the train CLI and the sweep, or of the train CLI only

UNITS = ("frames", "agent steps", "transitions", "pixels", "episodes", "updates", "observations", "evaluations", "GB")
UNITS += ("percent", None)
"""The units a setting may count in (``None``: not a count)."""


def setting(
    default: Any = None,
    *,
    help: str | None = None,
    unit: str | None = None,
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
    A setting of a command line, declared once as a dataclass field (see :mod:`sb3_collapse.commands.cli`);
    ``choices``, ``minimum``, ``maximum``, ``above`` (exclusive), ``metavar`` and ``required`` as ``argparse`` would.

    :param default: the default value (``None`` for a preset setting: the task's preset fills it)
    :param help: one sentence (default: the docstring under the field, :func:`declared`); other settings named in
        backticks (`` `reset_rule` ``) show as their flags
    :param unit: what it counts in, one of :data:`UNITS` (``None``: not a count)
    :param preset: whether the task's preset fills it (one of :data:`~sb3_collapse.presets.SETTING_NAMES`)
    :param cli: :data:`TRAINING`, :data:`RUN` or ``None`` (no flag)
    :param flag: the flag, when not ``--<name>`` (``--no-<name>`` when on by default); no dashes: a positional
    :param zero_means: what ``0`` means, for a setting with ``minimum=0``
    :param nargs: how many values the flag takes (``argparse``'s; choices and bounds hold for each)
    :param default_factory: instead of ``default``, for a mutable default
    :return: the dataclass field
    """
    if unit not in UNITS:
        raise ParameterError("unit", f"unit must be one of {UNITS}, got {unit!r}.")
    metadata = {key: value for key, value in locals().items() if key not in ("default", "default_factory")}
    if default_factory is not dataclasses.MISSING:
        return dataclasses.field(default_factory=default_factory, metadata=metadata)
    return dataclasses.field(default=default, metadata=metadata)


def declared(cls: type) -> type:
    """Give each field of the dataclass ``cls`` declared with :func:`setting` without ``help`` the docstring under it
    (CleanRL); :raises ParameterError: for a field with neither."""
    body = ast.parse(textwrap.dedent(inspect.getsource(cls))).body[0].body  # type: ignore[attr-defined]
    docs = {
        node.target.id: " ".join(doc.value.value.split())
        for node, doc in itertools.pairwise(body)
        if isinstance(node, ast.AnnAssign) and isinstance(doc, ast.Expr) and isinstance(doc.value, ast.Constant)
    }
    for field in dataclasses.fields(cls):  # type: ignore[arg-type]
        if field.metadata["help"] is None:
            if field.name not in docs:
                raise ParameterError("help", f"{cls.__name__}.{field.name} has no help: write a docstring under it.")
            field.metadata = types.MappingProxyType({**field.metadata, "help": docs[field.name]})
    return cls


@declared
@dataclass
class TrainConfig:
    """Settings of one training run (:func:`sb3_collapse.run.runner.train`), listed in ``docs/presets.md``; the
    DrQ-v2 hyperparameters default to ``None``: :meth:`resolve` takes them from ``preset(env)``."""

    env: str = setting("walker-walk", cli=RUN)
    """dm_control task: walker-walk, cartpole-swingup, quadruped-run, ..."""
    frames: int | None = setting(unit="frames", preset=True, minimum=1)
    """training budget, in frames (easy tasks 1.1M, medium 3.1M, hard 30.1M)"""
    seed: int = setting(0, cli=RUN)
    """random seed (environment, networks, exploration)"""
    logdir: str = setting("runs", cli=RUN)
    """parent folder of the run folder <task>_s<seed>"""
    run_name: str | None = setting(cli=RUN)
    """name of the run folder instead of <task>_s<seed>"""
    run_dir: str | None = setting(cli=RUN)
    """the exact run folder (created; new or empty, or an unfinished run to resume) instead of `logdir`/`run_name`"""
    action_repeat: int | None = setting(unit="frames", preset=True)
    """frames per agent step"""
    frame_stack: int | None = setting(preset=True)
    """stacked RGB frames per observation"""
    size: int = setting(84, unit="pixels")
    """image height and width, in pixels"""
    eval_every_frames: int | None = setting(unit="frames", preset=True, minimum=0, zero_means="no evaluation")
    """frames between evaluations of the deterministic policy, from frame 0, none at the budget's end"""
    eval_episodes: int | None = setting(unit="episodes", preset=True, minimum=0)
    """episodes per evaluation, on an evaluation environment seeded with `seed`, as the reference seeds its own"""
    checkpoint_every_frames: int = setting(100_000, unit="frames", minimum=0, zero_means="only at a signal")
    """frames between two checkpoints, to resume the run (SIGTERM or SIGINT write one too; deleted at the end)"""
    seed_frames: int | None = setting(unit="frames", preset=True, minimum=0)
    """frames of uniformly random actions before the first update"""
    batch_size: int | None = setting(preset=True)
    """minibatch size of each update (walker tasks 512, others 256)"""
    buffer_size: int | None = setting(unit="transitions", preset=True)
    """replay capacity, in transitions (agent steps); the preset's is capped at the run's agent steps"""
    learning_rate: float | None = setting(preset=True, flag="--lr")
    """Adam learning rate (humanoid 8e-5, others 1e-4)"""
    n_steps: int | None = setting(unit="agent steps", preset=True)
    """n-step return length, in agent steps (walker tasks 1, others 3)"""
    feature_dim: int | None = setting(preset=True)
    """actor and critic trunk size (humanoid 100, others 50)"""
    hidden_dim: int | None = setting(preset=True)
    """hidden units of the actor and the Q heads"""
    stddev_schedule: str | None = setting(unit="agent steps", preset=True)
    """exploration std: a float, linear(init,final,duration) or step_linear(...), durations in agent steps"""
    stddev_clip: float | None = setting(preset=True)
    """clip of the exploration noise in the updates"""
    tau: float | None = setting(preset=True)
    """soft-update coefficient of the target critic"""
    gamma: float | None = setting(preset=True)
    """discount factor"""
    train_freq: int | None = setting(unit="agent steps", preset=True)
    """agent steps (summed over the environments) per update"""
    augmentation_pad: int | None = setting(unit="pixels", preset=True)
    """random-shift padding, in pixels (0: no augmentation)"""
    replay_sampling: str | None = setting(preset=True, choices=REPLAY_SAMPLINGS)
    """drqv2: DrQ-v2's (finished episodes, no return from their last n-1 steps); sb3: SB3's (docs/algorithm.md)"""
    collapse_metrics_every_frames: int = setting(
        PAPER.check_every_frames, unit="frames", minimum=0, zero_means="no checks"
    )
    """frames between two checks of the collapse metrics of every named layer; the paper's by default"""
    collapse_metrics_batch: int = setting(512, unit="observations", minimum=2)
    """replay observations per collapse-metrics check (correlations need pairs)"""
    algorithm: str = setting("drqv2", cli=RUN, choices=ALGORITHMS)
    """drqv2, or SB3's td3 or sac with DrQ-v2's network sizes, without transplants (docs/interventions.md)"""
    reset_rule: bool = setting(False, cli=RUN)
    """reset from scratch when the agent has not escaped action collapse within a window (the paper's rule)"""
    intervention: str | None = setting(cli=RUN, choices=tuple(INTERVENTIONS))
    """what the reset rule does instead of the paper's reset from scratch (needs `reset_rule`; docs/interventions.md)"""
    reset_window_frames: int | None = setting(unit="frames")
    """the reset rule's window, in frames; default: Proposition 1's m, the frame at which `stddev_schedule` reaches
    its final value (its duration x `action_repeat`: the paper's 2e5 for the easy tasks, 1e6 medium, 4e6 hard)"""
    activation: str = setting("relu", cli=RUN, choices=ACTIVATIONS)
    """hidden activation of DrQ-v2's networks: relu, or leaky_relu of slope 0.01 (the paper's footnote 1)"""
    redo_every_updates: int = setting(0, unit="updates", cli=RUN, minimum=0, zero_means="no ReDo")
    """recycle the dormant units (convolutions' too) every this many updates, as ReDo (docs/interventions.md)"""
    init_cnn: str | None = setting(cli=RUN)
    """start the encoder (cnn1..cnn4) from this DrQv2 checkpoint (zip; a layer transplant); default: random"""
    init_mlp: str | None = setting(cli=RUN)
    """start the actor (mlp0..action) from this DrQv2 checkpoint (zip); default: random"""
    init_critic: str | None = setting(cli=RUN)
    """start the critic (and target critic) from this DrQv2 checkpoint (zip); default: random"""
    n_envs: int = setting(1, minimum=1)
    """training environments, in subprocesses when > 1; frames summed over them (docs/throughput.md)"""
    step_envs_during_updates: bool = setting(False)
    """step the environments while the learner updates, with the weights before them (DrQ-v2's order)"""
    compile_update: bool = setting(False)
    """compile the update with torch.compile (CUDA graphs on CUDA; about a minute at the first update on a CPU)"""
    tf32: bool = setting(True)
    """let float32 matmuls and convolutions use TensorFloat-32 on CUDA GPUs that have it (sb3_collapse.backends)"""
    deterministic: bool = setting(False)
    """reproducible CUDA kernels: no cuDNN autotuner, deterministic algorithms (slower on a GPU)"""
    snapshots: bool = setting(
        False, help=f"save the encoder and actor at every evaluation and the end into <run>/{SNAPSHOTS_DIR}/ (Figure 2)"
    )
    device: str = setting("auto", cli=RUN)
    """auto, cpu, cuda, cuda:1, ..."""
    torch_threads: int | None = setting(cli=RUN, minimum=1)
    """threads of torch's CPU operations (torch.set_num_threads); default: torch's"""
    progress_bar: bool = setting(True, cli=RUN)
    """show a progress bar"""
    verbose: int = setting(0)
    """SB3 verbosity (0: silent, 1: SB3's log tables)"""
    variant: str | None = setting(cli=None)
    """name of the variant; default: <algorithm>+<intervention> with the reset rule (drqv2+reset), else <algorithm>"""
    transplant: dict[str, str] | None = setting(cli=None)  # noqa: RUF009 - setting() returns a dataclass field
    """the sources of the initial weights in the sweep's transplant grid ({cnn: blank | good | bad, ...}), if any"""
    sources: dict[str, str] = setting(cli=None, default_factory=dict)  # noqa: RUF009 - a dataclass field
    """for each preset setting, "preset" or "user" (where its value came from); filled by resolve()"""

    @property
    def preset(self) -> TaskPreset:
        """DrQ-v2's preset of :attr:`env`."""
        return preset(self.env)

    @property
    def resolved(self) -> bool:
        """Whether every preset setting and the rule's window have a value (:meth:`resolve` was called)."""
        return all(getattr(self, name) is not None for name in (*SETTING_NAMES, "reset_window_frames"))

    def resolve(self) -> TrainConfig:
        """
        :return: a new config with every preset setting left at ``None`` taken from the task's preset, and
            :attr:`sources` filled in; the preset's ``buffer_size`` is capped at the run's agent steps; the rule's
            window left at ``None``, :func:`~sb3_collapse.presets.reset_window_frames` of the resolved exploration
            schedule and action repeat
        :raises ParameterError: for an unknown task (``env``)
        """
        try:
            task_preset = self.preset
        except ValueError as error:
            raise ParameterError("env", f"env: {error}") from None
        given = {name: getattr(self, name) for name in SETTING_NAMES}
        sources = {name: self.sources.get(name, PRESET if value is None else USER) for name, value in given.items()}
        values = {name: getattr(task_preset, name) if value is None else value for name, value in given.items()}
        if sources["buffer_size"] == PRESET:  # a larger buffer is never filled
            steps = max(1, values["frames"] // max(1, values["action_repeat"]))
            values["buffer_size"] = min(values["buffer_size"], steps)
        window = self.reset_window_frames
        if window is None:
            try:
                window = reset_window_frames(self.env, values["stddev_schedule"], values["action_repeat"])
            except ValueError:  # a malformed schedule: validate() names it
                window = PAPER.window_frames
        return dataclasses.replace(self, **values, reset_window_frames=window, sources=sources)

    def validate(self) -> None:
        """
        Check every setting before anything is built or written, each by the code that owns it (the run folder:
        :func:`~sb3_collapse.run.folder.check_run_folder`).

        :raises ParameterError: with a message naming the bad setting
        """
        config = self if self.resolved else self.resolve()
        for field in dataclasses.fields(config):
            if (problem := declared_problem(field, getattr(config, field.name), integer=True)) is not None:
                raise ParameterError(field.name, f"{field.name} {problem}")
        # A budget counts whole agent steps (frames // action_repeat); the preset's replay buffer is capped there.
        steps, needed = config.frames // config.action_repeat, 1  # type: ignore[operator]
        if config.algorithm == "drqv2" and config.sources.get("buffer_size") == PRESET:
            needed = config.n_steps * config.n_envs  # type: ignore[operator]
        if steps < needed:
            why = f"; the replay buffer they cap needs n_steps={config.n_steps} per environment" if needed > 1 else ""
            steps_of = f"a budget counts whole agent steps of action_repeat={config.action_repeat} frames{why}"
            message = f"frames must be >= {needed * config.action_repeat}: {steps_of}; got {config.frames}."
            raise ParameterError("frames", message)
        if config.intervention is not None and not config.reset_rule:
            message = f"intervention={config.intervention!r} is what the reset rule does: set reset_rule."
            raise ParameterError("intervention", message)
        if config.snapshots and (config.algorithm != "drqv2" or config.eval_every_frames == 0):
            got = f"got algorithm={config.algorithm!r}, eval_every_frames={config.eval_every_frames}"
            need = f"they need algorithm='drqv2' and eval_every_frames > 0 ({got})"
            raise ParameterError("snapshots", f"snapshots are saved at every evaluation of a DrQ-v2 run: {need}.")
        if config.algorithm != "drqv2":
            _check_drqv2_only(config)
        if config.eval_every_frames > 0 and config.eval_episodes < 1:  # type: ignore[operator]
            message = "eval_episodes must be >= 1 when evaluating (or set eval_every_frames=0)."
            raise ParameterError("eval_episodes", message)
        for name, owner in (("stddev_schedule", StddevSchedule), ("reset_window_frames", CollapseReset)):
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
        settings = (self.algorithm, self.activation, self.reset_rule, self.intervention, self.redo_every_updates)
        return variant_name(*settings)

    def record(self) -> dict[str, Any]:
        """:return: the run's settings file: every setting (resolved), ``variant``, ``preset`` and ``sources``"""
        config = self if self.resolved else self.resolve()
        task = config.preset
        preset_record = {"task": task.task, "tier": task.tier, "from_drqv2": task.from_drqv2}
        return {**dataclasses.asdict(config), "variant": config.variant_name, "preset": preset_record}


_BOUNDS = (("minimum", ">=", operator.ge), ("maximum", "<=", operator.le), ("above", ">", operator.gt))


def declared_problem(field: dataclasses.Field, value: Any, integer: bool) -> str | None:
    """:return: what is wrong with ``value`` (``None`` passes) against the ``choices`` and bounds of a ``field``
    declared with :func:`setting` (``"must be >= 1, got 0."``), ``None`` when nothing is"""
    metadata = field.metadata
    if value is None or (metadata["zero_means"] and value == 0 and not isinstance(value, bool)):
        return None
    if metadata["choices"] is not None and value not in metadata["choices"]:
        return f"must be one of {', '.join(metadata['choices'])}, got {value!r}."
    zero = f" (0: {metadata['zero_means']})" if metadata["zero_means"] else ""
    for key, sign, holds in _BOUNDS:
        if metadata[key] is None:
            continue
        if isinstance(value, bool) or not isinstance(value, int if integer else (int, float)):
            return f"must be {'an integer' if integer else 'a number'} {sign} {metadata[key]}{zero}, got {value!r}."
        if not holds(value, metadata[key]):
            return f"must be {sign} {metadata[key]}{zero}, got {value}."
        if not math.isfinite(value):  # a bounded setting is a finite number: inf passes a lower bound
            return f"must be a finite number {sign} {metadata[key]}{zero}, got {value}."
    return None


def check_declared(settings: Any) -> None:
    """:raises ParameterError: naming the first field of the dataclass ``settings`` declared with :func:`setting`
    whose value (each value, for ``nargs``) is out of its declared choices or range"""
    for field in dataclasses.fields(settings):
        value = getattr(settings, field.name)
        for item in value if field.metadata.get("nargs") is not None and value is not None else [value]:
            if "help" in field.metadata and (problem := declared_problem(field, item, integer=False)) is not None:
                raise ParameterError(field.name, f"{field.name} {problem}")


def _check_drqv2_only(config: TrainConfig) -> None:
    """Refuse DrQ-v2's own options for SB3's TD3 or SAC (``config.algorithm``)."""
    algorithm = config.algorithm
    if config.activation != "relu":
        message = f"is a DrQ-v2 option; algorithm={algorithm!r} keeps SB3's ReLU networks."
        raise ParameterError("activation", f"activation={config.activation!r} {message}")
    if config.size < NATURE_CNN_MIN_SIZE:
        message = f"pixels for algorithm={algorithm!r} (SB3's NatureCNN), got {config.size}."
        raise ParameterError("size", f"size must be >= {NATURE_CNN_MIN_SIZE} {message}")
    for name, default in (("n_envs", 1), ("step_envs_during_updates", False), ("compile_update", False)):
        if (value := getattr(config, name)) != default:
            message = f"algorithm={algorithm!r} trains with one environment and SB3's loop: leave it at {default!r}."
            raise ParameterError(name, f"{name}={value!r} is a DrQv2 option (docs/throughput.md); {message}")
    if config.init_from:
        group = next(iter(config.init_from))
        message = f"layer transplants are for DrQ-v2 checkpoints; algorithm={algorithm!r} cannot start from them."
        raise ParameterError(f"init_{group}", f"init_{group}: {message}")


def env_kwargs(config: TrainConfig) -> dict[str, Any]:
    """
    :param config: resolved settings
    :return: the pixel settings of ``make_dmc_env`` (``action_repeat``, ``frame_stack``, ``size``)
    """
    return dict(action_repeat=config.action_repeat, frame_stack=config.frame_stack, size=config.size)


def _model_kwargs(config: TrainConfig, *names: str) -> dict[str, Any]:
    """The keyword arguments that ``DrQv2`` and SB3's TD3 and SAC share, and the settings ``names``."""
    shared = ("learning_rate", "buffer_size", "batch_size", "gamma", "seed", "device", "verbose", *names)
    learning_starts = config.seed_frames // config.action_repeat  # type: ignore[operator]
    return {name: getattr(config, name) for name in shared} | {"learning_starts": learning_starts}


def drqv2_kwargs(config: TrainConfig) -> dict[str, Any]:
    """:return: the keyword arguments of ``DrQv2(policy, env, ...)`` for the resolved ``config``: its preset settings'
    (:func:`~sb3_collapse.presets.drqv2_kwargs_of`, as ``preset(task).drqv2_kwargs()`` makes them) and the run's"""
    kwargs = drqv2_kwargs_of({name: getattr(config, name) for name in SETTING_NAMES})
    kwargs["policy_kwargs"]["activation"] = config.activation
    run = ("seed", "device", "verbose", "step_envs_during_updates", "compile_update")
    return kwargs | {name: getattr(config, name) for name in run} | {"init_from": config.init_from or None}


def baseline_kwargs(config: TrainConfig) -> dict[str, Any]:
    """:return: the keyword arguments of :func:`~sb3_collapse.baselines.build_baseline` after the algorithm and the env,
    for the resolved ``config``"""

    return _model_kwargs(config, "feature_dim", "hidden_dim", "frame_stack")
