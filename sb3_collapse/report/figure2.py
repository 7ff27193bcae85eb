"""The paper's Figure 2 and Tables 1-6 of a sweep's task and variant (``python -m sb3_collapse.probe sweep``): "we
plot the probing MSE for three environment state components: torso velocity, joint orientation, and torso height".
The columns and readings: docs/figures.md#figure-2-and-tables-1-6-probing-over-training."""

from __future__ import annotations

import dataclasses
import math
import time
from collections import defaultdict
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.lines import Line2D
from stable_baselines3.common.utils import get_device

from sb3_collapse.errors import InputError
from sb3_collapse.paper import PAPER
from sb3_collapse.probe.pipeline import ROLLOUTS_NAME, RecordOptions
from sb3_collapse.probe.probing import ProbeSettings, agent_split, probe_each_checkpoint, probe_warnings
from sb3_collapse.probe.rollouts import REWARD_PREFIX, Rollouts
from sb3_collapse.protocol import (
    FIGURE2_PNG,
    FINAL_MODEL,
    PROBE_SUMMARY_JSON,
    SNAPSHOTS_DIR,
    SWEEP_PROBE_DIR,
    TABLES_1_6_CSV,
    snapshot_files,
    write_json_atomically,
)
from sb3_collapse.report.collapse_figure import PAPER_ROLES, agent_class
from sb3_collapse.report.loading import Sweep, Trial, load_sweep
from sb3_collapse.report.probe_outputs import checked_record_options, record_rollouts, report_warnings, warned
from sb3_collapse.report.statistics import across_seed_std, budget_frames, stage_indices, stages_caption
from sb3_collapse.report.style import frames_axis, layer_style
from sb3_collapse.report.tables import markdown_table, write_csv
from sb3_collapse.staged_outputs import StagedOutputs

ORIENTATION = "orientation (torso upright)"
"""The title of walker's second column: the paper's "joint orientation", read as the orientation the reward reads."""
PAPER_COLUMNS = ("torso velocity", ORIENTATION, "torso height")
"""The paper's three columns, in its order (Tables 1-6 are numbered by them)."""

FIGURE2_COLUMNS: dict[str, tuple[tuple[str, tuple[str, ...]], ...]] = {
    "walker": (
        ("torso velocity", ("reward:horizontal_velocity",)),
        (ORIENTATION, ("reward:torso_upright",)),
        ("torso height", ("reward:torso_height",)),
        ("root velocities (state)", tuple(f"velocity_{i}" for i in range(3))),
        ("leg orientations (state)", tuple(f"orientations_{i}" for i in range(2, 14))),
    ),
    "hopper": (
        ("torso velocity", ("reward:speed",)),
        ("torso height", ("reward:height",)),
        ("root velocities (state)", tuple(f"velocity_{i}" for i in range(3))),
        ("rootz (state)", ("position_0",)),
    ),
}
"""Domain -> the columns of Figure 2: title and the probe targets it averages."""
ROWS = (PAPER_ROLES[0], PAPER_ROLES[2])
"""The rows of Figure 2: well-performing and poorly performing agents (:func:`agent_class`)."""


def figure2_columns(task: str, components: Sequence[str], groups: Sequence[str]) -> list[tuple[str, tuple[str, ...]]]:
    """:return: Figure 2's columns of ``task`` whose probe targets all exist (another domain than
    :data:`FIGURE2_COLUMNS`': one per reward input, then per state component of ``groups``)"""
    domain = task.split("-")[0]
    available = set(components)
    if domain in FIGURE2_COLUMNS:
        return [(title, names) for title, names in FIGURE2_COLUMNS[domain] if set(names) <= available]
    by_group: dict[str, list[str]] = defaultdict(list)
    for component, group in zip(components, groups):
        by_group[group].append(component)
    columns = [(group, tuple(names)) for group, names in by_group.items()]
    return sorted(columns, key=lambda column: not column[0].startswith(REWARD_PREFIX))


