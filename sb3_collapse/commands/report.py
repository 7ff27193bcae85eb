"""``python -m sb3_collapse.report``: the report of a sweep folder or of one run folder (``--help``); errors in the
input print ``error: ...`` and exit with status 2."""

from __future__ import annotations

import argparse
from dataclasses import dataclass

from sb3_collapse.commands.cli import (
    CommandLine,
    add_setting_arguments,
    check_arguments,
    parsed_values,
    prog_name,
    report_unwritable_outputs,
    run_command,
    setting_flags,
)
from sb3_collapse.commands.report_pipelines import FixedInputSettings, write_report, write_run_report
from sb3_collapse.protocol import RESULT_JSON
from sb3_collapse.report.collapse_figure import is_run_folder
from sb3_collapse.report.headline import BASELINE_VARIANT
from sb3_collapse.report.pipeline import REPORT_FOLDER
from sb3_collapse.report.statistics import ReportSettings
from sb3_collapse.report.tables import grid_markdown
from sb3_collapse.run.config import RUN, declared, setting


@declared
@dataclass
class ReportFlags:
    """The flags of ``python -m sb3_collapse.report`` besides :class:`ReportSettings` and :class:`FixedInputSettings`
    (:func:`write_report`'s own)."""

    sweep: str | None = setting(cli=RUN, flag="sweep")
    """the sweep folder (--out of python -m sb3_collapse.sweep), or one run folder of the train CLI"""
    out: str | None = setting(cli=RUN, help=f"output folder; default: <sweep>/{REPORT_FOLDER}")
    reference: bool = setting(False, cli=RUN)
    """overlay the published DrQ-v2 curves (dashed mean, hatched band)"""
    include_unfinished: bool = setting(False, cli=RUN)
    """draw the partial curves of unfinished trials, dotted (never used in the table)"""
    tasks: tuple[str, ...] | None = setting(cli=RUN, nargs="+")
    """only these task folders; default: all"""
    variants: tuple[str, ...] | None = setting(cli=RUN, nargs="+")
    """only these variant folders; default: all"""
    rollouts_per_variant: bool = setting(False, cli=RUN)
    """Figures 4, 8, 9: each variant on its own variant's rollouts instead (other observations per variant); not
    allowed with --rollouts-variant"""
    overwrite: bool = setting(False, cli=RUN)
    """replace the files of a previous report in the output folder"""
    progress: bool = setting(True, cli=RUN)
    """show a progress bar"""


COMMANDS: dict[str, tuple[type, ...]] = {"": (ReportFlags, ReportSettings, FixedInputSettings)}
"""The flags, by the dataclasses that declare them (the parser, the help, the range checks and the table in
``docs/sweeps.md`` are generated from it)."""
RUN_FOLDER_FLAGS = ("sweep", "out", "overwrite", "progress", "rollouts", "fixed_samples", "device", "correlation")
RUN_FOLDER_FLAGS += ("train_episodes",)
"""The settings whose flags apply to one run folder (:func:`write_run_report`); the others are a sweep's."""


def build_parser() -> argparse.ArgumentParser:
    """The command line, its flags generated from :data:`COMMANDS`."""
    parser = CommandLine(
        prog=prog_name("sb3_collapse.report"),
        description=(
            "The figures and tables of a sweep folder <sweep>/<task>/<variant>/seed_<k>/: Figure 5 and the table, "
            "Figures 4, 8, 9 (collapse metrics of a picked well-performing, middle and poorly performing seed), "
            f"Figure 3 and Table 7 (cnn-<src>_mlp-<src> variants), and report/index.html; only finished trials "
            f"({RESULT_JSON}) enter the statistics. Given one run folder of the train CLI: its Figure 4 and index.html "
            "(with --rollouts, its snapshots on that fixed set too)."
        ),
    )
    one_reading = ("rollouts_variant", "rollouts_per_variant")  # every variant on one variant's rollouts, or its own
    for declaration in COMMANDS[""]:
        add_setting_arguments(parser, [n for n in setting_flags(declaration) if n not in one_reading], declaration)
    either = parser.add_mutually_exclusive_group()
    add_setting_arguments(either, ["rollouts_variant"], FixedInputSettings)
    add_setting_arguments(either, ["rollouts_per_variant"], ReportFlags)
    parser.set_defaults(rollouts_variant=None)  # given or not: argparse refuses a given one with its other reading
    return parser


@report_unwritable_outputs
def main(argv: list[str] | None = None) -> int:
    """:return: 0 on success, 2 on bad input (after ``error: ...`` on stderr); ``argv``: ``sys.argv[1:]`` when None"""
    parser = build_parser()
    args = parser.parse_args(argv)
    check_arguments(parser, args, *COMMANDS[""])
    settings = ReportSettings(**parsed_values(args, ReportSettings))
    collapse = FixedInputSettings(**parsed_values(args, FixedInputSettings))
    if is_run_folder(args.sweep):
        check_run_folder_flags(parser, args)
    collapse.rollouts_variant = None if args.rollouts_per_variant else args.rollouts_variant or BASELINE_VARIANT
    return run_command(parser, lambda: run(args, settings, collapse), help_pointer=False)


def check_run_folder_flags(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Refuse, in one line naming them, the flags given with a run folder that only a sweep folder uses."""
    flags = {name: flag for declaration in COMMANDS[""] for name, flag in setting_flags(declaration).items()}
    given = [
        flag
        for name, flag in flags.items()
        if name not in RUN_FOLDER_FLAGS and getattr(args, name) != parser.get_default(name)
    ]
    if given:
        used = ", ".join(flags[name] for name in RUN_FOLDER_FLAGS if flags[name].startswith("-"))  # not the folder
        run_folder = f"{args.sweep} is one run folder, whose report takes {used}"
        parser.error(f"{', '.join(given)}: for a sweep folder; {run_folder}.")


def run(args: argparse.Namespace, settings: ReportSettings, collapse: FixedInputSettings) -> int:
    """Write the report of the parsed ``args``; :return: 0"""
    if is_run_folder(args.sweep):
        trial, files = write_run_report(args.sweep, args.out, args.overwrite, collapse, args.progress)
        print(f"{trial.task} / {trial.variant} / seed {trial.seed} ({trial.status}): {len(trial.frames)} evaluations")
    else:
        flags = parsed_values(args, ReportFlags, "sweep", "out", "overwrite", "rollouts_per_variant")
        report = write_report(
            args.sweep, args.out, args.overwrite, settings=settings, collapse_settings=collapse, **flags
        )
        print(report.markdown)
        if report.grid:
            print(grid_markdown(report.grid, settings.success_return))
        files = report.files
    print("wrote " + ", ".join(str(path) for path in files))
    return 0
