"""The report as one function: read a sweep folder, compute the table and grid, write CSV, Markdown and PNG files."""

from __future__ import annotations

import csv
import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from tqdm.auto import tqdm

from sb3_collapse.errors import InputError
from sb3_collapse.presets import preset
from sb3_collapse.probe.fixed_inputs import FixedInputs, FixedMetrics
from sb3_collapse.protocol import (
    CONFIG_JSON,
    FIGURE2_PNG,
    RESULT_JSON,
    SWEEP_JSON,
    SWEEP_PROBE_DIR,
    TABLES_1_6_CSV,
    snapshot_files,
)
from sb3_collapse.report import html
from sb3_collapse.report.collapse_figure import (
    FIGURE4_LAYERS,
    ONLINE_INPUTS,
    AgentMetrics,
    AgentPick,
    FixedInputSettings,
    agent_metrics,
    default_rollouts,
    fixed_agent_rows,
    online_agent_rows,
    paper_figure_title,
    pick_paper_agents,
    plot_collapse_metrics,
    run_folder_trial,
    run_title,
    write_fixed_metrics_csv,
)
from sb3_collapse.report.headline import (
    HEADLINE_HEADER,
    PROPOSITION1_HEADER,
    PROPOSITION_1,
    HeadlineRow,
    Proposition1Row,
    figure5_curves,
    figure5_unfinished,
    headline_definitions,
    headline_markdown,
    headline_rows,
    headline_table,
    proposition1_rows,
    proposition1_table,
)
from sb3_collapse.report.loading import Sweep, Trial, load_sweep
from sb3_collapse.report.plots import plot_figure3b, plot_figure5, plot_transplant_grid
from sb3_collapse.report.reference import REFERENCE_LABEL, load_reference_curves
from sb3_collapse.report.statistics import (
    BandCurve,
    GridCell,
    ReportSettings,
    TransplantCurves,
    VariantSummary,
    band_curve,
    summarize,
    transplant_curves,
    transplant_grid,
    transplant_sources,
)
from sb3_collapse.report.tables import (
    GRID_COLUMNS,
    SUMMARY_COLUMNS,
    TABLE7_COLUMNS,
    grid_markdown,
    grid_rows,
    summary_markdown,
    summary_rows,
    table7_markdown,
    table7_rows,
    write_csv,
)
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
COLLAPSE_PNG = "collapse_metrics_{task}_{variant}.png"
"""Figure 4 of one task and variant (``collapse_metrics_walker-walk_drqv2.png``): the metrics on the fixed probing
set."""
COLLAPSE_FIXED_CSV = "collapse_metrics_{task}_{variant}.csv"
"""The values of :data:`COLLAPSE_PNG`: every metric of every snapshot of the picked agents on the fixed set."""
COLLAPSE_ONLINE_PNG = "collapse_metrics_online_{task}_{variant}.png"
"""The same agents' online metrics (their own replay batches at training time)."""
COLLAPSE_AGENTS_CSV = "collapse_agents.csv"
"""The agents of Figures 4, 8, 9: task, variant, row, seed, final return, the class's seeds, the pick seed, inputs."""
RUN_COLLAPSE_PNG = "collapse_metrics.png"
"""Figure 4 of a single run folder."""
OUTPUT_FILES = (
    FIGURE5_PNG,
    SUMMARY_CSV,
    GRID_CSV,
    GRID_MD,
    GRID_PNG,
    FIGURE3B_PNG,
    TABLE7_CSV,
    TABLE7_MD,
    COLLAPSE_PNG.format(task="*", variant="*"),
    COLLAPSE_FIXED_CSV.format(task="*", variant="*"),
    COLLAPSE_ONLINE_PNG.format(task="*", variant="*"),
    COLLAPSE_AGENTS_CSV,
    html.INDEX_HTML,
    SUMMARY_MD,
)
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
    :param curves: task -> the variants' Figure 5 curves (no transplant-grid cells: they are Figure 3's)
    :param references: task -> the published DrQ-v2 curve (with ``reference=True`` and when the data has it)
    :param notes: what the report noticed (unfinished trials, dropped frames, missing reference curves)
    :param markdown: the text of ``summary.md``
    :param transplant: task -> Figure 3(b)'s curves and Table 7's rows (empty without transplant variants)
    :param collapse: ``(task, variant)`` -> Figure 4's rows (well-performing, middle, poorly performing agent) on
        the fixed probing set, where it was computed (rollouts and snapshots found)
    :param files: the written files
    :param collapse_picks: ``(task, variant)`` -> the picked agents, for the variants that are not transplant cells
    :param collapse_online: ``(task, variant)`` -> the same rows with the online metrics (replay batches)
    :param collapse_inputs: ``(task, variant)`` -> the fixed set the rows of ``collapse`` were computed on
    :param collapse_fixed: ``(task, variant)`` -> seed -> every fixed-set metric of its snapshots
    :param headline: the paper's headline numbers beside the sweep's (top of ``summary.md`` and ``index.html``)
    :param proposition: Proposition 1's prediction beside the rule's escapes
    """

    sweep: Sweep
    rows: list[VariantSummary]
    grid: dict[str, list[GridCell]]
    curves: dict[str, list[BandCurve]]
    references: dict[str, BandCurve]
    notes: list[str]
    markdown: str
    transplant: dict[str, list[TransplantCurves]] = field(default_factory=dict)
    collapse: dict[tuple[str, str], list[AgentMetrics]] = field(default_factory=dict)
    files: list[Path] = field(default_factory=list)
    collapse_picks: dict[tuple[str, str], list[AgentPick]] = field(default_factory=dict)
    collapse_online: dict[tuple[str, str], list[AgentMetrics]] = field(default_factory=dict)
    collapse_inputs: dict[tuple[str, str], FixedInputs] = field(default_factory=dict)
    collapse_fixed: dict[tuple[str, str], dict[int, FixedMetrics]] = field(default_factory=dict)
    headline: list[HeadlineRow] = field(default_factory=list)
    proposition: list[Proposition1Row] = field(default_factory=list)


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
    collapse_settings: FixedInputSettings | None = None,
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
    :param collapse_settings: Figures 4, 8, 9: the pick's seed, the fixed observation set, the device
        (:class:`FixedInputSettings` defaults when ``None``)
    :return: the report (``files`` empty)
    :raises InputError: on a bad folder, file or setting
    """
    settings = settings or ReportSettings()
    try:
        settings.validate()
    except ValueError as error:
        raise InputError(str(error)) from error
    collapse_settings = collapse_settings or FixedInputSettings()
    collapse_settings.validate()
    sweep = load_sweep(sweep_dir, settings.collapse_tag, include_unfinished, tasks, variants, progress)
    rows = summarize(sweep, settings)
    notes = _notes(sweep, rows, include_unfinished)
    if not sweep.finished:
        notes.insert(0, "no finished trial yet: the table and figure have no statistics")
    curves = {task: figure5_curves(sweep, task, settings.percentiles) for task in sweep.tasks()}
    curves = {task: task_curves for task, task_curves in curves.items() if task_curves or _plain_variants(sweep, task)}
    references = {}
    if reference:
        for task in sweep.tasks():
            data = load_reference_curves(task)
            if data is None:
                notes.append(f"{task}: no published DrQ-v2 curve for this task; no reference overlay")
            else:
                references[task] = band_curve(REFERENCE_LABEL, data.frames, data.returns, settings.percentiles)
    grid = transplant_grid(rows, settings.success_return)
    report = Report(sweep, rows, grid, curves, references, notes, summary_markdown(rows, settings, notes))
    report.transplant = transplant_curves(sweep, settings.success_return)
    collapse_figures(report, settings, collapse_settings, progress)
    report.headline = headline_rows(sweep, rows, settings)
    report.proposition = proposition1_rows(sweep, rows)
    title = "# Sweep report\n\n"
    summary = summary_markdown(rows, settings, report.notes)  # with the notes of the collapse figures
    report.markdown = (
        title + headline_markdown(report.headline, report.proposition, settings) + "\n" + (summary.removeprefix(title))
    )
    return report


