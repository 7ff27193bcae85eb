"""End-to-end training frames/s of ``python -m sb3_collapse.train``, split into environment, update and overhead time.

Each configuration (number of environments x compiled update or not x environment steps overlapped with the updates
or not) is one run of the train CLI, in its own process (``sb3_collapse.train.main``), at the paper's walker-walk
configuration by default: 84x84 pixels, 3 stacked frames, action repeat 2, batch 512, 1-step returns, the 1024-unit
networks, DrQ-v2's one update per 2 transitions; SB3's replay sampling (DrQ-v2's waits for a finished episode, which
short runs do not reach; the cost of an update is the same); no evaluation, no collapse checks, no reset rule. The
run starts with ``--seed-frames`` frames of random actions (the warm-up: rendering only), then trains for
``--frames`` more frames; the CLI's result.json holds the time split of ``DrQv2.learn`` (``sb3_collapse.run.timing``):

- warm-up frames/s: frames of the warm-up / its seconds;
- learning frames/s: frames after the warm-up / their seconds, with the first round of updates counted at the mean
  time of the later ones; ``one-time (s)`` is what the first round took beyond that: ``torch.compile``'s
  compilation with a compiled update, cuDNN's autotuning, first allocations;
- env / update / overhead: shares of the learning seconds spent waiting for the environments, updating (replay
  sampling included), and in the rest (action selection, storing transitions, logging);
- ms/update: mean of the updates after the first round.

``--concurrent K`` starts K identical runs of each configuration at once (seeds 0..K-1) and adds, per configuration,
the sum of their learning frames/s: how many runs one machine (one GPU) serves at once, the sweep's
``--gpus-per-trial``. Throughput stops growing where the device is full; on CUDA the table also gives how many runs
the GPU's memory holds at each run's peak (``torch.cuda.max_memory_reserved``), leaving 10% free.

``--reference DIR`` also times DrQ-v2's own training loop, ``train.py`` of a checkout of facebookresearch/drqv2 at
``DIR`` (not part of this repository; it needs hydra-core, hydra-submitit-launcher, termcolor, OpenCV, torchvision
and tensorboard), first in each repeat, at the same task, warm-up and frames, batch size, n-step and hidden units,
with one environment at 84x84 (its size), no evaluation and no videos. It logs frames/s per training episode (1,000
frames) from its first update on, and its first such episode also counts the time since its start, so its learning
frames/s is the median over the later episodes (``--frames`` of 2,000 or more; ``--seed-frames`` of 4,000 or more,
an episode for each of its replay workers); the script prints it and each configuration's ratio to it (ours /
reference, learning frames/s, one run at once).

The machine's load average is printed before and after: on a shared machine, compare the rows of one run only, and
use ``--repeats`` (the configurations take turns; the table gives medians and ranges, the CSV every run). The CSV
gets each run's row when it ends; interrupted (Ctrl-C, ``timeout --signal=INT``), the script stops its runs and prints
the table of the finished ones. A configuration whose run fails is reported (one line: the configuration and its
error, after the run's error output) and the others go on; the exit status is then 1.

    python benchmarks/train_throughput.py                                       # CPU, a few minutes: small counts
    python benchmarks/train_throughput.py --envs 1 2 --compile off --batch-size 64
    python benchmarks/train_throughput.py --device cuda --seed-frames 4000 --frames 20000 --overlap off on
    python benchmarks/train_throughput.py --device cuda --envs 1 --seed-frames 4000 --frames 3000 --reference ../drqv2
    python benchmarks/train_throughput.py --device cuda --envs 2 --compile off --concurrent 1 2 4 8
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import itertools
import json
import os
import platform
import resource
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REFERENCE_EPISODE_FRAMES = 1000
"""Frames of a DeepMind Control episode (1,000 at every action repeat): the reference logs its frames/s per episode."""
REFERENCE_SIZE = 84
"""Image height and width of the reference's environments (fixed in its ``dmc.py``)."""
REFERENCE_LOADER_WORKERS = 4
"""The reference's replay loader workers (its ``replay_buffer_num_workers``): worker ``i`` samples only the stored
episodes whose index is ``i`` modulo 4, and fails while it has none."""

FIELDS = (
    "repeat", "concurrent", "run", "envs", "compiled", "overlap", "device", "batch_size", "warmup_frames", "warmup_fps",
    "learning_frames", "learning_fps", "env_share", "update_share", "overhead_share", "ms_per_update", "updates",
    "first_round_s", "one_time_s", "peak_rss_mb", "peak_gpu_mb", "wall_s",
)  # fmt: skip
"""Columns of the CSV, in order."""


