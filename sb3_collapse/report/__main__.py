"""``python -m sb3_collapse.report``: the report of a sweep folder or of one run folder (``--help``); errors in the
input print ``error: ...`` and exit with status 2."""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass, fields

from sb3_collapse.errors import InputError, cli_message, report_unwritable_outputs
from sb3_collapse.monitoring import CORRELATION_READINGS
from sb3_collapse.protocol import COLLAPSE_METRICS_CSV, RESULT_JSON
from sb3_collapse.report.collapse_figure import FixedInputSettings, is_run_folder
from sb3_collapse.report.headline import BASELINE_VARIANT
from sb3_collapse.report.pipeline import REPORT_FOLDER, write_report, write_run_report
from sb3_collapse.report.statistics import ReportSettings
from sb3_collapse.report.tables import grid_markdown
from sb3_collapse.run.config import setting
from sb3_collapse.run.settings import CommandLine, add_setting_arguments, check_arguments, prog_name

_REPORT, _FIXED = ReportSettings(), FixedInputSettings()


@dataclass
class ReportFlags:
    """The flags of ``python -m sb3_collapse.report`` (:class:`ReportSettings`, :class:`FixedInputSettings` and
    :func:`write_report`'s own)."""

    sweep: str | None = setting(
        help="the sweep folder (--out of python -m sb3_collapse.sweep), or one run folder of the train CLI",
        unit=None,
        flag="sweep",
    )
    out: str | None = setting(help=f"output folder; default: <sweep>/{REPORT_FOLDER}", unit=None)
    reference: bool = setting(False, help="overlay the published DrQ-v2 curves (dashed mean, hatched band)", unit=None)
    include_unfinished: bool = setting(
        False, help="draw the partial curves of unfinished trials, dotted (never used in the table)", unit=None
    )
    tasks: tuple[str, ...] | None = setting(help="only these task folders; default: all", unit=None, nargs="+")
    variants: tuple[str, ...] | None = setting(help="only these variant folders; default: all", unit=None, nargs="+")
    collapse_tag: str = setting(
        _REPORT.collapse_tag, help=f"{COLLAPSE_METRICS_CSV} tag that decides 'stuck in action collapse'", unit=None
    )
    collapse_threshold: float = setting(
        _REPORT.collapse_threshold,
        help="a seed is stuck when the median of its last `collapse_checks` values is <= this",
        unit=None,
    )
    collapse_checks: int = setting(
        _REPORT.collapse_checks, help="number of last collapse checks whose median is tested", unit=None, minimum=1
    )
    last_evals: int = setting(
        _REPORT.last_evals,
        help="the across-seed std is averaged over this many last evaluations",
        unit="evaluations",
        minimum=1,
    )
    success_return: float = setting(
        _REPORT.success_return, help="transplant grid: a seed succeeds when its final return is >= this", unit=None
    )
    percentiles: tuple[float, float] = setting(
        tuple(_REPORT.percentiles),
        help="Figure 5's band",
        unit="percent",
        nargs=2,
        metavar=("LOW", "HIGH"),
        minimum=0,
        maximum=100,
    )
    failure_return: float = setting(
        _FIXED.failure_return,
        help="Figures 4, 8, 9: a seed is poorly performing when its final return is < this, well-performing when "
        ">= `success_return`, middle in between",
        unit=None,
    )
    pick_seed: int = setting(
        _FIXED.pick_seed, help="Figures 4, 8, 9: seed of the random pick of one agent per class", unit=None
    )
    rollouts: str | None = setting(
        help="Figures 4, 8, 9: rollouts file whose observations every snapshot of the picked agents is run on; "
        "default: the rollouts of `rollouts_variant`",
        unit=None,
    )
    rollouts_variant: str | None = setting(
        help="Figures 4, 8, 9: every variant of a task is run on the rollouts that python -m sb3_collapse.probe "
        "sweep recorded from this variant's best well-performing seed, <sweep>/probe/<task>_<variant>/rollouts.npz; "
        f"default: {BASELINE_VARIANT}",
        unit=None,
    )
    rollouts_per_variant: bool = setting(
        False,
        help="Figures 4, 8, 9: each variant on its own variant's rollouts instead (other observations per variant); "
        "not allowed with `rollouts_variant`",
        unit=None,
    )
    fixed_samples: int = setting(
        _FIXED.fixed_samples,
        help="Figures 4, 8, 9: observations drawn from the rollouts (seeded)",
        unit="observations",
        minimum=0,
        zero_means="all",
    )
    device: str = setting(_FIXED.device, help="Figures 4, 8, 9: where the snapshots run: auto, cpu, cuda", unit=None)
    correlation: str = setting(
        _FIXED.correlation,
        help="Figures 4, 8, 9: the reading of the correlation column (every reading stays in the CSV files)",
        unit=None,
        choices=CORRELATION_READINGS,
    )
    train_episodes: bool = setting(
        False,
        help="Figures 4, 8, 9: the fixed set from the probe's training episodes of the rollouts only (Figure 1's H)",
        unit=None,
    )
    overwrite: bool = setting(False, help="replace the files of a previous report in the output folder", unit=None)
    progress: bool = setting(True, help="show a progress bar", unit=None)


