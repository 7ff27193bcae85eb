"""The report as one function: read a sweep folder, compute the tables and figures, write CSV, Markdown, PNG and
HTML files (:func:`write_report`; one run folder: :func:`write_run_report`)."""

from __future__ import annotations

import csv
import dataclasses
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from sb3_collapse.common.progress import on_terminal, progress_bar
from sb3_collapse.errors import InputError
from sb3_collapse.presets import TaskPreset, preset
from sb3_collapse.probe.fixed_inputs import FixedInputs, FixedMetrics
from sb3_collapse.probe.pipeline import ROLLOUTS_NAME
from sb3_collapse.protocol import (
    CONFIG_JSON,
    FIGURE2_PNG,
    RESULT_JSON,
    SWEEP_JSON,
    SWEEP_PROBE_DIR,
    TABLES_1_6_CSV,
    snapshot_files,
)
from sb3_collapse.report import collapse_figure, headline, html, tables
from sb3_collapse.report import statistics as stats
from sb3_collapse.report.collapse_figure import ONLINE_INPUTS, paper_figure_title, plot_collapse_metrics
from sb3_collapse.report.figure2 import stage_panels
from sb3_collapse.report.loading import Sweep, Trial, load_sweep
from sb3_collapse.report.plots import plot_figure3b, plot_figure5, plot_transplant_grid
from sb3_collapse.report.reference import REFERENCE_LABEL, load_reference_curves
from sb3_collapse.runfolder import read_json
from sb3_collapse.staged_outputs import StagedOutputs

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
RUN_COLLAPSE_PNG = "collapse_metrics.png"  # Figure 4 of a single run folder
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
    :param collapse_inputs: the fixed set of ``collapse``'s rows
    :param collapse_fixed: seed -> every fixed-set metric of its snapshots
    :param headline: the paper's headline numbers beside the sweep's
    :param proposition: Proposition 1's prediction beside the rule's escapes
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
    collapse_inputs: dict[tuple[str, str], FixedInputs] = field(default_factory=dict)
    collapse_fixed: dict[tuple[str, str], dict[int, FixedMetrics]] = field(default_factory=dict)
    headline: list[headline.HeadlineRow] = field(default_factory=list)
    proposition: list[headline.Proposition1Row] = field(default_factory=list)


def _notes(sweep: Sweep, rows: Sequence[stats.VariantSummary], include_unfinished: bool) -> list[str]:
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


def _transplant_notes(report: Report) -> list[str]:
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


def build_report(
    sweep_dir: str | Path,
    settings: stats.ReportSettings | None = None,
    reference: bool = False,
    include_unfinished: bool = False,
    tasks: Sequence[str] | None = None,
    variants: Sequence[str] | None = None,
    progress: bool = True,
    collapse_settings: collapse_figure.FixedInputSettings | None = None,
) -> Report:
    """
    Read a sweep and compute everything the report shows, without writing.

    :param sweep_dir: the sweep folder
    :param settings: the definitions (:class:`stats.ReportSettings` defaults when ``None``)
    :param reference: add the published DrQ-v2 curves of the tasks that the reference data has
    :param include_unfinished: read the partial curves of unfinished trials (drawn dotted; never in the table)
    :param tasks: only these tasks (``None``: all)
    :param variants: only these variants (``None``: all)
    :param progress: show the progress of the long stages
    :param collapse_settings: Figures 4, 8, 9 (:class:`collapse_figure.FixedInputSettings` defaults when ``None``)
    :return: the report (``files`` empty)
    :raises InputError: on a bad folder or setting, or a sweep none of whose trials can be read
    """
    settings = settings or stats.ReportSettings()
    settings.validate()
    collapse_settings = collapse_settings or collapse_figure.FixedInputSettings()
    collapse_settings.validate()
    sweep = load_sweep(sweep_dir, settings.collapse_tag, include_unfinished, tasks, variants, progress)
    rows = stats.summarize(sweep, settings)
    notes = _notes(sweep, rows, include_unfinished)
    plain = sorted({t.task for t in sweep.trials if stats.transplant_sources(t.variant) is None})  # Figure 5's panels
    curves = {task: headline.figure5_curves(sweep, task, settings.percentiles) for task in plain}
    references = {}
    for task in sweep.tasks() if reference else ():
        data = load_reference_curves(task)
        if data is None:
            notes.append(f"{task}: no published DrQ-v2 curve for this task; no reference overlay")
        else:
            references[task] = stats.band_curve(REFERENCE_LABEL, data.frames, data.returns, settings.percentiles)
    report = Report(sweep, rows, stats.transplant_grid(rows, settings.success_return), curves, references, notes, "")
    report.transplant = stats.transplant_curves(sweep, settings.success_return)
    report.notes += _transplant_notes(report)
    collapse_figures(report, settings, collapse_settings, progress)
    report.headline = headline.headline_rows(sweep, rows, settings)
    report.proposition = headline.proposition1_rows(sweep, rows)
    title = "# Sweep report\n\n"
    summary = tables.summary_markdown(rows, settings, report.notes).removeprefix(title)
    top = headline.headline_markdown(report.headline, report.proposition, settings)
    report.markdown = title + top + "\n" + summary + unfinished_markdown(sweep)
    return report