def train_arguments(
    args: argparse.Namespace, envs: int, compiled: bool, overlap: bool, run_dir: Path, seed: int = 0
) -> list[str]:
    """The train CLI's arguments of one configuration."""
    argv = [
        "--env",
        args.task,
        "--frames",
        str(args.seed_frames + args.frames),
        "--seed-frames",
        str(args.seed_frames),
        "--batch-size",
        str(args.batch_size),
        "--n-steps",
        str(args.n_steps),
        "--hidden-dim",
        str(args.hidden_dim),
        "--size",
        str(args.size),
        "--n-envs",
        str(envs),
        "--eval-every-frames",
        "0",
        "--collapse-metrics-every-frames",
        "0",
        "--buffer-size",
        str(args.buffer_size),
        "--device",
        args.device,
        "--run-dir",
        str(run_dir),
        "--seed",
        str(seed),
        "--no-progress-bar",
        # SB3's sampling: the updates start after the warm-up even before an episode has finished (DrQ-v2's sampling
        # waits for one, 1,000 frames per env on walker); an update costs the same either way.
        "--replay-sampling",
        "sb3",
    ]
    if compiled:
        argv.append("--compile-update")
    if overlap:
        argv.append("--step-envs-during-updates")
    if args.torch_threads is not None:
        argv += ["--torch-threads", str(args.torch_threads)]
    return argv


def child(argv: list[str]) -> None:
    """Run the train CLI in this process, then print its peak memory (RSS, and the GPU's when on CUDA) as JSON."""
    import torch as th

    from sb3_collapse.commands.train import main

    main(argv)
    peak_gpu = th.cuda.max_memory_reserved() / 2**20 if th.cuda.is_available() and th.cuda.is_initialized() else None
    peak_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print("PEAK " + json.dumps({"peak_rss_mb": round(peak_rss, 1), "peak_gpu_mb": peak_gpu}), flush=True)


def measure(
    args: argparse.Namespace, envs: int, compiled: bool, overlap: bool, folder: Path, concurrent: int = 1
) -> list[dict]:
    """
    One configuration: run it ``concurrent`` times at once, read their result.json, return their CSV rows.

    :raise RuntimeError: one line, if a run failed (its error output is written to stderr first; the other runs are
        stopped) or its results could not be read
    """
    folder.mkdir(parents=True, exist_ok=True)
    rows, processes = [], []
    start = time.perf_counter()
    with contextlib.ExitStack() as files:
        for run in range(concurrent):
            run_dir = (
                folder / f"envs{envs}_compiled{int(compiled)}_overlap{int(overlap)}_concurrent{concurrent}_run{run}"
            )
            command = [
                sys.executable,
                __file__,
                "--child",
                *train_arguments(args, envs, compiled, overlap, run_dir, run),
            ]
            # Output to files, not pipes: no child blocks on a full pipe while another one is waited for.
            out, err = (files.enter_context(open(f"{run_dir}.{name}", "w+")) for name in ("out", "err"))
            processes.append((run_dir, command, subprocess.Popen(command, stdout=out, stderr=err, text=True), out, err))
        for run, (run_dir, command, process, out, err) in enumerate(processes):
            try:
                process.wait()
            except KeyboardInterrupt:  # the runs got the same SIGINT: they write a checkpoint, which is not wanted
                for other in processes:
                    other[2].kill()
                    other[2].wait()
                raise
            out.seek(0)
            err.seek(0)
            if process.returncode != 0:
                for other in processes:
                    other[2].kill()
                    other[2].wait()
                raise failure(command, process.returncode, err.read(), f"run {run} ")
            try:
                row = read_run(args, run_dir, out.read(), time.perf_counter() - start)
            except (OSError, ValueError, KeyError, StopIteration) as error:  # no PEAK line, no result.json...
                raise RuntimeError(
                    f"run {run}: its results could not be read ({type(error).__name__}: {error})"
                ) from error
            rows.append(
                {"concurrent": concurrent, "run": run, "envs": envs, "compiled": compiled, "overlap": overlap, **row}
            )
    return rows