@dataclass
class PanelCurve:
    """One line of Figure 2, a layer in the panel of a row of :data:`ROWS` and a column: ``(agents, frames)`` each
    agent's mean test MSE over the column's targets, on the training frames every agent of the row has."""

    row: str
    column: str
    layer: str
    frames: np.ndarray
    values: np.ndarray
    agents: list[str]

    @property
    def mean(self) -> np.ndarray:
        """The mean across agents at each frame."""
        return self.values.mean(axis=0)


def panel_curves(
    rows: Sequence[Mapping[str, Any]], agents: Mapping[str, str], columns: Sequence[tuple[str, tuple[str, ...]]]
) -> list[PanelCurve]:
    """:return: a curve per (row, column, layer) with an agent, from probe ``rows`` (``agents``: label -> its row)"""
    values: dict[tuple[str, str, int, str], dict[str, float]] = defaultdict(dict)
    for r in rows:
        values[(r["agent"], r["layer"], int(r["frames"]), r["component"])] = r["test_mse"]  # type: ignore[index]
    layers = list(dict.fromkeys(r["layer"] for r in rows))
    curves = []
    for row in ROWS:
        members = [agent for agent, which in agents.items() if which == row]
        if not members:
            continue
        frame_sets = [{int(r["frames"]) for r in rows if r["agent"] == agent} for agent in members]
        frames = np.array(sorted(set.intersection(*frame_sets)), dtype=np.int64)
        for title, names in columns:
            for layer in layers:
                matrix = [[np.mean([values[(a, layer, int(f), n)] for n in names]) for f in frames] for a in members]
                matrix = np.array(matrix, dtype=np.float64).reshape(len(members), len(frames))
                curves.append(PanelCurve(row, title, layer, frames, matrix, members))
    return curves


def plot_figure2(
    curves: Sequence[PanelCurve],
    path: Path,
    title: str,
    flat_columns: Collection[str] = (),
    few_layers: Collection[str] = (),
) -> None:
    """The paper's Figure 2 to ``path``: a row per class of agents, a column per state column, a line per layer;
    in red the columns of a barely varying target (``flat_columns``) and the layers of ``few_layers`` (fewer test
    samples than max_tau, marked ``*``)."""
    rows = list(dict.fromkeys(c.row for c in curves))
    columns = list(dict.fromkeys(c.column for c in curves))
    layers = list(dict.fromkeys(c.layer for c in curves))
    height = 2.9 * len(rows) + 1.2
    fig, axes = plt.subplots(
        len(rows), len(columns), figsize=(4.3 * len(columns), height), squeeze=False, sharex=True, sharey="col"
    )
    fig.subplots_adjust(left=0.09, right=0.98, wspace=0.25, hspace=0.3, top=1 - 0.55 / height, bottom=0.95 / height)
    for curve in curves:
        ax = axes[rows.index(curve.row)][columns.index(curve.column)]
        ax.plot(curve.frames, curve.mean, marker="o", ms=2.5, lw=1.3, **layer_style(curve.layer))
        flat = " (barely varies)" if curve.column in flat_columns else ""
        ax.set_title(
            f"{curve.row} ({len(curve.agents)}): {curve.column}{flat}", fontsize=9, color="red" if flat else "black"
        )
    for ax in axes.flat:
        ax.grid(alpha=0.3)
        ax.set_ylim(bottom=0)
        ax.tick_params(labelsize=7)
    for row in axes:
        row[0].set_ylabel("test MSE (standardized)", fontsize=8)
    for ax in axes[-1]:
        frames_axis(ax, "training frames")
    handles = [Line2D([], [], lw=1.3, **layer_style(layer)) for layer in layers]
    legend = fig.legend(
        handles,
        [layer + "*" * (layer in few_layers) for layer in layers],
        loc="lower center",
        ncol=len(layers),
        fontsize=8,
        frameon=False,
    )
    for text in legend.get_texts():
        text.set_color("red" if text.get_text().endswith("*") else "black")
    marks = (
        "\nred: the warnings of summary.json (*: fewer test samples than max_tau)" if flat_columns or few_layers else ""
    )
    fig.suptitle(title + marks, fontsize=10)
    fig.savefig(path, dpi=90)
    plt.close(fig)