def collapse_figures(
    report: Report, settings: ReportSettings, collapse_settings: FixedInputSettings, progress: bool = False
) -> None:
    """
    Fill the report's Figures 4, 8, 9 (see :mod:`sb3_collapse.report.collapse_figure`): per task and variant that
    is not a transplant cell, the agents picked by :func:`pick_paper_agents`, their online rows, and their rows on
    the fixed probing set when the rollouts and the snapshots are there (else a note says what is missing).
    A rollouts file of ``collapse_settings`` serves the tasks it was recorded on; the other tasks read the rollouts
    of ``probe sweep`` in the sweep folder: one set per task, that of ``collapse_settings.rollouts_variant`` (the
    baseline) for every variant (each variant's own with ``rollouts_variant=None``).

    :param report: the report being built (``collapse*`` fields and ``notes`` are filled)
    :param settings: the report's definitions (``success_return``)
    :param collapse_settings: the pick's seed, the fixed set and where the checkpoints run
    :param progress: progress bars over the checkpoints
    :raises InputError: for a bad setting, a given rollouts file that cannot be read, or a checkpoint that does not
        fit the rollouts
    """
    collapse_settings.validate()
    sweep = report.sweep
    given = None  # a rollouts file given by the user serves the tasks it was recorded on
    if collapse_settings.rollouts is not None:
        given = collapse_settings.load(collapse_settings.rollouts)
    loaded: dict[Path, FixedInputs] = {}  # each rollouts file read once: the same set for the variants of a task
    for task in sweep.tasks():
        for variant in sweep.variants(task):
            if transplant_sources(variant) is not None:
                continue
            key = (task, variant)
            try:
                picks = pick_paper_agents(
                    sweep.select(task, variant),
                    collapse_settings.pick_seed,
                    settings.success_return,
                    collapse_settings.failure_return,
                )
            except ValueError as error:
                raise InputError(str(error), parameter="failure_return") from error
            if not any(pick.trial is not None for pick in picks):
                continue
            report.collapse_picks[key] = picks
            report.collapse_online[key] = online_agent_rows(picks, collapse_settings.layers)
            inputs = given if given is not None and given.fits(task) else None
            source = collapse_settings.rollouts_variant or variant
            rollouts = default_rollouts(sweep.path, task, source)
            missing = _fixed_inputs_missing(sweep.path, task, variant, picks, inputs is None, rollouts, source, given)
            if missing is not None:
                report.notes.append(missing)
                continue
            if inputs is None:
                if rollouts not in loaded:
                    loaded[rollouts] = collapse_settings.load(rollouts)
                inputs = loaded[rollouts]
            rows, computed = fixed_agent_rows(picks, inputs, collapse_settings, progress)
            report.collapse[key], report.collapse_inputs[key], report.collapse_fixed[key] = rows, inputs, computed