def failure(command: list[str], status: int, errors: str, run: str = "") -> RuntimeError:
    """
    Write a failed run's command and the end of its error output to stderr (the log keeps its traceback).

    :param status: its exit status (negative: the signal that killed it)
    :param run: what names the run, before the status, e.g. ``"run 1 "``
    :return: the error to raise, one line: how it ended and the last line of its error output
    """
    print(f"{' '.join(command)}:\n{errors[-3000:]}", file=sys.stderr, flush=True)
    last = next((line.strip() for line in reversed(errors.splitlines()) if line.strip()), "no error output")
    how = f"killed by {signal.Signals(-status).name}" if status < 0 else f"exited with status {status}"
    return RuntimeError(f"{run}{how}: {last}")


def read_run(args: argparse.Namespace, run_dir: Path, stdout: str, wall: float) -> dict:
    """The CSV row of one finished run: its result.json's timings and the peak memory its process printed."""
    peak = json.loads(next(line for line in stdout.splitlines() if line.startswith("PEAK "))[5:])
    summary = json.loads((run_dir / "result.json").read_text())
    timings = summary["timings"]
    config = json.loads((run_dir / "config.json").read_text())
    repeat = config["action_repeat"]
    warmup, learning = timings["warmup"], timings["learning"]
    steady_s = timings["steady_learning_s"]
    first_round_s = timings["first_round_s"] or 0.0
    later_updates = learning["updates"] - timings["first_round_updates"]
    if later_updates > 0:
        mean_update_s = (learning["update_s"] - first_round_s) / later_updates
    else:
        mean_update_s = learning["update_s"] / max(learning["updates"], 1)
    steady_update_s = learning["update_s"] - first_round_s + mean_update_s * timings["first_round_updates"]
    return {
        "device": args.device,
        "batch_size": args.batch_size,
        "warmup_frames": warmup["transitions"] * repeat,
        "warmup_fps": warmup["transitions"] * repeat / warmup["total_s"] if warmup["total_s"] else float("nan"),
        "learning_frames": learning["transitions"] * repeat,
        "learning_fps": learning["transitions"] * repeat / steady_s if steady_s else float("nan"),
        "env_share": learning["env_s"] / steady_s,
        "update_share": steady_update_s / steady_s,
        "overhead_share": 1 - (learning["env_s"] + steady_update_s) / steady_s,
        "ms_per_update": 1000 * mean_update_s,
        "one_time_s": first_round_s - mean_update_s * timings["first_round_updates"],
        "updates": learning["updates"],
        "first_round_s": first_round_s,
        **peak,
        "wall_s": wall,
    }


REFERENCE_LAUNCHER = """
import os, runpy, sys
import numpy as np
directory = sys.argv.pop(1)
sys.path.insert(0, directory)
os.environ["MUJOCO_GL"] = "egl"  # what train.py sets before it imports dm_control, imported here first
import dmc
make = dmc.make
def make_with_float32_actions(*args, **kwargs):
    env = make(*args, **kwargs)
    spec = env.action_spec()
    env.action_spec = lambda: spec.replace(dtype=np.float32)
    return env
dmc.make = make_with_float32_actions
import random, replay_buffer
def seed_worker(worker_id):
    seed = int(np.random.get_state()[1][0]) + worker_id
    np.random.seed(seed)
    random.seed(seed)
replay_buffer._worker_init_fn = seed_worker
sys.argv[0] = directory + "/train.py"
runpy.run_path(sys.argv[0], run_name="__main__")
"""
"""Runs the reference's ``train.py`` (``python -c REFERENCE_LAUNCHER DIR overrides...``) with two changes, without
which it stops at its first step or its first update: its environments declare the float32 actions its agent takes
(with dm_control 1.0, what this project installs, ``dmc.make``'s action spec ends as float64, and its replay storage
asserts that each stored action has its spec's dtype), and its replay loader's workers seed Python's ``random`` with
an ``int`` (Python 3.11 and later refuse the numpy integer it passes)."""


def reference_arguments(args: argparse.Namespace, run_dir: Path) -> list[str]:
    """The hydra overrides of the reference's ``train.py`` that match our configuration: the task, the warm-up and the
    frames (one agent step more, so that the episode ending at the last frame is logged), batch size, n-step, hidden
    units, device; no evaluation (``eval_every_frames=null``), videos, TensorBoard or snapshot."""
    return [
        f"task@_global_={args.task.replace('-', '_')}",  # the config's default list puts the task there
        f"num_seed_frames={args.seed_frames}",
        f"num_train_frames={args.seed_frames + args.frames + 8}",  # one more agent step, at action repeats up to 8
        "eval_every_frames=null",
        "save_video=false",
        "save_train_video=false",
        "use_tb=false",
        "save_snapshot=false",
        f"batch_size={args.batch_size}",
        f"nstep={args.n_steps}",
        f"agent.hidden_dim={args.hidden_dim}",
        f"device={args.device}",
        f"hydra.run.dir={run_dir}",
    ]


