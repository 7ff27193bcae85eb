"""What a report holds (:class:`Report`, computed by :func:`sb3_collapse.commands.report_pipelines.build_report`), its
file names, notes and ``index.html`` page."""

from __future__ import annotations

import csv
import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from sb3_collapse.presets import TaskPreset, preset
from sb3_collapse.protocol import (
    FIGURE2_PNG,
    SWEEP_JSON,
    SWEEP_PROBE_DIR,
    TABLES_1_6_CSV,
)
from sb3_collapse.report import collapse_figure, headline, html, tables
from sb3_collapse.report import statistics as stats
from sb3_collapse.report.collapse_figure import ONLINE_INPUTS, paper_figure_title
from sb3_collapse.report.figure2 import stage_panels
from sb3_collapse.report.loading import Sweep, Trial
from sb3_collapse.report.reference import REFERENCE_LABEL, load_reference_curves
from sb3_collapse.runfolder import read_json

FIGURE5_PNG = "figure5.png"
SUMMARY_CSV = "summary.csv"
SUMMARY_MD = "summary.md"
GRID_CSV = "transplant_grid.csv"
GRID_MD = "transplant_grid.md"
GRID_PNG = "transplant_grid.png"
FIGURE3B_PNG = "figure3b.png"
TABLE7_CSV = "table7.csv"
TABLE7_MD = "table7.md"
COLLAPSE_PNG = "collapse_metrics_{task}_{variant}.png"  # Figures 4, 8, 9 on the fixed probing set
COLLAPSE_FIXED_CSV = "collapse_metrics_{task}_{variant}.csv"  # their values
COLLAPSE_ONLINE_PNG = "collapse_metrics_online_{task}_{variant}.png"  # on the agents' own replay batches
COLLAPSE_AGENTS_CSV = "collapse_agents.csv"  # the agents of Figures 4, 8, 9 (AGENTS_COLUMNS)
RUN_COLLAPSE_PNG = "collapse_metrics.png"  # Figure 4 of a single run folder (online)
RUN_COLLAPSE_FIXED_PNG = "collapse_metrics_fixed.png"  # the same run's snapshots on a fixed probing set
RUN_COLLAPSE_FIXED_CSV = "collapse_metrics_fixed.csv"  # their values
_PATTERNS = tuple(
    name.format(task="*", variant="*") for name in (COLLAPSE_PNG, COLLAPSE_FIXED_CSV, COLLAPSE_ONLINE_PNG)
)
OUTPUT_FILES = (FIGURE5_PNG, SUMMARY_CSV, GRID_CSV, GRID_MD, GRID_PNG, FIGURE3B_PNG, TABLE7_CSV, TABLE7_MD)
OUTPUT_FILES += (*_PATTERNS, COLLAPSE_AGENTS_CSV, html.INDEX_HTML, SUMMARY_MD)
"""Every file a report may write; ``summary.md`` is moved in last, so its presence marks a complete report."""
REPORT_FOLDER = "report"
"""The default output folder inside the sweep folder."""
AGENTS_COLUMNS = ("task", "variant", "row", "seed", "final_return", "class_seeds", "seeds", "pick_seed", "inputs")
"""The columns of ``collapse_agents.csv``."""
UNFINISHED_HEADER = ("task", "variant", "seed", "status", "reason", "folder")
TRANSPLANT_NOTE = (
    "{what} not drawn: {why}; the layer-transplant variants cnn-<src>_mlp-<src> with <src> in "
    + ", ".join(stats.TRANSPLANT_SOURCES)
    + " produce {them} (python -m sb3_collapse.sweep --transplant-grid runs all nine)"
)
"""The note of a report without Figure 3 and Table 7."""
PRESET_COLUMNS = tuple(f.name for f in dataclasses.fields(TaskPreset) if f.name != "task")
"""The preset settings shown on the page, per task."""


