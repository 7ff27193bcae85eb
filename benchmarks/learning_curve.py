"""
Evidence that training learns: train one seed of a task at its DrQ-v2 preset with the train CLI
(``python -m sb3_collapse.train``) and draw its evaluation returns over the published DrQ-v2 curves of the task
(``sb3_collapse/report/data/``, :mod:`sb3_collapse.report.reference`).

    python benchmarks/learning_curve.py --env cartpole-balance --frames 60000

Target (cartpole-balance at its preset, one seed, on the CPU): an evaluation of at least 800 by 60,000 frames (the
published mean is 835 at 40k frames and 985 at 60k). The run can span several sittings: stop it (Ctrl-C, SIGTERM:
the train CLI writes a checkpoint and exits 75) and run the same command again to resume it; a finished run is
not trained again, only drawn. Flags this script does not know go to the train CLI unchanged (``--size 48``,
``--hidden-dim 64``...: the figure's title lists them, a run with them is not the preset's). Writes the PNG
(``--out``) and prints every evaluation and whether the target is met.

The scheduled evaluations (frame 0, then every ``eval_every_frames``: eval.csv) are drawn as a line; the saved final
model's evaluation, at the budget's last frame (the result file's ``saved_model_eval``), as a separate marker. Both
count for the target.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.ticker import FuncFormatter

from sb3_collapse.protocol import EVAL_CSV, EXIT_INTERRUPTED, FINISHED, RESULT_JSON
from sb3_collapse.report.reference import REFERENCE_LABEL, load_reference_curves


def parse_args(argv: list[str] | None = None) -> tuple[argparse.Namespace, list[str]]:
    p = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--env", default="cartpole-balance", help="the task (default: %(default)s)")
    p.add_argument("--frames", type=int, default=60_000, help="the run's budget, in frames (default: %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="the run's seed (default: %(default)s)")
    p.add_argument("--run-dir", help="the run folder, to resume (default: runs/learning_curve/<env>_s<seed>)")
    p.add_argument(
        "--checkpoint-every-frames",
        type=int,
        default=10_000,
        help="frames between the run's checkpoints, so that a killed run loses little (default: %(default)s)",
    )
    p.add_argument(
        "--torch-threads", type=int, default=1, help="torch threads of the run (default: %(default)s, a shared CPU)"
    )
    p.add_argument("--target-return", type=float, default=800.0, help="the target's return (default: %(default)s)")
    p.add_argument(
        "--target-frames", type=int, default=60_000, help="the target's frame, at most (default: %(default)s)"
    )
    p.add_argument("--out", help="the PNG (default: <run-dir>/learning_curve.png)")
    p.add_argument("--plot-only", action="store_true", help="draw the run folder as it is, train nothing")
    args, extra = p.parse_known_args(argv)
    if extra and extra[0] == "--":
        extra = extra[1:]
    return args, extra


def train_command(args: argparse.Namespace, run_dir: Path, extra: list[str]) -> list[str]:
    """The train CLI's command line of the run (the same at every sitting, so that it resumes)."""
    return [
        sys.executable, "-m", "sb3_collapse.train", "--env", args.env, "--frames", str(args.frames), "--seed",
        str(args.seed), "--run-dir", str(run_dir), "--checkpoint-every-frames", str(args.checkpoint_every_frames),
        "--torch-threads", str(args.torch_threads), "--no-progress-bar", *extra,
    ]  # fmt: skip


def finished(run_dir: Path) -> bool:
    """Whether the run folder holds a finished run."""
    try:
        return json.loads((run_dir / RESULT_JSON).read_text()).get("status") == FINISHED
    except (OSError, ValueError, AttributeError):
        return False


def read_evaluations(run_dir: Path) -> tuple[np.ndarray, np.ndarray, dict | None]:
    """:return: the scheduled evaluations' frames and returns, and the final model's evaluation (or ``None``)"""
    frames, returns = [], []
    if (run_dir / EVAL_CSV).exists():
        with (run_dir / EVAL_CSV).open(newline="") as file:
            for row in csv.DictReader(file):
                if row.get("mean_reward"):  # a row being written is left out
                    frames.append(int(row["frame"]))
                    returns.append(float(row["mean_reward"]))
    final_model = None
    if finished(run_dir):
        final_model = json.loads((run_dir / RESULT_JSON).read_text()).get("saved_model_eval")
    return np.asarray(frames, dtype=np.int64), np.asarray(returns), final_model


