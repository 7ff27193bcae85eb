"""Wall-time overhead of the collapse monitoring (CollapseMetrics + CollapseReset) at the paper's frequency.

Trains the same DrQ-v2 configuration twice in this process, with the same seed, once without and once with
``CollapseMetrics(check_every_frames=10_000, batch_size=512)`` and ``CollapseReset()`` (the paper's rule: a
check every 10,000 frames), and prints both wall times and their ratio. The metrics batch does not change the
training's random streams, so both runs make the same updates; the difference is the cost of the checks
(and noise: repeat with ``--repeats``, which alternates the order). Since run-to-run noise on a shared machine
can exceed the effect by far, the monitored run also reports the wall time spent inside the two callbacks
(every step's ``_on_step``, checks included) as a share of that same run.

It then times, on the trained model, one check in isolation (``CollapseMetrics.compute()`` on a metrics batch of
512 and the rule's gradient-norm read), one ``reset_from_scratch()``, and a gradient update at the paper's
batch size, and prints the overhead projected for DrQ-v2's configuration: one check per
``check_every_frames / action_repeat / train_freq`` updates of batch 256.

With ``--sets``, it instead times, interleaved in one process (a shared machine's load falls on every item alike),
rounds of: one gradient update at the paper's batch, one check of the default ``CollapseMetrics`` and one of the
extended set (``HEALTH_METRICS`` of the actor and the critic), the order rotating each round, on a model whose buffer
holds ``--fill`` random transitions; it prints the medians and each set's projected overhead at DrQ-v2's frequency.

Observations are 9x84x84 uint8 from ``RandomObservationEnv`` (no rendering), actions 6-d, action repeat 2.
The CPU default (batch 32, one update per 8 agent steps, 10,000 frames: one check, at the last step) takes
5-20 minutes on a shared 2-core CPU; it does fewer and cheaper updates between two checks than DrQ-v2 (563 updates of
batch 32, against 2,500 of batch 256), so its ratio is an upper bound of DrQ-v2's.

    python benchmarks/collapse_overhead.py                          # CPU-sized default
    python benchmarks/collapse_overhead.py --sets --rounds 5                  # default against extended set
    python benchmarks/collapse_overhead.py --device cuda --frames 40000 --batch-size 256 --train-freq 2 --repeats 2
"""

from __future__ import annotations

import argparse
import gc
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.utils import get_device

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository root, for tests/ (no install)

from sb3_collapse import CollapseMetrics, CollapseReset, DrQv2
from sb3_collapse.monitoring.health import HEALTH_METRICS
from tests.random_env import RandomObservationEnv


def synchronize(device: th.device) -> None:
    if device.type == "cuda":
        th.cuda.synchronize()


def build_model(args: argparse.Namespace, tensorboard_log: str | None) -> DrQv2:
    """The benchmark's DrQv2 on 9x84x84 random pixels with action repeat 2."""
    env = RandomObservationEnv(gym.spaces.Box(0, 255, (9, 84, 84), np.uint8), episode_length=500, action_repeat=2)
    steps = args.frames // 2
    return DrQv2(
        "CnnPolicy",
        env,
        buffer_size=min(steps, args.buffer_size),
        learning_starts=args.learning_starts,
        batch_size=args.batch_size,
        train_freq=args.train_freq,
        tensorboard_log=tensorboard_log,
        device=args.device,
        seed=args.seed,
    )


def monitoring(args: argparse.Namespace) -> list:
    """CollapseMetrics and CollapseReset at the paper's frequency."""
    return [
        CollapseMetrics(check_every_frames=args.check_every_frames, batch_size=args.metrics_batch),
        CollapseReset(check_every_frames=args.check_every_frames),
    ]


def time_inside(callback: BaseCallback) -> BaseCallback:
    """Accumulate the wall time of the callback's ``_on_step`` (its checks included) in ``callback.seconds``."""
    on_step = callback._on_step
    callback.seconds = 0.0

    def timed_on_step() -> bool:
        start = time.perf_counter()
        try:
            return on_step()
        finally:
            callback.seconds += time.perf_counter() - start

    callback._on_step = timed_on_step
    return callback


