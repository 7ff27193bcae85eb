"""
A fabricated but realistic sweep folder in the trial-folder contract of ``python -m sb3_collapse.sweep``, for the
report's tests (and any other test that needs a sweep without training): :func:`write_fake_sweep`. Import it
from a test module of this folder with ``from fabricated_sweep import write_fake_sweep`` (pytest puts the folder
of a test module without ``__init__.py`` on ``sys.path``).
"""

from __future__ import annotations

import csv
import fcntl
import json
import os
import socket
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

EVAL_EVERY = 10_000
"""Frames between evaluations (and between collapse checks) of the fabricated trials."""
FRAMES = 200_000
"""Frames trained by the fabricated drqv2 / drqv2+reset trials."""
TRANSPLANT_FRAMES = 50_000
COLLAPSE_TAGS = tuple(
    f"collapse/{layer}/{metric}"
    for layer in ("mlp0", "mlp1", "mlp2")
    for metric in ("numerical_rank", "input_correlation", "zero_fraction", "dead_fraction", "dead_units", "grad_norm")
) + ("collapse/action_std",)
"""Every tag a fabricated collapse_metrics.csv has: Figure 4's metrics of mlp0..mlp2, consistent with the trial's
collapse state (a collapsed check: rank ~1-3, correlation ~0.95, ~90% zeros and dead units, tiny grad norms), and
others."""


@dataclass
class FakeTrial:
    """
    What was written for one trial folder (the ground truth the tests compare with).

    :param task: task folder
    :param variant: variant folder
    :param seed: seed folder
    :param status: ``"finished"``, ``"running"`` (no result.json, a run.lock of the writing process) or another
        result.json status
    :param frames: evaluation frames written to eval.csv
    :param returns: mean evaluation returns written to eval.csv
    :param grad_frames: frames of the collapse checks written to collapse_metrics.csv
    :param grad_norms: ``collapse/mlp1/grad_norm`` at each check (nan rows are written as ``nan``); ``None`` when
        no collapse_metrics.csv was written
    :param resets: resets in result.json
    :param reset_frames: frames of the resets
    :param escaped: result.json ``escaped`` (``None`` for variants without the reset rule)
    :param escape_frame: frame of the escape
    """

    task: str
    variant: str
    seed: int
    status: str
    frames: np.ndarray
    returns: np.ndarray
    grad_frames: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    grad_norms: np.ndarray | None = None
    resets: int = 0
    reset_frames: list[int] = field(default_factory=list)
    escaped: bool | None = None
    escape_frame: int | None = None

    @property
    def finished(self) -> bool:
        return self.status == "finished"


@dataclass
class FakeSweep:
    """:param path: the sweep folder; :param trials: every trial written"""

    path: Path
    trials: list[FakeTrial]

    def select(self, task: str, variant: str, finished: bool = True) -> list[FakeTrial]:
        return [t for t in self.trials if t.task == task and t.variant == variant and t.finished == finished]


def _learning_curve(rng: np.random.Generator, frames: np.ndarray, start: int | None, top: float = 930.0) -> np.ndarray:
    """~25 while collapsed, then a sigmoid rise to ``top`` from frame ``start`` (``None``: never escapes)."""
    base = 25.0 + rng.normal(0.0, 2.0, len(frames))
    if start is None:
        return np.clip(base, 0.0, None)
    rise = (top - 25.0) / (1.0 + np.exp(-(frames - start - 30_000) / 8_000.0))
    return np.clip(base + rise * (frames >= start) + rng.normal(0.0, 8.0, len(frames)) * (frames >= start), 0, 1000)


def _grad_norms(rng: np.random.Generator, frames: np.ndarray, healthy_from: int | None) -> np.ndarray:
    """~1e-6 while collapsed, ~0.05 after ``healthy_from`` (``None``: always collapsed)."""
    norms = rng.uniform(1e-7, 5e-6, len(frames))
    if healthy_from is not None:
        healthy = frames >= healthy_from
        norms[healthy] = rng.uniform(0.02, 0.08, int(healthy.sum()))
    return norms


