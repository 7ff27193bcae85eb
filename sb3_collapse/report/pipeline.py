"""The report as one function: read a sweep folder, compute the table and grid, write CSV, Markdown and PNG files."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from sb3_collapse.report.errors import ReportError
from sb3_collapse.report.loading import Sweep, load_sweep
from sb3_collapse.report.plots import plot_figure5, plot_transplant_grid
from sb3_collapse.report.reference import REFERENCE_LABEL, load_reference_curves
from sb3_collapse.report.statistics import (
    BandCurve,
    GridCell,
    ReportSettings,
    VariantSummary,
    band_curve,
    summarize,
    transplant_grid,
    variant_curves,
)
from sb3_collapse.report.tables import (
    GRID_COLUMNS,
    SUMMARY_COLUMNS,
    grid_markdown,
    grid_rows,
    summary_markdown,
    summary_rows,
    write_csv,
)
from sb3_collapse.staged_outputs import StagedOutputs

FIGURE5_PNG = "figure5.png"
SUMMARY_CSV = "summary.csv"
SUMMARY_MD = "summary.md"
GRID_CSV = "transplant_grid.csv"
GRID_MD = "transplant_grid.md"
GRID_PNG = "transplant_grid.png"
OUTPUT_FILES = (FIGURE5_PNG, SUMMARY_CSV, GRID_CSV, GRID_MD, GRID_PNG, SUMMARY_MD)
"""Every file a report may write; ``summary.md`` is moved in last, so its presence marks a complete report."""
REPORT_FOLDER = "report"
"""The default output folder inside the sweep folder."""


@dataclass
class Report:
    """
    What a report computed and wrote.

    :param sweep: the loaded sweep
    :param rows: the table, one row per task and variant
    :param grid: the transplant grid per task (empty without transplant variants)
    :param curves: task -> the variants' Figure 5 curves
    :param references: task -> the published DrQ-v2 curve (with ``reference=True`` and when the data has it)
    :param notes: what the report noticed (unfinished trials, dropped frames, missing reference curves)
    :param markdown: the text of ``summary.md``
    :param files: the written files
    """

    sweep: Sweep
    rows: list[VariantSummary]
    grid: dict[str, list[GridCell]]
    curves: dict[str, list[BandCurve]]
    references: dict[str, BandCurve]
    notes: list[str]
    markdown: str
    files: list[Path] = field(default_factory=list)


def _notes(sweep: Sweep, rows: Sequence[VariantSummary], include_unfinished: bool) -> list[str]:
    notes = []
    for row in rows:
        if row.unfinished:
            seeds = [t for t in sweep.select(row.task, row.variant, finished=False)]
            listed = ", ".join(f"seed {t.seed} ({t.status})" for t in seeds)
            shown = " (partial curves dotted in figure5.png)" if include_unfinished else ""
            notes.append(
                f"{row.task} / {row.variant}: {row.unfinished} unfinished, not in the statistics: {listed}{shown}"
            )
        if row.dropped_frames:
            notes.append(
                f"{row.task} / {row.variant}: {row.dropped_frames} evaluation frame(s) not shared by every finished "
                "seed were left out (curves and table use the shared frames only)"
            )
        if row.seeds and row.final_frame is None:
            notes.append(f"{row.task} / {row.variant}: the finished seeds share no evaluation frame; no statistics")
    for trial in sweep.trials:
        notes += [f"{trial.task} / {trial.variant} / seed {trial.seed}: {note}" for note in trial.notes]
    return notes


def build_report(
    sweep_dir: str | Path,
    settings: ReportSettings | None = None,
    reference: bool = False,
    include_unfinished: bool = False,
    tasks: Sequence[str] | None = None,
    variants: Sequence[str] | None = None,
    progress: bool = True,
) -> Report:
    """
    Read a sweep and compute everything the report shows, without writing.

    :param sweep_dir: the sweep folder
    :param settings: the definitions (:class:`ReportSettings` defaults when ``None``)
    :param reference: add the published DrQ-v2 curves of the tasks that the reference data has
    :param include_unfinished: read the partial curves of unfinished trials (drawn dotted; never in the table)
    :param tasks: only these tasks (``None``: all)
    :param variants: only these variants (``None``: all)
    :param progress: show a progress bar while reading trials
    :return: the report (``files`` empty)
    :raises ReportError: on a bad folder, file or setting
    """
    settings = settings or ReportSettings()
    try:
        settings.validate()
    except ValueError as error:
        raise ReportError(str(error)) from error
    sweep = load_sweep(sweep_dir, settings.collapse_tag, include_unfinished, tasks, variants, progress)
    rows = summarize(sweep, settings)
    notes = _notes(sweep, rows, include_unfinished)
    if not sweep.finished:
        notes.insert(0, "no finished trial yet: the table and figure have no statistics")
    curves = {task: variant_curves(sweep, task, settings.percentiles) for task in sweep.tasks()}
    references = {}
    if reference:
        for task in sweep.tasks():
            data = load_reference_curves(task)
            if data is None:
                notes.append(f"{task}: no published DrQ-v2 curve for this task; no reference overlay")
            else:
                references[task] = band_curve(REFERENCE_LABEL, data.frames, data.returns, settings.percentiles)
    grid = transplant_grid(rows, settings.success_return)
    return Report(sweep, rows, grid, curves, references, notes, summary_markdown(rows, settings, notes))


def write_report(
    sweep_dir: str | Path,
    out: str | Path | None = None,
    settings: ReportSettings | None = None,
    reference: bool = False,
    include_unfinished: bool = False,
    tasks: Sequence[str] | None = None,
    variants: Sequence[str] | None = None,
    progress: bool = True,
    overwrite: bool = False,
) -> Report:
    """
    The report of a sweep folder, written to ``out`` (default ``<sweep>/report/``):

    - ``figure5.png``: per task, mean evaluation return over frames with the percentile band across seeds for each
      variant (plus the published DrQ-v2 curves with ``reference``, and dotted partial curves of unfinished
      trials with ``include_unfinished``);
    - ``summary.csv`` and ``summary.md``: the table per task and variant
      (:class:`~sb3_collapse.report.statistics.VariantSummary`);
    - ``transplant_grid.csv``, ``.md`` and ``.png`` when ``cnn-<src>_mlp-<src>`` variants are present.

    The files are staged and moved into ``out`` only when all are written (``summary.md`` last); outputs of a
    previous report that this one does not write are removed.

    :param sweep_dir: the sweep folder
    :param out: the output folder (``<sweep_dir>/report`` when ``None``)
    :param settings: the definitions (:class:`ReportSettings` defaults when ``None``)
    :param reference: overlay the published DrQ-v2 curves
    :param include_unfinished: draw the partial curves of unfinished trials
    :param tasks: only these tasks
    :param variants: only these variants
    :param progress: show a progress bar while reading trials
    :param overwrite: replace the outputs of a previous report in ``out``; otherwise their presence is an error
        (checked before the sweep is read)
    :return: the report, with ``files`` the written paths
    :raises ReportError: on a bad folder, file or setting; nothing is written then
    """
    settings = settings or ReportSettings()
    out_dir = Path(sweep_dir) / REPORT_FOLDER if out is None else Path(out)
    staged_outputs = StagedOutputs(out_dir, OUTPUT_FILES, SUMMARY_MD, overwrite=overwrite, error=ReportError)
    report = build_report(sweep_dir, settings, reference, include_unfinished, tasks, variants, progress)
    partial = {task: [t for t in report.sweep.unfinished if t.task == task] for task in report.sweep.tasks()}
    with staged_outputs as staged:
        plot_figure5(
            report.curves,
            staged.path(FIGURE5_PNG),
            report.references,
            partial if include_unfinished else None,
            settings.percentiles,
        )
        write_csv(summary_rows(report.rows), SUMMARY_COLUMNS, staged.path(SUMMARY_CSV))
        if report.grid:
            write_csv(grid_rows(report.grid), GRID_COLUMNS, staged.path(GRID_CSV))
            staged.path(GRID_MD).write_text(grid_markdown(report.grid, settings.success_return))
            plot_transplant_grid(report.grid, staged.path(GRID_PNG), settings.success_return)
        staged.path(SUMMARY_MD).write_text(report.markdown)
        report.files = staged.commit()
    return report