def measure_reference(args: argparse.Namespace, folder: Path) -> dict:
    """
    Run the reference's own ``train.py`` (``args.reference``, a checkout of facebookresearch/drqv2) once, in its
    own process, and read the frames/s it logged per training episode (``train.csv``).

    :return: ``learning_fps`` (the median over the episodes after the first logged one, whose time counts everything
        since the start), ``episodes`` (``(frame, fps)`` of each logged episode), ``wall_s``
    :raise RuntimeError: one line, if the run failed (its error output is written to stderr first) or logged no
        episode after its first one
    """
    run_dir = folder / "reference"
    run_dir.mkdir(parents=True, exist_ok=True)
    command = [sys.executable, "-c", REFERENCE_LAUNCHER, str(args.reference), *reference_arguments(args, run_dir)]
    start = time.perf_counter()
    with open(f"{run_dir}.out", "w+") as out, open(f"{run_dir}.err", "w+") as err:
        process = subprocess.Popen(
            command, stdout=out, stderr=err, text=True, env=dict(os.environ, HYDRA_FULL_ERROR="1")
        )
        try:
            process.wait()
        except KeyboardInterrupt:
            process.kill()
            process.wait()
            raise
        err.seek(0)
        errors = err.read()
    wall = time.perf_counter() - start
    if process.returncode != 0:
        raise failure(command, process.returncode, errors)
    try:
        with open(run_dir / "train.csv") as file:
            episodes = [(int(float(row["frame"])), float(row["fps"])) for row in csv.DictReader(file)]
    except (OSError, ValueError, KeyError) as error:
        raise RuntimeError(f"its train.csv could not be read ({type(error).__name__}: {error})") from error
    if len(episodes) < 2:
        raise RuntimeError(f"{len(episodes)} training episode(s) logged, 2 needed (the first counts its start)")
    return {
        "learning_fps": statistics.median(fps for _, fps in episodes[1:]),
        "episodes": episodes,
        "wall_s": wall,
    }


def print_table(rows: list[dict], gpu_memory_mb: float | None = None) -> None:
    """
    One line per configuration: medians over the repeats (frames/s with their range when repeated) and over the
    concurrent runs; with concurrent runs, the sum of their learning frames/s (median over the repeats), and on
    CUDA how many runs the GPU's memory holds at their peak.
    """
    configurations = sorted({(row["envs"], row["compiled"], row["overlap"], row["concurrent"]) for row in rows})
    concurrent = any(row["concurrent"] > 1 for row in rows)
    extra = f" {'runs':>4} {'sum fps':>8}" if concurrent else ""
    extra += f" {'peak GPU MB':>11} {'fit by memory':>13}" if gpu_memory_mb else ""
    print(
        f"{'envs':>4} {'compiled':>8} {'overlap':>7}{extra} {'warm-up fps':>17} {'learning fps':>17} {'env':>5} "
        f"{'update':>6} {'overhead':>8} {'ms/update':>9} {'one-time (s)':>12} {'peak RSS MB':>11}"
    )

    def spread(values: list[float], digits: int) -> str:
        median = statistics.median(values)
        return f"{median:.{digits}f}" + (
            f" ({min(values):.{digits}f}-{max(values):.{digits}f})" if len(values) > 1 else ""
        )

    for configuration in configurations:
        envs, compiled, overlap, runs = configuration
        group = [
            row for row in rows if (row["envs"], row["compiled"], row["overlap"], row["concurrent"]) == configuration
        ]

        def median(key: str, group: list[dict] = group) -> float:
            return statistics.median(row[key] for row in group)

        columns = ""
        if concurrent:
            repeats = sorted({row["repeat"] for row in group})
            sums = [sum(row["learning_fps"] for row in group if row["repeat"] == repeat) for repeat in repeats]
            columns += f" {runs:>4} {statistics.median(sums):>8.2f}"
        if gpu_memory_mb:
            peak = max(row["peak_gpu_mb"] for row in group)
            columns += f" {peak:>11.0f} {int(0.9 * gpu_memory_mb // peak):>13}"
        print(
            f"{envs:>4} {'yes' if compiled else 'no':>8} {'yes' if overlap else 'no':>7}{columns} "
            f"{spread([row['warmup_fps'] for row in group], 1):>17} "
            f"{spread([row['learning_fps'] for row in group], 2):>17} "
            f"{median('env_share'):>5.0%} {median('update_share'):>6.0%} {median('overhead_share'):>8.0%} "
            f"{median('ms_per_update'):>9.0f} {median('one_time_s'):>12.1f} {median('peak_rss_mb'):>11.0f}"
        )


