"""Train DrQ-v2 on a DeepMind Control task from pixels: ``python -m sb3_collapse.train --help``.

    python -m sb3_collapse.train --env walker-walk --frames 100000 --seed 0 --logdir runs/

Everything a run writes goes to one folder, ``<logdir>/<task>_s<seed>`` (``_2``, ``_3``... if it exists), or
exactly ``--run-dir``: ``config.json`` (the settings, written first), TensorBoard events and ``progress.csv`` (the
SB3 logger), ``eval.csv`` (one row per evaluation), ``collapse_metrics.csv`` (one group of rows per collapse
check), ``collapse_events.csv`` (resets and the escape, with ``--reset-rule``), ``final_model.zip`` (load it with
``DrQv2.load``) and ``result.json`` (the outcome, written last: a folder without it is an unfinished run).

``--init-cnn``, ``--init-mlp`` and ``--init-critic`` start the encoder, the actor or the critic from the weights of a
saved DrQv2 (the paper's layer transplants, ``DrQv2(init_from=...)``). Sweeps of many such runs on Ray:
``python -m sb3_collapse.sweep --help``.

Budgets are in frames, as in DrQ-v2 and the paper (frames = agent steps x action repeat); the exploration
schedule is in agent steps, as in DrQ-v2's configs. With ``--n-envs N`` (N environments in subprocesses), agent steps
are summed over the environments (transitions) everywhere: the budget, the seed frames, the schedule, the evaluation and
collapse-check periods and DrQ-v2's one update per 2 transitions mean the same as with one environment
(``docs/throughput.md``).
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import functools
import json
import os
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
from stable_baselines3.common.callbacks import BaseCallback, CallbackList, CheckpointCallback
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.logger import configure
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import SubprocVecEnv

from sb3_collapse.drqv2 import DrQv2, StddevSchedule
from sb3_collapse.drqv2.transplant import resolve_source_path
from sb3_collapse.envs import make_dmc_env, parse_task
from sb3_collapse.envs.rendering import ensure_rendering_backend
from sb3_collapse.monitoring import CollapseMetrics, CollapseReset


@dataclass
class TrainConfig:
    """
    Settings of one training run. Frame counts include the action repeat; ``stddev_schedule`` is in agent steps.

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
    :param eval_every_frames: frames between evaluations (and one at frame 0); ``0`` disables evaluation
    :param eval_episodes: episodes per evaluation (deterministic policy)
    :param checkpoint_every_frames: frames between intermediate checkpoints; ``0`` for the final one only
    :param seed_frames: frames of uniformly random actions before the first update
    :param batch_size: minibatch size
    :param buffer_size: replay capacity in transitions; ``None``: the run's agent steps, at most 1,000,000
    :param learning_rate: Adam learning rate
    :param n_steps: n-step return length
    :param feature_dim: actor and critic trunk size
    :param hidden_dim: hidden units of the actor and the Q heads
    :param stddev_schedule: exploration std schedule, durations in agent steps
    :param stddev_clip: noise clip in the updates
    :param collapse_metrics_every_frames: frames between two ``CollapseMetrics`` checks (collapse metrics of every
        named layer to TensorBoard); ``0`` disables them
    :param collapse_probe_batch: observations of the replay buffer in each ``CollapseMetrics`` probe batch
    :param reset_rule: apply the paper's reset-from-scratch rule (``CollapseReset``)
    :param reset_window_frames: frames the agent has to escape collapse before a reset (the rule's window)
    :param init_cnn: checkpoint (``DrQv2.save`` zip) whose encoder (``cnn1``..``cnn4``) the model starts from;
        ``None``: random (see ``DrQv2``'s ``init_from``, the paper's layer transplants)
    :param init_mlp: checkpoint whose actor (``mlp0``, ``mlp1``, ``mlp2``, ``action``) the model starts from
    :param init_critic: checkpoint whose critic (and target critic) the model starts from
    :param n_envs: training environments; more than one (or ``step_envs_during_updates``) runs them in subprocesses
        (``SubprocVecEnv``, seeds ``seed``, ``seed + 1``...). Frame counts and ``stddev_schedule`` are summed over them,
        and DrQ-v2 keeps one update per 2 transitions (see ``DrQv2``); the evaluation environment stays single
    :param step_envs_during_updates: step the environments while the learner updates (``DrQv2``'s option of that name:
        a one-round policy lag, DrQ-v2's reference order); runs the environments in subprocesses even when ``n_envs`` is 1
    :param compile_update: compile the update with ``torch.compile`` (``DrQv2``'s ``compile_update=True``: CUDA graphs on
        CUDA)
    :param device: ``"auto"``, ``"cpu"``, ``"cuda"``...
    :param torch_threads: threads of torch's CPU operations (``torch.set_num_threads``); ``None``: torch's default
    :param progress_bar: show a progress bar
    :param verbose: SB3 verbosity (0: silent, 1: log tables)
    :param variant: name of the variant in ``config.json`` and ``result.json``; ``None``: ``"drqv2+reset"`` with
        the reset rule, else ``"drqv2"``
    :param transplant: the sources of the initial weights, as the sweep's transplant grid names them
        (``{"cnn": "blank" | "good" | "bad", "mlp": ...}``), recorded in ``config.json``; ``None``: not a grid cell
    """

    env: str = "walker-walk"
    frames: int = 1_100_000
    seed: int = 0
    logdir: str = "runs"
    run_name: str | None = None
    run_dir: str | None = None
    action_repeat: int = 2
    frame_stack: int = 3
    size: int = 84
    eval_every_frames: int = 10_000
    eval_episodes: int = 10
    checkpoint_every_frames: int = 0
    seed_frames: int = 4000
    batch_size: int = 256
    buffer_size: int | None = None
    learning_rate: float = 1e-4
    n_steps: int = 3
    feature_dim: int = 50
    hidden_dim: int = 1024
    stddev_schedule: str = "linear(1.0,0.1,100000)"
    stddev_clip: float = 0.3
    collapse_metrics_every_frames: int = 10_000
    collapse_probe_batch: int = 512
    reset_rule: bool = False
    reset_window_frames: int = 200_000
    init_cnn: str | None = None
    init_mlp: str | None = None
    init_critic: str | None = None
    n_envs: int = 1
    step_envs_during_updates: bool = False
    compile_update: bool = False
    device: str = "auto"
    torch_threads: int | None = None
    progress_bar: bool = True
    verbose: int = 0
    variant: str | None = None
    transplant: dict[str, str] | None = None

    def validate(self) -> None:
        """
        :raises ValueError: with a message naming the bad setting
        """
        parse_task(self.env)
        StddevSchedule(self.stddev_schedule)
        positive = ("frames", "action_repeat", "frame_stack", "size", "batch_size", "n_steps", "feature_dim", "hidden_dim",
                    "collapse_probe_batch", "reset_window_frames", "n_envs")
        for name in positive:
            if getattr(self, name) < 1:
                raise ValueError(f"--{name.replace('_', '-')} must be >= 1, got {getattr(self, name)}.")
        for name in ("eval_every_frames", "eval_episodes", "checkpoint_every_frames", "seed_frames",
                     "collapse_metrics_every_frames"):
            if getattr(self, name) < 0:
                raise ValueError(f"--{name.replace('_', '-')} must be >= 0, got {getattr(self, name)}.")
        if self.eval_every_frames > 0 and self.eval_episodes < 1:
            raise ValueError("--eval-episodes must be >= 1 when evaluating (or pass --eval-every-frames 0).")
        if self.buffer_size is not None and self.buffer_size < 1:
            raise ValueError(f"--buffer-size must be >= 1 transition, got {self.buffer_size}.")
        if self.torch_threads is not None and self.torch_threads < 1:
            raise ValueError(f"--torch-threads must be >= 1, got {self.torch_threads}.")
        for group, path in self.init_from.items():
            try:
                resolve_source_path(group, path)
            except FileNotFoundError as error:
                raise ValueError(f"--init-{group}: {error}") from None
        run_dir = None if self.run_dir is None else Path(self.run_dir)
        if run_dir is not None and run_dir.exists() and (not run_dir.is_dir() or any(run_dir.iterdir())):
            raise ValueError(f"--run-dir {run_dir} exists and is not an empty folder: remove it or choose another.")

    @property
    def agent_steps(self) -> int:
        """Training budget in agent steps, summed over the environments (transitions)."""
        return max(1, self.frames // self.action_repeat)

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
        return "drqv2+reset" if self.reset_rule else "drqv2"


class PeriodicEvaluation(BaseCallback):
    """
    Deterministic evaluation at frame 0 and every ``every_frames`` frames, logged to TensorBoard
    (``eval/mean_reward``, ``eval/std_reward``) and appended to a CSV as soon as it is done.

    :param eval_env: evaluation environment (same pixel settings as the training one)
    :param every_frames: frames between evaluations
    :param episodes: episodes per evaluation
    :param csv_path: CSV file with columns ``frame, step, mean_reward, std_reward, episodes, wall_time_s``
    """

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
        return self.model.num_timesteps * self.model.action_repeat  # type: ignore[attr-defined]

    def _on_training_start(self) -> None:
        self.next_eval_frame = self._frames()
        self._maybe_evaluate()

    def _on_step(self) -> bool:
        self._maybe_evaluate()
        return True

    def _maybe_evaluate(self) -> None:
        if self._frames() >= self.next_eval_frame:
            self.evaluate()
            while self.next_eval_frame <= self._frames():
                self.next_eval_frame += self.every_frames

    def evaluate(self) -> dict[str, float]:
        """Evaluate now, log the result and append it to the CSV; return the CSV row."""
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
        new_file = not self.csv_path.exists()
        with self.csv_path.open("a", newline="") as file:
            writer = csv.DictWriter(file, fieldnames=list(row))
            if new_file:
                writer.writeheader()
            writer.writerow(row)
        self.rows.append(row)
        self.logger.record("eval/mean_reward", row["mean_reward"])
        self.logger.record("eval/std_reward", row["std_reward"])
        self.logger.record("eval/frames", row["frame"])
        self.logger.dump(step=self.model.num_timesteps)
        return row


@dataclass
class TrainResult:
    """
    :param run_dir: folder of the run
    :param model_path: the final checkpoint
    :param evaluations: one dict per evaluation (``frame``, ``step``, ``mean_reward``, ...)
    :param summary: the content of ``result.json`` (see :func:`run_summary`)
    """

    run_dir: Path
    model_path: Path
    evaluations: list[dict[str, float]]
    summary: dict[str, Any] = dataclasses.field(default_factory=dict)


def write_text_atomically(path: Path, text: str) -> None:
    """
    Write ``text`` to a temporary file next to ``path``, then rename it to ``path``: readers see either no file or
    the complete one.

    :param path: the file
    :param text: its content
    """
    handle, temporary = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(handle, "w") as file:
            file.write(text)
        os.replace(temporary, path)
    except BaseException:
        if os.path.exists(temporary):
            os.remove(temporary)
        raise


def write_json_atomically(path: Path, content: Any) -> None:
    """
    Write ``content`` as indented JSON with :func:`write_text_atomically`.

    :param path: the JSON file
    :param content: anything ``json.dumps`` accepts
    """
    write_text_atomically(path, json.dumps(content, indent=2) + "\n")


def run_summary(
    config: TrainConfig,
    task_id: str,
    model: DrQv2,
    evaluations: list[dict[str, float]],
    reset_rule: CollapseReset | None,
    wall_time_s: float,
) -> dict[str, Any]:
    """
    The content of ``result.json``: ``status`` (``"finished"``), ``task``, ``variant``, ``seed``, ``frames`` (frames
    trained, action repeat included), ``agent_steps``, ``final_eval`` (``frame``, ``mean_reward``, ``std_reward``
    of the last evaluation, or ``None`` without evaluation), ``resets`` (resets of the reset rule), ``reset_frames``
    (their frames), ``escaped`` (whether the rule saw an escape from action collapse; ``None`` without the rule),
    ``escape_frame`` (``None`` without escape), ``wall_time_s`` (seconds of the whole run) and ``timings`` (where the
    time of ``learn()`` went: ``DrQv2.timings.as_dict()``, see ``sb3_collapse.drqv2.timing``).

    :param config: the run's settings
    :param task_id: the task, ``<domain>-<task>``
    :param model: the trained model
    :param evaluations: the rows of ``eval.csv``
    :param reset_rule: the run's reset-rule callback, ``None`` without the rule
    :param wall_time_s: seconds the run took
    :return: the summary, JSON-serializable
    """
    last = evaluations[-1] if evaluations else None
    return {
        "status": "finished",
        "task": task_id,
        "variant": config.variant_name,
        "seed": config.seed,
        "frames": int(model.num_timesteps * model.action_repeat),
        "agent_steps": int(model.num_timesteps),
        "final_eval": None
        if last is None
        else {"frame": int(last["frame"]), "mean_reward": last["mean_reward"], "std_reward": last["std_reward"]},
        "resets": 0 if reset_rule is None else reset_rule.resets,
        "reset_frames": [] if reset_rule is None else [int(frame) for frame in reset_rule.reset_frames],
        "escaped": None if reset_rule is None else bool(reset_rule.escaped),
        "escape_frame": None if reset_rule is None or reset_rule.escape_frame is None else int(reset_rule.escape_frame),
        "wall_time_s": round(wall_time_s, 2),
        "timings": model.timings.as_dict(),
    }


def _monitored_dmc_env(task_id: str, seed: int, env_kwargs: dict[str, Any]) -> Monitor:
    return Monitor(make_dmc_env(task_id, seed=seed, **env_kwargs))


def _training_env(task_id: str, config: TrainConfig, env_kwargs: dict[str, Any]) -> Monitor | SubprocVecEnv:
    """One ``Monitor``-ed env in this process, or ``n_envs`` of them in subprocesses (seeds ``seed``, ``seed + 1``...)."""
    if config.n_envs == 1 and not config.step_envs_during_updates:
        return _monitored_dmc_env(task_id, config.seed, env_kwargs)
    ensure_rendering_backend()  # probed once here, inherited by the subprocesses
    factories = [functools.partial(_monitored_dmc_env, task_id, config.seed + i, env_kwargs) for i in range(config.n_envs)]
    return SubprocVecEnv(factories)


def _new_run_dir(logdir: Path, name: str) -> Path:
    run_dir, index = logdir / name, 1
    while run_dir.exists():
        index += 1
        run_dir = logdir / f"{name}_{index}"
    run_dir.mkdir(parents=True)
    return run_dir


def train(config: TrainConfig) -> TrainResult:
    """
    Train DrQ-v2 as ``config`` says, evaluating and logging on the way, and save the final model.

    :param config: the run's settings
    :return: where things were written, and the evaluations
    """
    start_time = time.time()
    config.validate()
    domain, task = parse_task(config.env)
    task_id = f"{domain}-{task}"
    env_kwargs = dict(action_repeat=config.action_repeat, frame_stack=config.frame_stack, size=config.size)
    if config.run_dir is not None:
        run_dir = Path(config.run_dir)
        run_dir.mkdir(parents=True, exist_ok=True)
    else:
        run_dir = _new_run_dir(Path(config.logdir), config.run_name or f"{task_id}_s{config.seed}")
    write_json_atomically(run_dir / "config.json", {**dataclasses.asdict(config), "variant": config.variant_name})
    if config.torch_threads is not None:
        th.set_num_threads(config.torch_threads)

    env = _training_env(task_id, config, env_kwargs)
    steps = config.agent_steps
    model = DrQv2(
        "CnnPolicy",
        env,
        learning_rate=config.learning_rate,
        buffer_size=config.buffer_size or min(1_000_000, steps),
        learning_starts=config.seed_frames // config.action_repeat,
        batch_size=config.batch_size,
        n_steps=config.n_steps,
        stddev_schedule=config.stddev_schedule,
        stddev_clip=config.stddev_clip,
        policy_kwargs=dict(feature_dim=config.feature_dim, hidden_dim=config.hidden_dim),
        seed=config.seed,
        device=config.device,
        verbose=config.verbose,
        init_from=config.init_from or None,
        step_envs_during_updates=config.step_envs_during_updates,
        compile_update=config.compile_update,
    )
    formats = ["stdout", "csv", "tensorboard"] if config.verbose else ["csv", "tensorboard"]
    model.set_logger(configure(str(run_dir), formats))

    callbacks: list[BaseCallback] = []
    evaluation = None
    if config.eval_every_frames > 0:
        eval_env = Monitor(make_dmc_env(task_id, seed=config.seed + 100_000, **env_kwargs))
        evaluation = PeriodicEvaluation(eval_env, config.eval_every_frames, config.eval_episodes, run_dir / "eval.csv")
        callbacks.append(evaluation)
    if config.checkpoint_every_frames > 0:
        save_freq = max(1, config.checkpoint_every_frames // config.action_repeat)
        callbacks.append(CheckpointCallback(save_freq, str(run_dir / "checkpoints"), name_prefix="drqv2"))
    if config.collapse_metrics_every_frames > 0:
        metrics = CollapseMetrics(
            config.collapse_metrics_every_frames,
            batch_size=config.collapse_probe_batch,
            csv_path=run_dir / "collapse_metrics.csv",
        )
        callbacks.append(metrics)
    reset_rule = None
    if config.reset_rule:
        check_every = min(10_000, config.reset_window_frames)  # the paper's: one check every 10,000 frames
        reset_rule = CollapseReset(
            config.reset_window_frames,
            check_every_frames=check_every,
            events_path=run_dir / "collapse_events.csv",
            verbose=1,
        )
        callbacks.append(reset_rule)

    print(
        f"DrQ-v2 on {task_id} from pixels: {config.frames:,} frames = {steps:,} agent steps "
        f"(action repeat {config.action_repeat}{f', summed over {config.n_envs} envs' if config.n_envs > 1 else ''}), "
        f"seed {config.seed}, device {model.device}.\n"
        f"Writing to {run_dir} (tensorboard --logdir {run_dir if config.run_dir else config.logdir})",
        flush=True,
    )
    model.learn(steps, callback=CallbackList(callbacks), log_interval=1, progress_bar=config.progress_bar)
    model_path = run_dir / "final_model.zip"
    model.save(model_path)
    if evaluation is not None and evaluation.rows and evaluation.rows[-1]["step"] < model.num_timesteps:
        evaluation.evaluate()  # the budget's last frames were not evaluated yet
    model.logger.close()
    env.close()
    evaluations = evaluation.rows if evaluation is not None else []
    if evaluations:
        last = evaluations[-1]
        print(f"Last evaluation at frame {last['frame']:,}: {last['mean_reward']:.1f} +- {last['std_reward']:.1f}")
    summary = run_summary(config, task_id, model, evaluations, reset_rule, time.time() - start_time)
    write_json_atomically(run_dir / "result.json", summary)  # last: it marks the run as finished
    print(f"Saved {model_path}")
    return TrainResult(run_dir=run_dir, model_path=model_path, evaluations=evaluations, summary=summary)


def training_arguments() -> argparse.ArgumentParser:
    """
    The training flags shared by ``python -m sb3_collapse.train`` and the sweep (``argparse`` parent, no
    ``--help``): every :class:`TrainConfig` setting that is the same for all the runs of a sweep. The run's task,
    seed, folder, device, reset rule and initial weights are flags of the train CLI only (the sweep sets them
    per trial).
    """
    d = TrainConfig()
    p = argparse.ArgumentParser(add_help=False)
    g = p.add_argument_group("training settings")
    g.add_argument("--frames", type=int, default=d.frames, help="training budget, in frames (1.1M: DrQ-v2's easy tasks)")
    g.add_argument("--action-repeat", type=int, default=d.action_repeat, help="frames per agent step")
    g.add_argument("--frame-stack", type=int, default=d.frame_stack, help="stacked RGB frames per observation")
    g.add_argument("--size", type=int, default=d.size, help="image height and width, in pixels")
    g.add_argument("--eval-every-frames", type=int, default=d.eval_every_frames, help="frames between evaluations, also one at frame 0; 0 disables them")
    g.add_argument("--eval-episodes", type=int, default=d.eval_episodes, help="episodes per evaluation (deterministic policy)")
    g.add_argument("--checkpoint-every-frames", type=int, default=d.checkpoint_every_frames, help="frames between intermediate checkpoints; 0: final checkpoint only")
    g.add_argument("--seed-frames", type=int, default=d.seed_frames, help="frames of uniformly random actions before learning starts")
    g.add_argument("--batch-size", type=int, default=d.batch_size, help="minibatch size of each update")
    g.add_argument("--buffer-size", type=int, default=d.buffer_size, help="replay capacity, in transitions (agent steps); default: the run's agent steps, at most 1,000,000")
    g.add_argument("--lr", dest="learning_rate", type=float, default=d.learning_rate, help="Adam learning rate")
    g.add_argument("--n-steps", type=int, default=d.n_steps, help="n-step return length, in agent steps")
    g.add_argument("--feature-dim", type=int, default=d.feature_dim, help="actor and critic trunk size")
    g.add_argument("--hidden-dim", type=int, default=d.hidden_dim, help="hidden units of the actor and Q heads")
    g.add_argument("--stddev-schedule", default=d.stddev_schedule, help="exploration std: a float, linear(init,final,duration) or step_linear(...), durations in agent steps")
    g.add_argument("--stddev-clip", type=float, default=d.stddev_clip, help="clip of the exploration noise in the updates")
    g.add_argument("--collapse-metrics-every-frames", type=int, default=d.collapse_metrics_every_frames, help="frames between two checks of the collapse metrics (TensorBoard collapse/..., collapse_metrics.csv); 0 disables them")
    g.add_argument("--collapse-probe-batch", type=int, default=d.collapse_probe_batch, help="replay observations per collapse-metrics check")
    g.add_argument("--reset-window-frames", type=int, default=d.reset_window_frames, help="the reset rule's window, in frames")
    g.add_argument("--n-envs", type=int, default=d.n_envs, help="training environments (in subprocesses when more than 1); frames and agent steps are summed over them, with one update per 2 transitions as with one")
    g.add_argument("--step-envs-during-updates", action="store_true", help="step the environments (in subprocesses) while the learner updates: the actions of that step come from the weights before the updates (DrQ-v2's reference order)")
    g.add_argument("--compile-update", action="store_true", help="compile the update with torch.compile (CUDA graphs on CUDA); compilation takes tens of seconds at the first update")
    g.add_argument("--verbose", type=int, default=d.verbose, help="1: print SB3's log tables")
    return p


def training_settings(parsed: argparse.Namespace) -> dict[str, Any]:
    """
    :param parsed: arguments parsed by a parser with :func:`training_arguments` as a parent
    :return: the :class:`TrainConfig` fields of :func:`training_arguments`, by field name
    """
    names = [action.dest for action in training_arguments()._actions if action.dest != "help"]
    return {name: getattr(parsed, name) for name in names}


def build_parser() -> argparse.ArgumentParser:
    """The command line of ``python -m sb3_collapse.train``, one flag per :class:`TrainConfig` field."""
    d = TrainConfig()
    p = argparse.ArgumentParser(
        prog="python -m sb3_collapse.train",
        description="Train DrQ-v2 from pixels on a DeepMind Control task, with periodic evaluation, "
        "TensorBoard logs and a final checkpoint. Frames = agent steps x action repeat.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
        parents=[training_arguments()],
    )
    g = p.add_argument_group("this run")
    g.add_argument("--env", default=d.env, help="dm_control task: walker-walk, cartpole-swingup, quadruped-run, ...")
    g.add_argument("--seed", type=int, default=d.seed, help="random seed")
    g.add_argument("--logdir", default=d.logdir, help="parent folder of the run folder <task>_s<seed>")
    g.add_argument("--run-name", default=d.run_name, help="run folder name instead of <task>_s<seed>")
    g.add_argument("--run-dir", default=d.run_dir, help="the exact run folder (new or empty), instead of --logdir/--run-name")
    g.add_argument("--reset-rule", action="store_true", help="reset training from scratch when the agent has not escaped action collapse within each window (the paper's rule)")
    g.add_argument("--init-cnn", default=d.init_cnn, help="start the encoder from this DrQv2 checkpoint (zip); default: random")
    g.add_argument("--init-mlp", default=d.init_mlp, help="start the actor (mlp0..action) from this DrQv2 checkpoint (zip); default: random")
    g.add_argument("--init-critic", default=d.init_critic, help="start the critic from this DrQv2 checkpoint (zip); default: random")
    g.add_argument("--device", default=d.device, help="auto, cpu, cuda, cuda:1, ...")
    g.add_argument("--torch-threads", type=int, default=d.torch_threads, help="threads of torch's CPU operations; default: torch's")
    g.add_argument("--no-progress-bar", dest="progress_bar", action="store_false", help="hide the progress bar")
    return p


def main(argv: list[str] | None = None) -> int:
    """
    :param argv: command-line arguments (``sys.argv[1:]`` when ``None``)
    :return: exit status
    """
    parser = build_parser()
    config = TrainConfig(**vars(parser.parse_args(argv)))
    try:
        config.validate()
    except ValueError as error:
        parser.error(str(error))
    train(config)
    return 0


if __name__ == "__main__":
    sys.exit(main())
