"""Cost of a layer transplant (``DrQv2(..., init_from=...)``) at DrQ-v2's full size.

Saves one DrQv2 source (9x84x84 uint8 ``RandomObservationEnv`` observations, 6-d actions, hidden 1024, feature
50 by default) to a temporary folder, then times, ``--repeats`` times each, the two steps the transplant adds to
building a model: reading the source zip (``load_sources``: policy weights and settings only) and checking plus
copying the groups into a freshly built policy (``transplant``). It also times a blank build and a build with
``init_from`` for reference (the build is dominated by the networks' initialization and is noisy on a shared
machine). Prints the minimum and median of each, in seconds.

    python benchmarks/transplant_cost.py
    python benchmarks/transplant_cost.py --size 64 --hidden-dim 256 --repeats 3 --groups cnn mlp
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch as th

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository root, for tests/ (no install)

from sb3_collapse import DrQv2
from sb3_collapse.drqv2.transplant import TRANSPLANT_GROUPS, check_init_from, load_sources, transplant
from tests.random_env import RandomObservationEnv


def timed(function: Callable[[], object], repeats: int) -> tuple[float, float]:
    """``(min, median)`` wall time of ``repeats`` calls, in seconds."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
    return min(times), statistics.median(times)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", type=int, default=84, help="image height and width, in pixels")
    parser.add_argument("--frame-stack", type=int, default=3, help="stacked RGB frames per observation")
    parser.add_argument("--hidden-dim", type=int, default=1024, help="hidden units of the actor and the Q heads")
    parser.add_argument("--feature-dim", type=int, default=50, help="actor and critic trunk size")
    parser.add_argument("--groups", nargs="+", choices=list(TRANSPLANT_GROUPS), default=list(TRANSPLANT_GROUPS))
    parser.add_argument("--repeats", type=int, default=5, help="timed calls of each step")
    parser.add_argument("--device", default="cpu", help="device of the built models")
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error("--repeats must be >= 1")

    space = gym.spaces.Box(0, 255, (3 * args.frame_stack, args.size, args.size), np.uint8)
    kwargs = {
        "buffer_size": 100,
        "policy_kwargs": {"hidden_dim": args.hidden_dim, "feature_dim": args.feature_dim},
        "device": args.device,
    }

    def build(**extra: object) -> DrQv2:
        return DrQv2("CnnPolicy", RandomObservationEnv(space, action_repeat=2), seed=1, **kwargs, **extra)

    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "source.zip"
        build().save(path)
        init_from = {group: str(path) for group in args.groups}
        resolved = check_init_from(init_from)
        sources = load_sources(resolved)
        target = build()
        rows = {
            "read the source zip (load_sources)": timed(lambda: load_sources(resolved), args.repeats),
            f"check + copy {'+'.join(args.groups)} (transplant)": timed(
                lambda: transplant(target.policy, sources), args.repeats
            ),
            "build a blank model": timed(build, args.repeats),
            "build with init_from": timed(lambda: build(init_from=init_from), args.repeats),
        }
        size_mb = os.path.getsize(path) / 1e6
    print(
        f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, torch {th.__version__}, "
        f"device {args.device}"
    )
    print(f"source: {space.shape} pixels, hidden {args.hidden_dim}, feature {args.feature_dim}, zip {size_mb:.1f} MB")
    for name, (fastest, median) in rows.items():
        print(f"{name:45s} min {fastest:7.3f} s   median {median:7.3f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
