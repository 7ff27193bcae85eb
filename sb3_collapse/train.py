"""Train DrQ-v2 on a DeepMind Control task from pixels: ``python -m sb3_collapse.train --help`` (docs/training.md).
The command line of :func:`sb3_collapse.run.runner.train`, its flags generated from :class:`TrainConfig`'s settings."""

from __future__ import annotations

import argparse
import re
import sys

from sb3_collapse.errors import (
    DivergenceError,
    InputError,
    OutputError,
    TrainingInterrupted,
    cli_message,
    report_unwritable_outputs,
)
from sb3_collapse.protocol import CONFIG_JSON, EXIT_INTERRUPTED
from sb3_collapse.run.config import TrainConfig
from sb3_collapse.run.folder import check_run_folder
from sb3_collapse.run.runner import train
from sb3_collapse.run.settings import CommandLine, add_run_arguments, prog_name, show_settings, training_arguments

CLI_ONLY_FLAGS = ("--show-settings",)
"""The flags of this command line that are not settings of :class:`TrainConfig`."""


def build_parser() -> argparse.ArgumentParser:
    """:return: the command line of ``python -m sb3_collapse.train``, one flag per :class:`TrainConfig` setting"""
    parser = CommandLine(
        prog=prog_name("sb3_collapse.train"),
        description="Train DrQ-v2 from pixels on a DeepMind Control task, with periodic evaluation, "
        "TensorBoard logs and a final checkpoint. Frames = agent steps x action repeat. The DrQ-v2 settings "
        "default to the task's preset (DrQ-v2's published per-task config: sb3_collapse.presets.preset(TASK), "
        f"docs/presets.md); a flag overrides it, and {CONFIG_JSON} records every value and where it came from.",
        parents=[training_arguments()],
    )
    run = add_run_arguments(parser)
    run.add_argument(
        "--show-settings", action="store_true", help="print the resolved settings (and where each came from) and exit"
    )
    return parser


@report_unwritable_outputs
def main(argv: list[str] | None = None) -> int:
    """:return: the exit status of the command line, given its arguments ``argv`` (``None``: ``sys.argv[1:]``)"""
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
    try:
        train(config)
    except InputError as error:  # raised before training: nothing was written
        parser.error(re.sub(r"init_from\['(\w+)'\]", r"--init-\1", cli_message(error, parser)))
    except (OutputError, DivergenceError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 1
    except TrainingInterrupted as error:
        print(
            f"Stopped by {error.signal_name} after the checkpoint {error.checkpoint}: run the same command again to "
            f"resume (exit status {EXIT_INTERRUPTED}).",
            file=sys.stderr,
        )
        return EXIT_INTERRUPTED
    return 0


if __name__ == "__main__":
    sys.exit(main())
