"""Environment throughput of ``make_dmc_env``: agent steps and frames per second, with and without rendering.

    python benchmarks/env_speed.py                         # walker-walk, 500 agent steps
    python benchmarks/env_speed.py --task quadruped-run --steps 1000

Frames are simulator control steps: one agent step is ``action_repeat`` frames, rendered once (84x84).
"CPU cores" is the process's CPU time (all its threads) over the wall time: above 1, the renderer runs on several
cores (Mesa's llvmpipe uses a thread per core by default), which bounds what more environments can add on the
same cores.
"""

from __future__ import annotations

import argparse
import os
import resource
import time

import numpy as np

from sb3_collapse.envs import make_dmc_env


def steps_per_second(task: str, steps: int, obs_type: str, action_repeat: int, seed: int = 0) -> tuple[float, float]:
    """
    :return: agent steps per second with uniformly random actions, episode resets included, and the CPU cores the
        process used meanwhile (CPU seconds of all its threads per second)
    """
    env = make_dmc_env(task, seed=seed, action_repeat=action_repeat, obs_type=obs_type)
    env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    low, high = env.action_space.low, env.action_space.high
    start, cpu_start = time.perf_counter(), _cpu_seconds()
    for _ in range(steps):
        _, _, terminated, truncated, _ = env.step(rng.uniform(low, high).astype(np.float32))
        if terminated or truncated:
            env.reset()
    elapsed, cpu = time.perf_counter() - start, _cpu_seconds() - cpu_start
    env.close()
    return steps / elapsed, cpu / elapsed


def _cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--task", default="walker-walk", help="dm_control task, e.g. walker-walk")
    parser.add_argument("--steps", type=int, default=500, help="agent steps to time")
    parser.add_argument("--action-repeat", type=int, default=2, help="frames per agent step")
    args = parser.parse_args()

    rows = [
        (obs_type, steps_per_second(args.task, args.steps, obs_type, args.action_repeat))
        for obs_type in ("pixels", "state")
    ]
    print(
        f"task {args.task}, action repeat {args.action_repeat}, {args.steps} agent steps, "
        f"MUJOCO_GL={os.environ.get('MUJOCO_GL')}"
    )
    print(f"{'observations':>12} {'agent steps/s':>14} {'frames/s':>9} {'ms per agent step':>18} {'CPU cores':>10}")
    for obs_type, (sps, cores) in rows:
        print(f"{obs_type:>12} {sps:>14.1f} {sps * args.action_repeat:>9.1f} {1000 / sps:>18.2f} {cores:>10.2f}")


if __name__ == "__main__":
    main()