TABLE_NUMBERS = {(row, column): 1 + 2 * column + row for row in range(2) for column in range(3)}
"""(row, column of :data:`PAPER_COLUMNS`) of Figure 2 -> its table in the paper (Table 1: subplot (1, 1))."""


TABLE_COLUMNS = ("table", "row", "column", "layer", "agents", "stage", "frame", "std")
"""The columns of ``tables_1_6.csv``."""


def stage_table_rows(curves: Sequence[PanelCurve], budget_frames: int | None = None) -> list[dict]:
    """:return: Tables 1-6 (:data:`TABLE_COLUMNS`): per panel, layer and stage of ``budget_frames`` (``None``: the
    paper's), the std across the row's agents"""
    table_rows = []
    for curve in curves:
        in_paper = curve.row in ROWS and curve.column in PAPER_COLUMNS
        number = TABLE_NUMBERS[(ROWS.index(curve.row), PAPER_COLUMNS.index(curve.column))] if in_paper else ""
        stages = stage_indices(curve.frames, budget_frames) if len(curve.frames) else []
        stds = across_seed_std(curve.values[:, stages], axis=0) if stages else []
        for stage, (index, std) in enumerate(zip(stages, stds)):
            values = (number, curve.row, curve.column, curve.layer, len(curve.agents), stage, int(curve.frames[index]))
            table_rows.append(dict(zip(TABLE_COLUMNS, (*values, float(std)))))
    return table_rows


def stage_panels(table_rows: Sequence[Mapping[str, Any]]) -> list[tuple[str, list[str], list[list[Any]]]]:
    """:return: Tables 1-6 of :func:`stage_table_rows` (or its CSV), numbered first: ``(title, header, rows)``, a row
    per layer with its std per stage"""
    panels: dict[tuple[str, str, str], list[Mapping[str, Any]]] = defaultdict(list)
    for r in table_rows:
        panels[(str(r["table"]), r["row"], r["column"])].append(r)
    tables = []
    numbered_first = sorted(panels.items(), key=lambda item: (not item[0][0], item[0][0].zfill(3)))
    for (number, row, column), entries in numbered_first:
        frames = list(dict.fromkeys(int(e["frame"]) for e in entries))
        stds: dict[str, dict[int, float]] = defaultdict(dict)
        for e in entries:
            stds[e["layer"]][int(e["frame"])] = float(e["std"] or "nan")
        title = f"Table {number}".rstrip() + f": {row} agents ({entries[0]['agents']}), {column}"
        header = ["layer", *(f"std at {f:,} frames" for f in frames)]
        tables.append((title, header, [[layer, *(by.get(f, math.nan) for f in frames)] for layer, by in stds.items()]))
    return tables


def stage_tables_markdown(table_rows: Sequence[Mapping[str, Any]]) -> str:
    """:return: Tables 1-6 as Markdown (:func:`stage_panels`)"""
    lines = ["# Tables 1-6: std of the probe's test MSE across agents at four training stages", ""]
    for title, header, rows in stage_panels(table_rows):
        body = [[row[0], *("-" if math.isnan(v) else f"{v:.3f}" for v in row[1:])] for row in rows]
        lines += [f"## {title}", "", *markdown_table(header, body), ""]
    lines.append(stages_caption("shared snapshots") + " Std across agents, ddof=1 (- with one agent).")
    return "\n".join(lines) + "\n"


