"""
``python -m sb3_collapse.probe sweep``: the paper's Figure 2 and Tables 1-6 for one task and variant of a sweep
folder whose trials saved snapshots (``--snapshots``: their encoder and actor at every evaluation).

1. The finished trials are split by final return: well-performing (``>= success_return``, default
   ``PAPER.success_return``) and poorly performing (``< failure_return``, default ``PAPER.failure_return``); the
   others are not probed.
2. Rollouts are recorded once, from the well-performing seed of the highest final return (its final model), or
   read from ``rollouts_path``.
3. Every snapshot of those trials is probed on them (``cnn0``, the normalized pixels, once for all).
4. Figure 2 (``figure2.png``), Tables 1-6 (``tables_1_6.csv``/``.md``), all probe rows (``probe.csv``) and
   ``summary.json`` are written into ``out``, only when everything succeeded.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from stable_baselines3.common.utils import get_device
from tqdm.auto import tqdm

from sb3_collapse.errors import ProbeError, ReportError
from sb3_collapse.paper import PAPER
from sb3_collapse.probe.checkpoints import load_checkpoint
from sb3_collapse.probe.figure2 import (
    ROWS,
    figure2_columns,
    panel_curves,
    plot_figure2,
    stage_table_rows,
    stage_tables_markdown,
)
from sb3_collapse.probe.pipeline import ROLLOUTS_NAME, RecordOptions, record
from sb3_collapse.probe.probing import MIN_EPISODES, ProbeSettings, probe_checkpoint, split_by_episode
from sb3_collapse.probe.report import write_csv, write_json
from sb3_collapse.probe.rollouts import Rollouts
from sb3_collapse.protocol import (
    FIGURE2_PNG,
    FINAL_MODEL,
    SNAPSHOTS_DIR,
    SWEEP_PROBE_DIR,
    TABLES_1_6_CSV,
    snapshot_files,
)
from sb3_collapse.report.loading import Trial, load_sweep
from sb3_collapse.report.statistics import budget_frames
from sb3_collapse.staged_outputs import StagedOutputs

TABLES_MD = "tables_1_6.md"
PROBE_CSV = "probe.csv"
SUMMARY_JSON = "summary.json"
OUTPUT_FILES = (FIGURE2_PNG, TABLES_1_6_CSV, TABLES_MD, PROBE_CSV, ROLLOUTS_NAME, SUMMARY_JSON)
"""Every file ``probe sweep`` writes (``summary.json`` last)."""
DEFAULT_OUT = SWEEP_PROBE_DIR
"""The default output folder, inside the sweep folder."""


def split_agents(
    trials: Sequence[Trial],
    success_return: float = PAPER.success_return,
    failure_return: float = PAPER.failure_return,
) -> tuple[list[Trial], list[Trial]]:
    """
    :param trials: finished trials
    :param success_return: a final return ``>=`` this is well-performing
    :param failure_return: a final return ``<`` this is poorly performing
    :return: ``(well, poor)``, each by decreasing final return
    """
    ranked = sorted((t for t in trials if t.finished and len(t.returns)), key=lambda t: (-t.returns[-1], t.seed))
    return [t for t in ranked if t.returns[-1] >= success_return], [t for t in ranked if t.returns[-1] < failure_return]


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
    Figure 2 and Tables 1-6 of one task and variant of a sweep (see the module's documentation).

    :param sweep_dir: the sweep folder
    :param task: its task folder, e.g. ``"walker-walk"``
    :param variant: its variant folder
    :param out: the output folder (default ``<sweep>/probe/<task>_<variant>``)
    :param settings: the probe's settings
    :param rollouts_path: rollouts to probe on (``None``: record them from the best well-performing seed)
    :param record_options: how to record (``env`` and the pixel settings come from the recording checkpoint)
    :param success_return: final return of a well-performing agent, at least
    :param failure_return: final return of a poorly performing agent, below
    :param overwrite: replace a previous run's outputs in ``out``
    :param command: the command line, for the summary
    :param jobs: checkpoints probed at once (threads: the forward passes and OMP fits run in torch, outside Python's
        lock). ``settings.memory_gb`` bounds them all together: each gets ``memory_gb / jobs`` for its activations
        (snapshots themselves are small: benchmarks/README.md#checkpoint-sizes). The first checkpoint is probed
        alone, so that the others reuse its ``cnn0`` probe. The results do not depend on ``jobs``
    :return: the summary (as written to ``summary.json``)
    :raises ProbeError: for bad input (nothing written then)
    """
    started = time.perf_counter()
    settings = settings or ProbeSettings()
    settings.validate()
    if isinstance(jobs, bool) or not isinstance(jobs, int) or jobs < 1:
        raise ProbeError(f"jobs must be an integer >= 1, got {jobs!r}.", parameter="jobs")
    if not failure_return <= success_return:
        raise ProbeError(
            f"failure_return must be <= success_return, got {failure_return:g} and {success_return:g}.",
            parameter="failure_return",
        )
    try:
        sweep = load_sweep(sweep_dir, tasks=[task], variants=[variant], progress=False)
    except ReportError as error:
        raise ProbeError(
            str(error), parameter=error.parameter if error.parameter != "sweep" else "sweep_dir"
        ) from error
    well, poor = split_agents(sweep.finished, success_return, failure_return)
    if not well and not poor:
        finals = ", ".join(f"seed {t.seed}: {t.returns[-1]:.0f}" for t in sweep.finished) or "no finished trial"
        raise ProbeError(
            f"{task} / {variant} has no well-performing (final return >= {success_return:g}) nor poorly performing "
            f"(< {failure_return:g}) finished trial ({finals}); lower success_return or raise failure_return.",
            parameter="success_return",
        )
    agents = [(trial, ROWS[0]) for trial in well] + [(trial, ROWS[1]) for trial in poor]
    files = {trial.seed: snapshot_files(trial.path) for trial, _ in agents}
    lacking = [t for t, _ in agents if not files[t.seed]]
    if lacking:
        raise ProbeError(
            f"no {SNAPSHOTS_DIR}/*.zip in {', '.join(str(t.path) for t in lacking)}: train the trials with "
            "--snapshots (TrainConfig.snapshots) to probe them over training."
        )
    record_options = record_options or RecordOptions()
    if rollouts_path is None:
        if not well:
            raise ProbeError(
                f"{task} / {variant} has no well-performing trial (final return >= {success_return:g}) to record "
                "rollouts from: pass rollouts_path (python -m sb3_collapse.probe record GOOD.zip).",
                parameter="rollouts_path",
            )
        record_options.check()
        if record_options.episodes < MIN_EPISODES:
            raise ProbeError(
                f"episodes must be >= {MIN_EPISODES}, got {record_options.episodes}.", parameter="episodes"
            )
    out = Path(sweep_dir) / DEFAULT_OUT.format(task=task, variant=variant) if out is None else Path(out)
    device = get_device(settings.device)
    with StagedOutputs(out, OUTPUT_FILES, SUMMARY_JSON, overwrite=overwrite, error=ProbeError) as staged:
        if rollouts_path is None:
            source = well[0].path / FINAL_MODEL
            source = source if source.exists() else files[well[0].seed][-1]
            recorder = load_checkpoint(source, device=device)
            rollouts = record(recorder, record_options, settings.progress)
            rollouts.save(staged.path(ROLLOUTS_NAME))
            recorded_from = str(source)
            del recorder
        else:
            rollouts = Rollouts.load(rollouts_path)
            recorded_from = str(rollouts_path)
        split = split_by_episode(rollouts.episode_ids, settings.fractions, settings.split_seed)
        reuse: dict = {}
        quiet = dataclasses.replace(settings, progress=False, memory_gb=settings.memory_gb / jobs)
        work = [(trial, which, path) for trial, which in agents for path in files[trial.seed]]

        def probe_one(item: tuple[Trial, str, Path]) -> list[dict[str, Any]]:
            trial, which, path = item
            checkpoint = load_checkpoint(path, device=device)
            checkpoint.label = f"seed_{trial.seed}/{path.stem}"
            result = probe_checkpoint(checkpoint, rollouts, split, quiet, reuse)
            for row in result.rows:
                row.update(agent=f"seed {trial.seed}", agent_row=which, final_return=float(trial.returns[-1]))
            return result.rows

        per_checkpoint: list[list[dict[str, Any]]] = []
        with tqdm(total=len(work), desc="probing checkpoints", unit="checkpoint", disable=not settings.progress) as bar:
            per_checkpoint.append(probe_one(work[0]))  # alone: the others reuse its cnn0 probe
            bar.update()
            with ThreadPoolExecutor(max_workers=jobs) as pool:
                for result_rows in pool.map(probe_one, work[1:]):  # in the order of work, whatever finishes first
                    per_checkpoint.append(result_rows)
                    bar.update()
        rows = [row for result_rows in per_checkpoint for row in result_rows]
        names, groups, _ = rollouts.targets()
        columns = figure2_columns(task, names, groups)
        curves = panel_curves(rows, {f"seed {t.seed}": which for t, which in agents}, columns)
        described = f"well-performing: {len(well)}, poorly performing: {len(poor)}"
        plot_figure2(curves, staged.path(FIGURE2_PNG), f"{task} / {variant}: OMP probing over training ({described})")
        table_rows = stage_table_rows(curves, budget_frames([trial for trial, _ in agents]))
        if table_rows:
            write_csv(table_rows, staged.path(TABLES_1_6_CSV))
        staged.path(TABLES_MD).write_text(stage_tables_markdown(table_rows))
        write_csv(rows, staged.path(PROBE_CSV))
        summary = {
            "complete": True,
            "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "command": list(command) if command is not None else None,
            "sweep": str(sweep_dir),
            "task": task,
            "variant": variant,
            "success_return": success_return,
            "failure_return": failure_return,
            "agents": [
                {"seed": t.seed, "row": which, "final_return": float(t.returns[-1]), "checkpoints": len(files[t.seed])}
                for t, which in agents
            ],
            "not_probed": [
                {"seed": t.seed, "final_return": float(t.returns[-1])} for t in sweep.finished if t.seed not in files
            ],
            "unfinished": [t.seed for t in sweep.unfinished],
            "rollouts": {"recorded_from": recorded_from, "samples": len(rollouts), "episodes": rollouts.n_episodes},
            "columns": {title: list(targets) for title, targets in columns},
            "settings": {k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(settings).items()},
            "jobs": jobs,
            "total_seconds": round(time.perf_counter() - started, 1),
        }
        write_json(summary, staged.path(SUMMARY_JSON))
        written = staged.commit()
    print("Wrote " + ", ".join(str(f) for f in written))
    return summary
