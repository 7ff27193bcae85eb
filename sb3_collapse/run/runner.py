"""
Train DrQ-v2 (or SB3's TD3 or SAC) on a DeepMind Control task from pixels as a
:class:`~sb3_collapse.run.config.TrainConfig` says (:func:`train`, behind ``python -m sb3_collapse.train`` and every
sweep trial), into one run folder it resumes from bit for bit. See docs/training.md and docs/checkpoints.md.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import os
import shutil
import signal
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch as th
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback, CallbackList
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv, VecEnv

from sb3_collapse.backends import configure_backends
from sb3_collapse.baselines import DRQV2_ONLY_SETTINGS, build_baseline
from sb3_collapse.common.progress import on_terminal
from sb3_collapse.drqv2 import DrQv2
from sb3_collapse.envs import make_dmc_env, parse_task
from sb3_collapse.envs.rendering import ensure_rendering_backend
from sb3_collapse.envs.replay import EpisodeReplay
from sb3_collapse.errors import (
    FULL_DISK_ERRNOS,
    CheckpointError,
    DivergenceError,
    InputError,
    NonFiniteDataError,
    OutputError,
    TrainingInterrupted,
    unwritable_message,
)
from sb3_collapse.monitoring import CollapseMetrics, CollapseReset, PeriodicEvaluation, frames_of
from sb3_collapse.monitoring.periodic_redo import PeriodicReDo
from sb3_collapse.paper import PAPER
from sb3_collapse.protocol import (
    CHECKPOINTS_DIR,
    COLLAPSE_EVENTS_CSV,
    COLLAPSE_METRICS_CSV,
    EVAL_CSV,
    FINAL_MODEL,
    FINISHED,
    LOCK_FILE,
    PROGRESS_CSV,
    RESULT_JSON,
    SNAPSHOTS_DIR,
    atomic_output,
    write_failure,
    write_json_atomically,
)
from sb3_collapse.run.checkpoints import LoadedCheckpoint, ResumableCheckpoints
from sb3_collapse.run.config import USER, TrainConfig, baseline_kwargs, drqv2_kwargs, env_kwargs
from sb3_collapse.run.cpu_allocator import tune_cpu_allocator
from sb3_collapse.run.folder import check_run_folder, new_run_dir, open_run_dir
from sb3_collapse.run.lock import RunLock
from sb3_collapse.run.resumed_logger import resumed_logger
from sb3_collapse.run.signals import StopSignals, stop_signals
from sb3_collapse.run.snapshots import Snapshots
from sb3_collapse.run.timing import LearnTimer, LearnTimings, TimedVecEnv


@dataclass
class TrainResult:
    """
    :param run_dir: folder of the run
    :param model_path: the final model
    :param evaluations: one dict per scheduled evaluation (``frame``, ``step``, ``mean_reward``, ...)
    :param summary: the content of the result file (:func:`run_summary`)
    :param saved_model_evaluation: the evaluation of the saved final model (same keys), ``None`` without evaluations
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
    The content of the run's result file (keys :data:`~sb3_collapse.protocol.RESULT_KEYS`, each in docs/sweeps.md).

    :param config: the run's settings
    :param task_id: the task, ``<domain>-<task>``
    :param model: the trained model
    :param evaluations: the evaluation rows
    :param reset_rule: the run's reset-rule callback, ``None`` without the rule
    :param wall_time_s: seconds the run took
    :param resumes: times the run was resumed from a checkpoint
    :param saved_model_eval: the evaluation of the saved final model
    :param timings: the time split of the run's ``learn()``
    :return: the summary, JSON-serializable
    """
    last, saved = (evaluations[-1] if evaluations else None), saved_model_eval
    if saved is not None:
        saved = {"frame": int(saved["frame"]), "mean_reward": saved["mean_reward"], "std_reward": saved["std_reward"],
                 "episodes": int(saved["episodes"])}  # fmt: skip
    return {
        "status": FINISHED,
        "task": task_id,
        "variant": config.variant_name,
        "seed": config.seed,
        "frames": int(frames_of(model)),
        "agent_steps": int(model.num_timesteps),
        "final_eval": last
        and {"frame": int(last["frame"]), **{key: last[key] for key in ("mean_reward", "std_reward")}},
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


def train(config: TrainConfig) -> TrainResult:
    """
    Train as ``config`` says (preset settings left at ``None`` from the task's preset), evaluating and logging on the
    way, and save the final model. Bad input is refused before the run folder is created; a later failure marks the
    folder as failed. An unfinished run with the same settings is resumed (docs/checkpoints.md#using-them).

    :param config: the run's settings
    :return: where things were written, and the evaluations
    :raises InputError: for bad input (a ``ParameterError`` for a bad setting), before anything is written, or when
        another process trains into the folder
    :raises TrainingInterrupted: after a SIGTERM or SIGINT, once the checkpoint is written
    :raises OutputError: when an output cannot be written (a full disk): the previous checkpoint is intact
    :raises NonFiniteDataError: when the environment returns a reward or an observation that is not finite
    """
    start_time = time.time()
    config = config.resolve()
    config.validate()
    check_run_folder(config)
    task_id = "-".join(parse_task(config.env))  # <domain>-<task>
    if config.torch_threads is not None:
        th.set_num_threads(config.torch_threads)
    configure_backends(tf32=config.tf32, deterministic=config.deterministic)

    try:
        env, eval_env, model = build_envs_and_model(config, task_id)
    except InputError:
        raise
    except (ValueError, TypeError, MemoryError, FileNotFoundError) as error:  # bad input: nothing written yet
        raise InputError(str(error)) from error

    if config.run_dir is not None:
        run_dir = Path(config.run_dir)
    else:
        run_dir = new_run_dir(Path(config.logdir), config.run_name or f"{task_id}_s{config.seed}", config)
    with contextlib.ExitStack() as stack:
        try:
            run_dir.mkdir(parents=True, exist_ok=True)
            stack.enter_context(RunLock(run_dir))
        except OSError as error:  # a read-only or full disk, no permission: nothing was written
            message = unwritable_message(error)
            if message is None:
                raise
            raise InputError(f"run folder: {message}") from None
        checkpoint = open_run_dir(run_dir, config)
        try:
            try:
                result = _train_into(config, task_id, run_dir, model, env, eval_env, start_time, checkpoint)
            except CheckpointError as error:  # damaged: found as their replay chunks were read, each one set aside
                if not error.damaged:
                    raise
                for closing in (env, eval_env):
                    if closing is not None:
                        closing.close()
                env, eval_env, model = build_envs_and_model(config, task_id)  # from frame 0, as a new run
                checkpoint = open_run_dir(run_dir, config)  # sets the checkpoints aside, and says why it restarts
                result = _train_into(config, task_id, run_dir, model, env, eval_env, start_time, checkpoint)
            (run_dir / LOCK_FILE).unlink(missing_ok=True)  # finished: no process may take the folder any more
            return result
        except TrainingInterrupted:
            raise
        except BaseException as error:
            write_failure(run_dir, model.num_timesteps, frames_of(model), error)
            raise


def _monitored_dmc_env(task_id: str, seed: int, pixels: dict[str, Any], worker: bool = False) -> EpisodeReplay:
    """The env of a run, ``Monitor``-ed and ``EpisodeReplay``-ed; a ``SubprocVecEnv`` ``worker`` ignores SIGINT and
    SIGTERM (the main process answers them with a checkpoint, which needs it)."""
    if worker:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
    return EpisodeReplay(Monitor(make_dmc_env(task_id, seed=seed, **pixels)))


def build_envs_and_model(
    config: TrainConfig, task_id: str
) -> tuple[EpisodeReplay | VecEnv, EpisodeReplay | None, BaseAlgorithm]:
    """:return: the training env(s) (``n_envs`` in subprocesses, seeds ``seed``, ``seed + 1``...), the evaluation env
    (``None`` without evaluations) and the model of :func:`train` for the resolved ``config``"""
    pixels = env_kwargs(config)
    env: EpisodeReplay | VecEnv
    if config.n_envs == 1 and not config.step_envs_during_updates:
        env = _monitored_dmc_env(task_id, config.seed, pixels)
    else:
        ensure_rendering_backend()  # checked once here, inherited by the subprocesses
        seeds = range(config.seed, config.seed + config.n_envs)
        env = SubprocVecEnv([functools.partial(_monitored_dmc_env, task_id, seed, pixels, True) for seed in seeds])
    eval_env = None
    if config.eval_every_frames > 0:  # seeded as the reference's (dmc.make(..., cfg.seed), as the training env)
        eval_env = _monitored_dmc_env(task_id, config.seed, pixels)
    model: BaseAlgorithm
    if config.algorithm != "drqv2":  # SB3's TD3 or SAC from the same pixels
        model = build_baseline(config.algorithm, env, **baseline_kwargs(config))
    else:
        single = env
        env = TimedVecEnv(single if isinstance(single, VecEnv) else DummyVecEnv([lambda: single]))
        model = DrQv2("CnnPolicy", env, **drqv2_kwargs(config))
        if model.device.type == "cpu":
            tune_cpu_allocator()  # a process-wide setting: glibc keeps the update's freed buffers for reuse
    return env, eval_env, model


def _run_callbacks(
    config: TrainConfig, run_dir: Path, eval_env: EpisodeReplay | None
) -> tuple[list[BaseCallback], PeriodicEvaluation | None, CollapseReset | None]:
    """:return: the run's callbacks (evaluation with its snapshots, collapse metrics, reset rule, ReDo), the
    evaluation and the reset rule, as its settings ask"""
    callbacks: list[BaseCallback] = []
    evaluation = None
    if eval_env is not None:
        snapshots = Snapshots(run_dir / SNAPSHOTS_DIR) if config.snapshots else None
        evaluation = PeriodicEvaluation(
            eval_env, config.eval_every_frames, config.eval_episodes, run_dir / EVAL_CSV, callback_after_eval=snapshots
        )
        callbacks.append(evaluation)
    if config.collapse_metrics_every_frames > 0:
        every, batch = config.collapse_metrics_every_frames, config.collapse_metrics_batch
        callbacks.append(CollapseMetrics(every, batch_size=batch, csv_path=run_dir / COLLAPSE_METRICS_CSV))
    reset_rule = None
    if config.reset_rule:
        window = config.reset_window_frames  # resolved: the task's exploration end unless given
        assert window is not None, "train() runs resolved settings."
        reset_rule = CollapseReset(
            window,
            check_every_frames=min(PAPER.check_every_frames, window),
            batch_size=config.collapse_metrics_batch,
            events_path=run_dir / COLLAPSE_EVENTS_CSV,
            intervention=config.intervention or "reset",
            verbose=1,
        )
        callbacks.append(reset_rule)
    if config.redo_every_updates > 0:
        callbacks.append(PeriodicReDo(config.redo_every_updates, batch_size=config.collapse_metrics_batch))
    return callbacks, evaluation, reset_rule


def budget_note(config: TrainConfig) -> str | None:
    """:return: ``"Note: ..."`` when the resolved ``config`` does not train exactly ``frames`` (not a multiple of the
    action repeat times ``n_envs``, which step at once: the agent steps round up), else ``None``"""
    trained = -(-config.agent_steps // config.n_envs) * config.n_envs
    if trained * config.action_repeat == config.frames:
        return None
    unit = f"{config.action_repeat}" + (
        f" x {config.n_envs} environments ({config.action_repeat * config.n_envs})" if config.n_envs > 1 else ""
    )
    return (
        f"Note: the budget of {config.frames:,} frames is not a multiple of the action repeat {unit}: the run trains "
        f"{trained * config.action_repeat:,} frames ({trained:,} agent steps)."
    )


def _announce(config: TrainConfig, task_id: str, run_dir: Path, model: BaseAlgorithm) -> None:
    """Print what the run trains, with which settings (and where they came from), and where it writes."""
    user = sorted(name for name, source in config.sources.items() if source == USER)
    tier = config.preset.tier
    origin = f"DrQ-v2's {tier} preset"
    if not config.preset.from_drqv2:
        origin = f"the {tier} tier (DrQ-v2 published no config for {task_id})"
    if config.algorithm == "drqv2":
        algorithm, sampling = "DrQ-v2", config.replay_sampling
        details = f"{config.n_steps}-step returns, lr {config.learning_rate:g}, {sampling} replay sampling"
    else:
        algorithm = f"SB3's {type(model).__name__}"
        details = f"lr {config.learning_rate:g}; DrQ-v2-only settings not used: {', '.join(DRQV2_ONLY_SETTINGS)}"
    rule = f", reset rule: {config.intervention or 'reset'}" if config.reset_rule else ""
    note = budget_note(config)
    if note is not None:
        print(note, flush=True)
    print(
        f"{algorithm} on {task_id} from pixels{rule}: {config.frames:,} frames = {config.agent_steps:,} agent steps "
        f"(action repeat {config.action_repeat}{f', summed over {config.n_envs} envs' if config.n_envs > 1 else ''}), "
        f"seed {config.seed}, device {model.device}.\n"
        f"Settings: {origin}" + (f", overridden: {', '.join(user)}" if user else "") + f" (batch {config.batch_size}, "
        f"{details}).\n"
        f"Writing to {run_dir} (tensorboard --logdir {run_dir if config.run_dir else config.logdir})",
        flush=True,
    )


def _train_into(
    config: TrainConfig,
    task_id: str,
    run_dir: Path,
    model: BaseAlgorithm,
    env: EpisodeReplay | VecEnv,
    eval_env: EpisodeReplay | None,
    start_time: float,
    checkpoint: LoadedCheckpoint | None = None,
) -> TrainResult:
    """:func:`train` once the model is built and the run folder holds the settings (or a checkpoint to resume)."""
    callbacks, evaluation, reset_rule = _run_callbacks(config, run_dir, eval_env)
    earlier = {"elapsed_s": 0.0, "resumes": 0}  # what the earlier processes of a resumed run did
    checkpoints = ResumableCheckpoints(
        run_dir / CHECKPOINTS_DIR,
        config.checkpoint_every_frames,
        callbacks=callbacks,
        eval_env=eval_env,
        csv_files=[run_dir / name for name in (PROGRESS_CSV, EVAL_CSV, COLLAPSE_METRICS_CSV, COLLAPSE_EVENTS_CSV)],
        extra_state=lambda: {**earlier, "elapsed_s": earlier["elapsed_s"] + time.time() - start_time},
        verbose=1,
    )
    checkpoints.init_callback(model)
    with stop_signals(checkpoints) as stops:  # from the resume (it may read GBs of replay) to the result file
        if checkpoint is not None:
            checkpoint, notes = checkpoints.resume(checkpoint)  # an older one when the newer's replay is damaged
            print(f"Resuming {run_dir} from its checkpoint at frame {checkpoint.frames:,} ({checkpoint.folder.name}).")
            for note in notes:
                print(f"Note: {note}")
            earlier = {**checkpoint.state["extra"], "resumes": checkpoint.state["extra"]["resumes"] + 1}
            if evaluation is not None:
                evaluation.start_time = start_time - earlier["elapsed_s"]
        callbacks.append(checkpoints)
        timer = LearnTimer(env if isinstance(env, TimedVecEnv) else None)
        formats = ["stdout", "csv", "tensorboard"] if config.verbose else ["csv", "tensorboard"]
        model.set_logger(resumed_logger(run_dir, formats, checkpoint))

        _announce(config, task_id, run_dir, model)
        with contextlib.ExitStack() as open_files:  # closed on every way out: the environment, then the logger's files
            open_files.callback(env.close)
            open_files.push(_logger_closer(model))
            _learn(config, model, [*callbacks, timer], checkpoints, resumed=checkpoint is not None)
            model_path = run_dir / FINAL_MODEL
            try:
                stops.doing = "the training is done; " + (
                    "writing a checkpoint after the final save, then stopping before the evaluation of the final model"
                    if evaluation is not None
                    else "finishing its final outputs (seconds)"
                )
                with atomic_output(model_path) as temporary:
                    model.save(temporary)
                saved_model_eval = None
                if evaluation is not None:  # the saved model: outside the schedule, labelled apart
                    saved_model_eval = _evaluate_saved_model(evaluation, checkpoints, stops)  # and its snapshot
                stops.doing = "the training and its evaluation are done; finishing the final outputs (seconds)"
                open_files.close()  # the logs complete before the result file marks the run as finished
                evaluations = evaluation.rows if evaluation is not None else []
                _print_last_evaluations(evaluations, saved_model_eval)
                wall_time_s, resumes = earlier["elapsed_s"] + time.time() - start_time, earlier["resumes"]
                timings = timer.timings if isinstance(model, DrQv2) else None
                summary = run_summary(
                    config, task_id, model, evaluations, reset_rule, wall_time_s, resumes, saved_model_eval, timings
                )
                write_json_atomically(run_dir / RESULT_JSON, summary)  # last: it marks the run as finished
            except OSError as error:
                message = unwritable_message(error)
                if message is None:
                    raise
                raise OutputError(
                    f"{message} The run's final outputs are not written; {_resumes(checkpoints)}."
                ) from None
    shutil.rmtree(run_dir / CHECKPOINTS_DIR, ignore_errors=True)  # the run is over: its checkpoints are of no use
    print(f"Saved {model_path}")
    return TrainResult(run_dir, model_path, evaluations, summary, saved_model_evaluation=saved_model_eval)


def _evaluate_saved_model(
    evaluation: PeriodicEvaluation, checkpoints: ResumableCheckpoints, stops: StopSignals
) -> dict[str, float]:
    """:return: the evaluation of the saved final model; a stop before or during it (episodes at paper scale take
    longer than a scheduler's grace period) gives it up: a checkpoint of the run as it was before it, then
    ``TrainingInterrupted`` (the same command resumes there and evaluates it)"""
    state = checkpoints.capture()  # before the evaluation steps the evaluation env
    try:
        with stops.abortable("stopping the evaluation of the final model, writing a checkpoint, then stopping"):
            return evaluation.evaluate_saved_model()
    except KeyboardInterrupt:  # raised by the stop handler (abortable), which asked the checkpoints to stop
        if checkpoints.stop_signal is None:
            raise
        raise TrainingInterrupted(checkpoints.save(state), checkpoints.stop_signal) from None


def _resumes(checkpoints: ResumableCheckpoints) -> str:
    """How the same command continues the run: from its last checkpoint, or from frame 0."""
    kept = checkpoints.last_checkpoint
    return f"it resumes from the checkpoint {kept.name}, which is intact" if kept is not None else "it restarts the run"


def _learn(
    config: TrainConfig,
    model: BaseAlgorithm,
    callbacks: list[BaseCallback],
    checkpoints: ResumableCheckpoints,
    resumed: bool,
) -> None:
    """``model.learn`` up to the run's agent steps (the learn timer last in ``callbacks``), inside ``stop_signals``:
    SIGINT/SIGTERM stop it with a checkpoint; :raises DivergenceError:, :raises NonFiniteDataError: (an env's),
    :raises OutputError: (an unwritable run folder) naming the checkpoint."""
    try:
        model.learn(
            config.agent_steps - model.num_timesteps,
            callback=CallbackList(callbacks),
            log_interval=1,
            progress_bar=on_terminal(config.progress_bar),  # no bar frames in a log
            reset_num_timesteps=not resumed,
        )
    except DivergenceError as error:
        kept = checkpoints.last_checkpoint
        where = f"its last checkpoint, {kept}, holds the weights before it" if kept else "no checkpoint was written"
        raise DivergenceError(f"{error} The run stops; {where}. Try a smaller --lr in another run folder.") from None
    except NonFiniteDataError as error:  # from an environment, refused before it was stored
        kept = checkpoints.last_checkpoint
        where = f"its last checkpoint, {kept}, holds none of it" if kept else "no checkpoint was written"
        raise NonFiniteDataError(
            f"{config.env} at agent step {model.num_timesteps:,} (frame {frames_of(model):,}): {error} The run stops; "
            f"{where}. A rerun meets it again: fix the environment, or train another --seed in another run folder."
        ) from None
    except OSError as error:  # the run folder became read-only, or full, while training (a log, a file of a callback)
        if unwritable_message(error) is None:
            raise
        where = error.filename if error.filename is not None else "a file of the run folder"
        fix = "Free space" if error.errno in FULL_DISK_ERRNOS else "Make the folder writable again"
        raise OutputError(
            f"could not write {where} ({os.strerror(error.errno)}) at frame {frames_of(model):,}: the run stops. "
            f"{fix}, then run the same command again: {_resumes(checkpoints)}."
        ) from None


def _logger_closer(model: BaseAlgorithm) -> Callable[..., bool]:
    """An ``ExitStack`` exit callback closing ``model.logger`` (its ``OSError`` dropped after another error)."""

    def close(exc_type: type[BaseException] | None, *_: object) -> bool:
        with contextlib.suppress(*(() if exc_type is None else (OSError,))):
            model.logger.close()
        return False

    return close


def _print_last_evaluations(evaluations: list[dict[str, Any]], saved_model_eval: dict[str, Any] | None) -> None:
    """Print the last scheduled evaluation and that of the saved final model (frames, mean +- std return)."""
    last = evaluations[-1] if evaluations else None
    for label, row in (("Last scheduled evaluation", last), ("Saved final model", saved_model_eval)):
        if row is not None:
            outside = " (outside the schedule)" if row is saved_model_eval else ""
            print(f"{label} at frame {row['frame']:,}{outside}: {row['mean_reward']:.1f} +- {row['std_reward']:.1f}")
