"""The report's tables as CSV rows and Markdown text: ``summary.csv``/``.md`` and ``transplant_grid.csv``/``.md``."""

from __future__ import annotations

import csv
import math
from collections.abc import Sequence
from dataclasses import fields
from pathlib import Path
from typing import Any

from sb3_collapse.protocol import COLLAPSE_METRICS_CSV, FINISHED, RESULT_JSON
from sb3_collapse.report.statistics import (
    GridCell,
    ReportSettings,
    TransplantCurves,
    VariantSummary,
    stages_caption,
)
from sb3_collapse.run.variants import TRANSPLANT_SOURCES

SUMMARY_COLUMNS = tuple(
    f.name for f in fields(VariantSummary) if f.name not in ("dropped_frames", "finals", "seed_ids")
)
"""Columns of ``summary.csv`` (:class:`~sb3_collapse.report.statistics.VariantSummary`)."""
GRID_COLUMNS = tuple(f.name for f in fields(GridCell))
"""Columns of ``transplant_grid.csv``."""
TABLE7_COLUMNS = ("task", "cnn", "mlp", "successes", "stage", "frame", "std")
"""Columns of ``table7.csv``: one row per transplant cell and training stage."""


def _cell(value: Any) -> Any:
    """CSV cell: empty for None and nan, full precision otherwise."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return ""
    return value


def summary_rows(rows: Sequence[VariantSummary]) -> list[dict[str, Any]]:
    """:return: one dict per table row, keys :data:`SUMMARY_COLUMNS`, empty strings for undefined values"""
    return [{column: _cell(getattr(row, column)) for column in SUMMARY_COLUMNS} for row in rows]


def grid_rows(grid: dict[str, list[GridCell]]) -> list[dict[str, Any]]:
    """:return: one dict per grid cell, keys :data:`GRID_COLUMNS`"""
    return [{column: getattr(cell, column) for column in GRID_COLUMNS} for cells in grid.values() for cell in cells]


def write_csv(rows: Sequence[dict[str, Any]], columns: Sequence[str], path: Path) -> None:
    """Write ``rows`` with a header of ``columns``."""
    with path.open("w", newline="") as file:
        writer = csv.DictWriter(file, fieldnames=list(columns))
        writer.writeheader()
        writer.writerows(rows)


def _number(value: float, digits: int = 1) -> str:
    return "-" if value is None or math.isnan(value) else f"{value:.{digits}f}"


def markdown_table(header: Sequence[str], body: Sequence[Sequence[str]]) -> list[str]:
    """:return: the lines of a Markdown table"""
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(cells) + " |" for cells in body]
    return lines


def summary_markdown(rows: Sequence[VariantSummary], settings: ReportSettings, notes: Sequence[str] = ()) -> str:
    """:return: the table as Markdown, its definitions and the ``notes`` under it"""
    names = "task|variant|seeds|unfinished|final frame|final return (mean ± std)|stuck in collapse|collapse unknown"
    header = [*names.split("|"), "resets", "seeds reset", "escaped", f"std over last {settings.last_evals} evals"]
    body = [
        [row.task, row.variant, str(row.seeds), str(row.unfinished)]
        + ["-" if row.final_frame is None else f"{row.final_frame:,}"]
        + ["-" if row.seeds == 0 else f"{_number(row.final_mean)} ± {_number(row.final_std)}"]
        + [f"{row.stuck}/{row.seeds}", str(row.collapse_unknown), str(row.resets_total), str(row.seeds_reset)]
        + [f"{row.escaped}/{row.reset_rule_seeds}" if row.reset_rule_seeds else "-", _number(row.last_evals_std_mean)]
        for row in rows
    ]
    lines = ["# Sweep report", "", *markdown_table(header, body), "", summary_definitions(settings)]
    if notes:
        lines += ["", "Notes:", ""] + [f"- {note}" for note in notes]
    return "\n".join(lines) + "\n"


def summary_definitions(settings: ReportSettings) -> str:
    """:return: what the table's columns mean with ``settings``, one paragraph"""
    low, high = settings.percentiles
    return (
        f"Definitions: only finished trials (`{RESULT_JSON}` status `{FINISHED}`) enter the statistics; *unfinished* "
        "counts the other trial folders. Returns are compared on the evaluation frames that every finished seed of "
        "a variant has; *final return* is each seed's return at the last of them (*final frame*, environment "
        "frames, action repeat included). Standard deviations are across seeds (ddof=1). A seed is *stuck in "
        f"collapse* when the median of its last {settings.collapse_checks} values of `{settings.collapse_tag}` in "
        f"`{COLLAPSE_METRICS_CSV}` is <= {settings.collapse_threshold:g}; *collapse unknown* seeds logged no such "
        f"value. *Resets* sums `{RESULT_JSON}`'s `resets`; *seeds reset* counts seeds with at least one; *escaped* "
        "counts seeds whose reset rule saw an escape, over the seeds that ran the rule. "
        f"*Std over last {settings.last_evals} evals*: the across-seed std at each of the last "
        f"{settings.last_evals} aligned frames, averaged. Figure 5's band: {low:g}th to {high:g}th percentile "
        "across seeds."
    )


def grid_markdown(grid: dict[str, list[GridCell]], success_return: float) -> str:
    """:return: the transplant grids as Markdown: per task, CNN (rows) x MLP source, cells ``successes/seeds``"""
    lines = ["# Layer transplants (Figure 3(a))", ""]
    lines.append(f"Successful seeds (final evaluation return >= {success_return:g}) over finished seeds.")
    for task, cells in grid.items():
        lookup = {(c.cnn, c.mlp): c for c in cells}
        cell = {key: "-" if c.seeds == 0 else f"{c.successes}/{c.seeds}" for key, c in lookup.items()}
        body = [[f"{cnn} CNN"] + [cell[(cnn, mlp)] for mlp in TRANSPLANT_SOURCES] for cnn in TRANSPLANT_SOURCES]
        lines += ["", f"## {task}", ""]
        lines += markdown_table([""] + [f"{mlp} MLP" for mlp in TRANSPLANT_SOURCES], body)
        unfinished = sum(c.unfinished for c in cells)
        if unfinished:
            lines += ["", f"{unfinished} unfinished trial(s) not counted."]
    return "\n".join(lines) + "\n"


def table7_rows(curves: dict[str, list[TransplantCurves]]) -> list[dict[str, Any]]:
    """:return: one dict per cell and stage, keys :data:`TABLE7_COLUMNS`"""
    return [
        dict(zip(TABLE7_COLUMNS, (c.task, c.cnn, c.mlp, len(c.returns), stage, frame, _cell(std))))
        for cells in curves.values()
        for c in cells
        for stage, (frame, std) in enumerate(zip(c.stage_frames, c.stage_std))
    ]


def table7_markdown(curves: dict[str, list[TransplantCurves]], success_return: float) -> str:
    """:return: the paper's Table 7 per task: the std of the successful seeds' returns at the four stages"""
    lines = [f"# Table 7: std of the successful seeds' returns (final return >= {success_return:g})", ""]
    for task, cells in curves.items():
        header = ["combination", "successful seeds"] + [f"{frame:,} frames" for frame in cells[0].stage_frames]
        body = [[c.label, str(len(c.returns))] + [_number(std) for std in c.stage_std] for c in cells]
        lines += [f"## {task}", ""] + markdown_table(header, body) + [""]
    lines.append(
        stages_caption("cell's aligned evaluations") + " Std across successful seeds, ddof=1 (- with one seed)."
    )
    return "\n".join(lines) + "\n"