@dataclass
class Report:
    """
    What a report computed and wrote (``collapse*``: Figures 4, 8, 9 by ``(task, variant)``).

    :param sweep: the loaded sweep
    :param rows: the table, one row per task and variant
    :param grid: task -> Figure 3(a)'s cells
    :param curves: task -> Figure 5's curves
    :param references: task -> the published DrQ-v2 curve
    :param notes: what the report noticed
    :param markdown: the text of ``summary.md``
    :param transplant: task -> Figure 3(b)'s curves and Table 7's rows
    :param collapse: the rows on the fixed probing set, where computed
    :param files: the written files
    :param collapse_picks: the picked agents
    :param collapse_online: their rows with the online metrics
    :param collapse_inputs: the fixed set of ``collapse``'s rows (:class:`~sb3_collapse.probe.fixed_inputs.FixedInputs`)
    :param collapse_fixed: seed -> every fixed-set metric of its snapshots
        (:class:`~sb3_collapse.probe.fixed_inputs.FixedMetrics`)
    :param headline: the paper's headline numbers beside the sweep's
    :param proposition: Proposition 1's prediction beside the rule's escapes
    :param settings: the definitions it was computed with
    :param layers: the layers of Figures 4, 8, 9
    :param partial: task -> the unfinished trials whose partial curves Figure 5 draws dotted (``None``: not drawn)
    """

    sweep: Sweep
    rows: list[stats.VariantSummary]
    grid: dict[str, list[stats.GridCell]]
    curves: dict[str, list[stats.BandCurve]]
    references: dict[str, stats.BandCurve]
    notes: list[str]
    markdown: str
    transplant: dict[str, list[stats.TransplantCurves]] = field(default_factory=dict)
    collapse: dict[tuple[str, str], list[collapse_figure.AgentMetrics]] = field(default_factory=dict)
    files: list[Path] = field(default_factory=list)
    collapse_picks: dict[tuple[str, str], list[collapse_figure.AgentPick]] = field(default_factory=dict)
    collapse_online: dict[tuple[str, str], list[collapse_figure.AgentMetrics]] = field(default_factory=dict)
    collapse_inputs: dict[tuple[str, str], Any] = field(default_factory=dict)
    collapse_fixed: dict[tuple[str, str], dict[int, Any]] = field(default_factory=dict)
    headline: list[headline.HeadlineRow] = field(default_factory=list)
    proposition: list[headline.Proposition1Row] = field(default_factory=list)
    settings: stats.ReportSettings = field(default_factory=stats.ReportSettings)
    layers: tuple[str, ...] = ()
    partial: dict[str, list[Trial]] | None = None


def sweep_notes(sweep: Sweep, rows: Sequence[stats.VariantSummary], include_unfinished: bool) -> list[str]:
    notes = [] if sweep.finished else ["no finished trial yet: the table and figure have no statistics"]
    for row in rows:
        name = f"{row.task} / {row.variant}"
        if row.unfinished:
            listed = ", ".join(f"seed {t.seed} ({t.status})" for t in sweep.select(row.task, row.variant, False))
            shown = " (partial curves dotted in figure5.png)" if include_unfinished else ""
            notes.append(f"{name}: {row.unfinished} unfinished, not in the statistics: {listed}{shown}")
        if row.dropped_frames:
            notes.append(
                f"{name}: {row.dropped_frames} evaluation frame(s) not shared by every finished seed were left out "
                "(curves and table use the shared frames only)"
            )
        if row.seeds and row.final_frame is None:
            notes.append(f"{name}: the finished seeds share no evaluation frame; no statistics")
    return notes + [f"{t.task} / {t.variant} / seed {t.seed}: {note}" for t in sweep.trials for note in t.notes]


def transplant_notes(report: Report) -> list[str]:
    """The notes that say why Figure 3 or Table 7 is missing, and which variants would produce them."""
    if not report.grid:
        why = "no transplant variant in this sweep"
        return [TRANSPLANT_NOTE.format(what="Figure 3 and Table 7", why=why, them="them")]
    lacking = [task for task in report.grid if task not in report.transplant]
    if lacking:
        why = f"{', '.join(lacking)}: no transplant cell with a successful seed"
        return [TRANSPLANT_NOTE.format(what="Figure 3(b) and Table 7", why=why, them="them, once a seed succeeds")]
    return []


def unfinished_rows(sweep: Sweep) -> list[tuple[object, ...]]:
    """:return: one row per trial that is not finished (:data:`UNFINISHED_HEADER`), damaged ones with their reason"""
    return [(t.task, t.variant, t.seed, t.status, t.reason or "-", str(t.path)) for t in sweep.unfinished]


def unfinished_markdown(sweep: Sweep) -> str:
    """:return: the ``Unfinished trials`` section of ``summary.md``"""
    rows = [[str(cell) for cell in row] for row in unfinished_rows(sweep)]
    body = tables.markdown_table(UNFINISHED_HEADER, rows) if rows else ["Every trial folder is finished."]
    return "\n".join(["", "## Unfinished trials", "", *body]) + "\n"


