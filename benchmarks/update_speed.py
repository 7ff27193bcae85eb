"""Milliseconds per DrQ-v2 gradient update, ours (eager and compiled) against the reference implementation's operations.

- ``ours``: ``DrQv2.train(gradient_steps=1)``, i.e. replay sampling, integer-crop augmentation on uint8 straight
  into channels_last, channels_last convolutions with their ReLU fused (oneDNN, CPU), the actor's backward restricted
  to the actor's parameters;
- ``ours-ieee``: ``ours`` with IEEE float32 matmuls and convolutions on CUDA (TensorFloat-32 off; the same as
  ``ours`` on the CPU);
- ``ours-no-prefetch``: ``ours`` with each replay batch drawn when its update is due, on the training thread
  (pageable memory, blocking copies on CUDA; on the CPU the same work as ``ours``, which draws the next batch just
  before the update instead);
- ``ours compiled``: the same with ``compile_update=True`` (``torch.compile`` of the update's forward and backward
  passes; ``mode="reduce-overhead"``, CUDA graphs, on CUDA). Its compilation time is printed (the first update's
  time minus the median);
- ``reference ops``: ``tests.drqv2_reference.reference_update``, the operations of facebookresearch/drqv2's
  ``DrQV2Agent.update``: ``grid_sample`` augmentation on float images, a full backward of the actor loss
  (gradients of the critic computed and discarded), here with NCHW convolutions each followed by its own ReLU,
  non-fused Adam and the C library's default allocator, as the reference runs.
  The batch is sampled from the same kind of buffer (the reference samples in DataLoader workers; sampling
  is included in both timings).

Each implementation runs in its own process, on identical networks and synthetic replay data. The processes take
turns (one times ``--updates`` updates while the others wait), ``--rounds`` times, so that the ratios compare
updates timed under the same load on a shared machine; the table gives the median over the rounds of each round's
median, and the median of the per-round ratios. Its rows (one per batch size) are printed as they are measured; an
implementation whose process fails, or is not ready within ``--ready-timeout`` seconds, is reported and left out, and
an interrupted run (Ctrl-C, ``timeout --signal=INT``) keeps the rows it printed. ``--compiled-batch-sizes`` limits
``ours-compiled`` (a compilation per batch size) to some of the batch sizes.

Observations are 9x84x84 uint8 (3 stacked RGB frames; ``--size`` for smaller ones), actions 6-d (walker). No
rendering is involved.

    python benchmarks/update_speed.py                  # batch 256 and 32 on the default device
    python benchmarks/update_speed.py --batch-sizes 256 --updates 10 --device cuda
    python benchmarks/update_speed.py --impls reference ours ours-compiled --batch-sizes 32 --rounds 5
"""

from __future__ import annotations

import argparse
import os
import platform
import select
import signal
import subprocess
import sys
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3.common.logger import configure
from stable_baselines3.common.utils import get_device

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository root, for tests/ (no install)

from sb3_collapse.backends import configure_backends
from sb3_collapse.drqv2 import DrQv2
from sb3_collapse.run.cpu_allocator import tune_cpu_allocator
from tests.drqv2_reference import reference_update
from tests.random_env import RandomObservationEnv

IMPLS = ("reference", "ours", "ours-compiled", "ours-ieee", "ours-no-prefetch")
"""Implementations this script times (``--impls``): ``ours`` and ``ours-compiled`` with TensorFloat-32 on CUDA (the
train command's default, ``sb3_collapse.backends``), ``ours-ieee`` without it (``--no-tf32``), ``ours-no-prefetch``
without drawing the batches ahead (``ReplayPrefetcher(enabled=False)``: ``sb3_collapse.drqv2.prefetch``); the
reference with torch's defaults, as it runs."""


