"""
Offline OMP probing of checkpoints: ``python -m sb3_collapse.probe --help``.

    python -m sb3_collapse.probe ckpt.zip                                      # record rollouts, then probe
    python -m sb3_collapse.probe good.zip bad.zip ckpt_*.zip --rollouts walker.npz --out probe/
    python -m sb3_collapse.probe record good.zip --env walker-walk --episodes 20 --out walker.npz
    python -m sb3_collapse.probe sweep runs/sweep --task walker-walk           # Figure 2 and Tables 1-6
    python -m sb3_collapse.probe film good.zip bad.zip --seeds 0 1 --out film/ # Figures 6-7: frames and actions

``run`` (the default when the first argument is not a sub-command) probes; ``record`` records rollouts; ``sweep``
probes the snapshots of a sweep's well- and poorly performing seeds.
Errors in the input print ``error: ...`` and exit with status 2.
"""

from __future__ import annotations

import argparse
import contextlib
import signal
import sys
from collections.abc import Iterator
from typing import Any

from sb3_collapse.errors import ProbeError, cli_message, report_unwritable_outputs
from sb3_collapse.paper import PAPER
from sb3_collapse.probe.film import FILM_FRAMES, FILM_SIZE, STRIP_EVERY_FRAMES, film_to_folder
from sb3_collapse.probe.pipeline import RecordOptions, probe_to_folder, record_to_file
from sb3_collapse.probe.probing import PROBE_LAYERS, ProbeSettings
from sb3_collapse.probe.sweep import DEFAULT_OUT, probe_sweep
from sb3_collapse.protocol import EXIT_INTERRUPTED, SNAPSHOTS_DIR

PROG = "python -m sb3_collapse.probe"
SUBCOMMANDS = ("run", "record", "sweep", "film")


def _recording_arguments(parser: argparse.ArgumentParser, defaults: RecordOptions) -> None:
    group = parser.add_argument_group("recording (settings left out come from the checkpoint, else make_dmc_env's)")
    group.add_argument(
        "--env", default=defaults.env, help="dm_control task, e.g. walker-walk (default: the checkpoint's)"
    )
    group.add_argument("--episodes", type=int, default=defaults.episodes, help="episodes to record")
    group.add_argument(
        "--max-steps",
        type=int,
        default=defaults.max_steps,
        help="cap on agent steps per episode (default: the task's time limit, 500 agent steps for walker at action "
             "repeat 2)",
    )
    group.add_argument(
        "--seed", type=int, default=defaults.seed, help="seed of the env's initial states and the action noise"
    )
    group.add_argument(
        "--stochastic",
        action="store_true",
        help="sample the policy's own exploration instead of its deterministic action",
    )
    group.add_argument(
        "--noise-std",
        type=float,
        default=defaults.noise_std,
        help="std of Gaussian noise added to each action (actions in [-1, 1])",
    )
    group.add_argument("--action-repeat", type=int, help="frames per agent step")
    group.add_argument("--frame-stack", type=int, help="stacked RGB frames per observation")
    group.add_argument("--size", type=int, help="image height and width, in pixels")
    group.add_argument("--camera-id", type=int, help="camera of the renders")


def _probe_arguments(parser: argparse.ArgumentParser, settings: ProbeSettings) -> None:
    parser.add_argument(
        "--layers", nargs="+", help=f"layers to probe (default: those of {' '.join(PROBE_LAYERS)} the model has)"
    )
    parser.add_argument(
        "--max-tau", type=int, default=settings.max_tau, help="largest sparsity; every tau in 1..max-tau is validated"
    )
    parser.add_argument(
        "--split",
        type=float,
        nargs=3,
        default=list(settings.fractions),
        metavar=("TRAIN", "VAL", "TEST"),
        help="fractions of the episodes",
    )
    parser.add_argument("--split-seed", type=int, default=settings.split_seed, help="seed of the episode shuffle")
    parser.add_argument("--batch-size", type=int, default=settings.batch_size, help="observations per forward pass")
    parser.add_argument(
        "--memory-gb",
        type=float,
        default=settings.memory_gb,
        help="activations held at once, in GB; layers share a forward pass while they fit",
    )
    parser.add_argument(
        "--min-std",
        type=float,
        default=settings.min_std,
        help="feature columns of a smaller train std are dropped as constant",
    )
    parser.add_argument("--device", default=settings.device, help="auto (CUDA when available), cpu, cuda, ...")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bars")