def _fixed_inputs_missing(
    sweep_path: Path,
    task: str,
    variant: str,
    picks: Sequence[AgentPick],
    needs_rollouts: bool,
    rollouts: Path,
    source: str,
    given: FixedInputs | None,
) -> str | None:
    """
    Why Figure 4 on the probing samples cannot be drawn for a task and variant, as a note of the report.

    :param needs_rollouts: whether the sweep's rollouts file ``rollouts`` is needed (no given file fits the task)
    :param source: the variant whose rollouts are read
    :param given: the rollouts file given by the user, if any
    :return: the note, or ``None`` when the rollouts and every picked agent's snapshots are there
    """
    online = COLLAPSE_ONLINE_PNG.format(task=task, variant=variant)
    if needs_rollouts and not rollouts.is_file():
        other = "" if given is None else f" ({given.source} was recorded on {given.task})"
        return (
            f"{task} / {variant}: Figure 4 on the probing samples not drawn: no {rollouts}{other} (run "
            f"python -m sb3_collapse.probe sweep {sweep_path} --task {task} --variant {source}, or pass "
            f"--rollouts); {online} shows the online metrics"
        )
    lacking = [pick.trial.seed for pick in picks if pick.trial is not None and not snapshot_files(pick.trial.path)]
    if lacking:
        return (
            f"{task} / {variant}: Figure 4 on the probing samples not drawn: seed(s) "
            f"{', '.join(map(str, lacking))} have no snapshots (train with --snapshots); "
            f"{online} shows the online metrics"
        )
    return None


AGENTS_COLUMNS = ("task", "variant", "row", "seed", "final_return", "class_seeds", "seeds", "pick_seed", "inputs")