def agents_rows(report: Report) -> list[dict[str, object]]:
    """:return: one row of ``collapse_agents.csv`` per row of Figures 4, 8, 9 (:data:`AGENTS_COLUMNS`)"""
    rows = []
    for (task, variant), picks in report.collapse_picks.items():
        inputs = report.collapse_inputs.get((task, variant))
        for pick in picks:
            seed, final = ("", "") if pick.trial is None else (pick.trial.seed, pick.trial.final_return)
            classes = " ".join(map(str, pick.candidates))
            described = "online only" if inputs is None else inputs.describe()
            values = (task, variant, pick.role, seed, final, classes, pick.seeds, pick.pick_seed, described)
            rows.append(dict(zip(AGENTS_COLUMNS, values)))
    return rows


def _preset_rows(tasks: Sequence[str]) -> list[list[object]]:
    rows = []
    for task in tasks:
        try:
            task_preset = preset(task)
        except ValueError:
            rows.append([task, "(not a DeepMind Control suite task)"] + [""] * (len(PRESET_COLUMNS) - 1))
            continue
        rows.append([task] + [getattr(task_preset, column) for column in PRESET_COLUMNS])
    return rows


def _reference_rows(report: Report) -> list[list[object]]:
    """Per task: the published DrQ-v2 return at the frame nearest to the sweep's last frame and at its own end."""
    rows: list[list[object]] = []
    for task in report.sweep.tasks():
        data = load_reference_curves(task)
        if data is None:
            rows.append([task, "-", "-", "-", "no published curve for this task"])
            continue
        last = max((int(c.frames[-1]) for c in report.curves.get(task, [])), default=int(data.frames[-1]))
        for index, what in (
            (int(abs(data.frames - last).argmin()), "nearest to the sweep's last frame"),
            (len(data.frames) - 1, "end of the published run"),
        ):
            values = data.returns[:, index]
            mean = f"{values.mean():.1f} ± {values.std(ddof=1):.1f}"
            rows.append([task, int(data.frames[index]), mean, len(values), what])
    return rows


def _tables_1_6(path: Path) -> list[str]:
    """Tables 1-6 of ``python -m sb3_collapse.probe sweep`` as HTML tables, one per panel (layers x stages)."""
    if not path.exists() or not path.stat().st_size:
        return [html.paragraph(f"{path}: no tables (no agent in a row).", "note")]
    with path.open(newline="") as file:
        return [html.table(header, rows, title) for title, header, rows in stage_panels(list(csv.DictReader(file)))]


