"""
Reports of a sweep folder (the paper's Figure 5, the table, the transplant grid): ``python -m sb3_collapse.report
--help``.

    python -m sb3_collapse.report runs/                          # writes runs/report/, prints the table
    python -m sb3_collapse.report runs/ --reference --out figs/  # with the published DrQ-v2 curves
    python -m sb3_collapse.report runs/walker-walk_s0            # one run folder: its Figure 4

Errors in the input print ``error: ...`` and exit with status 2.
"""

from __future__ import annotations

import argparse
import sys

from sb3_collapse.errors import ReportError, cli_message, report_unwritable_outputs
from sb3_collapse.protocol import COLLAPSE_METRICS_CSV, RESULT_JSON
from sb3_collapse.report.collapse_figure import is_run_folder
from sb3_collapse.report.fixed_inputs import FixedInputSettings
from sb3_collapse.report.headline import BASELINE_VARIANT
from sb3_collapse.report.loading import DEFAULT_COLLAPSE_TAG
from sb3_collapse.report.pipeline import REPORT_FOLDER, write_report, write_run_report
from sb3_collapse.report.statistics import ReportSettings
from sb3_collapse.report.tables import grid_markdown

PROG = "python -m sb3_collapse.report"


def build_parser() -> argparse.ArgumentParser:
    """The command line."""
    defaults = ReportSettings()
    parser = argparse.ArgumentParser(
        prog=PROG,
        description=(
            "Figure 5 (mean evaluation return and percentile band across seeds, per task and variant), the table "
            "(final return, seeds stuck in action collapse, resets, std over the last evaluations) and, when "
            "cnn-<src>_mlp-<src> variants exist, the transplant grid of a sweep folder "
            f"<sweep>/<task>/<variant>/seed_<k>/, the collapse metrics of a randomly picked well-performing, middle "
            "and poorly performing seed (Figures 4, 8, 9: on the fixed probing set of python -m sb3_collapse.probe "
            "sweep, and online on their replay batches), Figure 3(b) and Table 7, and report/index.html with all of "
            "them. Only finished "
            f"trials ({RESULT_JSON}) enter the statistics. Given a single run folder of python -m sb3_collapse.train "
            "instead, it draws that run's collapse metrics (Figure 4) and its index.html."
        ),
    )
    parser.add_argument(
        "sweep", help="the sweep folder (--out of python -m sb3_collapse.sweep), or one run folder of the train CLI"
    )
    parser.add_argument("--out", help=f"output folder (default: <sweep>/{REPORT_FOLDER})")
    parser.add_argument(
        "--reference", action="store_true", help="overlay the published DrQ-v2 curves (dashed mean, hatched band)"
    )
    parser.add_argument(
        "--include-unfinished",
        action="store_true",
        help="draw the partial curves of unfinished trials, dotted (never used in the table)",
    )
    parser.add_argument("--tasks", nargs="+", help="only these task folders (default: all)")
    parser.add_argument("--variants", nargs="+", help="only these variant folders (default: all)")
    parser.add_argument(
        "--collapse-tag",
        default=DEFAULT_COLLAPSE_TAG,
        help=f"{COLLAPSE_METRICS_CSV} tag that decides 'stuck in action collapse' (default: %(default)s)",
    )
    parser.add_argument(
        "--collapse-threshold",
        type=float,
        default=defaults.collapse_threshold,
        help="a seed is stuck when the median of its last --collapse-checks values is <= this (default: %(default)g)",
    )
    parser.add_argument(
        "--collapse-checks",
        type=int,
        default=defaults.collapse_checks,
        help="number of last collapse checks whose median is tested (default: %(default)s)",
    )
    parser.add_argument(
        "--last-evals",
        type=int,
        default=defaults.last_evals,
        help="the across-seed std is averaged over this many last evaluations (default: %(default)s)",
    )
    parser.add_argument(
        "--success-return",
        type=float,
        default=defaults.success_return,
        help="transplant grid: a seed succeeds when its final return is >= this (default: %(default)g)",
    )
    parser.add_argument(
        "--percentiles",
        type=float,
        nargs=2,
        metavar=("LOW", "HIGH"),
        default=list(defaults.percentiles),
        help="Figure 5's band, in percent (default: 5 95)",
    )
    collapse = FixedInputSettings()
    parser.add_argument(
        "--failure-return",
        type=float,
        default=collapse.failure_return,
        help="Figures 4, 8, 9: a seed is poorly performing when its final return is < this, well-performing when "
        ">= --success-return, middle in between (default: %(default)g)",
    )
    parser.add_argument(
        "--pick-seed",
        type=int,
        default=collapse.pick_seed,
        help="Figures 4, 8, 9: seed of the random pick of one agent per class (default: %(default)s)",
    )
    parser.add_argument(
        "--rollouts",
        help="Figures 4, 8, 9: rollouts file whose observations every snapshot of the picked agents is run "
        "on, for the tasks it was recorded on (default: the rollouts of --rollouts-variant)",
    )
    sets = parser.add_mutually_exclusive_group()
    sets.add_argument(
        "--rollouts-variant",
        help="Figures 4, 8, 9: every variant of a task is run on the rollouts that python -m sb3_collapse.probe "
        "sweep recorded from this variant's best well-performing seed, <sweep>/probe/<task>_<variant>/rollouts.npz "
        f"(default: {collapse.rollouts_variant})",
    )
    sets.add_argument(
        "--rollouts-per-variant",
        action="store_true",
        help="Figures 4, 8, 9: each variant on its own variant's rollouts instead (other observations per variant)",
    )
    parser.add_argument(
        "--fixed-samples",
        type=int,
        default=collapse.fixed_samples,
        help="Figures 4, 8, 9: observations drawn from the rollouts (seeded; 0: all) (default: %(default)s)",
    )
    parser.add_argument(
        "--device",
        default=collapse.device,
        help="Figures 4, 8, 9: where the snapshots run: auto, cpu, cuda (default: %(default)s)",
    )
    parser.add_argument(
        "--overwrite", action="store_true", help="replace the files of a previous report in the output folder"
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    return parser


@report_unwritable_outputs
def main(argv: list[str] | None = None) -> int:
    """
    :param argv: the arguments (``sys.argv[1:]`` when ``None``)
    :return: 0 on success, 2 on bad input (after ``error: ...`` on stderr)
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    settings = ReportSettings(
        collapse_tag=args.collapse_tag,
        collapse_threshold=args.collapse_threshold,
        collapse_checks=args.collapse_checks,
        last_evals=args.last_evals,
        success_return=args.success_return,
        percentiles=(args.percentiles[0], args.percentiles[1]),
    )
    collapse = FixedInputSettings(
        pick_seed=args.pick_seed,
        failure_return=args.failure_return,
        rollouts=args.rollouts,
        rollouts_variant=None if args.rollouts_per_variant else (args.rollouts_variant or BASELINE_VARIANT),
        fixed_samples=args.fixed_samples or None,
        device=args.device,
    )
    if is_run_folder(args.sweep):
        try:
            trial, files = write_run_report(args.sweep, out=args.out, overwrite=args.overwrite)
        except ReportError as error:
            print(f"error: {cli_message(error, parser)}", file=sys.stderr)
            return 2
        print(f"{trial.task} / {trial.variant} / seed {trial.seed} ({trial.status}): {len(trial.frames)} evaluations")
        print("wrote " + ", ".join(str(path) for path in files))
        return 0
    try:
        report = write_report(
            args.sweep,
            out=args.out,
            settings=settings,
            reference=args.reference,
            include_unfinished=args.include_unfinished,
            tasks=args.tasks,
            variants=args.variants,
            progress=not args.no_progress,
            overwrite=args.overwrite,
            collapse_settings=collapse,
        )
    except ReportError as error:
        print(f"error: {cli_message(error, parser)}", file=sys.stderr)
        return 2
    print(report.markdown)
    if report.grid:
        print(grid_markdown(report.grid, settings.success_return))
    print("wrote " + ", ".join(str(path) for path in report.files))
    return 0


if __name__ == "__main__":
    sys.exit(main())