def agents_rows(report: Report) -> list[dict[str, object]]:
    """:return: one row of ``collapse_agents.csv`` per row of Figures 4, 8, 9 (:data:`AGENTS_COLUMNS`)"""
    rows = []
    for (task, variant), picks in report.collapse_picks.items():
        inputs = report.collapse_inputs.get((task, variant))
        for pick in picks:
            rows.append(
                {
                    "task": task,
                    "variant": variant,
                    "row": pick.role,
                    "seed": "" if pick.trial is None else pick.trial.seed,
                    "final_return": "" if pick.trial is None else pick.trial.final_return,
                    "class_seeds": " ".join(map(str, pick.candidates)),
                    "seeds": pick.seeds,
                    "pick_seed": pick.pick_seed,
                    "inputs": "online only" if inputs is None else inputs.describe(),
                }
            )
    return rows


def _plain_variants(sweep: Sweep, task: str) -> bool:
    """Whether ``task`` has a variant that is not a transplant-grid cell (it gets a Figure 5 panel)."""
    return any(transplant_sources(variant) is None for variant in sweep.variants(task))


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
    collapse_settings: FixedInputSettings | None = None,
) -> Report:
    """
    The report of a sweep folder, written to ``out`` (default ``<sweep>/report/``): Figure 5 and its table
    (``summary.csv``/``.md``, led by the headline numbers and Proposition 1), the transplant grid, Figure 3(b) and
    Table 7 when transplant variants are present, Figures 4, 8, 9 per task and variant where the rollouts and
    snapshots are there, and ``index.html`` with all of them. The files are staged and moved into ``out`` only when
    all are written; outputs of a previous report that this one does not write are removed. Every file:
    docs/figures.md and docs/sweeps.md#reports-python--m-sb3_collapsereport-runssweep.

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
    :param collapse_settings: Figures 4, 8, 9 (:class:`FixedInputSettings` defaults when ``None``)
    :return: the report, with ``files`` the written paths
    :raises InputError: on a bad folder, file or setting; nothing is written then
    """
    settings = settings or ReportSettings()
    out_dir = Path(sweep_dir) / REPORT_FOLDER if out is None else Path(out)
    staged_outputs = StagedOutputs(out_dir, OUTPUT_FILES, SUMMARY_MD, overwrite=overwrite, error=InputError)
    report = build_report(
        sweep_dir, settings, reference, include_unfinished, tasks, variants, progress, collapse_settings
    )
    partial = {task: figure5_unfinished(report.sweep, task) for task in report.curves}
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
        if report.transplant:
            plot_figure3b(report.transplant, staged.path(FIGURE3B_PNG), settings.success_return)
            write_csv(table7_rows(report.transplant), TABLE7_COLUMNS, staged.path(TABLE7_CSV))
            staged.path(TABLE7_MD).write_text(table7_markdown(report.transplant, settings.success_return))
        _write_collapse_figures(report, staged, (collapse_settings or FixedInputSettings()).layers, progress)
        if report.collapse_picks:
            write_csv(agents_rows(report), AGENTS_COLUMNS, staged.path(COLLAPSE_AGENTS_CSV))
        staged.path(html.INDEX_HTML).write_text(sweep_page(report, settings, staged.path))
        staged.path(SUMMARY_MD).write_text(report.markdown)
        report.files = staged.commit()
    return report


def _write_collapse_figures(report: Report, staged: StagedOutputs, layers: Sequence[str], progress: bool) -> None:
    """
    Write Figures 4, 8, 9 of each picked task and variant into ``staged``: the online metrics' figure, and, where
    the snapshots were run on fixed inputs, their figure and their CSV file.

    :param layers: the layers drawn
    :param progress: show a progress bar
    """
    for (task, variant), picks in tqdm(
        report.collapse_picks.items(), desc="collapse figures", unit="figure", disable=not progress
    ):
        path = staged.path(COLLAPSE_ONLINE_PNG.format(task=task, variant=variant))
        title = paper_figure_title(task, variant, picks, ONLINE_INPUTS)
        plot_collapse_metrics(report.collapse_online[(task, variant)], path, title, layers)
        if (task, variant) in report.collapse:
            inputs = report.collapse_inputs[(task, variant)]
            path = staged.path(COLLAPSE_PNG.format(task=task, variant=variant))
            title = paper_figure_title(task, variant, picks, inputs.describe())
            plot_collapse_metrics(report.collapse[(task, variant)], path, title, layers, "snapshots")
            write_fixed_metrics_csv(
                staged.path(COLLAPSE_FIXED_CSV.format(task=task, variant=variant)),
                picks,
                report.collapse_fixed[(task, variant)],
            )