TABLES_MD = "tables_1_6.md"
PROBE_CSV = "probe.csv"
SUMMARY_JSON = PROBE_SUMMARY_JSON
OUTPUT_FILES = (FIGURE2_PNG, TABLES_1_6_CSV, TABLES_MD, PROBE_CSV, ROLLOUTS_NAME, SUMMARY_JSON)
"""Every file ``probe sweep`` writes (``summary.json`` last)."""


def split_agents(
    trials: Sequence[Trial], success_return: float = PAPER.success_return, failure_return: float = PAPER.failure_return
) -> tuple[list[Trial], list[Trial]]:
    """:return: ``(well, poor)`` finished trials (:func:`agent_class`), each by decreasing final return"""
    ranked = sorted((t for t in trials if t.finished and len(t.returns)), key=lambda t: (-t.final_return, t.seed))
    classes = [agent_class(t.final_return, success_return, failure_return) for t in ranked]
    return [t for t, c in zip(ranked, classes) if c == ROWS[0]], [t for t, c in zip(ranked, classes) if c == ROWS[1]]


def probe_sweep(
    sweep_dir: str | Path,
    task: str,
    variant: str = "drqv2",
    out: str | Path | None = None,
    settings: ProbeSettings | None = None,
    rollouts_path: str | Path | None = None,
    record_options: RecordOptions | None = None,
    success_return: float = PAPER.success_return,
    failure_return: float = PAPER.failure_return,
    overwrite: bool = False,
    command: Sequence[str] | None = None,
    jobs: int = 1,
) -> dict[str, Any]:
    """
    Figure 2 and Tables 1-6 of one task and variant of a sweep, written into ``out`` only when everything succeeded;
    a damaged trial is listed (``damaged``), not probed. The steps: docs/figures.md.

    :param sweep_dir: the sweep folder
    :param task: its task folder, e.g. ``"walker-walk"``
    :param variant: its variant folder
    :param out: the output folder (default ``<sweep>/probe/<task>_<variant>``)
    :param settings: the probe's settings
    :param rollouts_path: rollouts to probe on (``None``: record them from the best well-performing seed, or pool
        those of the ``record_options.pool_agents`` best)
    :param record_options: how to record
    :param success_return: final return of a well-performing agent, at least
    :param failure_return: final return of a poorly performing agent, below
    :param overwrite: replace a previous run's outputs in ``out``
    :param command: the command line, for the summary
    :param jobs: checkpoints probed at once
    :return: the summary (as written to ``summary.json``)
    :raises InputError: for bad input (nothing written then)
    """
    started = time.perf_counter()
    settings = settings or ProbeSettings()
    record_options = record_options or RecordOptions()
    sweep, agents, files = _sweep_agents(
        sweep_dir, task, variant, settings, rollouts_path, record_options, success_return, failure_return, jobs
    )
    out = Path(sweep_dir) / SWEEP_PROBE_DIR.format(task=task, variant=variant) if out is None else Path(out)
    with StagedOutputs(out, OUTPUT_FILES, SUMMARY_JSON, overwrite=overwrite, error=InputError) as staged:
        rollouts, recorded_from = _sweep_rollouts(agents, files, rollouts_path, record_options, settings, staged)
        rows, warnings = _probe_agents(agents, files, rollouts, settings, jobs)
        report_warnings(warnings)
        columns = _write_figure2(rows, rollouts, agents, task, variant, staged, warnings)
        summary = {
            "complete": True,
            "created": datetime.now(UTC).isoformat(timespec="seconds"),
            "command": list(command) if command is not None else None,
            "sweep": str(sweep_dir),
            "task": task,
            "variant": variant,
            "success_return": success_return,
            "failure_return": failure_return,
            "agents": [
                {"seed": t.seed, "row": which, "final_return": t.final_return, "checkpoints": len(files[t.seed])}
                for t, which in agents
            ],
            "not_probed": [
                {"seed": t.seed, "final_return": t.final_return} for t in sweep.finished if t.seed not in files
            ],
            "unfinished": [t.seed for t in sweep.unfinished],
            "damaged": [{"seed": t.seed, "reason": t.reason} for t in sweep.unfinished if t.reason],
            "rollouts": {"recorded_from": recorded_from, "samples": len(rollouts), "episodes": rollouts.n_episodes},
            "columns": {title: list(targets) for title, targets in columns},
            "settings": {k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(settings).items()},
            "jobs": jobs,
            "warnings": warnings,
            "total_seconds": round(time.perf_counter() - started, 1),
        }
        write_json_atomically(staged.path(SUMMARY_JSON), summary)
        written = staged.commit()
    for damaged in summary["damaged"]:
        print(f"Not probed: seed {damaged['seed']}: {damaged['reason']}")
    print("Wrote " + ", ".join(str(f) for f in written))
    return summary


