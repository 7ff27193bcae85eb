"""The command line ``python -m sb3_collapse.probe`` (``run``, ``record``, ``sweep``, ``film``, ``health``):
docs/probe.md."""

from __future__ import annotations

import argparse
import inspect
import signal
import sys
from dataclasses import dataclass
from typing import Any

from sb3_collapse.commands.cli import (
    CommandLine,
    add_setting_arguments,
    check_arguments,
    cli_message,
    parsed_values,
    prog_name,
    report_unwritable_outputs,
    run_command,
)
from sb3_collapse.commands.probe_pipelines import (
    film_to_folder,
    health_to_folder,
    probe_sweep,
    probe_to_folder,
    record_to_file,
)
from sb3_collapse.errors import InputError
from sb3_collapse.paper import PAPER
from sb3_collapse.probe.film import FILM_FRAMES, FILM_SIZE
from sb3_collapse.probe.health import HealthSettings
from sb3_collapse.probe.probing import ProbeSettings, check_fractions
from sb3_collapse.probe.rollouts import RecordOptions
from sb3_collapse.protocol import EXIT_INTERRUPTED, SWEEP_PROBE_DIR
from sb3_collapse.report.film import STRIP_EVERY_FRAMES
from sb3_collapse.run.config import setting
from sb3_collapse.run.signals import stop_signal_handlers


@dataclass
class RunFlags:
    """
    probe checkpoints (the default)

    Probe each checkpoint's layers for every state component with OMP; write probe.csv, summary.json,
    mse_by_layer.png and (for checkpoints of distinct training steps) mse_over_training.png into --out, only when the
    whole run succeeds. Without --rollouts, rollouts of the first checkpoint are recorded first and saved to
    <out>/rollouts.npz.
    """

    checkpoints: tuple[str, ...] | None = setting(
        help="SB3 zips of DrQv2, TD3, DDPG or SAC", unit=None, flag="checkpoints", nargs="+"
    )
    rollouts: str | None = setting(
        help="rollouts .npz from `record`; default: record them from the first checkpoint", unit=None
    )
    out: str = setting("probe", help="output folder", unit=None)
    overwrite: bool = setting(False, help="replace a previous run's outputs in `out`", unit=None)


@dataclass
class SweepFlags:
    """
    Figure 2 and Tables 1-6 of a sweep's task and variant

    Split the finished trials of one task and variant by final return (well-performing >= --success-return, poorly
    performing < --failure-return), record rollouts once from the best well-performing seed (or read --rollouts),
    probe every snapshot of those trials (train with --snapshots) and write figure2.png (rows well/poor, columns the
    reward inputs torso velocity, torso orientation and torso height, then state columns), tables_1_6.csv/.md (std
    across agents at four training stages), probe.csv and summary.json.
    """

    sweep: str | None = setting(
        help="the sweep folder (--out of python -m sb3_collapse.sweep)", unit=None, flag="sweep"
    )
    task: str | None = setting(help="the task folder, e.g. walker-walk", unit=None, required=True)
    variant: str = setting("drqv2", help="the variant folder", unit=None)
    out: str | None = setting(help=f"output folder; default: <sweep>/{SWEEP_PROBE_DIR}", unit=None)
    rollouts: str | None = setting(help="rollouts .npz to probe on; default: record them from the best seed", unit=None)
    success_return: float = setting(PAPER.success_return, help="well-performing: final return >= this", unit=None)
    failure_return: float = setting(PAPER.failure_return, help="poorly performing: final return < this", unit=None)
    overwrite: bool = setting(False, help="replace a previous run's outputs in `out`", unit=None)
    jobs: int = setting(
        1, help="checkpoints probed at once (threads); --memory-gb bounds them all together", unit=None, minimum=1
    )