PRESET_COLUMNS = (
    "tier",
    "from_drqv2",
    "frames",
    "action_repeat",
    "frame_stack",
    "batch_size",
    "learning_rate",
    "n_steps",
    "feature_dim",
    "hidden_dim",
    "stddev_schedule",
    "eval_every_frames",
)
"""The preset settings shown on the page, per task."""


def _preset_rows(tasks: Sequence[str]) -> list[list[object]]:
    rows = []
    for task in tasks:
        try:
            task_preset = preset(task)
        except ValueError:
            rows.append([task] + ["(not a DeepMind Control suite task)"] + [""] * (len(PRESET_COLUMNS) - 1))
            continue
        rows.append([task] + [getattr(task_preset, column) for column in PRESET_COLUMNS])
    return rows


def _reference_rows(report: Report) -> list[list[object]]:
    """Per task: the published DrQ-v2 return at the frame nearest to the sweep's last frame and at its own end."""
    rows = []
    for task in report.sweep.tasks():
        data = load_reference_curves(task)
        if data is None:
            rows.append([task, "-", "-", "-", "no published curve for this task"])
            continue
        last = max((int(c.frames[-1]) for c in report.curves.get(task, [])), default=int(data.frames[-1]))
        for frame_index, what in (
            (int(abs(data.frames - last).argmin()), "nearest to the sweep's last frame"),
            (len(data.frames) - 1, "end of the published run"),
        ):
            values = data.returns[:, frame_index]
            rows.append(
                [
                    task,
                    int(data.frames[frame_index]),
                    f"{values.mean():.1f} ± {values.std(ddof=1):.1f}",
                    len(values),
                    what,
                ]
            )
    return rows


def _tables_1_6(path: Path) -> list[str]:
    """Tables 1-6 of ``python -m sb3_collapse.probe sweep`` as HTML tables, one per panel (layers x stages)."""
    if not path.exists() or not path.stat().st_size:
        return [html.paragraph(f"{path}: no tables (no agent in a row).", "note")]
    with path.open(newline="") as file:
        entries = list(csv.DictReader(file))
    panels: dict[tuple[str, str, str, str], dict[str, dict[str, str]]] = {}
    for e in entries:
        key = (e["table"], e["row"], e["column"], e["agents"])
        panels.setdefault(key, {}).setdefault(e["layer"], {})[e["frame"]] = e["std"]
    parts = []
    for (number, row, column, agents), layers in panels.items():
        frames = list(dict.fromkeys(frame for stds in layers.values() for frame in stds))
        rows = [[layer, *(float(stds[f]) if stds.get(f) else None for f in frames)] for layer, stds in layers.items()]
        header = ["layer", *(f"std at {int(f):,} frames" for f in frames)]
        parts.append(html.table(header, rows, f"Table {number}: {row} agents ({agents}), {column}"))
    return parts


def sweep_page(report: Report, settings: ReportSettings, png: Callable[[str], Path]) -> str:
    """
    The report's ``index.html``: the sweep's settings and presets, the table, the unfinished trials, Figure 5, the
    published DrQ-v2 reference, Figures 4/8/9, the transplant grid, Figure 3(b) and Table 7, images embedded.

    :param report: the computed report
    :param settings: its definitions
    :param png: name of a written figure -> its path (the figures must be written)
    :return: the HTML text
    """
    sweep = report.sweep
    sections = [
        _headline_section(report, settings),
        _settings_section(sweep, settings),
        _summary_section(report, settings),
        _unfinished_section(sweep),
        _curves_section(report, settings, png),
    ]
    if report.collapse_picks:
        sections.append(_collapse_section(report, png))
    probing = _probing_section(sweep)
    if probing.parts:
        sections.append(probing)
    if report.grid:
        sections.append(_transplant_section(report, settings, png))
    title = f"Sweep report: {sweep.path}"
    return html.html_page(title, sections, f"{len(sweep.finished)} finished, {len(sweep.unfinished)} unfinished trials")