def print_reference_ratios(rows: list[dict], reference_fps: list[float]) -> None:
    """One line: the reference's learning frames/s (median over the repeats) and each configuration's median learning
    frames/s over it (runs alone only: ``concurrent`` 1)."""
    reference = statistics.median(reference_fps)
    configurations = sorted({(row["envs"], row["compiled"], row["overlap"]) for row in rows if row["concurrent"] == 1})
    ratios = []
    for envs, compiled, overlap in configurations:
        fps = statistics.median(
            row["learning_fps"]
            for row in rows
            if (row["envs"], row["compiled"], row["overlap"], row["concurrent"]) == (envs, compiled, overlap, 1)
        )
        name = f"{envs} envs {'compiled' if compiled else 'eager'}{' overlap' if overlap else ''}"
        ratios.append(f"{name} {fps / reference:.2f}x")
    print(f"reference: {reference:.2f} learning frames/s; ours / reference: {'; '.join(ratios)}")


def machine(device: str) -> str:
    """The device in words, with the CPU count and the load average."""
    import torch as th

    if device.startswith("cuda"):
        name = th.cuda.get_device_name(th.device(device))
    else:
        processor = platform.processor() or platform.machine()
        name = f"cpu ({processor}, {os.cpu_count()} cores, {th.get_num_threads()} torch threads)"
    return f"{name}; torch {th.__version__}"


def gpu_memory_mb(device: str) -> float | None:
    """Total memory of the CUDA device, in MB; ``None`` on the CPU."""
    import torch as th

    if not device.startswith("cuda"):
        return None
    return th.cuda.get_device_properties(th.device(device)).total_memory / 2**20