@dataclass
class FilmFlags:
    """
    frames of an episode and the actions taken (Figures 6-7)

    Run each agent from a reset (on its own observations) and render a larger view after each agent step:
    filmstrip.png (one row per checkpoint and episode seed, every --every-frames frames, the action values plotted
    under each strip), one animated GIF per row and actions.csv, into --out.
    """

    checkpoints: tuple[str, ...] | None = setting(
        help="SB3 zips (full models or snapshots)", unit=None, flag="checkpoints", nargs="+"
    )
    out: str = setting("film", help="output folder", unit=None)
    frames: int = setting(FILM_FRAMES, help="environment frames per film", unit="frames", minimum=1)
    size: int = setting(FILM_SIZE, help="height and width of the film's renders", unit="pixels", minimum=16)
    every_frames: int = setting(
        STRIP_EVERY_FRAMES, help="frames between two pictures of the strip", unit="frames", minimum=1
    )
    seeds: tuple[int, ...] = setting((0,), help="episode seeds (one row each)", unit=None, nargs="+")
    env: str | None = setting(help="dm_control task, when a checkpoint does not say", unit=None)
    device: str = setting("auto", help="auto, cpu, cuda, ...", unit=None)
    overwrite: bool = setting(False, help="replace a previous film in `out`", unit=None)
    progress: bool = setting(True, help="show the progress bar", unit=None)


@dataclass
class RecordFlags:
    """
    record rollouts of an agent

    Run an agent in its DeepMind Control pixel env and save observations, the named true-state components, actions,
    rewards and episode ids to a compressed .npz.
    """

    checkpoint: str | None = setting(
        help="SB3 zip of the agent (usually a well-performing one)", unit=None, flag="checkpoint"
    )
    out: str = setting("rollouts.npz", help="the .npz to write", unit=None)
    overwrite: bool = setting(False, help="replace an existing file", unit=None)
    device: str = setting("auto", help="auto, cpu, cuda, ...", unit=None)
    progress: bool = setting(True, help="show the progress bar", unit=None)


@dataclass
class HealthFlags:
    """
    network health of checkpoints: the metrics of CollapseMetrics (but the gradient norm), offline

    Measure each checkpoint's actor and critic (rank, correlation, dead and dormant units, stable and effective rank,
    active fraction, feature and weight norms, Q values, action spread; docs/monitoring.md) on one observation set:
    --rollouts, else the first checkpoint's own rollouts (its DeepMind Control pixel env, or with --env a gymnasium
    id for a model of vector observations). Checkpoints of distinct training steps (a run folder: its snapshots) are
    a time series: weight change from the first, units dormant at this checkpoint and the one before. Write
    health.csv, health_<network>.png and health.json into --out, only when every checkpoint was measured.
    """

    checkpoints: tuple[str, ...] | None = setting(
        help="SB3 zips of DrQv2, TD3, DDPG or SAC (CNN or MLP policies), snapshots, or run folders (their snapshots)",
        unit=None,
        flag="checkpoints",
        nargs="+",
    )
    rollouts: str | None = setting(
        help="rollouts .npz from `record`; default: record them from the first checkpoint", unit=None
    )
    out: str = setting("health", help="output folder", unit=None)
    overwrite: bool = setting(False, help="replace a previous run's outputs in `out`", unit=None)


COMMANDS: dict[str, tuple[type, ...]] = {
    "run": (RunFlags, ProbeSettings, RecordOptions),
    "record": (RecordFlags, RecordOptions),
    "sweep": (SweepFlags, ProbeSettings, RecordOptions),
    "film": (FilmFlags,),
    "health": (HealthFlags, HealthSettings, RecordOptions),
}
"""Each sub-command's flags, by the dataclasses that declare them (its parser, its help, its range checks and its
table in ``docs/probe.md`` are generated from them); the first one's docstring is its help line and description."""

RECORDING_TITLE = "recording (settings left out come from the checkpoint, else make_dmc_env's)"