def collapse_figures(
    report: Report,
    settings: stats.ReportSettings,
    collapse_settings: collapse_figure.FixedInputSettings,
    progress: bool = False,
) -> None:
    """Fill the report's ``collapse*`` fields (Figures 4, 8, 9) per task and variant that is not a transplant cell:
    the picked agents, their online rows, and their rows on the fixed probing set where the rollouts and snapshots
    are there (else a note in ``notes``). See docs/figures.md."""
    sweep = report.sweep
    given = None if collapse_settings.rollouts is None else collapse_settings.load(collapse_settings.rollouts)
    loaded: dict[Path, FixedInputs] = {}  # each rollouts file read once
    pick = collapse_settings.pick_seed, settings.success_return, collapse_settings.failure_return
    for task in sweep.tasks():
        for variant in sweep.variants(task):
            if stats.transplant_sources(variant) is not None:
                continue
            key = (task, variant)
            try:
                picks = collapse_figure.pick_paper_agents(sweep.select(task, variant), *pick)
            except ValueError as error:
                raise InputError(str(error), parameter="failure_return") from error
            if not any(pick.trial is not None for pick in picks):
                continue
            report.collapse_picks[key] = picks
            report.collapse_online[key] = collapse_figure.online_agent_rows(
                picks, collapse_settings.layers, collapse_settings.correlation
            )
            inputs = given if given is not None and given.fits(task) else None
            source = collapse_settings.rollouts_variant or variant
            rollouts = sweep.path / SWEEP_PROBE_DIR.format(task=task, variant=source) / ROLLOUTS_NAME
            why = _why_no_fixed_inputs(sweep.path, task, source, picks, rollouts if inputs is None else None, given)
            if why is not None:
                online = COLLAPSE_ONLINE_PNG.format(task=task, variant=variant)
                report.notes.append(
                    f"{task} / {variant}: Figure 4 on the probing samples not drawn: {why}; {online} shows the online "
                    "metrics"
                )
                continue
            if inputs is None:
                if rollouts not in loaded:
                    loaded[rollouts] = collapse_settings.load(rollouts)
                inputs = loaded[rollouts]
            bar = on_terminal(progress)  # elsewhere one line, no bar frames
            if progress and not bar:
                print(f"fixed-set metrics: {task} / {variant}", file=sys.stderr, flush=True)
            rows, computed = collapse_figure.fixed_agent_rows(picks, inputs, collapse_settings, bar)
            report.collapse[key], report.collapse_inputs[key], report.collapse_fixed[key] = rows, inputs, computed


def _why_no_fixed_inputs(
    sweep_path: Path,
    task: str,
    source: str,
    picks: Sequence[collapse_figure.AgentPick],
    rollouts: Path | None,
    given: FixedInputs | None,
) -> str | None:
    """:return: why Figure 4 on the probing samples cannot be drawn (``rollouts``: the file needed), else ``None``"""
    if rollouts is not None and not rollouts.is_file():
        other = "" if given is None else f" ({given.source} was recorded on {given.task})"
        return (
            f"no {rollouts}{other} (run python -m sb3_collapse.probe sweep {sweep_path} --task {task} --variant "
            f"{source}, or pass --rollouts)"
        )
    lacking = [str(pick.trial.seed) for pick in picks if pick.trial is not None and not snapshot_files(pick.trial.path)]
    return f"seed(s) {', '.join(lacking)} have no snapshots (train with --snapshots)" if lacking else None


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


