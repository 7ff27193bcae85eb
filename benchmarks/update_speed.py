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
  non-fused Adam and the C library's default allocator, as the reference runs, with torch's default flags (cuDNN's
  autotuner off). The batch is sampled from the same kind of buffer (the reference samples in DataLoader workers;
  sampling is included in both timings);
- ``reference-autotune``: ``reference`` with cuDNN's autotuner on (``torch.backends.cudnn.benchmark = True``), as
  facebookresearch/drqv2's ``train.py`` sets it on import, and as ours runs (``sb3_collapse.backends``); the same as
  ``reference`` on the CPU.

Each implementation runs in its own process, on identical networks and synthetic replay data. The processes take
turns (one times ``--updates`` updates while the others wait), ``--rounds`` times, so that the ratios compare
updates timed under the same load on a shared machine; a table gives the median over the rounds of each round's
median, and the median of the per-round ratios to its first implementation. The eager implementations start at once
and are timed first: their table's rows (one per batch size) are printed, each as soon as it is measured, before
``ours-compiled`` starts compiling (up to a minute per batch size); then a second table times all of them again
beside it, at ``--compiled-batch-sizes``. An implementation whose process fails, or is not ready within
``--ready-timeout`` seconds of its start, is reported and left out (exit status 1); an interrupted run (Ctrl-C,
``timeout --signal=INT``) keeps the rows it printed.

Observations are 9x84x84 uint8 (3 stacked RGB frames; ``--size`` for smaller ones), actions 6-d (walker). No
rendering is involved.

    python benchmarks/update_speed.py                  # batch 256 and 32 on the default device
    python benchmarks/update_speed.py --batch-sizes 256 --updates 10 --device cuda
    python benchmarks/update_speed.py --impls reference ours ours-compiled --batch-sizes 32 --rounds 5
    python benchmarks/update_speed.py --device cuda --impls reference reference-autotune ours --batch-sizes 512
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

IMPLS = ("reference", "ours", "ours-compiled", "ours-ieee", "ours-no-prefetch", "reference-autotune")
"""Implementations this script times (``--impls``): ``ours`` and ``ours-compiled`` with TensorFloat-32 on CUDA (the
train command's default, ``sb3_collapse.backends``), ``ours-ieee`` without it (``--no-tf32``), ``ours-no-prefetch``
without drawing the batches ahead (``ReplayPrefetcher(enabled=False)``: ``sb3_collapse.drqv2.prefetch``); the
reference with torch's defaults, as it runs, and ``reference-autotune`` with cuDNN's autotuner on, as DrQ-v2's
``train.py`` runs it."""
COMPILED = "ours-compiled"
"""The implementation that compiles (``torch.compile``): started and timed after the eager ones."""


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