def sweep_page(report: Report, settings: stats.ReportSettings, png: Callable[[str], Path]) -> str:
    """:return: the report's ``index.html`` (``png``: name of a written figure -> its path): the headline, settings,
    table, unfinished trials, Figure 5 and the reference, Figures 4/8/9, 2, Tables 1-6, Figure 3 and Table 7"""
    sweep, low, high = report.sweep, *settings.percentiles
    top = html.Section("The paper's headline beside this sweep's")
    top.parts += [
        html.table(headline.HEADLINE_HEADER, headline.headline_table(report.headline)),
        html.paragraph("Proposition 1", tag="h3"),
        html.paragraph(f"“{headline.PROPOSITION_1}” (Section 5.2)"),
        html.table(headline.PROPOSITION1_HEADER, headline.proposition1_table(report.proposition))
        if report.proposition
        else html.paragraph("No rule variant with its baseline in this sweep.", "note"),
        html.paragraph(headline.headline_definitions(settings), "note"),
    ]
    about = html.Section("Settings")
    if (sweep.path / SWEEP_JSON).exists():
        about.parts.append(html.settings_table(read_json(sweep.path / SWEEP_JSON), f"{SWEEP_JSON} of the sweep"))
    else:
        about.parts.append(html.paragraph(f"{sweep.path / SWEEP_JSON} is missing: the settings are unknown.", "note"))
    about.parts.append(html.table(("task", *PRESET_COLUMNS), _preset_rows(sweep.tasks()), "DrQ-v2 presets per task"))
    about.parts.append(html.settings_table(dataclasses.asdict(settings), "the report's definitions"))
    summary = html.Section("Summary table")
    summary.parts.append(html.dict_table(tables.summary_rows(report.rows), tables.SUMMARY_COLUMNS))
    summary.parts.append(html.paragraph(tables.summary_definitions(settings), tag="pre"))
    if report.notes:
        summary.parts += [html.paragraph("Notes", tag="h3"), html.bullet_list(report.notes)]
    unfinished = html.Section("Unfinished trials")
    rows = unfinished_rows(sweep)
    unfinished.parts.append(
        html.table(UNFINISHED_HEADER, rows) if rows else html.paragraph("Every trial folder is finished.")
    )
    curves = html.Section("Figure 5: evaluation return")
    caption = (
        "Mean evaluation return over frames per task and variant (DrQ-v2, with the rule and the other "
        f"interventions; the transplant cells are in Figure 3), {low:g}th-{high:g}th percentile band across finished "
        "seeds" + (" (dashed: published DrQ-v2)" if report.references else ".")
    )
    reference = f"{REFERENCE_LABEL} (facebookresearch/drqv2 curves)"
    curves.parts += [
        html.figure(png(FIGURE5_PNG), caption),
        html.table(("task", "frame", "return (mean ± std)", "seeds", "which"), _reference_rows(report), reference),
    ]
    sections = [top, about, summary, unfinished, curves]
    if report.collapse_picks:
        sections.append(_collapse_section(report, png))
    probing = html.Section("Figure 2 and Tables 1-6: probing over training")
    for task in sweep.tasks():
        for variant in sweep.variants(task):
            folder = sweep.path / SWEEP_PROBE_DIR.format(task=task, variant=variant)
            if (folder / FIGURE2_PNG).exists():
                probing.parts.append(html.figure(folder / FIGURE2_PNG, f"Figure 2, {task} / {variant} ({folder})."))
                probing.parts += _tables_1_6(folder / TABLES_1_6_CSV)
    sections += [probing] if probing.parts else []
    sections.append(_transplant_section(report, settings, png))
    subtitle = f"{len(sweep.finished)} finished, {len(sweep.unfinished)} unfinished trials"
    return html.html_page(f"Sweep report: {sweep.path}", sections, subtitle)


def _collapse_section(report: Report, png: Callable[[str], Path]) -> html.Section:
    """Figures 4, 8, 9 (fixed-input and online collapse metrics) and the picked agents, per task and variant."""
    collapse = html.Section("Figures 4, 8, 9: collapse metrics of three agents")
    events = "vertical lines: resets and escapes of the reset rule."
    agents = agents_rows(report)
    for key, picks in report.collapse_picks.items():
        names = {"task": key[0], "variant": key[1]}
        if key in report.collapse:
            title = paper_figure_title(*key, picks, report.collapse_inputs[key].describe()).replace("\n", "; ")
            caption = f"{title}; every snapshot run on the same observations; {events}"
            collapse.parts.append(html.figure(png(COLLAPSE_PNG.format(**names)), caption))
        title = paper_figure_title(*key, picks, ONLINE_INPUTS).replace("\n", "; ")
        caption = f"Online metrics (not the paper's inputs): {title}; {events}"
        collapse.parts.append(html.figure(png(COLLAPSE_ONLINE_PNG.format(**names)), caption))
        collapse.parts.append(html.dict_table([r for r in agents if (r["task"], r["variant"]) == key], AGENTS_COLUMNS))
    return collapse


def _transplant_section(report: Report, settings: stats.ReportSettings, png: Callable[[str], Path]) -> html.Section:
    """Figure 3(a) (the transplant grid), Figure 3(b) and Table 7, or the note that says why they are missing."""
    transplant = html.Section("Figure 3 and Table 7: layer transplants")
    transplant.parts += [html.paragraph(note, "note") for note in transplant_notes(report)]
    if report.grid:
        caption = f"Figure 3(a): successful seeds (final return >= {settings.success_return:g})."
        transplant.parts += [
            html.figure(png(GRID_PNG), caption),
            html.dict_table(tables.grid_rows(report.grid), tables.GRID_COLUMNS),
        ]
    if report.transplant:
        caption = "Figure 3(b): the successful seeds' curves per transplant cell."
        transplant.parts.append(html.figure(png(FIGURE3B_PNG), caption))
    for task, cells in report.transplant.items():
        header = ["combination", "successful seeds"] + [f"std at {f:,} frames" for f in cells[0].stage_frames]
        rows = [[c.label, len(c.returns), *c.stage_std] for c in cells]
        transplant.parts.append(html.table(header, rows, f"Table 7, {task}"))
    return transplant