def plot(args: argparse.Namespace, run_dir: Path, extra: list[str], out: Path) -> str:
    """Draw the run's evaluations over the published curves into ``out``; return the target's verdict, one line."""
    frames, returns, final_model = read_evaluations(run_dir)
    fig, ax = plt.subplots(figsize=(7.5, 4.5))
    reference = load_reference_curves(args.env)
    last = max([args.frames, args.target_frames, *(frames.tolist() or [0])])
    if reference is not None:
        keep = reference.frames <= last
        ref_frames, ref_returns = reference.frames[keep], reference.returns[:, keep]
        low, high = np.percentile(ref_returns, [5, 95], axis=0)
        ax.plot(ref_frames, ref_returns.mean(axis=0), "--", marker=".", color="0.35", label=f"{REFERENCE_LABEL}, "
                f"mean of {len(reference.seeds)} seeds")  # fmt: skip
        ax.fill_between(ref_frames, low, high, color="0.35", alpha=0.15, lw=0, label="published, 5th-95th percentile")
    if len(frames):
        ax.plot(frames, returns, "o-", color="C0", label=f"this run, seed {args.seed} (scheduled evaluations)")
    if final_model is not None:
        saved = ([final_model["frame"]], [final_model["mean_reward"]])
        ax.plot(*saved, "D", color="C3", label="this run, saved final model")
    ax.axhline(args.target_return, color="C2", lw=0.8, ls=":")
    ax.axvline(args.target_frames, color="C2", lw=0.8, ls=":", label=f"target: >= {args.target_return:g} by "
               f"{args.target_frames:,} frames")  # fmt: skip
    ax.set_xlim(0, last * 1.02)
    ax.set_xlabel("frames (action repeat included)")
    ax.set_ylabel("evaluation return")
    ax.xaxis.set_major_formatter(FuncFormatter(lambda x, _: f"{x / 1000:g}k" if x else "0"))
    overrides = f"; overrides: {' '.join(extra)}" if extra else " at its DrQ-v2 preset"
    unfinished = "" if finished(run_dir) else f" (unfinished: evaluated up to frame {max(frames, default=0):,})"
    ax.set_title(textwrap.fill(f"{args.env}, {args.frames:,} frames{overrides}{unfinished}", 110), fontsize=8)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    points = list(zip(frames.tolist(), returns.tolist()))
    if final_model is not None:
        points.append((int(final_model["frame"]), float(final_model["mean_reward"])))
    in_time = [(f, r) for f, r in points if f <= args.target_frames]
    if not in_time:
        return f"target (>= {args.target_return:g} by {args.target_frames:,} frames): no evaluation yet"
    best_frame, best = max(in_time, key=lambda point: point[1])
    met = best >= args.target_return
    reached = max(frame for frame, _ in points)
    verdict = "met" if met else ("not met" if reached >= args.target_frames else "not met yet")
    return (
        f"target (>= {args.target_return:g} by {args.target_frames:,} frames): {verdict}; best {best:.1f} at frame "
        f"{best_frame:,} (evaluations up to frame {reached:,})"
    )


def main(argv: list[str] | None = None) -> int:
    args, extra = parse_args(argv)
    run_dir = Path(args.run_dir or f"runs/learning_curve/{args.env}_s{args.seed}")
    out = Path(args.out) if args.out else run_dir / "learning_curve.png"
    status = 0
    if not args.plot_only and not finished(run_dir):
        command = train_command(args, run_dir, extra)
        print("Training (the same command resumes it):", " ".join(command), flush=True)
        env = {**os.environ, "OMP_NUM_THREADS": str(args.torch_threads), "MKL_NUM_THREADS": str(args.torch_threads)}
        process = subprocess.Popen(command, env=env)
        try:
            status = process.wait()
        except KeyboardInterrupt:  # the run got the same SIGINT: let it write its checkpoint and exit (75)
            status = process.wait()
        if status == EXIT_INTERRUPTED:
            print("Interrupted: run the same command again to resume the run.")
        elif status != 0:
            print(f"The run failed (exit status {status}); see {run_dir}.")
    frames, _, _ = read_evaluations(run_dir)
    if len(frames) or finished(run_dir):
        verdict = plot(args, run_dir, extra, out)
        for frame, value in zip(*read_evaluations(run_dir)[:2]):
            print(f"  frame {int(frame):>9,}: {value:8.1f}")
        final_model = read_evaluations(run_dir)[2]
        if final_model is not None:
            print(f"  frame {final_model['frame']:>9,}: {final_model['mean_reward']:8.1f}  (saved final model)")
        print(verdict)
        print(f"Figure: {out}")
    return status


if __name__ == "__main__":
    sys.exit(main())
