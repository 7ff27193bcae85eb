"""The report's folder pipelines (``python -m sb3_collapse.report``): read a sweep or run folder, compute (the
fixed-input metrics of Figures 4, 8, 9 with :mod:`sb3_collapse.probe`), draw with :mod:`sb3_collapse.report` and
write the report folder (staged: all files or none)."""

from __future__ import annotations

import csv
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from stable_baselines3.common.utils import get_device

from sb3_collapse.common.progress import on_terminal, progress_bar
from sb3_collapse.drqv2.checks import check_device
from sb3_collapse.errors import InputError
from sb3_collapse.monitoring import CORRELATION_READINGS, FIGURE_CORRELATION
from sb3_collapse.paper import PAPER, metric_tag
from sb3_collapse.probe.fixed_inputs import FIXED_SAMPLES, FixedInputs, FixedMetrics, fixed_metrics, load_fixed_inputs
from sb3_collapse.probe.pipeline import ROLLOUTS_NAME
from sb3_collapse.protocol import CONFIG_JSON, RESULT_JSON, SWEEP_PROBE_DIR, snapshot_files
from sb3_collapse.report import collapse_figure, headline, html, tables
from sb3_collapse.report import pipeline as page
from sb3_collapse.report import statistics as stats
from sb3_collapse.report.headline import BASELINE_VARIANT
from sb3_collapse.report.loading import Trial, load_sweep
from sb3_collapse.report.plots import plot_figure3b, plot_figure5, plot_transplant_grid
from sb3_collapse.report.reference import REFERENCE_LABEL, load_reference_curves
from sb3_collapse.run.config import RUN, check_declared, declared, setting
from sb3_collapse.runfolder import read_json
from sb3_collapse.staged_outputs import StagedOutputs


@declared
@dataclass
class FixedInputSettings:
    """How Figures 4, 8, 9 pick their agents and compute on the fixed observation set, each setting declared once
    (the report's flags and range checks are generated from them); ``rollouts_variant=None``: each variant on its own
    variant's rollouts, ``fixed_samples`` ``None`` or 0: every observation."""

    pick_seed: int = setting(0, cli=RUN)
    """Figures 4, 8, 9: seed of the random pick of one agent per class"""
    failure_return: float = setting(PAPER.failure_return, cli=RUN)
    """Figures 4, 8, 9: a seed is poorly performing when its final return is < this, well-performing when >= the
    success return, middle in between"""
    rollouts: str | Path | None = setting(cli=RUN)  # noqa: RUF009  (a declaration, as every field here)
    """Figures 4, 8, 9: rollouts file whose observations every snapshot of the picked agents is run on; default: the
    rollouts of `rollouts_variant`"""
    rollouts_variant: str | None = setting(BASELINE_VARIANT, cli=RUN)
    """Figures 4, 8, 9: every variant of a task is run on the rollouts that python -m sb3_collapse.probe sweep recorded
    from this variant's best well-performing seed, <sweep>/probe/<task>_<variant>/rollouts.npz"""
    fixed_samples: int | None = setting(FIXED_SAMPLES, cli=RUN, unit="observations", minimum=2, zero_means="all")
    """Figures 4, 8, 9: observations drawn from the rollouts (seeded)"""
    sample_seed: int = setting(0, cli=None)
    """seed of the draw of `fixed_samples`"""
    device: str = setting("auto", cli=RUN)
    """Figures 4, 8, 9: where the snapshots run: auto, cpu, cuda"""
    batch_size: int = setting(256, cli=None, minimum=1)
    """observations per forward pass"""
    layers: tuple[str, ...] = setting(collapse_figure.FIGURE4_LAYERS, cli=None)
    """the layers measured and drawn"""
    correlation: str = setting(FIGURE_CORRELATION, cli=RUN, choices=CORRELATION_READINGS)
    """Figures 4, 8, 9: the reading of the correlation column (every reading stays in the CSV files)"""
    train_episodes: bool = setting(False, cli=RUN)
    """Figures 4, 8, 9: the fixed set from the probe's training episodes of the rollouts only (Figure 1's H)"""

    def validate(self) -> None:
        """:raises InputError: on a setting out of its declared range, or a rollouts file that does not exist"""
        check_declared(self)
        if self.rollouts is not None and not Path(self.rollouts).is_file():
            raise InputError(
                f"rollouts {self.rollouts} is not a file; give the rollouts.npz of python -m sb3_collapse.probe sweep "
                "(or of probe record).",
                parameter="rollouts",
            )
        check_device(self.device)

    def load(self, path: str | Path) -> FixedInputs:
        """:return: the fixed set of the rollouts file ``path`` (InputError: not a rollouts file)"""
        try:
            return load_fixed_inputs(path, self.fixed_samples or None, self.sample_seed, self.train_episodes)
        except InputError as error:
            raise InputError(str(error), parameter="rollouts") from error