def _sweep_rollouts(
    agents: list[tuple[Trial, str]],
    files: dict[int, list[Path]],
    rollouts_path: str | Path | None,
    record_options: RecordOptions,
    settings: ProbeSettings,
    staged: StagedOutputs,
) -> tuple[Rollouts, str]:
    """:return: the rollouts to probe on (``rollouts_path``, or recorded from the final model or last checkpoint of
    the best agent, or of the ``record_options.pool_agents`` best, pooled), and where they come from"""
    if rollouts_path is not None:
        return Rollouts.load(rollouts_path), str(rollouts_path)
    wells = [trial for trial, which in agents if which == ROWS[0]][: record_options.pool_agents]
    sources = [t.path / FINAL_MODEL if (t.path / FINAL_MODEL).exists() else files[t.seed][-1] for t in wells]
    rollouts = record_rollouts(sources, get_device(settings.device), record_options, settings, staged)
    return rollouts, ", ".join(map(str, sources))


def _probe_agents(
    agents: list[tuple[Trial, str]],
    files: dict[int, list[Path]],
    rollouts: Rollouts,
    settings: ProbeSettings,
    jobs: int,
) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """:return: the probe's rows of every checkpoint of every agent, with its agent, row and final return, and the
    probe's warnings (of each distinct split, :func:`agent_split`)"""
    splits = {trial.seed: agent_split(rollouts.episode_ids, settings, trial.seed) for trial, _ in agents}
    work = [(trial, which, path) for trial, which in agents for path in files[trial.seed]]
    labels = [f"seed_{trial.seed}/{path.stem}" for trial, _, path in work]
    paths, work_splits = [path for _, _, path in work], [splits[trial.seed] for trial, _, _ in work]
    per_checkpoint = probe_each_checkpoint(paths, labels, rollouts, work_splits, settings, jobs)
    for (trial, which, _), result_rows in zip(work, per_checkpoint):
        for row in result_rows:
            row.update(agent=f"seed {trial.seed}", agent_row=which, final_return=trial.final_return)
    rows = [row for result_rows in per_checkpoint for row in result_rows]
    if not settings.split_per_agent:  # one split for every agent
        return rows, probe_warnings(rollouts, work_splits[0], rows, settings)
    warnings: list[dict[str, Any]] = []
    for seed, split in splits.items():  # each agent's split: the warnings of the rows probed on it, once each
        for warning in probe_warnings(rollouts, split, [r for r in rows if r["agent"] == f"seed {seed}"], settings):
            if warning not in warnings:
                warnings.append(warning)
    return rows, warnings