def _metric(rng: np.random.Generator, tag: str, mlp1_norm: float) -> float:
    """A value of ``tag`` consistent with the check's mlp1 gradient norm (collapsed below 1e-3)."""
    _, layer, metric = tag.split("/") if tag.count("/") == 2 else ("", "", tag)
    collapsed = not mlp1_norm > 1e-3
    width = 50 if layer == "mlp0" else 1024
    if metric == "numerical_rank":
        return rng.uniform(1.0, 3.0) if collapsed else rng.uniform(0.2, 0.6) * min(width, 100)
    if metric == "input_correlation":
        return rng.uniform(0.9, 0.99) if collapsed else rng.uniform(0.2, 0.4)
    if metric in ("zero_fraction", "dead_fraction"):
        return rng.uniform(0.85, 0.95) if collapsed else rng.uniform(0.4, 0.6)
    if metric == "dead_units":
        return float(round(width * (rng.uniform(0.85, 0.95) if collapsed else rng.uniform(0.1, 0.3))))
    if metric == "grad_norm":
        return mlp1_norm * {"mlp0": 0.5, "mlp2": 2.0}.get(layer, 1.0)  # mlp1's own; nan where it is nan
    return rng.uniform(0.0, 1.0)


_HELD_LOCKS: list = []
"""The run-folder locks of the fabricated running trials, held for the life of the process that wrote them."""