def write_report(
    sweep_dir: str | Path,
    out: str | Path | None = None,
    settings: stats.ReportSettings | None = None,
    reference: bool = False,
    include_unfinished: bool = False,
    tasks: Sequence[str] | None = None,
    variants: Sequence[str] | None = None,
    progress: bool = True,
    overwrite: bool = False,
    collapse_settings: collapse_figure.FixedInputSettings | None = None,
) -> Report:
    """
    The report of a sweep folder (:func:`build_report`, whose parameters it shares), written to ``out``: staged,
    moved in only when every file is written; outputs of a previous report that this one does not write are removed.
    Every file: docs/figures.md and docs/sweeps.md#reports-python--m-sb3_collapsereport-runssweep.

    :param out: the output folder (``<sweep_dir>/report`` when ``None``)
    :param overwrite: replace the outputs of a previous report in ``out`` (else an error, before the sweep is read)
    :return: the report, with ``files`` the written paths
    :raises InputError: on a bad folder or setting; nothing is written then
    """
    settings = settings or stats.ReportSettings()
    layers = (collapse_settings or collapse_figure.FixedInputSettings()).layers
    out_dir = Path(sweep_dir) / REPORT_FOLDER if out is None else Path(out)
    staged_outputs = StagedOutputs(out_dir, OUTPUT_FILES, SUMMARY_MD, overwrite=overwrite, error=InputError)
    report = build_report(
        sweep_dir, settings, reference, include_unfinished, tasks, variants, progress, collapse_settings
    )
    partial = None
    if include_unfinished:  # the unfinished trials of Figure 5's variants, drawn dotted
        plain = [t for t in report.sweep.unfinished if stats.transplant_sources(t.variant) is None]
        partial = {task: [t for t in plain if t.task == task] for task in report.curves}
    with staged_outputs as staged:
        plot_figure5(report.curves, staged.path(FIGURE5_PNG), report.references, partial, settings.percentiles)
        tables.write_csv(tables.summary_rows(report.rows), tables.SUMMARY_COLUMNS, staged.path(SUMMARY_CSV))
        if report.grid:
            tables.write_csv(tables.grid_rows(report.grid), tables.GRID_COLUMNS, staged.path(GRID_CSV))
            staged.path(GRID_MD).write_text(tables.grid_markdown(report.grid, settings.success_return))
            plot_transplant_grid(report.grid, staged.path(GRID_PNG), settings.success_return)
        if report.transplant:
            plot_figure3b(report.transplant, staged.path(FIGURE3B_PNG), settings.success_return)
            tables.write_csv(tables.table7_rows(report.transplant), tables.TABLE7_COLUMNS, staged.path(TABLE7_CSV))
            staged.path(TABLE7_MD).write_text(tables.table7_markdown(report.transplant, settings.success_return))
        for key, picks in progress_bar(report.collapse_picks.items(), "collapse figures", "figure", progress):
            path = staged.path(COLLAPSE_ONLINE_PNG.format(task=key[0], variant=key[1]))
            title = paper_figure_title(*key, picks, ONLINE_INPUTS)
            plot_collapse_metrics(report.collapse_online[key], path, title, layers)
            if key in report.collapse:
                path = staged.path(COLLAPSE_PNG.format(task=key[0], variant=key[1]))
                title = paper_figure_title(*key, picks, report.collapse_inputs[key].describe())
                plot_collapse_metrics(report.collapse[key], path, title, layers, "snapshots")
                path = staged.path(COLLAPSE_FIXED_CSV.format(task=key[0], variant=key[1]))
                collapse_figure.write_fixed_metrics_csv(path, picks, report.collapse_fixed[key])
        if report.collapse_picks:
            tables.write_csv(agents_rows(report), AGENTS_COLUMNS, staged.path(COLLAPSE_AGENTS_CSV))
        staged.path(html.INDEX_HTML).write_text(sweep_page(report, settings, staged.path))
        staged.path(SUMMARY_MD).write_text(report.markdown)
        report.files = staged.commit()
    return report


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
    transplant.parts += [html.paragraph(note, "note") for note in _transplant_notes(report)]
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


def write_run_report(
    run_dir: str | Path,
    out: str | Path | None = None,
    overwrite: bool = False,
    layers: Sequence[str] = collapse_figure.FIGURE4_LAYERS,
) -> tuple[Trial, list[Path]]:
    """The report of one run folder of the train CLI into ``out`` (``<run_dir>/report`` when ``None``): its online
    Figure 4 (``collapse_metrics.png``) and ``index.html`` with the run's settings, as far as its files go. Returns
    the run (as a trial) and the written files; an InputError when it is not a run folder or a file is malformed."""
    out_dir = Path(run_dir) / REPORT_FOLDER if out is None else Path(out)
    run_files = (RUN_COLLAPSE_PNG, html.INDEX_HTML)
    staged_outputs = StagedOutputs(out_dir, run_files, html.INDEX_HTML, overwrite=overwrite, error=InputError)
    trial = collapse_figure.run_folder_trial(run_dir)
    agent = collapse_figure.agent_metrics(trial, "run", layers)
    with staged_outputs as staged:
        title = f"{trial.task} / {trial.variant} / seed {trial.seed}: collapse metrics over training ({trial.status})"
        title += f"\non {ONLINE_INPUTS}"
        plot_collapse_metrics([agent], staged.path(RUN_COLLAPSE_PNG), title, layers)
        section = html.Section("Figure 4: collapse metrics over training")
        section.parts.append(html.figure(staged.path(RUN_COLLAPSE_PNG), title))
        config = html.Section("Settings")
        config.parts.append(html.settings_table(read_json(trial.path / CONFIG_JSON), f"{CONFIG_JSON} of the run"))
        if trial.result is not None:
            config.parts.append(html.settings_table(trial.result, f"{RESULT_JSON} of the run"))
        staged.path(html.INDEX_HTML).write_text(html.html_page(f"Run report: {trial.path}", [section, config], title))
        files = staged.commit()
    return trial, files