def _record_options(args: argparse.Namespace) -> RecordOptions:
    return RecordOptions(
        env=args.env,
        episodes=args.episodes,
        max_steps=args.max_steps,
        seed=args.seed,
        deterministic=not args.stochastic,
        noise_std=args.noise_std,
        action_repeat=args.action_repeat,
        frame_stack=args.frame_stack,
        size=args.size,
        camera_id=args.camera_id,
    )


def build_parser() -> argparse.ArgumentParser:
    """The command line: sub-commands ``run`` (the default) and ``record``."""
    parser = argparse.ArgumentParser(
        prog=PROG,
        description="Linear probing with a sparsity constraint (OMP) of an actor's layers cnn0..cnn4, mlp0..mlp2 "
        "for the true state of DeepMind Control tasks (Section 4.1 of the action-collapse paper). Without a "
        "sub-command, the arguments are those of `run`.",
        epilog=f"examples:\n  {PROG} ckpt.zip\n"
        f"  {PROG} good.zip bad.zip ckpt_*.zip --rollouts walker.npz --out probe/\n"
        f"  {PROG} record good.zip --env walker-walk --episodes 20 --out walker.npz",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = parser.add_subparsers(dest="command", metavar="{run,record,sweep,film}")
    defaults, settings = RecordOptions(), ProbeSettings()

    run = sub.add_parser(
        "run",
        help="probe checkpoints (the default)",
        description="Probe each checkpoint's layers for every state component with OMP; write probe.csv, "
        "summary.json, mse_by_layer.png and (for checkpoints of distinct training steps) mse_over_training.png "
        "into --out, only when the whole run succeeds. Without --rollouts, rollouts of the first checkpoint are "
        "recorded first and saved to <out>/rollouts.npz.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    run.add_argument("checkpoints", nargs="+", help="SB3 zips of DrQv2, TD3, DDPG or SAC")
    run.add_argument("--rollouts", help="rollouts .npz from `record` (default: record them from the first checkpoint)")
    run.add_argument("--out", default="probe", help="output folder")
    run.add_argument("--overwrite", action="store_true", help="replace a previous run's outputs in --out")
    _probe_arguments(run, settings)
    _recording_arguments(run, defaults)

    swp = sub.add_parser(
        "sweep",
        help="Figure 2 and Tables 1-6 of a sweep's task and variant",
        description="Split the finished trials of one task and variant by final return (well-performing >= "
        "--success-return, poorly performing < --failure-return), record rollouts once from the best well-performing "
        f"seed (or read --rollouts), probe every {SNAPSHOTS_DIR}/*.zip of those trials (train with "
        "--snapshots) and write figure2.png (rows well/poor, columns the reward inputs torso velocity, torso "
        "orientation and torso height, then state columns), tables_1_6.csv/.md (std across agents at four training "
        "stages), probe.csv and summary.json.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    swp.add_argument("sweep", help="the sweep folder (--out of python -m sb3_collapse.sweep)")
    swp.add_argument("--task", required=True, help="the task folder, e.g. walker-walk")
    swp.add_argument("--variant", default="drqv2", help="the variant folder")
    swp.add_argument("--out", help=f"output folder (default: <sweep>/{DEFAULT_OUT})")
    swp.add_argument("--rollouts", help="rollouts .npz to probe on (default: record them from the best seed)")
    swp.add_argument(
        "--success-return", type=float, default=PAPER.success_return, help="well-performing: final return >= this"
    )
    swp.add_argument(
        "--failure-return", type=float, default=PAPER.failure_return, help="poorly performing: final return < this"
    )
    swp.add_argument("--overwrite", action="store_true", help="replace a previous run's outputs in --out")
    swp.add_argument(
        "--jobs", type=int, default=1, help="checkpoints probed at once (threads); --memory-gb bounds them all together"
    )
    _probe_arguments(swp, settings)
    _recording_arguments(swp, defaults)

    flm = sub.add_parser(
        "film",
        help="frames of an episode and the actions taken (Figures 6-7)",
        description="Run each agent from a reset (on its own observations) and render a larger view after each "
        "agent step: filmstrip.png (one row per checkpoint and episode seed, every --every-frames frames, the "
        "action values plotted under each strip), one animated GIF per row and actions.csv, into --out.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    flm.add_argument("checkpoints", nargs="+", help="SB3 zips (full models or snapshots)")
    flm.add_argument("--out", default="film", help="output folder")
    flm.add_argument("--frames", type=int, default=FILM_FRAMES, help="environment frames per film")
    flm.add_argument("--size", type=int, default=FILM_SIZE, help="height and width of the film's renders, in pixels")
    flm.add_argument(
        "--every-frames", type=int, default=STRIP_EVERY_FRAMES, help="frames between two pictures of the strip"
    )
    flm.add_argument("--seeds", type=int, nargs="+", default=[0], help="episode seeds (one row each)")
    flm.add_argument("--env", help="dm_control task, when a checkpoint does not say")
    flm.add_argument("--device", default="auto", help="auto, cpu, cuda, ...")
    flm.add_argument("--overwrite", action="store_true", help="replace a previous film in --out")
    flm.add_argument("--no-progress", action="store_true", help="hide the progress bar")

    rec = sub.add_parser(
        "record",
        help="record rollouts of an agent",
        description="Run an agent in its DeepMind Control pixel env and save observations, the named true-state "
        "components, actions, rewards and episode ids to a compressed .npz.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    rec.add_argument("checkpoint", help="SB3 zip of the agent (usually a well-performing one)")
    rec.add_argument("--out", default="rollouts.npz", help="the .npz to write")
    rec.add_argument("--overwrite", action="store_true", help="replace an existing file")
    rec.add_argument("--device", default="auto", help="auto, cpu, cuda, ...")
    rec.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    _recording_arguments(rec, defaults)
    return parser


def _settings(args: argparse.Namespace) -> ProbeSettings:
    return ProbeSettings(
        layers=args.layers,
        max_tau=args.max_tau,
        fractions=tuple(args.split),
        split_seed=args.split_seed,
        batch_size=args.batch_size,
        memory_gb=args.memory_gb,
        min_std=args.min_std,
        device=args.device,
        progress=not args.no_progress,
    )


@report_unwritable_outputs
def main(argv: list[str] | None = None) -> int:
    """
    :param argv: the arguments (``sys.argv[1:]`` when ``None``); a first argument that is not a sub-command
        (nor ``-h``/``--help``) means ``run``
    :return: the exit status: 0, 2 for bad input, 75 when a SIGINT or SIGTERM stopped it (nothing written)
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    if not argv:
        parser.print_help(sys.stderr)
        return 2
    if argv[0] not in (*SUBCOMMANDS, "-h", "--help"):
        argv = ["run", *argv]
    args = parser.parse_args(argv)
    try:
        with _sigterm_as_interrupt():
            _run(args, argv)
    except ProbeError as error:
        print(f"error: {cli_message(error, parser)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as stop:
        name = stop.args[0] if stop.args else "SIGINT"
        print(
            f"\nStopped by {name}: nothing was written under {args.out or 'the output folder'} (the outputs are "
            "staged and "
            f"moved there only when complete); run the same command again (exit status {EXIT_INTERRUPTED}).",
            file=sys.stderr,
        )
        return EXIT_INTERRUPTED
    return 0


@contextlib.contextmanager
def _sigterm_as_interrupt() -> Iterator[None]:
    """While inside, a SIGTERM stops the command as a Ctrl-C does (``KeyboardInterrupt("SIGTERM")``): the staged
    outputs are removed on the way out instead of being left by a process killed where it stood."""

    def stop(_signum: int, _frame: Any) -> None:
        raise KeyboardInterrupt("SIGTERM")

    previous = signal.signal(signal.SIGTERM, stop)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _run(args: argparse.Namespace, argv: list[str]) -> None:
    """Run the sub-command of ``args``."""
    if args.command == "record":
        record_to_file(
            args.checkpoint, args.out, _record_options(args), args.overwrite, args.device, not args.no_progress
        )
    elif args.command == "film":
        film_to_folder(
            args.checkpoints,
            args.out,
            frames=args.frames,
            size=args.size,
            every_frames=args.every_frames,
            seeds=args.seeds,
            env=args.env,
            device=args.device,
            overwrite=args.overwrite,
            progress=not args.no_progress,
        )
    elif args.command == "sweep":
        probe_sweep(
            args.sweep,
            args.task,
            args.variant,
            out=args.out,
            settings=_settings(args),
            rollouts_path=args.rollouts,
            record_options=_record_options(args),
            success_return=args.success_return,
            failure_return=args.failure_return,
            overwrite=args.overwrite,
            command=[PROG, *argv],
            jobs=args.jobs,
        )
    else:
        probe_to_folder(
            args.checkpoints,
            args.out,
            _settings(args),
            rollouts_path=args.rollouts,
            record_options=_record_options(args),
            overwrite=args.overwrite,
            command=[PROG, *argv],
        )


if __name__ == "__main__":
    sys.exit(main())