def _sweep_agents(
    sweep_dir: str | Path,
    task: str,
    variant: str,
    settings: ProbeSettings,
    rollouts_path: str | Path | None,
    record_options: RecordOptions,
    success_return: float,
    failure_return: float,
    jobs: int,
) -> tuple[Sweep, list[tuple[Trial, str]], dict[int, list[Path]]]:
    """:return: the sweep, its agents with their row of Figure 2 (the well-performing first) and seed -> snapshots,
    :func:`probe_sweep`'s arguments checked before any work (:raises InputError: naming the bad one)"""
    settings.validate()
    if isinstance(jobs, bool) or not isinstance(jobs, int) or jobs < 1:
        raise InputError(f"jobs must be an integer >= 1, got {jobs!r}.", parameter="jobs")
    if not failure_return <= success_return:
        raise InputError(
            f"failure_return must be <= success_return, got {failure_return:g} and {success_return:g}.",
            parameter="failure_return",
        )
    try:
        sweep = load_sweep(sweep_dir, tasks=[task], variants=[variant], progress=False)
    except InputError as error:
        raise InputError(
            str(error), parameter=error.parameter if error.parameter != "sweep" else "sweep_dir"
        ) from error
    well, poor = split_agents(sweep.finished, success_return, failure_return)
    if not well and not poor:
        finals = ", ".join(f"seed {t.seed}: {t.final_return:.0f}" for t in sweep.finished) or "no finished trial"
        raise InputError(
            f"{task} / {variant} has no well-performing (final return >= {success_return:g}) nor poorly performing "
            f"(< {failure_return:g}) finished trial ({finals}); lower success_return or raise failure_return.",
            parameter="success_return",
        )
    agents = [(trial, ROWS[0]) for trial in well] + [(trial, ROWS[1]) for trial in poor]
    files = {trial.seed: snapshot_files(trial.path) for trial, _ in agents}
    lacking = [t for t, _ in agents if not files[t.seed]]
    if lacking:
        raise InputError(
            f"no {SNAPSHOTS_DIR}/*.zip in {', '.join(str(t.path) for t in lacking)}: train the trials with "
            "--snapshots (TrainConfig.snapshots) to probe them over training."
        )
    if rollouts_path is None:
        if not well:
            raise InputError(
                f"{task} / {variant} has no well-performing trial (final return >= {success_return:g}) to record "
                "rollouts from: pass rollouts_path (python -m sb3_collapse.probe record GOOD.zip).",
                parameter="rollouts_path",
            )
        checked_record_options(record_options, pooled=True)
        if record_options.pool_agents > len(well):
            raise InputError(
                f"pool_agents={record_options.pool_agents} but {task} / {variant} has {len(well)} well-performing "
                f"trial(s) (final return >= {success_return:g}) to record from: pass at most {len(well)}.",
                parameter="pool_agents",
            )
    return sweep, agents, files


def _write_figure2(
    rows: list[dict[str, Any]],
    rollouts: Rollouts,
    agents: Sequence[tuple[Trial, str]],
    task: str,
    variant: str,
    staged: StagedOutputs,
    warnings: Sequence[dict[str, Any]] = (),
) -> list[tuple[str, tuple[str, ...]]]:
    """Write Figure 2 (marking what ``warnings`` name), Tables 1-6 and ``probe.csv`` into ``staged``; :return: Figure
    2's columns"""
    names, groups, _ = rollouts.targets()
    columns = figure2_columns(task, names, groups)
    curves = panel_curves(rows, {f"seed {t.seed}": which for t, which in agents}, columns)
    well = sum(which == ROWS[0] for _, which in agents)
    described = f"well-performing: {well}, poorly performing: {len(agents) - well}"
    flat = [title for title, targets in columns if warned(warnings, "targets") & set(targets)]
    title = f"{task} / {variant}: OMP probing over training ({described})"
    plot_figure2(curves, staged.path(FIGURE2_PNG), title, flat, warned(warnings, "layers"))
    table_rows = stage_table_rows(curves, budget_frames([trial for trial, _ in agents]))
    if table_rows:
        write_csv(table_rows, list(table_rows[0]), staged.path(TABLES_1_6_CSV))
    staged.path(TABLES_MD).write_text(stage_tables_markdown(table_rows))
    write_csv(rows, list(rows[0]), staged.path(PROBE_CSV))
    return columns