def fixed_agent_rows(
    picks: Sequence[collapse_figure.AgentPick],
    inputs: FixedInputs,
    settings: FixedInputSettings,
    progress: bool = False,
) -> tuple[list[collapse_figure.AgentMetrics], dict[int, FixedMetrics]]:
    """:return: the rows of Figures 4, 8, 9 (the columns of :func:`~sb3_collapse.report.collapse_figure.figure4_metrics`
    of each snapshot on ``inputs``, the training-time gradient norms), and seed -> its fixed-set metrics"""
    rows, computed = collapse_figure.online_agent_rows(picks, settings.layers, settings.correlation), {}
    fixed_columns = [
        metric for metric, _ in collapse_figure.figure4_metrics(settings.correlation) if metric != "grad_norm"
    ]
    tags = [metric_tag(layer, metric) for layer in settings.layers for metric in fixed_columns]
    how = (inputs, settings.layers, get_device(settings.device), settings.batch_size, progress)
    for row in rows:
        if row.trial is None:
            continue
        fixed = fixed_metrics(snapshot_files(row.trial.path), *how, f"seed {row.trial.seed} checkpoints")
        computed[row.trial.seed] = fixed
        row.metrics = {tag: value for tag, value in row.metrics.items() if tag.endswith("/grad_norm")}
        row.metrics |= {tag: fixed.metrics[tag] for tag in tags if tag in fixed.metrics}
        row.widths = fixed.widths or row.widths
    return rows, computed


def build_report(
    sweep_dir: str | Path,
    settings: stats.ReportSettings | None = None,
    reference: bool = False,
    include_unfinished: bool = False,
    tasks: Sequence[str] | None = None,
    variants: Sequence[str] | None = None,
    progress: bool = True,
    collapse_settings: FixedInputSettings | None = None,
) -> page.Report:
    """
    Read a sweep and compute everything the report shows, without writing.

    :param sweep_dir: the sweep folder
    :param settings: the definitions (:class:`stats.ReportSettings` defaults when ``None``)
    :param reference: add the published DrQ-v2 curves of the tasks that the reference data has
    :param include_unfinished: read the partial curves of unfinished trials (drawn dotted; never in the table)
    :param tasks: only these tasks (``None``: all)
    :param variants: only these variants (``None``: all)
    :param progress: show the progress of the long stages
    :param collapse_settings: Figures 4, 8, 9 (:class:`FixedInputSettings` defaults when ``None``)
    :return: the report (``files`` empty)
    :raises InputError: on a bad folder or setting, or a sweep none of whose trials can be read
    """
    settings = settings or stats.ReportSettings()
    settings.validate()
    collapse_settings = collapse_settings or FixedInputSettings()
    collapse_settings.validate()
    sweep = load_sweep(sweep_dir, settings.collapse_tag, include_unfinished, tasks, variants, progress)
    rows = stats.summarize(sweep, settings)
    notes = page.sweep_notes(sweep, rows, include_unfinished)
    plain = sorted({t.task for t in sweep.trials if stats.transplant_sources(t.variant) is None})  # Figure 5's panels
    curves = {task: headline.figure5_curves(sweep, task, settings.percentiles) for task in plain}
    references = {}
    for task in sweep.tasks() if reference else ():
        data = load_reference_curves(task)
        if data is None:
            notes.append(f"{task}: no published DrQ-v2 curve for this task; no reference overlay")
        else:
            references[task] = stats.band_curve(REFERENCE_LABEL, data.frames, data.returns, settings.percentiles)
    report = page.Report(
        sweep, rows, stats.transplant_grid(rows, settings.success_return), curves, references, notes, ""
    )
    report.settings, report.layers = settings, collapse_settings.layers
    if include_unfinished:  # the unfinished trials of Figure 5's variants, drawn dotted
        unfinished = [t for t in sweep.unfinished if stats.transplant_sources(t.variant) is None]
        report.partial = {task: [t for t in unfinished if t.task == task] for task in curves}
    report.transplant = stats.transplant_curves(sweep, settings.success_return)
    report.notes += page.transplant_notes(report)
    collapse_figures(report, settings, collapse_settings, progress)
    report.headline = headline.headline_rows(sweep, rows, settings)
    report.proposition = headline.proposition1_rows(sweep, rows)
    title = "# Sweep report\n\n"
    summary = tables.summary_markdown(rows, settings, report.notes).removeprefix(title)
    top = headline.headline_markdown(report.headline, report.proposition, settings)
    report.markdown = title + top + "\n" + summary + page.unfinished_markdown(sweep)
    return report


