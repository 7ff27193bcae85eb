"""Bytes per transition and sampling time of FrameStackReplayBuffer against SB3's NStepReplayBuffer.

Both buffers receive the same transitions: 9x84x84 uint8 observations (3 stacked 3x84x84 frames, a reset
repeating the first frame as ``make_dmc_env`` does), 6-d actions (walker), episodes of 500 agent steps
(1000 frames at action repeat 2) ending with a time limit. Frames are random: neither buffer compresses.

- bytes per transition: the ``nbytes`` of each buffer's arrays divided by its capacity; the 550,000-transition
  figure (1.1M frames at action repeat 2) is computed without allocating (SB3's: obs, next_obs, action,
  reward, done, timeout per transition);
- sample time: median milliseconds of ``sample(batch_size)`` (n-step returns, n=3), after warm-up calls,
  with the same random indices for both buffers, whose batches are checked to be identical.

    python benchmarks/replay_buffer.py                       # 20,000 transitions (SB3's buffer: ~2.5 GB)
    python benchmarks/replay_buffer.py --transitions 5000 --samples 20
"""

from __future__ import annotations

import argparse
import gc
import os
import platform
import time

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3.common.buffers import NStepReplayBuffer, ReplayBuffer

from sb3_collapse.drqv2 import FrameStackReplayBuffer
from sb3_collapse.drqv2.replay_buffer import frame_stack_storage_bytes

FRAME_STACK = 3
OBSERVATIONS = gym.spaces.Box(0, 255, (3 * FRAME_STACK, 84, 84), np.uint8)
ACTIONS = gym.spaces.Box(-1.0, 1.0, (6,), np.float32)
FULL_RUN_TRANSITIONS = 550_000


def fill(buffer: ReplayBuffer, transitions: int, episode_length: int, seed: int = 0) -> None:
    """Add ``transitions`` frame-stacked transitions of one env, episodes ending with a time limit."""
    rng = np.random.default_rng(seed)
    obs = None
    for step in range(transitions):
        if step % episode_length == 0:
            obs = np.concatenate([rng.integers(0, 256, (1, 3, 84, 84), dtype=np.uint8)] * FRAME_STACK, axis=1)
        next_obs = np.concatenate([obs[:, 3:], rng.integers(0, 256, (1, 3, 84, 84), dtype=np.uint8)], axis=1)
        truncated = step % episode_length == episode_length - 1
        action = rng.uniform(-1, 1, (1, 6)).astype(np.float32)
        buffer.add(obs, next_obs, action, rng.random(1), np.array([truncated]), [{"TimeLimit.truncated": truncated}])
        obs = next_obs


def sb3_bytes_per_transition() -> int:
    """SB3's buffers: obs and next_obs, action (float32), reward, done, timeout (float32) per transition."""
    return 2 * int(np.prod(OBSERVATIONS.shape)) + 6 * 4 + 3 * 4


def measure(buffer: ReplayBuffer, batch_size: int, samples: int, seed: int) -> tuple[float, list[th.Tensor]]:
    """Median ms of ``sample(batch_size)`` over ``samples`` calls after 3 warm-up calls, and the first batch."""
    np.random.seed(seed)
    first = list(buffer.sample(batch_size))
    for _ in range(2):
        buffer.sample(batch_size)
    times = []
    for _ in range(samples):
        start = time.perf_counter()
        buffer.sample(batch_size)
        times.append((time.perf_counter() - start) * 1000)
    return float(np.median(times)), first


def cpu_name() -> str:
    """The CPU model from /proc/cpuinfo (Linux), else what ``platform`` says."""
    try:
        with open("/proc/cpuinfo") as cpuinfo:
            for line in cpuinfo:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--transitions", type=int, default=20_000, help="transitions in each buffer (its capacity)")
    parser.add_argument("--batch-size", type=int, default=256, help="transitions per sample")
    parser.add_argument("--samples", type=int, default=50, help="timed samples (median reported)")
    parser.add_argument("--episode-length", type=int, default=500, help="agent steps per episode")
    args = parser.parse_args()

    rows = []
    first_batches = []
    for name, cls, kwargs in (
        ("SB3 NStepReplayBuffer", NStepReplayBuffer, {"n_steps": 3, "gamma": 0.99}),
        ("FrameStackReplayBuffer", FrameStackReplayBuffer, {"n_steps": 3, "gamma": 0.99, "frame_stack": FRAME_STACK}),
    ):
        buffer = cls(args.transitions, OBSERVATIONS, ACTIONS, device="cpu", **kwargs)
        start = time.perf_counter()
        fill(buffer, args.transitions, args.episode_length)
        fill_s = time.perf_counter() - start
        if isinstance(buffer, FrameStackReplayBuffer):
            nbytes = buffer.nbytes
            full_run = frame_stack_storage_bytes(FULL_RUN_TRANSITIONS, OBSERVATIONS, ACTIONS, FRAME_STACK)
        else:
            arrays = ("observations", "next_observations", "actions", "rewards", "dones", "timeouts")
            nbytes = sum(getattr(buffer, array).nbytes for array in arrays)
            full_run = FULL_RUN_TRANSITIONS * sb3_bytes_per_transition()
        sample_ms, first = measure(buffer, args.batch_size, args.samples, seed=1)
        first_batches.append(first)
        rows.append((name, nbytes / args.transitions, full_run, sample_ms, fill_s))
        del buffer
        gc.collect()

    identical = all(th.equal(a, b) for a, b in zip(*first_batches))
    print(
        f"machine: {cpu_name()}, {os.cpu_count()} cores; torch {th.__version__}; numpy {np.__version__}; "
        f"obs 9x84x84 uint8, 6-d actions, {args.transitions:,} transitions, episodes of {args.episode_length} "
        f"steps, n-step 3, batch {args.batch_size}, median of {args.samples} samples"
    )
    print(f"{'buffer':<24} {'bytes/transition':>17} {'550k transitions (GB)':>22} {'sample (ms)':>12} {'fill (s)':>9}")
    for name, per_transition, full_run, sample_ms, fill_s in rows:
        print(f"{name:<24} {per_transition:>17,.0f} {full_run / 1e9:>22.2f} {sample_ms:>12.2f} {fill_s:>9.1f}")
    (_, sb3_bytes, _, sb3_ms, _), (_, ours_bytes, _, ours_ms, _) = rows
    print(
        f"FrameStackReplayBuffer: {sb3_bytes / ours_bytes:.2f}x fewer bytes per transition, sampling "
        f"{sb3_ms / ours_ms:.2f}x as fast; same batch for the same seed: {'yes' if identical else 'NO'}"
    )


if __name__ == "__main__":
    main()