def main() -> int:
    """:return: the exit status: 1 if a configuration failed, else 0 (interrupted too)"""
    if sys.argv[1:2] == ["--child"]:  # one configuration: the rest are the train CLI's arguments
        child(sys.argv[2:])
        return 0
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--envs", type=int, nargs="+", default=[1, 2, 4], help="numbers of training environments")
    parser.add_argument(
        "--compile", nargs="+", choices=["off", "on"], default=["off", "on"], help="compiled update or not"
    )
    parser.add_argument(
        "--overlap",
        nargs="+",
        choices=["off", "on"],
        default=["off"],
        help="environment steps during the updates (--step-envs-during-updates) or not",
    )
    parser.add_argument("--task", default="walker-walk", help="dm_control task")
    parser.add_argument("--seed-frames", type=int, default=200, help="warm-up frames (random actions, no update)")
    parser.add_argument("--frames", type=int, default=48, help="frames timed after the warm-up (4 frames per update)")
    parser.add_argument("--batch-size", type=int, default=512, help="minibatch size (the paper's walker-walk: 512)")
    parser.add_argument("--n-steps", type=int, default=1, help="n-step returns (the paper's walker-walk: 1)")
    parser.add_argument("--hidden-dim", type=int, default=1024, help="hidden units of the actor and the Q heads")
    parser.add_argument("--size", type=int, default=84, help="image height and width")
    parser.add_argument("--buffer-size", type=int, default=100_000, help="replay capacity, in transitions")
    parser.add_argument("--device", default="cpu", help="cpu, cuda, cuda:1...")
    parser.add_argument(
        "--torch-threads", type=int, default=None, help="torch CPU threads of the learner; default: torch's"
    )
    parser.add_argument(
        "--concurrent",
        type=int,
        nargs="+",
        default=[1],
        help="identical runs of each configuration started at once (runs per machine or GPU)",
    )
    parser.add_argument(
        "--repeats",
        type=int,
        default=1,
        help="runs of every configuration, taking turns (the table gives medians, and the ranges)",
    )
    parser.add_argument("--csv", default="runs/train_throughput.csv", help="where to write the table (one row per run)")
    parser.add_argument("--keep-runs", default=None, help="keep the run folders here (default: a temporary folder)")
    parser.add_argument(
        "--reference",
        default=None,
        metavar="DIR",
        help="also time train.py of a facebookresearch/drqv2 checkout at DIR, its own loop (needs --frames >= 2000)",
    )
    args = parser.parse_args()
    signal.signal(signal.SIGINT, signal.default_int_handler)  # interruptible whatever it inherited (update_speed.py)
    if args.reference is not None:
        if not (Path(args.reference) / "train.py").is_file():
            parser.error(f"--reference: no train.py in {args.reference} (a checkout of facebookresearch/drqv2)")
        seed_frames = REFERENCE_LOADER_WORKERS * REFERENCE_EPISODE_FRAMES
        if args.frames < 2 * REFERENCE_EPISODE_FRAMES or args.seed_frames < seed_frames:
            parser.error(
                f"--reference needs --frames >= {2 * REFERENCE_EPISODE_FRAMES} and --seed-frames >= {seed_frames}: "
                f"each of its {REFERENCE_LOADER_WORKERS} replay workers needs a finished episode of its own, and it "
                "logs its frames/s per episode, the first one counting the time since its start"
            )

    print(
        f"{args.task}, {args.size}x{args.size}, batch {args.batch_size}, {args.n_steps}-step, hidden "
        f"{args.hidden_dim}; "
        f"{args.seed_frames} warm-up frames, then {args.frames} frames timed; {machine(args.device)}"
    )
    print(f"load average before: {' '.join(f'{x:.2f}' for x in os.getloadavg())}", flush=True)
    rows, failed, references = [], [], []
    Path(args.csv).parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as temporary, open(args.csv, "w", newline="") as file:
        writer = csv.DictWriter(file, fieldnames=FIELDS)
        writer.writeheader()
        file.flush()
        folder = Path(args.keep_runs or temporary)
        try:
            configurations = list(
                itertools.product(args.concurrent, args.envs, [m == "on" for m in args.compile],
                                  [m == "on" for m in args.overlap])
            )  # fmt: skip
            jobs = itertools.product(range(args.repeats), configurations)
            for index, (repeat, (concurrent, envs, compiled, overlap)) in enumerate(jobs):
                if args.reference is not None and index % len(configurations) == 0:  # first in each repeat
                    try:
                        references.append(measure_reference(args, folder / f"repeat{repeat}"))
                    except RuntimeError as error:  # reported; the configurations go on
                        failed.append("reference")
                        print(f"  failed: reference ({args.reference}/train.py): {error}", flush=True)
                    else:
                        episodes = ", ".join(f"{fps:.1f}" for _, fps in references[-1]["episodes"])
                        print(f"  done: reference ({args.reference}/train.py, 1 env, "
                              f"{REFERENCE_SIZE}x{REFERENCE_SIZE}): "
                              f"{references[-1]['learning_fps']:.2f} frames/s after the warm-up; per episode "
                              f"{episodes} (the first counts the time since its start)", flush=True)  # fmt: skip
                label = f"{envs} envs, compiled {compiled}, overlap {overlap}, {concurrent} at once"
                try:
                    runs = measure(args, envs, compiled, overlap, folder / f"repeat{repeat}", concurrent)
                except RuntimeError as error:  # reported; the other configurations go on
                    failed.append(label)
                    print(f"  failed: {label}: {error}", flush=True)
                    continue
                runs = [{"repeat": repeat, **row} for row in runs]
                rows += runs
                writer.writerows(runs)  # row by row: an interrupted benchmark keeps its runs
                file.flush()
                warmup = " ".join(f"{row['warmup_fps']:.1f}" for row in runs)
                learning = " ".join(f"{row['learning_fps']:.2f}" for row in runs)
                print(f"  done: {label}: {warmup} frames/s in the warm-up, {learning} after it", flush=True)
        except KeyboardInterrupt:
            print(f"interrupted: the table holds the {len(rows)} finished runs", flush=True)
    print(f"load average after: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    if rows:
        print_table(rows, gpu_memory_mb(args.device))
    if references and any(row["concurrent"] == 1 for row in rows):
        print_reference_ratios(rows, [reference["learning_fps"] for reference in references])
        if args.size != REFERENCE_SIZE:
            reference_size = f"{REFERENCE_SIZE}x{REFERENCE_SIZE}"
            print(f"  (ours at {args.size}x{args.size}, the reference at {reference_size}: not the same work)")
    print(f"wrote {args.csv}")
    if failed:
        print(f"failed: {len(failed)} configuration(s), left out of the table: {'; '.join(failed)}")
    return int(bool(failed))


if __name__ == "__main__":
    sys.exit(main())