def worker_ignores_sigint() -> None:
    """A worker's first act: SIGINT, blocked since it started (the parent's mask), ignored, then unblocked (a pending
    one is discarded): the process group's SIGINT is for the parent."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})


def worker(impl: str, batch_sizes: list[int], device: str, buffer_size: int, size: int, hidden_dim: int) -> None:
    """
    One implementation in this process: build the model, make two warm-up updates per batch size (the first
    compiles a compiled update) and print their times, then answer each ``<batch> <updates>`` line of stdin with the
    milliseconds of that many updates.
    """
    reference = impl.startswith("reference")
    if not reference:
        configure_backends(tf32=impl != "ours-ieee")
    elif impl == "reference-autotune":
        th.backends.cudnn.benchmark = True  # what facebookresearch/drqv2's train.py sets, and nothing else
    model = build_model(
        device,
        reference=reference,
        buffer_size=buffer_size,
        compile_update=impl == COMPILED,
        size=size,
        hidden_dim=hidden_dim,
    )
    if model.device.type == "cpu":
        tune_cpu_allocator()  # as the train CLI does; SB3_COLLAPSE_TUNE_MALLOC=0 (the reference's worker) declines
    if impl == "ours-no-prefetch":
        model.replay_prefetcher.enabled = False
    if reference:
        updates = {b: (lambda b=b: reference_update(model, model.replay_buffer.sample(b))) for b in batch_sizes}
    else:
        updates = {b: (lambda b=b: model.train(gradient_steps=1, batch_size=b)) for b in batch_sizes}
    warmup = [f"{timed_ms(updates[b], model.device):.3f}" for b in batch_sizes for _ in range(2)]
    print("ready", *warmup, flush=True)
    for line in sys.stdin:
        batch_size, count = map(int, line.split())
        print(" ".join(f"{timed_ms(updates[batch_size], model.device):.3f}" for _ in range(count)), flush=True)


def start_workers(
    impls: list[str], args: argparse.Namespace, sizes: dict[str, list[int]], workers: dict[str, subprocess.Popen]
) -> dict[str, list[float]]:
    """
    Start the processes of ``impls`` at once and wait until each has built its model and made its warm-up updates,
    at most ``args.ready_timeout`` seconds from their start. One that fails or is not ready in time is reported,
    killed and left out.

    :param workers: the running processes by implementation: each one started is added at once (so that the caller
        stops it whatever happens next), each one left out removed
    :return: the warm-up times (ms, two per batch size of ``sizes[impl]``) of the implementations that are ready
    """
    for impl in impls:
        # The reference runs with the default C allocator, as it runs on its own; ours as the train CLI sets it up
        # (sb3_collapse.run.cpu_allocator, on the CPU only).
        env = dict(os.environ, SB3_COLLAPSE_TUNE_MALLOC="0" if impl.startswith("reference") else "1")
        command = [sys.executable, __file__, "--worker", impl, "--device", args.device, "--buffer-size",
                   str(args.buffer_size), "--size", str(args.size), "--hidden-dim", str(args.hidden_dim),
                   "--batch-sizes", *map(str, sizes[impl])]  # fmt: skip
        # The SIGINT that `timeout --signal=INT` sends to the process group is for this process, which stops the
        # workers: SIGINT is blocked while a worker starts (the mask is inherited through exec), and the worker
        # ignores it before it unblocks it (worker_ignores_sigint). This process's handler is never swapped: a SIGINT
        # sent meanwhile stays pending and reaches it once unblocked, never lost.
        signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        try:
            workers[impl] = subprocess.Popen(command, env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        finally:
            signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    deadline = None if args.ready_timeout is None else time.monotonic() + args.ready_timeout
    waiting = {workers[impl].stdout: impl for impl in impls}
    warmups = {}
    while waiting:
        left = None if deadline is None else max(0.0, deadline - time.monotonic())
        ready, _, _ = select.select(list(waiting), [], [], left)
        if not ready:  # the deadline passed
            for impl in waiting.values():
                stop_worker(workers, impl, f"not ready after {args.ready_timeout:g} s")
            break
        for stream in ready:
            impl = waiting.pop(stream)
            reply = stream.readline().split()  # the worker prints one whole line, flushed
            if reply and reply[0] == "ready":
                warmups[impl] = [float(value) for value in reply[1:]]
            else:
                stop_worker(workers, impl, "failed (its error is above)")
    return warmups


def stop_worker(workers: dict[str, subprocess.Popen], impl: str, why: str) -> None:
    """Report that ``impl`` is left out and why, kill its process and remove it from ``workers``."""
    print(f"{impl}: {why}; skipped", flush=True)
    process = workers.pop(impl)
    process.kill()
    process.wait()


def time_table(
    impls: list[str], batch_sizes: list[int], args: argparse.Namespace, workers: dict[str, subprocess.Popen]
) -> dict[int, dict[str, list[float]]]:
    """
    Time ``impls`` taking turns, ``args.rounds`` rounds of ``args.updates`` updates per batch size, and print the
    table: a header, then each batch size's row (flushed) as soon as it is measured. An implementation whose process
    fails is reported and left out (removed from ``workers``).

    :return: per batch size, each implementation's medians (ms, one per round)
    """
    print(table_header(impls), flush=True)
    table = {}
    for batch_size in batch_sizes:
        medians = table[batch_size] = {impl: [] for impl in impls if impl in workers}
        for _ in range(args.rounds):
            for impl in list(medians):
                try:
                    workers[impl].stdin.write(f"{batch_size} {args.updates}\n")
                    workers[impl].stdin.flush()
                    times = [float(value) for value in workers[impl].stdout.readline().split()]
                except (BrokenPipeError, ValueError):
                    times = []
                if not times:
                    stop_worker(workers, impl, f"its process failed at batch {batch_size} (its error is above)")
                    del medians[impl]
                    continue
                medians[impl].append(float(np.median(times)))
        print(table_row(batch_size, impls, medians), flush=True)
    return table


def main() -> int:
    """:return: the exit status: 1 if an implementation failed or was not ready in time, else 0 (interrupted too)"""
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
        worker_ignores_sigint()
        worker(args.worker, args.batch_sizes, args.device, args.buffer_size, args.size, args.hidden_dim)
        return 0
    # SIGINT interrupts this process whatever it inherited: a shell's background job, or a parent that ignored it,
    # passes SIGINT on ignored, and Python then installs no handler (`timeout --signal=INT` would do nothing).
    signal.signal(signal.SIGINT, signal.default_int_handler)

    device = get_device(args.device)
    name = (
        th.cuda.get_device_name(device)
        if device.type == "cuda"
        else f"cpu ({platform.processor() or platform.machine()}), {th.get_num_threads()} threads"
    )
    print(f"device: {name}; torch {th.__version__}; obs 9x{args.size}x{args.size} uint8, 6-d actions, hidden "
          f"{args.hidden_dim}; {args.rounds} rounds of {args.updates} updates per implementation, taking turns",
          flush=True)  # fmt: skip
    impls = list(dict.fromkeys(args.impls))
    sizes = {impl: list(args.batch_sizes) for impl in impls}
    if args.compiled_batch_sizes is not None and COMPILED in sizes:
        sizes[COMPILED] = [b for b in args.batch_sizes if b in args.compiled_batch_sizes]
    eager = [impl for impl in impls if impl != COMPILED]
    compiled = COMPILED in impls and bool(sizes[COMPILED])
    workers: dict[str, subprocess.Popen] = {}
    started: set[str] = set()  # those no longer in workers failed
    try:
        if eager:
            print(f"eager: {', '.join(eager)} (started at once)", flush=True)
            started.update(eager)
            start_workers(eager, args, sizes, workers)
            if workers:
                time_table([impl for impl in eager if impl in workers], args.batch_sizes, args, workers)
        if compiled:
            print(f"{COMPILED} (compiling at batch {', '.join(map(str, sizes[COMPILED]))}), then everything again "
                  "beside it", flush=True)  # fmt: skip
            started.add(COMPILED)
            warmups = start_workers([COMPILED], args, sizes, workers)
            if COMPILED in workers:
                first_updates = ", ".join(
                    f"{ms / 1000:.1f} s at batch {b}" for ms, b in zip(warmups[COMPILED][::2], sizes[COMPILED])
                )
                print(f"{COMPILED} ready; its first update (compiling): {first_updates}", flush=True)
                table = time_table([impl for impl in impls if impl in workers], sizes[COMPILED], args, workers)
                for index, batch_size in enumerate(sizes[COMPILED]):
                    if table[batch_size].get(COMPILED):
                        first, steady = warmups[COMPILED][2 * index], np.median(table[batch_size][COMPILED])
                        print(f"compilation, batch {batch_size}: first update {first / 1000:.1f} s, i.e. "
                              f"~{(first - steady) / 1000:.1f} s more than a compiled update (each batch size is "
                              "compiled for its own shapes)", flush=True)  # fmt: skip
    except KeyboardInterrupt:
        print("interrupted: the rows above are complete", flush=True)
        return 0  # what was measured is printed; a worker still starting is no failure
    finally:
        for process in workers.values():
            process.kill()
            process.wait()
    return int(bool(started - workers.keys()))


def column_widths(impls: list[str]) -> tuple[int, int]:
    """:return: the widths of the millisecond columns and of the ratio columns of a table of ``impls``, the first
    being the baseline (each header fits, with two spaces before it)"""
    ms = max(len(f"{impl} (ms)") for impl in impls) + 2
    ratio = max((len(f"{impl} / {impls[0]}") for impl in impls[1:]), default=0) + 2
    return max(ms, 12), max(ratio, 20)


def table_header(impls: list[str]) -> str:
    """The header of a table of ``impls`` (:func:`table_row`), the first being the baseline."""
    ms, ratio = column_widths(impls)
    return (
        f"{'batch':>6}"
        + "".join(f"{impl + ' (ms)':>{ms}}" for impl in impls)
        + "".join(f"{impl + ' / ' + impls[0]:>{ratio}}" for impl in impls[1:])
    )


def table_row(batch_size: int, impls: list[str], medians: dict[str, list[float]]) -> str:
    """One row of a table of ``impls``: each implementation's median milliseconds, and its median ratio per round to
    the first of ``impls`` (with their range); ``-`` where an implementation did not run at this batch size."""
    ms, ratio = column_widths(impls)
    baseline = impls[0]
    row = f"{batch_size:>6}" + "".join(
        f"{np.median(medians[impl]):>{ms}.1f}" if medians.get(impl) else f"{'-':>{ms}}" for impl in impls
    )
    for impl in impls[1:]:
        if not medians.get(impl) or not medians.get(baseline):
            row += f"{'-':>{ratio}}"
            continue
        rounds = min(len(medians[impl]), len(medians[baseline]))
        per_round = np.array(medians[impl][:rounds]) / np.array(medians[baseline][:rounds])
        row += f"{f'{np.median(per_round):.2f} ({per_round.min():.2f}-{per_round.max():.2f})':>{ratio}}"
    return row


if __name__ == "__main__":
    sys.exit(main())
