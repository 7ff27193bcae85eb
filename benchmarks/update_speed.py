"""Milliseconds per DrQ-v2 gradient update, ours against the reference implementation's operations.

- ``ours``: ``DrQv2.train(gradient_steps=1)``, i.e. replay sampling, integer-crop augmentation on uint8,
  channels_last convolutions, the actor's backward restricted to the actor's parameters;
- ``reference ops``: ``sb3_collapse.drqv2.reference.reference_update``, the operations of facebookresearch/drqv2's
  ``DrQV2Agent.update``: ``grid_sample`` augmentation on float images, a full backward of the actor loss
  (gradients of the critic computed and discarded), here with NCHW convolutions, non-fused Adam and the C
  library's default allocator, as the reference runs.
  The batch is sampled from the same kind of buffer (the reference samples in DataLoader workers; sampling
  is included in both timings).

Each runs in its own process, on identical networks and synthetic replay data.

Observations are 9x84x84 uint8 (3 stacked RGB frames), actions 6-d (walker). No rendering is involved.

    python benchmarks/update_speed.py                  # batch 256 and 32 on the default device
    python benchmarks/update_speed.py --batch-sizes 256 --updates 10 --device cuda
"""

from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys
import time

import numpy as np
import torch as th
from stable_baselines3.common.logger import configure
from stable_baselines3.common.utils import get_device

from sb3_collapse.drqv2 import DrQv2
from sb3_collapse.drqv2.reference import reference_update
from sb3_collapse.envs.synthetic import RandomObservationEnv


def build_model(device: str, reference: bool, buffer_size: int, seed: int = 0) -> DrQv2:
    """A DrQv2 on synthetic 9x84x84 observations with a filled buffer; ``reference``: NCHW, non-fused Adam."""
    model = DrQv2(
        "CnnPolicy",
        RandomObservationEnv(),
        buffer_size=buffer_size,
        learning_starts=0,
        device=device,
        seed=seed,
        policy_kwargs=dict(encoder_kwargs=dict(channels_last=not reference), optimizer_kwargs=dict(fused=not reference)),
    )
    rng = np.random.default_rng(seed)
    obs_shape, action_dim = model.observation_space.shape, model.action_space.shape[0]
    for i in range(buffer_size):
        obs = rng.integers(0, 256, (1, *obs_shape), dtype=np.uint8)
        next_obs = rng.integers(0, 256, (1, *obs_shape), dtype=np.uint8)
        action = rng.uniform(-1, 1, (1, action_dim)).astype(np.float32)
        done = np.array([i % 500 == 499])
        model.replay_buffer.add(obs, next_obs, action, rng.random(1), done, [{"TimeLimit.truncated": bool(done[0])}])
    model.set_logger(configure(folder=None, format_strings=[]))
    model.policy.set_training_mode(True)
    return model


def time_updates(update, updates: int, device: th.device) -> float:
    """Median milliseconds of ``updates`` calls, after two warm-up calls."""
    update()
    update()
    times = []
    for _ in range(updates):
        if device.type == "cuda":
            th.cuda.synchronize()
        start = time.perf_counter()
        update()
        if device.type == "cuda":
            th.cuda.synchronize()
        times.append((time.perf_counter() - start) * 1000)
    return float(np.median(times))


def measure(impl: str, batch_sizes: list[int], updates: int, device: str, buffer_size: int) -> list[float]:
    """Median ms per update of one implementation, for each batch size (in this process)."""
    model = build_model(device, reference=impl == "reference", buffer_size=buffer_size)
    if impl == "ours":
        return [time_updates(lambda b=b: model.train(gradient_steps=1, batch_size=b), updates, model.device) for b in batch_sizes]
    return [time_updates(lambda b=b: reference_update(model, model.replay_buffer.sample(b)), updates, model.device) for b in batch_sizes]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--batch-sizes", type=int, nargs="+", default=[256, 32], help="minibatch sizes")
    parser.add_argument("--updates", type=int, default=5, help="timed updates per measurement (median reported)")
    parser.add_argument("--device", default="auto", help="cpu, cuda or auto")
    parser.add_argument("--buffer-size", type=int, default=1000, help="transitions in the synthetic buffer")
    parser.add_argument("--impl", choices=["ours", "reference"], help=argparse.SUPPRESS)
    args = parser.parse_args()

    if args.impl:  # one implementation, in a child process: print the timings as one line
        print(" ".join(f"{ms:.3f}" for ms in measure(args.impl, args.batch_sizes, args.updates, args.device, args.buffer_size)))
        return

    # Each implementation runs in its own process: the reference with the default C allocator, as it runs
    # on its own; ours as DrQv2 sets it up (sb3_collapse.drqv2.cpu_allocator, on the CPU only).
    timings = {}
    for impl in ("reference", "ours"):
        env = dict(os.environ, SB3_COLLAPSE_TUNE_MALLOC="1" if impl == "ours" else "0")
        command = [sys.executable, __file__, "--impl", impl, "--updates", str(args.updates), "--device", args.device,
                   "--buffer-size", str(args.buffer_size), "--batch-sizes", *map(str, args.batch_sizes)]
        output = subprocess.run(command, env=env, check=True, capture_output=True, text=True).stdout
        timings[impl] = [float(value) for value in output.split()]

    device = get_device(args.device)
    name = th.cuda.get_device_name(device) if device.type == "cuda" else f"cpu ({platform.processor() or platform.machine()}), {th.get_num_threads()} threads"
    print(f"device: {name}; torch {th.__version__}; obs 9x84x84 uint8, 6-d actions; median of {args.updates} updates")
    print(f"{'batch':>6} {'reference ops (ms)':>19} {'ours (ms)':>10} {'ours / reference':>17}")
    for batch_size, ref_ms, ours_ms in zip(args.batch_sizes, timings["reference"], timings["ours"]):
        print(f"{batch_size:>6} {ref_ms:>19.1f} {ours_ms:>10.1f} {ours_ms / ref_ms:>17.2f}")


if __name__ == "__main__":
    main()
