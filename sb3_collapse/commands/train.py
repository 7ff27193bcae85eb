"""Train DrQ-v2 on a DeepMind Control task from pixels: ``python -m sb3_collapse.train --help`` (docs/training.md).
The command line of :func:`sb3_collapse.run.runner.train`, its flags generated from :class:`TrainConfig`'s settings."""

from __future__ import annotations

import argparse
import re

from sb3_collapse import errors
from sb3_collapse.commands.cli import (
    CommandLine,
    add_run_arguments,
    cli_message,
    prog_name,
    report_unwritable_outputs,
    run_command,
    show_settings,
    training_arguments,
)
from sb3_collapse.protocol import CONFIG_JSON, EXIT_INTERRUPTED
from sb3_collapse.run.config import TrainConfig
from sb3_collapse.run.folder import check_run_folder
from sb3_collapse.run.runner import train


def build_parser() -> argparse.ArgumentParser:
    """:return: the command line of ``python -m sb3_collapse.train``, one flag per :class:`TrainConfig` setting"""
    parser = CommandLine(
        prog=prog_name("sb3_collapse.train"),
        description="Train DrQ-v2 from pixels on a DeepMind Control task (frames = agent steps x action repeat). "
        "The DrQ-v2 settings default to the task's preset (DrQ-v2's published config, docs/presets.md); a flag "
        f"overrides it, and {CONFIG_JSON} records every value and where it came from.",
        parents=[training_arguments()],
    )
    run = add_run_arguments(parser)
    run.add_argument(
        "--show-settings", action="store_true", help="print the resolved settings (and where each came from) and exit"
    )
    return parser


@report_unwritable_outputs
def main(argv: list[str] | None = None) -> int:
    """Run the command line with ``argv`` (``sys.argv[1:]`` when ``None``); return the exit status."""

    parser = build_parser()
    arguments = vars(parser.parse_args(argv))
    show = arguments.pop("show_settings")
    try:
        config = TrainConfig(**arguments).resolve()
        config.validate()
        check_run_folder(config)
    except ValueError as error:
        parser.error(cli_message(error, parser))
    if show:
        print("\n".join(show_settings(config)))
        return 0

    def stopped(stop: BaseException) -> str:
        assert isinstance(stop, errors.TrainingInterrupted)  # the one stop caught here
        resume = f"run the same command again to resume (exit status {EXIT_INTERRUPTED})"
        return f"Stopped by {stop.signal_name} after the checkpoint {stop.checkpoint}: {resume}."

    def message(error: BaseException) -> str:  # DrQv2's init_from['cnn'] is the flag --init-cnn here
        return re.sub(r"init_from\['(\w+)'\]", r"--init-\1", cli_message(error, parser))

    return run_command(parser, lambda: run(config), stopped, stops=(errors.TrainingInterrupted,), message=message)


def run(config: TrainConfig) -> int:
    """Train as the resolved ``config`` says; :return: 0 (raised: bad input before training, a failure, a stop)"""
    train(config)
    return 0