def _write_trial(root: Path, trial: FakeTrial, rng: np.random.Generator, partial_last_line: bool = False) -> None:
    folder = root / trial.task / trial.variant / f"seed_{trial.seed}"
    folder.mkdir(parents=True)
    sources = trial.variant.removeprefix("cnn-").split("_mlp-") if trial.variant.startswith("cnn-") else None
    config = {
        "env": trial.task,
        "frames": int(trial.frames[-1]) if len(trial.frames) else 0,
        "seed": trial.seed,
        "action_repeat": 2,
        "feature_dim": 50,
        "hidden_dim": 1024,
        "eval_every_frames": EVAL_EVERY,
        "variant": trial.variant,
        "transplant": None if sources is None else {"cnn": sources[0], "mlp": sources[1]},
    }
    (folder / "config.json").write_text(json.dumps(config, indent=2))
    with (folder / "eval.csv").open("w", newline="") as file:
        writer = csv.writer(file)
        writer.writerow(["frame", "step", "mean_reward", "std_reward", "episodes", "wall_time_s"])
        for i, (frame, value) in enumerate(zip(trial.frames, trial.returns)):
            writer.writerow([int(frame), int(frame) // 2, repr(float(value)), 3.5, 10, 12.5 * i])
        if partial_last_line:
            file.write(f"{int(trial.frames[-1]) + EVAL_EVERY},{(int(trial.frames[-1]) + EVAL_EVERY) // 2},31.")
    with (folder / "progress.csv").open("w") as file:
        file.write("time/frames,train/actor_loss\n")
        file.writelines(f"{int(frame)},{-rng.uniform(0, 10):.4f}\n" for frame in trial.frames)
    if trial.grad_norms is not None:
        with (folder / "collapse_metrics.csv").open("w", newline="") as file:
            writer = csv.writer(file)
            writer.writerow(["frame", "step", "tag", "value"])
            state = 0.0  # the other metrics follow the last finite grad norm (a nan row is a logging gap)
            for frame, norm in zip(trial.grad_frames, trial.grad_norms):
                state = state if np.isnan(norm) else norm
                for tag in COLLAPSE_TAGS:
                    value = _metric(rng, tag, norm if tag.endswith("/grad_norm") else state)
                    writer.writerow(
                        [int(frame), int(frame) // 2, tag, "nan" if np.isnan(value) else repr(float(value))]
                    )
    if trial.escaped is not None:
        with (folder / "collapse_events.csv").open("w", newline="") as file:
            writer = csv.writer(file)
            writer.writerow(["frame", "step", "event", "resets"])
            for i, frame in enumerate(trial.reset_frames):
                writer.writerow([frame, frame // 2, "reset", i + 1])
            if trial.escape_frame is not None:
                writer.writerow([trial.escape_frame, trial.escape_frame // 2, "escape", trial.resets])
    if trial.status == "running":  # a process trains into it: the writing process stands in, holding the lock
        lock = (folder / "run.lock").open("w")
        fcntl.flock(lock.fileno(), fcntl.LOCK_EX)
        lock.write(f"pid {os.getpid()} on host {socket.gethostname()} since 2026-01-01 00:00:00\n")
        lock.flush()
        _HELD_LOCKS.append(lock)
    else:
        result = {
            "status": trial.status,
            "task": trial.task,
            "variant": trial.variant,
            "seed": trial.seed,
            "frames": int(trial.frames[-1]),
            "agent_steps": int(trial.frames[-1]) // 2,
            "final_eval": {"frame": int(trial.frames[-1]), "mean_reward": float(trial.returns[-1]), "std_reward": 3.5},
            "saved_model_eval": {  # this version's key: eval.csv holds the scheduled evaluations only
                "frame": int(trial.frames[-1]),
                "mean_reward": float(trial.returns[-1]),
                "std_reward": 3.5,
                "episodes": 10,
            },
            "resets": trial.resets,
            "reset_frames": trial.reset_frames,
            "escaped": trial.escaped,
            "escape_frame": trial.escape_frame,
            "wall_time_s": 1234.5,
        }
        (folder / "result.json").write_text(json.dumps(result, indent=2))


def write_fake_sweep(root: str | Path, seed: int = 0) -> FakeSweep:
    """
    Write a sweep folder like ``python -m sb3_collapse.sweep --tasks walker-walk hopper-stand --seeds 5
    --variants drqv2 drqv2+reset`` would (frames 0 to 200,000, an evaluation and a collapse check every 10,000
    frames), plus a transplant grid on walker-walk, with known collapse states:

    - walker-walk / drqv2: seeds 1 and 3 collapsed for good (returns ~25, mlp1 grad norm ~1e-6); seed 4 has nan
      grad-norm rows; seed 5 unfinished (no result.json, eval.csv cut mid-line); seed 6 ``"status": "failed"``.
    - walker-walk / drqv2+reset: seed 0 reset at 60,000 frames and escaped at 110,000; seed 2 reset at 60,000
      and 120,000 and escaped at 170,000; the others escaped without a reset.
    - hopper-stand / drqv2: seed 0 collapsed; seed 2 a middle agent whose last five grad norms have median 9e-4
      (stuck by the median rule); seed 4 without collapse_metrics.csv (unknown).
    - hopper-stand / drqv2+reset: seed 1 reset once; seed 3 with a header-only collapse_metrics.csv (unknown);
      seed 4 evaluated once more, at 210,000 frames (not on the shared grid).
    - walker-walk / cnn-<src>_mlp-<src>: frames 0 to 50,000, every cell but cnn-bad_mlp-blank, 2 seeds (3 for
      good/good, with final returns exactly 900.0 and 899.99); bad MLP never succeeds; blank/blank has one
      unfinished seed too.

    :param root: the sweep folder to create
    :param seed: seed of the noise
    :return: what was written
    """
    root = Path(root)
    rng = np.random.default_rng(seed)
    root.mkdir(parents=True, exist_ok=True)
    (root / "sweep.json").write_text(json.dumps({"tasks": ["walker-walk", "hopper-stand"], "seeds": 5}))
    frames = np.arange(0, FRAMES + 1, EVAL_EVERY, dtype=np.int64)
    checks = frames[1:]
    trials: list[FakeTrial] = []

    def add(task: str, variant: str, seed_: int, start: int | None, top: float = 930.0, **extra: object) -> FakeTrial:
        grid = extra.pop("frames", frames)
        trial = FakeTrial(
            task, variant, seed_, str(extra.pop("status", "finished")), grid, _learning_curve(rng, grid, start, top)
        )
        trial.grad_frames = checks
        trial.grad_norms = _grad_norms(rng, checks, None if start is None else start + 10_000)
        for key, value in extra.items():
            setattr(trial, key, value)
        trials.append(trial)
        return trial

    # walker-walk / drqv2
    for s, start in enumerate([40_000, None, 70_000, None, 50_000]):
        trial = add("walker-walk", "drqv2", s, start)
        if s == 4:
            trial.grad_norms = trial.grad_norms.copy()
            trial.grad_norms[[5, 19]] = np.nan  # a nan in the last five checks: dropped, the median of the rest used
    add("walker-walk", "drqv2", 5, 40_000, status="running", frames=frames[:6])
    add("walker-walk", "drqv2", 6, 40_000, status="failed", frames=frames[:4])
    # walker-walk / drqv2+reset
    resets = {0: ([60_000], 110_000), 2: ([60_000, 120_000], 170_000)}
    for s in range(5):
        reset_frames, escape = resets.get(s, ([], 50_000 + 10_000 * s))
        start = escape - 40_000
        trial = add("walker-walk", "drqv2+reset", s, start, escaped=True, escape_frame=escape)
        trial.resets, trial.reset_frames = len(reset_frames), reset_frames
    # hopper-stand / drqv2
    for s, start in enumerate([None, 60_000, 80_000, 50_000, 90_000]):
        trial = add("hopper-stand", "drqv2", s, start, top=410.0 if s == 2 else 930.0)
        if s == 2:
            trial.grad_norms = trial.grad_norms.copy()
            trial.grad_norms[-5:] = [5e-4, 2e-3, 8e-4, 3e-3, 9e-4]
        if s == 4:
            trial.grad_norms = None
    # hopper-stand / drqv2+reset
    for s in range(5):
        grid = np.append(frames, FRAMES + EVAL_EVERY) if s == 4 else frames
        trial = add("hopper-stand", "drqv2+reset", s, 40_000 + 20_000 * s, escaped=True, frames=grid)
        trial.escape_frame = 40_000 + 20_000 * s + 10_000 * 5
        if s == 1:
            trial.resets, trial.reset_frames = 1, [60_000]
        if s == 3:
            trial.grad_norms = np.zeros(0)
            trial.grad_frames = np.zeros(0, dtype=np.int64)
    # walker-walk transplant grid
    short = frames[frames <= TRANSPLANT_FRAMES]
    finals = {
        ("blank", "blank"): [950.0, 500.0],
        ("blank", "good"): [920.0, 940.0],
        ("blank", "bad"): [26.0, 24.0],
        ("good", "blank"): [930.0, 910.0],
        ("good", "good"): [960.0, 900.0, 899.99],
        ("good", "bad"): [25.0, 27.0],
        ("bad", "good"): [905.0, 300.0],
        ("bad", "bad"): [23.0, 28.0],
    }
    for (cnn, mlp), values in finals.items():
        for s, final in enumerate(values):
            trial = add("walker-walk", f"cnn-{cnn}_mlp-{mlp}", s, 0 if mlp != "bad" else None, frames=short)
            trial.returns = np.linspace(25.0, final, len(short))
            trial.grad_frames, trial.grad_norms = short[1:], _grad_norms(rng, short[1:], None if mlp == "bad" else 0)
    add("walker-walk", "cnn-blank_mlp-blank", 2, 0, status="running", frames=short[:3])

    for trial in trials:
        _write_trial(root, trial, rng, partial_last_line=(trial.status == "running" and trial.variant == "drqv2"))
    return FakeSweep(root, trials)


def write_probe_sweep(root: str | Path, run_dir: str | Path, finals: dict[int, float], seed: int = 0) -> Path:
    """
    A sweep folder ``<root>/walker-walk/drqv2/seed_<k>/`` whose trials have real snapshots: those of a
    trained run (``run_dir``, trained with ``snapshots``), with Gaussian noise added to every encoder and
    actor weight per seed (std 0.05 x the weight's std, so that the seeds' probes differ), and fabricated
    evaluation curves ending at ``finals[k]``; result.json says finished. The run's final model is copied as
    each trial's final model (it records the rollouts).

    :param root: the sweep folder to create
    :param run_dir: a run folder of ``python -m sb3_collapse.train --snapshots``
    :param finals: seed -> final return
    :param seed: seed of the noise
    :return: ``root``
    """
    import shutil

    import torch as th

    from sb3_collapse.protocol import SNAPSHOTS_DIR
    from sb3_collapse.run.snapshots import load_snapshot, save_snapshot

    root, run_dir = Path(root), Path(run_dir)
    sources = sorted((run_dir / SNAPSHOTS_DIR).glob("*.zip"))
    frames = np.array([int(p.stem.split("_")[1]) for p in sources], dtype=np.int64)
    generator = th.Generator().manual_seed(seed)
    for k, final in finals.items():
        returns = np.linspace(25.0, final, len(frames))
        trial = FakeTrial("walker-walk", "drqv2", k, "finished", frames, returns)
        _write_trial(root, trial, np.random.default_rng(seed + k))
        folder = root / "walker-walk" / "drqv2" / f"seed_{k}"
        shutil.copy(run_dir / "final_model.zip", folder / "final_model.zip")
        for source in sources:
            model = load_snapshot(source)
            with th.no_grad():
                for name, parameter in model.policy.named_parameters():
                    if name.startswith(("encoder.", "actor.")) and parameter.numel() > 1:
                        noise = th.randn(parameter.shape, generator=generator) * 0.05 * parameter.std()
                        parameter.add_(noise)
            save_snapshot(model, folder / SNAPSHOTS_DIR / source.name)
    return root


def write_final_models(fake: FakeSweep, task: str = "walker-walk", variant: str = "drqv2") -> dict[int, Path]:
    """
    Give the finished trials of a task and variant of a fabricated sweep a ``final_model.zip`` (an empty zip: the
    transplant donors' pick only needs the file), as a finished sweep has.

    :param fake: :func:`write_fake_sweep`'s sweep
    :param task: the task
    :param variant: the variant
    :return: seed -> the written path
    """
    import zipfile

    paths = {}
    for trial in fake.select(task, variant):
        path = fake.path / task / variant / f"seed_{trial.seed}" / "final_model.zip"
        with zipfile.ZipFile(path, "w"):
            pass
        paths[trial.seed] = path
    return paths