def build_model(
    device: str,
    reference: bool,
    buffer_size: int,
    seed: int = 0,
    compile_update: bool = False,
    size: int = 84,
    hidden_dim: int = 1024,
) -> DrQv2:
    """A DrQv2 on synthetic 9 x ``size`` x ``size`` uint8 observations and 6-d actions with a filled buffer;
    ``reference``: NCHW, ReLU after each convolution, non-fused Adam."""
    model = DrQv2(
        "CnnPolicy",
        RandomObservationEnv(gym.spaces.Box(0, 255, (9, size, size), np.uint8)),
        buffer_size=buffer_size,
        learning_starts=0,
        device=device,
        seed=seed,
        compile_update=compile_update,
        policy_kwargs=dict(
            hidden_dim=hidden_dim,
            encoder_kwargs=dict(channels_last=not reference, fused_relu=not reference),
            optimizer_kwargs=dict(fused=not reference),
        ),
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


def timed_ms(update, device: th.device) -> float:
    """Milliseconds of one call of ``update`` (synchronizing CUDA before and after)."""
    if device.type == "cuda":
        th.cuda.synchronize()
    start = time.perf_counter()
    update()
    if device.type == "cuda":
        th.cuda.synchronize()
    return (time.perf_counter() - start) * 1000


def worker(impl: str, batch_sizes: list[int], device: str, buffer_size: int, size: int, hidden_dim: int) -> None:
    """
    One implementation in this process: build the model, make two warm-up updates per batch size (the first
    compiles a compiled update) and print their times, then answer each ``<batch> <updates>`` line of stdin with the
    milliseconds of that many updates.
    """
    if impl != "reference":
        configure_backends(tf32=impl != "ours-ieee")
    model = build_model(
        device,
        reference=impl == "reference",
        buffer_size=buffer_size,
        compile_update=impl == "ours-compiled",
        size=size,
        hidden_dim=hidden_dim,
    )
    if model.device.type == "cpu":
        tune_cpu_allocator()  # as the train CLI does; SB3_COLLAPSE_TUNE_MALLOC=0 (the reference's worker) declines
    if impl == "ours-no-prefetch":
        model.replay_prefetcher.enabled = False
    if impl == "reference":
        updates = {b: (lambda b=b: reference_update(model, model.replay_buffer.sample(b))) for b in batch_sizes}
    else:
        updates = {b: (lambda b=b: model.train(gradient_steps=1, batch_size=b)) for b in batch_sizes}
    warmup = [f"{timed_ms(updates[b], model.device):.3f}" for b in batch_sizes for _ in range(2)]
    print("ready", *warmup, flush=True)
    for line in sys.stdin:
        batch_size, count = map(int, line.split())
        print(" ".join(f"{timed_ms(updates[batch_size], model.device):.3f}" for _ in range(count)), flush=True)


def start_worker(impl: str, args: argparse.Namespace, batch_sizes: list[int]) -> tuple[subprocess.Popen, list[float]]:
    """
    Start the process of ``impl`` and wait until it has built its model and made its warm-up updates (at most
    ``args.ready_timeout`` seconds).

    :return: the process and its warm-up times (ms, two per batch size)
    :raise RuntimeError: if it failed or did not get ready in time (the process is killed)
    """
    # The reference runs with the default C allocator, as it runs on its own; ours as the train CLI sets it up
    # (sb3_collapse.run.cpu_allocator, on the CPU only).
    env = dict(os.environ, SB3_COLLAPSE_TUNE_MALLOC="0" if impl == "reference" else "1")
    command = [sys.executable, __file__, "--worker", impl, "--device", args.device, "--buffer-size",
               str(args.buffer_size), "--size", str(args.size), "--hidden-dim", str(args.hidden_dim),
               "--batch-sizes", *map(str, batch_sizes)]  # fmt: skip
    process = subprocess.Popen(command, env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    ready, _, _ = select.select([process.stdout], [], [], args.ready_timeout)
    reply = process.stdout.readline().split() if ready else []
    if not reply or reply[0] != "ready":
        process.kill()
        process.wait()
        why = "not ready" if not ready else "failed (its error is above)"
        raise RuntimeError(f"{why} after {args.ready_timeout:g} s" if not ready else why)
    return process, [float(value) for value in reply[1:]]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--batch-sizes", type=int, nargs="+", default=[256, 32], help="minibatch sizes")
    parser.add_argument(
        "--compiled-batch-sizes",
        type=int,
        nargs="+",
        default=None,
        help="the batch sizes at which ours-compiled runs (each compiles anew); default: all",
    )
    parser.add_argument("--updates", type=int, default=3, help="timed updates per implementation and round")
    parser.add_argument("--rounds", type=int, default=3, help="rounds of turns between the implementations")
    parser.add_argument("--impls", nargs="+", choices=IMPLS, default=list(IMPLS[:2]), help="implementations to time")
    parser.add_argument("--device", default="auto", help="cpu, cuda or auto")
    parser.add_argument("--buffer-size", type=int, default=1000, help="transitions in the synthetic buffer")
    parser.add_argument("--size", type=int, default=84, help="image height and width (DrQ-v2: 84)")
    parser.add_argument("--hidden-dim", type=int, default=1024, help="hidden units of the actor and critic (1024)")
    parser.add_argument(
        "--ready-timeout",
        type=float,
        default=None,
        help="seconds an implementation may take to build and warm up (compile) before it is skipped",
    )
    parser.add_argument("--worker", choices=IMPLS, help=argparse.SUPPRESS)
    args = parser.parse_args()

    if args.worker:
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # the main process stops the workers
        worker(args.worker, args.batch_sizes, args.device, args.buffer_size, args.size, args.hidden_dim)
        return

    device = get_device(args.device)
    name = (
        th.cuda.get_device_name(device)
        if device.type == "cuda"
        else f"cpu ({platform.processor() or platform.machine()}), {th.get_num_threads()} threads"
    )
    print(f"device: {name}; torch {th.__version__}; obs 9x{args.size}x{args.size} uint8, 6-d actions, hidden "
          f"{args.hidden_dim}; {args.rounds} rounds of {args.updates} updates per implementation, taking turns",
          flush=True)  # fmt: skip
    sizes = {impl: list(args.batch_sizes) for impl in args.impls}
    if args.compiled_batch_sizes is not None and "ours-compiled" in sizes:
        sizes["ours-compiled"] = [b for b in args.batch_sizes if b in args.compiled_batch_sizes]
    workers, warmups = {}, {}
    try:
        for impl in args.impls:  # one at a time: building and compiling do not overlap
            if not sizes[impl]:
                continue
            try:
                workers[impl], warmups[impl] = start_worker(impl, args, sizes[impl])
            except RuntimeError as error:
                print(f"{impl}: {error}; skipped", flush=True)
        impls = list(workers)
        baseline = impls[0] if impls else None
        print(f"{'batch':>6} " + " ".join(f"{impl + ' (ms)':>20}" for impl in impls)
              + "".join(f"{impl + ' / ' + baseline:>30}" for impl in impls[1:]), flush=True)  # fmt: skip
        for batch_size in args.batch_sizes:  # one row per batch size, printed once measured
            medians = {impl: [] for impl in workers if batch_size in sizes[impl]}
            for _ in range(args.rounds):
                for impl in list(medians):
                    try:
                        workers[impl].stdin.write(f"{batch_size} {args.updates}\n")
                        workers[impl].stdin.flush()
                        times = [float(value) for value in workers[impl].stdout.readline().split()]
                    except (BrokenPipeError, ValueError):
                        times = []
                    if not times:
                        print(f"{impl}: its process failed at batch {batch_size} (its error is above); skipped",
                              flush=True)  # fmt: skip
                        del medians[impl], workers[impl]
                        continue
                    medians[impl].append(float(np.median(times)))
            print(table_row(batch_size, impls, baseline, medians), flush=True)
            if batch_size in sizes.get("ours-compiled", []) and "ours-compiled" in medians:
                first = warmups["ours-compiled"][2 * sizes["ours-compiled"].index(batch_size)]
                steady = np.median(medians["ours-compiled"])
                print(f"compilation, batch {batch_size}: first update {first / 1000:.1f} s, i.e. "
                      f"~{(first - steady) / 1000:.1f} s more than a compiled update (each batch size is compiled "
                      "for its own shapes)", flush=True)  # fmt: skip
    except KeyboardInterrupt:
        print("interrupted: the rows above are complete", flush=True)
    finally:
        for process in workers.values():
            process.kill()
            process.wait()


def table_row(batch_size: int, impls: list[str], baseline: str | None, medians: dict[str, list[float]]) -> str:
    """One row of the table: each implementation's median milliseconds, and its median ratio to ``baseline`` per
    round (with their range); ``-`` where an implementation did not run at this batch size."""
    row = f"{batch_size:>6} " + " ".join(
        f"{np.median(medians[impl]):>20.1f}" if medians.get(impl) else f"{'-':>20}" for impl in impls
    )
    for impl in impls[1:]:
        if not medians.get(impl) or not medians.get(baseline):
            row += f"{'-':>30}"
            continue
        rounds = min(len(medians[impl]), len(medians[baseline]))
        per_round = np.array(medians[impl][:rounds]) / np.array(medians[baseline][:rounds])
        row += f"{np.median(per_round):>18.2f} ({per_round.min():.2f}-{per_round.max():.2f})"
    return row


if __name__ == "__main__":
    main()