COMMANDS: dict[str, tuple[type, ...]] = {"": (ReportFlags,)}
"""The flags, by the dataclass that declares them (the parser, the help, the range checks and the table in
``docs/sweeps.md`` are generated from it)."""


def build_parser() -> argparse.ArgumentParser:
    """The command line, its flags generated from :class:`ReportFlags`."""
    parser = CommandLine(
        prog=prog_name("sb3_collapse.report"),
        description=(
            "The figures and tables of a sweep folder <sweep>/<task>/<variant>/seed_<k>/: Figure 5 and the table, "
            "Figures 4, 8, 9 (collapse metrics of a picked well-performing, middle and poorly performing seed), "
            f"Figure 3 and Table 7 (cnn-<src>_mlp-<src> variants), and report/index.html; only finished trials "
            f"({RESULT_JSON}) enter the statistics. Given one run folder of the train CLI: its Figure 4 and index.html."
        ),
    )
    add_setting_arguments(parser, declaration=ReportFlags)
    return parser


@report_unwritable_outputs
def main(argv: list[str] | None = None) -> int:
    """:return: 0 on success, 2 on bad input (after ``error: ...`` on stderr); ``argv``: ``sys.argv[1:]`` when None"""
    parser = build_parser()
    args = parser.parse_args(argv)
    check_arguments(parser, args, ReportFlags)
    if args.rollouts_per_variant and args.rollouts_variant is not None:
        parser.error("argument --rollouts-per-variant: not allowed with argument --rollouts-variant")
    settings = ReportSettings(**{f.name: getattr(args, f.name) for f in fields(ReportSettings)})
    settings.percentiles = (args.percentiles[0], args.percentiles[1])
    collapse = FixedInputSettings(
        pick_seed=args.pick_seed,
        failure_return=args.failure_return,
        rollouts=args.rollouts,
        rollouts_variant=None if args.rollouts_per_variant else (args.rollouts_variant or BASELINE_VARIANT),
        fixed_samples=args.fixed_samples or None,
        device=args.device,
        correlation=args.correlation,
        train_episodes=args.train_episodes,
    )
    try:
        if is_run_folder(args.sweep):
            trial, files = write_run_report(args.sweep, out=args.out, overwrite=args.overwrite)
            print(
                f"{trial.task} / {trial.variant} / seed {trial.seed} ({trial.status}): {len(trial.frames)} evaluations"
            )
        else:
            flags = (args.reference, args.include_unfinished, args.tasks, args.variants, args.progress, args.overwrite)
            report = write_report(args.sweep, args.out, settings, *flags, collapse_settings=collapse)
            print(report.markdown)
            if report.grid:
                print(grid_markdown(report.grid, settings.success_return))
            files = report.files
    except InputError as error:
        print(f"error: {cli_message(error, parser)}", file=sys.stderr)
        return 2
    print("wrote " + ", ".join(str(path) for path in files))
    return 0


if __name__ == "__main__":
    sys.exit(main())