def _headline_section(report: Report, settings: ReportSettings) -> html.Section:
    """The paper's headline numbers and Proposition 1 beside this sweep's."""
    headline = html.Section("The paper's headline beside this sweep's")
    headline.parts.append(html.table(HEADLINE_HEADER, headline_table(report.headline)))
    headline.parts.append(html.heading("Proposition 1"))
    headline.parts.append(html.paragraph(f"“{PROPOSITION_1}” (Section 5.2)"))
    if report.proposition:
        headline.parts.append(html.table(PROPOSITION1_HEADER, proposition1_table(report.proposition)))
    else:
        headline.parts.append(html.paragraph("No rule variant with its baseline in this sweep.", "note"))
    headline.parts.append(html.paragraph(headline_definitions(settings), "note"))
    return headline


def _settings_section(sweep: Sweep, settings: ReportSettings) -> html.Section:
    """The sweep's settings, the DrQ-v2 presets of its tasks and the report's definitions."""
    about = html.Section("Settings")
    sweep_json = sweep.path / SWEEP_JSON
    if sweep_json.exists():
        about.parts.append(html.settings_table(read_json(sweep_json), caption=f"{SWEEP_JSON} of the sweep"))
    else:
        about.parts.append(html.paragraph(f"{sweep_json} is missing: the sweep's settings are unknown.", "note"))
    about.parts.append(html.table(("task", *PRESET_COLUMNS), _preset_rows(sweep.tasks()), "DrQ-v2 presets per task"))
    about.parts.append(html.settings_table(dataclasses.asdict(settings), caption="the report's definitions"))
    return about


def _summary_section(report: Report, settings: ReportSettings) -> html.Section:
    """The summary table, its column definitions and the report's notes."""
    summary = html.Section("Summary table")
    summary.parts.append(html.dict_table(summary_rows(report.rows), SUMMARY_COLUMNS))
    definitions = summary_markdown(report.rows, settings).split("\n\n", 2)[-1].split("\nNotes:")[0].strip()
    summary.parts.append(html.preformatted(definitions))
    if report.notes:
        summary.parts += [html.heading("Notes"), html.bullet_list(report.notes)]
    return summary


def _unfinished_section(sweep: Sweep) -> html.Section:
    """The trial folders that did not finish, or a line saying every one did."""
    unfinished = html.Section("Unfinished trials")
    if sweep.unfinished:
        unfinished.parts.append(
            html.table(
                ("task", "variant", "seed", "status", "folder"),
                [(t.task, t.variant, t.seed, t.status, str(t.path)) for t in sweep.unfinished],
            )
        )
    else:
        unfinished.parts.append(html.paragraph("Every trial folder is finished."))
    return unfinished


def _curves_section(report: Report, settings: ReportSettings, png: Callable[[str], Path]) -> html.Section:
    """Figure 5 (evaluation return over frames) and the published DrQ-v2 reference beside it."""
    curves = html.Section("Figure 5: evaluation return")
    low, high = settings.percentiles
    curves.parts.append(
        html.figure(
            png(FIGURE5_PNG),
            f"Mean evaluation return over frames per task and variant (DrQ-v2, with the rule and the other "
            f"interventions; the transplant cells are in Figure 3), {low:g}th-{high:g}th percentile band across "
            "finished seeds" + (" (dashed: published DrQ-v2)" if report.references else "."),
        )
    )
    curves.parts.append(
        html.table(
            ("task", "frame", "return (mean ± std)", "seeds", "which"),
            _reference_rows(report),
            f"{REFERENCE_LABEL} (facebookresearch/drqv2 curves)",
        )
    )
    return curves


def _collapse_section(report: Report, png: Callable[[str], Path]) -> html.Section:
    """Figures 4, 8, 9 (fixed-input and online collapse metrics) and the picked agents, per task and variant."""
    collapse = html.Section("Figures 4, 8, 9: collapse metrics of three agents")
    for (task, variant), picks in report.collapse_picks.items():
        events = "vertical lines: resets and escapes of the reset rule."
        if (task, variant) in report.collapse:
            inputs = report.collapse_inputs[(task, variant)].describe()
            collapse.parts.append(
                html.figure(
                    png(COLLAPSE_PNG.format(task=task, variant=variant)),
                    paper_figure_title(task, variant, picks, inputs).replace("\n", "; ")
                    + f"; every snapshot run on the same observations; {events}",
                )
            )
        collapse.parts.append(
            html.figure(
                png(COLLAPSE_ONLINE_PNG.format(task=task, variant=variant)),
                "Online metrics (not the paper's inputs): "
                + paper_figure_title(task, variant, picks, ONLINE_INPUTS).replace("\n", "; ")
                + f"; {events}",
            )
        )
        collapse.parts.append(
            html.dict_table(
                [r for r in agents_rows(report) if (r["task"], r["variant"]) == (task, variant)], AGENTS_COLUMNS
            )
        )
    return collapse