def collapse_figures(
    report: page.Report,
    settings: stats.ReportSettings,
    collapse_settings: FixedInputSettings,
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
                online = page.COLLAPSE_ONLINE_PNG.format(task=task, variant=variant)
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
            rows, computed = fixed_agent_rows(picks, inputs, collapse_settings, bar)
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


def write_report(
    sweep_dir: str | Path,
    out: str | Path | None = None,
    overwrite: bool = False,
    progress: bool = True,
    **build_options: Any,
) -> page.Report:
    """
    The report of a sweep folder (:func:`build_report`'s), written to ``out``: staged, moved in only when every file
    is written; outputs of a previous report that this one does not write are removed. Every file: docs/figures.md
    and docs/sweeps.md#reports-python--m-sb3_collapsereport-runssweep.

    :param sweep_dir: the sweep folder
    :param out: the output folder (``<sweep_dir>/report`` when ``None``)
    :param overwrite: replace the outputs of a previous report in ``out`` (else an error, before the sweep is read)
    :param progress: show the progress of the long stages (reading, drawing)
    :param build_options: the other keywords of :func:`build_report` (``settings``, ``reference``,
        ``include_unfinished``, ``tasks``, ``variants``, ``collapse_settings``; its defaults for those left out)
    :return: the report, with ``files`` the written paths
    :raises InputError: on a bad folder or setting; nothing is written then
    :raises TypeError: on a keyword :func:`build_report` does not take
    """
    out_dir = Path(sweep_dir) / page.REPORT_FOLDER if out is None else Path(out)
    staged_outputs = StagedOutputs(out_dir, page.OUTPUT_FILES, page.SUMMARY_MD, overwrite=overwrite, error=InputError)
    report = build_report(sweep_dir, progress=progress, **build_options)
    settings = report.settings
    with staged_outputs as staged:
        plot_figure5(
            report.curves, staged.path(page.FIGURE5_PNG), report.references, report.partial, settings.percentiles
        )
        tables.write_csv(tables.summary_rows(report.rows), tables.SUMMARY_COLUMNS, staged.path(page.SUMMARY_CSV))
        if report.grid:
            tables.write_csv(tables.grid_rows(report.grid), tables.GRID_COLUMNS, staged.path(page.GRID_CSV))
            staged.path(page.GRID_MD).write_text(tables.grid_markdown(report.grid, settings.success_return))
            plot_transplant_grid(report.grid, staged.path(page.GRID_PNG), settings.success_return)
        if report.transplant:
            plot_figure3b(report.transplant, staged.path(page.FIGURE3B_PNG), settings.success_return)
            tables.write_csv(tables.table7_rows(report.transplant), tables.TABLE7_COLUMNS, staged.path(page.TABLE7_CSV))
            staged.path(page.TABLE7_MD).write_text(tables.table7_markdown(report.transplant, settings.success_return))
        for key, picks in progress_bar(report.collapse_picks.items(), "collapse figures", "figure", progress):
            path = staged.path(page.COLLAPSE_ONLINE_PNG.format(task=key[0], variant=key[1]))
            title = collapse_figure.paper_figure_title(*key, picks, collapse_figure.ONLINE_INPUTS)
            collapse_figure.plot_collapse_metrics(report.collapse_online[key], path, title, report.layers)
            if key in report.collapse:
                path = staged.path(page.COLLAPSE_PNG.format(task=key[0], variant=key[1]))
                title = collapse_figure.paper_figure_title(*key, picks, report.collapse_inputs[key].describe())
                collapse_figure.plot_collapse_metrics(report.collapse[key], path, title, report.layers, "snapshots")
                path = staged.path(page.COLLAPSE_FIXED_CSV.format(task=key[0], variant=key[1]))
                write_fixed_metrics_csv(path, picks, report.collapse_fixed[key])
        if report.collapse_picks:
            tables.write_csv(page.agents_rows(report), page.AGENTS_COLUMNS, staged.path(page.COLLAPSE_AGENTS_CSV))
        staged.path(html.INDEX_HTML).write_text(page.sweep_page(report, settings, staged.path))
        staged.path(page.SUMMARY_MD).write_text(report.markdown)
        report.files = staged.commit()
    return report


def write_run_report(
    run_dir: str | Path,
    out: str | Path | None = None,
    overwrite: bool = False,
    collapse_settings: FixedInputSettings | None = None,
    progress: bool = True,
) -> tuple[Trial, list[Path]]:
    """
    The report of one run folder of the train CLI into ``out``, as far as its files go: its online Figure 4
    (``collapse_metrics.png``), with ``collapse_settings.rollouts`` its snapshots on that fixed probing set too
    (``collapse_metrics_fixed.png`` and ``.csv``), and ``index.html`` with the run's settings.

    :param run_dir: the run folder
    :param out: the output folder (``<run_dir>/report`` when ``None``)
    :param overwrite: replace the outputs of a previous report in ``out`` (else an error, before the run is read)
    :param collapse_settings: the layers, the correlation's reading and the fixed set (:class:`FixedInputSettings`
        defaults when ``None``: the online figure only); its agent-picking settings do not apply to one run
    :param progress: show the progress of the snapshots' metrics
    :return: the run (as a trial) and the written files
    :raises InputError: not a run folder, a malformed file, a setting out of range, rollouts of another task, or a
        fixed set asked of a run without snapshots; nothing is written then
    """
    settings = collapse_settings or FixedInputSettings()
    settings.validate()
    out_dir = Path(run_dir) / page.REPORT_FOLDER if out is None else Path(out)
    run_files = (page.RUN_COLLAPSE_PNG, page.RUN_COLLAPSE_FIXED_PNG, page.RUN_COLLAPSE_FIXED_CSV, html.INDEX_HTML)
    staged_outputs = StagedOutputs(out_dir, run_files, html.INDEX_HTML, overwrite=overwrite, error=InputError)
    trial = collapse_figure.run_folder_trial(run_dir)
    agent = collapse_figure.agent_metrics(trial, "run", settings.layers, settings.correlation)
    fixed = None
    if settings.rollouts is not None:
        inputs = settings.load(settings.rollouts)
        if not inputs.fits(trial.task):
            message = f"rollouts {settings.rollouts} were recorded on {inputs.task}, not on the run's {trial.task}."
            raise InputError(message, parameter="rollouts")
        if not snapshot_files(trial.path):
            message = f"rollouts: {trial.path} has no snapshots to run on them (train with --snapshots)."
            raise InputError(message, parameter="rollouts")
        pick = collapse_figure.AgentPick("run", trial, [trial.seed], 1, 0)
        fixed = (pick, inputs, *fixed_agent_rows([pick], inputs, settings, on_terminal(progress)))
    name = f"{trial.task} / {trial.variant} / seed {trial.seed}: collapse metrics over training ({trial.status})"
    with staged_outputs as staged:
        section = html.Section("Figure 4: collapse metrics over training")
        title = f"{name}\non {collapse_figure.ONLINE_INPUTS}"
        collapse_figure.plot_collapse_metrics([agent], staged.path(page.RUN_COLLAPSE_PNG), title, settings.layers)
        section.parts.append(html.figure(staged.path(page.RUN_COLLAPSE_PNG), title))
        if fixed is not None:
            pick, inputs, rows, computed = fixed
            title = f"{name}\nrank, correlation, dead units on {inputs.describe()}; gradient norms at training time"
            path = staged.path(page.RUN_COLLAPSE_FIXED_PNG)
            collapse_figure.plot_collapse_metrics(rows, path, title, settings.layers, "snapshots")
            section.parts.append(html.figure(path, title))
            write_fixed_metrics_csv(staged.path(page.RUN_COLLAPSE_FIXED_CSV), [pick], computed)
        config = html.Section("Settings")
        config.parts.append(html.settings_table(read_json(trial.path / CONFIG_JSON), f"{CONFIG_JSON} of the run"))
        if trial.result is not None:
            config.parts.append(html.settings_table(trial.result, f"{RESULT_JSON} of the run"))
        staged.path(html.INDEX_HTML).write_text(html.html_page(f"Run report: {trial.path}", [section, config], name))
        files = staged.commit()
    return trial, files


FIXED_CSV_COLUMNS = ("role", "seed", "final_return", "checkpoint", "frame", "tag", "value")


def write_fixed_metrics_csv(
    path: Path, picks: Sequence[collapse_figure.AgentPick], computed: dict[int, FixedMetrics]
) -> None:
    """Write every fixed-set metric of the picked agents (``computed``: :func:`fixed_agent_rows`), long format."""
    with path.open("w", newline="") as file:
        writer = csv.writer(file)
        writer.writerow(FIXED_CSV_COLUMNS)
        for pick in picks:
            if pick.trial is None or pick.trial.seed not in computed:
                continue
            fixed = computed[pick.trial.seed]
            final = pick.trial.final_return
            for tag, (frames, values) in fixed.metrics.items():
                for checkpoint, frame, value in zip(fixed.checkpoints, frames, values):
                    writer.writerow(
                        [pick.role, pick.trial.seed, repr(final), checkpoint.name, int(frame), tag, repr(float(value))]
                    )