def build_parser() -> argparse.ArgumentParser:
    """The command line: sub-commands ``run`` (the default), ``sweep``, ``film`` and ``record``, their flags
    generated from :data:`COMMANDS`."""
    prog = prog_name("sb3_collapse.probe")
    parser = CommandLine(
        prog=prog,
        description="Linear probing with a sparsity constraint (OMP) of an actor's layers cnn0..cnn4, mlp0..mlp2 "
        "for the true state of DeepMind Control tasks (Section 4.1 of the action-collapse paper). Without a "
        "sub-command, the arguments are those of `run`.",
        epilog=f"examples:\n  {prog} ckpt.zip\n"
        f"  {prog} good.zip bad.zip ckpt_*.zip --rollouts walker.npz --out probe/\n"
        f"  {prog} record good.zip --env walker-walk --episodes 20 --out walker.npz",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = parser.add_subparsers(dest="command", metavar="{" + ",".join(COMMANDS) + "}")
    for command, declarations in COMMANDS.items():
        help_line, description = inspect.getdoc(declarations[0]).split("\n\n", 1)
        subparser = sub.add_parser(command, help=help_line, description=description)
        for declaration in declarations:
            group = subparser.add_argument_group(RECORDING_TITLE) if declaration is RecordOptions else subparser
            add_setting_arguments(group, declaration=declaration)
    return parser


@report_unwritable_outputs
def main(argv: list[str] | None = None) -> int:
    """
    :param argv: the arguments (``sys.argv[1:]`` when ``None``; without a sub-command: ``run``)
    :return: the exit status: 0, 1 when the simulator could not step, 2 for bad input, 75 when a SIGINT or SIGTERM
        stopped it (nothing written)
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    if not argv:
        parser.print_help(sys.stderr)
        return 2
    if argv[0] not in (*COMMANDS, "-h", "--help"):
        argv = ["run", *argv]
    args = parser.parse_args(argv)
    subparsers = next(action for action in parser._actions if isinstance(action, argparse._SubParsersAction))
    command_parser = subparsers.choices[args.command]
    if ProbeSettings in COMMANDS[args.command]:  # the split as a whole first: every --split error in the same words
        try:
            check_fractions(args.fractions)
        except InputError as error:
            command_parser.error(cli_message(error, command_parser))
    check_arguments(command_parser, args, *COMMANDS[args.command])

    def stopped(stop: BaseException) -> str:
        name, out = stop.args[0] if stop.args else "SIGINT", args.out or "the output folder"
        return (
            f"\nStopped by {name}: nothing was written under {out} (the outputs are staged and moved there only when "
            f"complete); run the same command again (exit status {EXIT_INTERRUPTED})."
        )

    return run_command(parser, lambda: _run(args, [parser.prog, *argv]), stopped, help_pointer=False)


def _interrupt(signum: int, _frame: Any) -> None:
    """A SIGTERM or SIGINT stops the command as a Ctrl-C does (``KeyboardInterrupt("SIGTERM")``)."""
    raise KeyboardInterrupt(signal.Signals(signum).name)


def _run(args: argparse.Namespace, command: list[str]) -> int:
    """Run the sub-command of ``args`` (``command``: the command line, recorded in the summary); :return: 0"""
    with stop_signal_handlers(_interrupt):  # the staged outputs are removed on the way out
        _run_sub_command(args, command)
    return 0


def _run_sub_command(args: argparse.Namespace, command: list[str]) -> None:
    """The sub-command of ``args``, run."""
    record = RecordOptions(**parsed_values(args, RecordOptions)) if RecordOptions in COMMANDS[args.command] else None
    if args.command == "record":
        record_to_file(args.checkpoint, args.out, record, args.overwrite, args.device, args.progress)
    elif args.command == "film":
        film_to_folder(args.checkpoints, **parsed_values(args, FilmFlags, "checkpoints"))
    elif args.command == "health":
        health = HealthSettings(**parsed_values(args, HealthSettings))
        health_to_folder(args.checkpoints, args.out, health, args.rollouts, record, args.overwrite, command)
    else:
        probe = dict(settings=ProbeSettings(**parsed_values(args, ProbeSettings)), record_options=record)
        probe["command"] = command
        if args.command == "sweep":
            probe_sweep(
                args.sweep, rollouts_path=args.rollouts, **probe, **parsed_values(args, SweepFlags, "sweep", "rollouts")
            )
        else:
            probe_to_folder(args.checkpoints, args.out, rollouts_path=args.rollouts, overwrite=args.overwrite, **probe)