def _probing_section(sweep: Sweep) -> html.Section:
    """Figure 2 and Tables 1-6 of every probe folder of the sweep; no parts when none was written."""
    probing = html.Section("Figure 2 and Tables 1-6: probing over training")
    for task in sweep.tasks():
        for variant in sweep.variants(task):
            folder = sweep.path / SWEEP_PROBE_DIR.format(task=task, variant=variant)
            if (folder / FIGURE2_PNG).exists():
                probing.parts.append(html.figure(folder / FIGURE2_PNG, f"Figure 2, {task} / {variant} ({folder})."))
                probing.parts += _tables_1_6(folder / TABLES_1_6_CSV)
    return probing


def _transplant_section(report: Report, settings: ReportSettings, png: Callable[[str], Path]) -> html.Section:
    """Figure 3(a) (the transplant grid), Figure 3(b) and Table 7."""
    transplant = html.Section("Figure 3 and Table 7: layer transplants")
    transplant.parts.append(
        html.figure(png(GRID_PNG), f"Figure 3(a): successful seeds (final return >= {settings.success_return:g}).")
    )
    transplant.parts.append(html.dict_table(grid_rows(report.grid), GRID_COLUMNS))
    if report.transplant:
        transplant.parts.append(
            html.figure(png(FIGURE3B_PNG), "Figure 3(b): the successful seeds' curves per transplant cell.")
        )
        for task, cells in report.transplant.items():
            header = ["combination", "successful seeds"] + [f"std at {f:,} frames" for f in cells[0].stage_frames]
            rows = [[c.label, len(c.returns), *c.stage_std] for c in cells]
            transplant.parts.append(html.table(header, rows, f"Table 7, {task}"))
    return transplant


RUN_OUTPUT_FILES = (RUN_COLLAPSE_PNG, html.INDEX_HTML)
"""The files of a single run folder's report (``index.html`` last)."""


def write_run_report(
    run_dir: str | Path, out: str | Path | None = None, overwrite: bool = False, layers: Sequence[str] = FIGURE4_LAYERS
) -> tuple[Trial, list[Path]]:
    """
    The report of one run folder of ``python -m sb3_collapse.train`` (``runs/walker-walk_s0``): Figure 4 of this
    run alone (``collapse_metrics.png``: return, numerical rank, correlation, dead units, gradient norm over
    frames, resets marked; the online metrics, on its replay batches) and ``index.html`` with it and the run's
    settings. An unfinished run is drawn as far as its files go.

    :param run_dir: the run folder
    :param out: the output folder (``<run_dir>/report`` when ``None``)
    :param overwrite: replace the outputs of a previous report
    :param layers: the layers drawn
    :return: the run (as a trial) and the written files
    :raises InputError: when the folder is not a run folder or a file is malformed
    """
    out_dir = Path(run_dir) / REPORT_FOLDER if out is None else Path(out)
    staged_outputs = StagedOutputs(out_dir, RUN_OUTPUT_FILES, html.INDEX_HTML, overwrite=overwrite, error=InputError)
    trial = run_folder_trial(run_dir)
    agent = agent_metrics(trial, "run", layers)
    with staged_outputs as staged:
        title = run_title(trial)
        plot_collapse_metrics([agent], staged.path(RUN_COLLAPSE_PNG), title, layers)
        section = html.Section("Figure 4: collapse metrics over training")
        section.parts.append(html.figure(staged.path(RUN_COLLAPSE_PNG), title))
        config = html.Section("Settings")
        config.parts.append(html.settings_table(read_json(trial.path / CONFIG_JSON), f"{CONFIG_JSON} of the run"))
        if trial.result is not None:
            config.parts.append(html.settings_table(trial.result, f"{RESULT_JSON} of the run"))
        page = html.html_page(f"Run report: {trial.path}", [section, config], title)
        staged.path(html.INDEX_HTML).write_text(page)
        files = staged.commit()
    return trial, files