def train(args: argparse.Namespace, monitored: bool, folder: str, frames: int) -> tuple[float, float, DrQv2, list]:
    """
    Wall and CPU seconds of ``learn(frames / 2)`` (CPU time of this process, all threads: less sensitive than
    wall time to other jobs on a shared machine), the model, and its callbacks (empty when not monitored; each
    with ``seconds``, its own wall time inside this run).
    """
    model = build_model(args, folder)
    callbacks = [time_inside(callback) for callback in monitoring(args)] if monitored else []
    synchronize(model.device)
    start, start_cpu = time.perf_counter(), time.process_time()
    model.learn(
        frames // 2,
        callback=callbacks or None,
        progress_bar=args.progress,
        tb_log_name="monitored" if monitored else "plain",
    )
    synchronize(model.device)
    return time.perf_counter() - start, time.process_time() - start_cpu, model, callbacks


def median_seconds(function, repeats: int, device: th.device) -> float:
    times = []
    for _ in range(repeats):
        synchronize(device)
        start = time.perf_counter()
        function()
        synchronize(device)
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def compare_sets(args: argparse.Namespace, device: th.device) -> None:
    """``--sets``: an update, a default check and an extended check, interleaved; medians and projected overheads."""
    model = build_model(args, None)
    model.learning_starts = args.fill + 1  # collect only: no update while the buffer fills
    model.learn(args.fill)
    checks = {
        "default": CollapseMetrics(args.check_every_frames, batch_size=args.metrics_batch),
        "extended": CollapseMetrics(
            args.check_every_frames, batch_size=args.metrics_batch, metrics=HEALTH_METRICS, networks=("actor", "critic")
        ),
    }
    for callback in checks.values():
        callback.init_callback(model)
        callback.memory.remember_weights(model, callback.networks)
    model.policy.set_training_mode(True)
    items = {
        "update": lambda: model.train(gradient_steps=1, batch_size=args.paper_batch),
        **{name: callback.compute for name, callback in checks.items()},
    }
    times: dict[str, list[float]] = {name: [] for name in items}
    names = list(items)
    for round_ in range(args.rounds):
        for name in names[round_ % len(names) :] + names[: round_ % len(names)]:
            times[name].append(median_seconds(items[name], 1, device))
    update = statistics.median(times["update"])
    updates_per_check = args.check_every_frames / 2 / 2  # DrQ-v2: action repeat 2, one update per 2 agent steps
    print(f"{args.rounds} interleaved rounds; one update at batch {args.paper_batch}: {1e3 * update:.0f} ms (median)")
    for name, callback in checks.items():
        check = statistics.median(times[name])
        tags = len(callback.compute() or {})
        print(
            f"{name} check ({tags} tags, a batch of {args.metrics_batch}): {check:.2f} s median "
            f"({', '.join(f'{t:.2f}' for t in times[name])}); projected overhead at DrQ-v2's frequency "
            f"({updates_per_check:,.0f} updates per check): {100 * check / (check + updates_per_check * update):.3f}%"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=10_000, help="frames per run (agent steps x 2)")
    parser.add_argument("--batch-size", type=int, default=32, help="minibatch of the updates (DrQ-v2: 256)")
    parser.add_argument("--train-freq", type=int, default=8, help="agent steps per update (DrQ-v2: 2)")
    parser.add_argument("--learning-starts", type=int, default=500, help="agent steps of warm-up")
    parser.add_argument("--buffer-size", type=int, default=100_000, help="replay capacity (at most frames / 2)")
    parser.add_argument("--check-every-frames", type=int, default=10_000, help="frames between checks (paper: 10,000)")
    parser.add_argument("--metrics-batch", type=int, default=512, help="observations of the metrics batch (512)")
    parser.add_argument("--paper-batch", type=int, default=256, help="batch of the projected DrQ-v2 update")
    parser.add_argument("--repeats", type=int, default=1, help="pairs of runs; the order alternates")
    parser.add_argument("--device", default="auto", help="cpu, cuda or auto")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--progress", action="store_true", help="show a progress bar per run")
    parser.add_argument("--sets", action="store_true", help="time the default and the extended checks, interleaved")
    parser.add_argument("--rounds", type=int, default=5, help="--sets: rounds of update, default and extended check")
    parser.add_argument("--fill", type=int, default=2_000, help="--sets: random transitions stored first")
    args = parser.parse_args()
    if args.frames < args.check_every_frames:
        parser.error(f"--frames {args.frames} gives no check every {args.check_every_frames} frames.")

    device = get_device(args.device)
    name = (
        th.cuda.get_device_name(device)
        if device.type == "cuda"
        else f"cpu ({platform.processor() or platform.machine()}), {th.get_num_threads()} threads"
    )
    print(
        f"device: {name}; torch {th.__version__}; 9x84x84 uint8 obs, action repeat 2, {args.frames:,} frames per run, "
        f"batch {args.batch_size}, one update per {args.train_freq} agent steps, check every "
        f"{args.check_every_frames:,} frames"
    )
    if args.sets:
        compare_sets(args, device)
        return

    wall: dict[bool, list[float]] = {False: [], True: []}
    cpu: dict[bool, list[float]] = {False: [], True: []}
    with tempfile.TemporaryDirectory() as folder:
        # Untimed warm-up: one-time costs (kernel selection, first page faults) must not land in the first run.
        train(args, True, folder, frames=min(args.frames, 2 * args.learning_starts + 200))
        for repeat in range(args.repeats):
            order = (False, True) if repeat % 2 == 0 else (True, False)
            for with_monitoring in order:
                seconds, cpu_seconds, model, callbacks = train(args, with_monitoring, folder, args.frames)
                wall[with_monitoring].append(seconds)
                cpu[with_monitoring].append(cpu_seconds)
                label = "with monitoring   " if with_monitoring else "without monitoring"
                checks = ""
                if callbacks:
                    inside = sum(callback.seconds for callback in callbacks)
                    checks = (
                        f", {callbacks[0].n_checks} checks, {callbacks[1].resets} resets; {inside:.2f} s inside the "
                        f"two callbacks = {100 * inside / seconds:.2f}% of this run"
                    )
                print(
                    f"run {repeat + 1} {label}: {seconds:8.1f} s wall, {cpu_seconds:8.1f} s CPU "
                    f"({model._n_updates} updates{checks})",
                    flush=True,
                )
                if with_monitoring and repeat == args.repeats - 1:
                    trained, metrics, rule = model, *callbacks
                else:
                    del model
                    gc.collect()

        for unit, times in (("wall", wall), ("CPU", cpu)):
            ratio = sum(times[True]) / sum(times[False])
            print(
                f"overhead, {unit} time: {sum(times[True]):.1f} s / {sum(times[False]):.1f} s = {ratio:.4f} "
                f"({100 * (ratio - 1):+.2f}%)"
            )

        # One check, a reset and an update, each in isolation, on the trained model and its full buffer.
        check = median_seconds(metrics.compute, 3, device)
        rule_check = median_seconds(rule.read_metric, 3, device)
        trained.policy.set_training_mode(True)
        update = median_seconds(lambda: trained.train(gradient_steps=1, batch_size=args.paper_batch), 3, device)
        reset = median_seconds(trained.reset_from_scratch, 1, device)
    updates_per_check = args.check_every_frames / 2 / 2  # DrQ-v2: action repeat 2, one update per 2 agent steps
    print(
        f"one CollapseMetrics check (a batch of {args.metrics_batch}, every layer): {check:.2f} s; "
        f"one CollapseReset check: {1e3 * rule_check:.3f} ms; reset_from_scratch: {1e3 * reset:.0f} ms"
    )
    print(
        f"one update at batch {args.paper_batch}: {1e3 * update:.0f} ms; DrQ-v2 does {updates_per_check:,.0f} of them "
        f"between two checks: projected overhead {100 * (check + rule_check) / (updates_per_check * update):.3f}% "
        "(updates only, a lower bound of the training time)"
    )


if __name__ == "__main__":
    main()
