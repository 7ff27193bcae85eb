"""Wall time of ``python -m sb3_collapse.report`` on a sweep of the paper's size (Figure 5: 3 tasks x 2 variants x 40
seeds).

Writes a synthetic sweep folder in the trial-folder contract into a temporary folder: per trial an ``eval.csv``
with an evaluation every 10,000 frames up to 1.1M frames (111 rows) and a long-format ``collapse_metrics.csv``
with a check every 10,000 frames and ``--tags`` tags per check (the monitoring logs about 60: 9 layers x 6
metrics, grad norms, action spread), a ``result.json``; then times ``write_report`` (reading, statistics, the
PNG figures and tables) and prints the times, the trial count and the rows read.

    python benchmarks/report_scale.py                      # 240 trials, about 1.6M collapse-metric rows
    python benchmarks/report_scale.py --seeds 5 --tags 10  # quicker
"""

from __future__ import annotations

import argparse
import csv
import json
import platform
import tempfile
import time
from pathlib import Path

import numpy as np

from sb3_collapse.commands.report_pipelines import write_report


def write_sweep(root: Path, tasks: list[str], seeds: int, frames: int, every: int, tags: int) -> int:
    """Write the synthetic sweep; return the number of collapse-metric rows written."""
    rng = np.random.default_rng(0)
    grid = np.arange(0, frames + 1, every)
    tag_names = ["collapse/mlp1/grad_norm"] + [f"collapse/layer{i}/metric" for i in range(tags - 1)]
    rows = 0
    for task in tasks:
        for variant in ("drqv2", "drqv2+reset"):
            for seed in range(seeds):
                folder = root / task / variant / f"seed_{seed}"
                folder.mkdir(parents=True)
                stuck = variant == "drqv2" and rng.random() < 0.3
                start = int(rng.integers(50_000, 300_000))
                returns = 25 + (0 * grid if stuck else 900 / (1 + np.exp(-(grid - start) / 30_000)))
                with (folder / "eval.csv").open("w", newline="") as file:
                    writer = csv.writer(file)
                    writer.writerow(["frame", "step", "mean_reward", "std_reward", "episodes", "wall_time_s"])
                    writer.writerows([f, f // 2, r + rng.normal(0, 5), 3.0, 10, 1.0] for f, r in zip(grid, returns))
                with (folder / "collapse_metrics.csv").open("w", newline="") as file:
                    writer = csv.writer(file)
                    writer.writerow(["frame", "step", "tag", "value"])
                    for frame in grid[1:]:
                        norm = 1e-6 if stuck or frame < start else 0.05
                        writer.writerow([frame, frame // 2, tag_names[0], norm])
                        writer.writerows([frame, frame // 2, tag, rng.random()] for tag in tag_names[1:])
                        rows += tags
                result = {
                    "status": "finished",
                    "task": task,
                    "variant": variant,
                    "seed": seed,
                    "frames": frames,
                    "agent_steps": frames // 2,
                    "final_eval": None,
                    "resets": 0 if variant == "drqv2" else int(rng.integers(0, 3)),
                    "reset_frames": [],
                    "escaped": None if variant == "drqv2" else True,
                    "escape_frame": None,
                    "wall_time_s": 1.0,
                }
                (folder / "result.json").write_text(json.dumps(result))
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", nargs="+", default=["walker-walk", "hopper-stand", "finger-spin"])
    parser.add_argument("--seeds", type=int, default=40)
    parser.add_argument("--frames", type=int, default=1_100_000, help="frames per trial")
    parser.add_argument("--every", type=int, default=10_000, help="frames between evaluations and checks")
    parser.add_argument("--tags", type=int, default=60, help="collapse-metric tags per check")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "runs"
        start = time.perf_counter()
        rows = write_sweep(root, args.tasks, args.seeds, args.frames, args.every, args.tags)
        written = time.perf_counter() - start
        start = time.perf_counter()
        report = write_report(root, reference=True, progress=False)
        elapsed = time.perf_counter() - start
    print(f"machine: {platform.processor() or platform.machine()}, python {platform.python_version()}")
    print(
        f"trials: {len(report.sweep.trials)}, collapse-metric rows: {rows:,} (synthetic sweep written in "
        f"{written:.1f} s)"
    )
    print(f"write_report (read, statistics, figure5.png with reference, tables): {elapsed:.1f} s")


if __name__ == "__main__":
    main()
