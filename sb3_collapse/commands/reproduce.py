"""
``python -m sb3_collapse.reproduce --out DIR``: the paper's protocol as five stages, each started when its inputs
exist, skipped when done and resumed when interrupted (run the same command again); docs/reproduce.md.

``sweep`` (Figure 5's trials), ``transplant`` (Study 2's grid, donors drawn from ``sweep``), ``probe`` (``probe
sweep`` per task: Figure 2, Tables 1-6, the fixed inputs of Figures 4, 8, 9), ``film`` (Figures 6-7) and ``report``
(every figure and table, the headline, Proposition 1, and ``paper.md``: each of the paper's items and its file).
Here: the flags, the stages run on the folder pipelines, ``paper.md`` and the dry run's lines; the sizes, the classes
of agents, a reproduction folder's state and the plan: :mod:`sb3_collapse.sweep.reproduction`.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sb3_collapse.commands.cli import (
    CommandLine,
    add_setting_arguments,
    check_arguments,
    prog_name,
    report_unwritable_outputs,
    run_command,
)
from sb3_collapse.commands.sweep import ResourceFlags
from sb3_collapse.errors import InputError
from sb3_collapse.paper import PAPER, PAPER_RESULTS
from sb3_collapse.protocol import (
    EXIT_INTERRUPTED,
    FIGURE2_PNG,
    FINAL_MODEL,
    SWEEP_PROBE_DIR,
    TABLES_1_6_CSV,
    write_json_atomically,
    write_text_atomically,
)
from sb3_collapse.run.config import RUN, declared, setting
from sb3_collapse.runfolder import RunStatus, read_json, run_status
from sb3_collapse.sweep.reproduction import (
    FILMS_DIR,
    INPUTS,
    PAPER_MD,
    REPORT_DIR,
    SCALES,
    SETTINGS_JSON,
    SNAPSHOT_VARIANTS,
    STAGES,
    SWEEP_DIR,
    TINY_SCALE,
    VARIANTS,
    Classes,
    Reproduction,
    film_agents,
    pick_grid_donors,
    reproduction_plan,
)

STAGE_HELP = {
    "sweep": "Figure 5's trials (the DrQ-v2 ones keep snapshots)",
    "transplant": "Study 2's nine grid cells on walker-walk, donors drawn from the sweep",
    "probe": "probe sweep of each task (Figure 2, Tables 1-6, the fixed inputs of Figures 4, 8, 9)",
    "film": "Figures 6-7 from a good and a poor agent",
    "report": "every figure and table, the headline, Proposition 1, and paper.md",
}
"""What each stage does (the command's help)."""
REFERENCE_FPS = 69.5  # benchmarks/README.md#reference-rate: the median of DrQ-v2's published walker-walk curves
REFERENCE_FPS_SOURCE = (
    "DrQ-v2's own walker-walk rate, evaluations included, from the hour column of its published curves "
    "(benchmarks/README.md#reference-rate; this package's GPU rate is not measured yet: "
    "benchmarks/README.md#train-throughput-gpu); pass --frames-per-second with a measured rate"
)
"""The default training rate of the dry run's GPU-hours, and where it comes from."""


# --- the stages ------------------------------------------------------------------------------------------------------


NOT_DONE = "not_done"
"""The key of a stage's record that says why it ended without its outputs (its trials failed, a task could not be
probed): the stage stays undone, named, and the stages that do not read it go on."""


def run_sweep_stage(job: Reproduction, trials: list, checkpoints: Mapping, donors: Mapping | None) -> dict[str, Any]:
    """Train ``trials`` into the sweep folder (finished ones skipped, unfinished ones resumed).

    :return: the stage's record: trials, and the damaged ones named (:data:`NOT_DONE` when a trial failed in a way
        a rerun may fix; ``KeyboardInterrupt`` when interrupted)
    """
    from sb3_collapse.commands.sweep import print_summary
    from sb3_collapse.sweep.cluster import import_ray, ray_session
    from sb3_collapse.sweep.runner import run_sweep, trial_left_as_is
    from sb3_collapse.sweep.trials import trial_dir

    folders = [trial_dir(job.sweep, trial) for trial in trials]  # to train: neither finished nor left as they are
    pending = any(run_status(folder) != RunStatus.FINISHED and trial_left_as_is(folder) is None for folder in folders)
    if pending and not import_ray().is_initialized():  # one Ray for both training stages (run_sweep takes it as is)
        job.resources.enter_context(ray_session(job.address, connect_timeout_s=job.connect_timeout_s))

    summary = run_sweep(
        trials,
        job.sweep,
        dict(job.scale.training),
        checkpoints,
        job.cpus_per_trial,
        job.gpus_per_trial,
        job.address,
        progress_bar=job.progress,
        donors=donors,
        connect_timeout_s=job.connect_timeout_s,
        snapshot_variants=SNAPSHOT_VARIANTS,
        trials_per_worker=job.scale.trials_per_worker,
    )
    status = print_summary(summary, str(job.sweep))
    if summary.interrupted:
        raise KeyboardInterrupt
    if status != 0 and set(summary.failed) - set(summary.damaged):
        return {NOT_DONE: f"{len(summary.failed)} trial(s) failed (listed above)"}
    return {
        "trials": len(trials),
        "trained_now": len(summary.finished),
        "damaged": {str(trial): reason for trial, reason in summary.damaged.items()},
    }


def stage_sweep(job: Reproduction) -> dict[str, Any]:
    """Stage ``sweep``: Figure 5's trials, the DrQ-v2 ones with snapshots."""
    return run_sweep_stage(job, job.sweep_trials(), {}, None)


def stage_transplant(job: Reproduction) -> dict[str, Any]:
    """Stage ``transplant``: the nine cells on Study 2's task, from two good and two bad agents of the sweep."""
    try:
        checkpoints, record, classes = pick_grid_donors(job)
    except InputError as error:
        return {NOT_DONE: str(error).replace("--donors-from ", "")}
    print(classes.line(f"donors of {job.transplant_task}"))
    for key, donor in record["tasks"][job.transplant_task].items():
        print(f"  donor {key}: seed {donor['seed']} (final return {donor['final_return']:.1f}) {donor['path']}")
    return {**run_sweep_stage(job, job.grid_trials(), checkpoints, record), "donors": record}


def stage_probe(job: Reproduction) -> dict[str, Any]:
    """Stage ``probe``: ``probe sweep`` of each task's DrQ-v2 trials (a task done before is skipped)."""
    from sb3_collapse.commands.probe_pipelines import SUMMARY_NAME as SUMMARY_JSON
    from sb3_collapse.commands.probe_pipelines import probe_sweep

    done, failed = {}, []
    for task in job.tasks:
        folder = job.sweep / SWEEP_PROBE_DIR.format(task=task, variant="drqv2")
        classes = job.classes(task)
        if (folder / SUMMARY_JSON).is_file():
            print(f"probe {task}: done before ({folder}): skipped")
        else:
            print(classes.line(f"probe {task}"))
            try:
                probe_sweep(
                    job.sweep,
                    task,
                    "drqv2",
                    folder,
                    job.scale.probe,
                    record_options=job.scale.record,
                    success_return=classes.success_return,
                    failure_return=classes.failure_return,
                    overwrite=True,
                    command=[*prog_name("sb3_collapse.reproduce").split(), "--out", str(job.out)],
                )
            except InputError as error:
                print(f"probe {task}: not done: {error}")
                failed.append(task)
                continue
        done[task] = {"folder": str(folder), **dataclasses.asdict(classes)}
    return {"tasks": done, **({NOT_DONE: f"{', '.join(failed)} not probed (the reason above)"} if failed else {})}


def stage_film(job: Reproduction) -> dict[str, Any]:
    """Stage ``film``: Figure 6 (walker-walk: the poor agent from two initial states) and Figure 7 (finger-spin)."""
    from sb3_collapse.commands.probe_pipelines import FILMSTRIP_PNG, film_to_folder
    from sb3_collapse.sweep.trials import Trial, trial_dir

    films = {}
    for number, task in zip((6, 7), PAPER.film_tasks):
        if task not in job.tasks:
            print(f"film: Figure {number} films {task}, not in --tasks: skipped")
            continue
        folder = job.out / FILMS_DIR / f"figure{number}_{task}"
        try:
            (good, good_return), (poor, poor_return), classes, note = film_agents(job, task)
        except InputError as error:
            return {"films": films, NOT_DONE: str(error)}
        named = (
            f"good: seed {good} (final return {good_return:.1f}), poor: seed {poor} (final return {poor_return:.1f})"
        )
        print(f"film Figure {number}, {task}: {named}" + (f"; {note}" if note else ""))
        if not (folder / FILMSTRIP_PNG).is_file() or not (folder / "actions.csv").is_file():
            paths = [trial_dir(job.sweep, Trial(task, "drqv2", seed)) / FINAL_MODEL for seed in (good, poor)]
            film_to_folder(
                paths,
                folder,
                job.scale.film_frames,
                job.scale.film_size,
                job.scale.film_every_frames,
                seeds=(0, 1) if number == 6 else (0,),
                device="auto",
                overwrite=True,
                progress=job.progress,
            )
        films[f"figure{number}"] = {
            "task": task,
            "folder": str(folder),
            "good": {"seed": good, "final_return": good_return},
            "poor": {"seed": poor, "final_return": poor_return},
            "classes": dataclasses.asdict(classes),
            "note": note,
        }
    return {"films": films}


def stage_report(job: Reproduction) -> dict[str, Any]:
    """Stage ``report``: the sweep's report (every figure and table but the films) and ``paper.md``."""
    from sb3_collapse.commands.report_pipelines import FixedInputSettings, write_report
    from sb3_collapse.report.statistics import ReportSettings

    classes = job.report_classes()
    print(classes.line("report"))
    settings = ReportSettings(success_return=classes.success_return)
    fixed = FixedInputSettings(failure_return=classes.failure_return, rollouts_variant="drqv2")
    report = write_report(
        job.sweep,
        job.out / REPORT_DIR,
        overwrite=True,
        settings=settings,
        tasks=job.tasks,
        progress=job.progress,
        collapse_settings=fixed,
    )
    text = paper_markdown(job, report, classes)
    write_text_atomically(job.out / PAPER_MD, text)
    print(f"Wrote {job.out / REPORT_DIR} ({len(report.files)} files) and {job.out / PAPER_MD}")
    return {"classes": dataclasses.asdict(classes), "files": [str(path) for path in report.files]}


STAGE_FUNCTIONS = {
    "sweep": stage_sweep,
    "transplant": stage_transplant,
    "probe": stage_probe,
    "film": stage_film,
    "report": stage_report,
}


# --- paper.md --------------------------------------------------------------------------------------------------------


def paper_items(job: Reproduction) -> list[tuple[str, str, list[Path]]]:
    """:return: each of the paper's figures and tables: its name, what it shows, the files of this reproduction that
    hold it (relative names resolve under ``out``)"""
    from sb3_collapse.commands.probe_pipelines import TABLES_MD
    from sb3_collapse.report import pipeline as rp

    report, walker = job.out / REPORT_DIR, job.transplant_task
    probe = job.sweep / SWEEP_PROBE_DIR.format(task=walker, variant="drqv2")
    collapse = {task: report / rp.COLLAPSE_PNG.format(task=task, variant="drqv2") for task in PAPER.figure5_tasks}
    films = {number: job.out / FILMS_DIR / f"figure{number}_{task}" for number, task in zip((6, 7), PAPER.film_tasks)}
    return [
        ("Figure 2", f"probing MSE over training, {walker}", [probe / FIGURE2_PNG]),
        ("Figure 3(a)", "successful seeds of the transplant grid", [report / rp.GRID_PNG, report / rp.GRID_MD]),
        ("Figure 3(b)", "the successful seeds' curves per cell", [report / rp.FIGURE3B_PNG]),
        ("Figure 4", f"collapse metrics of three agents, {walker}", [collapse["walker-walk"]]),
        ("Figure 5", "DrQ-v2 against DrQ-v2 + the rule", [report / rp.FIGURE5_PNG]),
        ("Figure 6", "film of a good and a poor agent, walker-walk", [films[6] / "filmstrip.png"]),
        ("Figure 7", "film of a good and a poor agent, finger-spin", [films[7] / "filmstrip.png"]),
        ("Figure 8", "collapse metrics of three agents, hopper-stand", [collapse["hopper-stand"]]),
        ("Figure 9", "collapse metrics of three agents, finger-spin", [collapse["finger-spin"]]),
        (
            "Tables 1-6",
            f"std of Figure 2's panels at four stages, {walker}",
            [probe / TABLES_MD, probe / TABLES_1_6_CSV],
        ),
        ("Table 7", "std of Figure 3(b) at four stages", [report / rp.TABLE7_MD]),
        ("Headline", "stuck seeds and std, against the paper's numbers", [report / rp.SUMMARY_MD]),
        ("Proposition 1", "1 - p^n against the rule's escapes", [report / rp.SUMMARY_MD]),
    ]


def paper_markdown(job: Reproduction, report: Any, classes: Classes) -> str:
    """:return: ``paper.md``: the classes, then a row per item of :func:`paper_items` (its files, or missing), the
    films' agents, and the report's headline and Proposition 1"""
    lines = [
        "# The paper's figures and tables, reproduced",
        "",
        (
            f"Scale: {job.scale.name}; tasks {', '.join(job.tasks)}; {job.seeds} seeds per task and variant; "
            f"{job.transplant_seeds} per transplant cell. {classes.line('Classes of the report')}."
        ),
        "",
        "| item | what | files |",
        "|---|---|---|",
    ]
    for name, what, paths in paper_items(job):
        cells = [
            f"[{path.relative_to(job.out)}]({path.relative_to(job.out)})"
            if path.is_file()
            else f"missing: {path.relative_to(job.out)}"
            for path in paths
        ]
        lines.append(f"| {name} | {what} | {'; '.join(cells)} |")
    film = job.done("film") or {}
    for name, entry in film.get("films", {}).items():
        good, poor = entry["good"], entry["poor"]
        lines.append(
            f"\n{name}: {entry['task']}, good agent seed {good['seed']} (final return {good['final_return']:.1f}), "
            f"poor agent seed {poor['seed']} (final return {poor['final_return']:.1f})"
            + (f"; {entry['note']}" if entry["note"] else "")
        )
    donors = (job.done("transplant") or {}).get("donors")
    if donors:
        for key, donor in donors["tasks"][job.transplant_task].items():
            lines.append(f"\nDonor {key}: seed {donor['seed']} (final return {donor['final_return']:.1f})")
    paper = ", ".join(f"{r.task} {r.stuck_baseline}/{r.seeds}" for r in PAPER_RESULTS)
    lines += ["", f"The paper's DrQ-v2 seeds stuck in action collapse: {paper}.", "", report.markdown]
    return "\n".join(lines) + "\n"


# --- the plan (--dry-run) --------------------------------------------------------------------------------------------


def dry_run(job: Reproduction, stages: Sequence[str], fps: float, fps_source: str) -> int:
    """Print every stage's plan (trials, frames, GPU-hours, RAM, disk, trials at once); write nothing."""
    from sb3_collapse.commands.sweep import plan_lines
    from sb3_collapse.sweep.plan import size_text

    print(f"Plan of {job.out} at the {job.scale.name} scale (nothing written):")
    planned = reproduction_plan(job, stages, fps)
    for stage in stages:
        marker = job.done(stage)
        state = "done: skipped" if marker is not None else "to run"
        if stage in planned["stages"]:
            entry = planned["stages"][stage]
            trials, plan, hours = entry["trials"], entry["plan"], entry["trial_hours"]
            what = (
                f"{len(job.tasks)} tasks x {', '.join(VARIANTS)} x {job.seeds} seeds"
                if stage == "sweep"
                else f"{job.transplant_task} x 9 cells x {job.transplant_seeds} seeds, donors: two good and two bad "
                "DrQ-v2 agents of the sweep stage"
            )
            print(f"\nstage {stage} ({state}): {trials} trials ({what}), {plan['trials_pending']} to train")
            snapshots = ", ".join(SNAPSHOT_VARIANTS) if stage == "sweep" else "none"
            print(f"  snapshots kept by: {snapshots}")
            if plan["trials_pending"]:
                lines = "\n".join(plan_lines(plan))  # the sweep's wording names the flag: say the rate's source
                print(
                    lines.replace(" (--frames-per-second)", "" if fps_source == "--frames-per-second" else " (below)")
                )
            gpus = job.gpus_per_trial
            on = (
                f"{hours * gpus:,.1f} GPU-hours at --gpus-per-trial {gpus:g}"
                if gpus > 0
                else (f"{hours:,.1f} GPU-hours at one GPU per trial (--gpus-per-trial 0 trains on CPUs)")
            )
            print(f"  compute: {hours:,.1f} trial-hours at {fps:g} frames/s per trial ({fps_source}): {on}")
        elif stage == "probe":
            probe = job.scale.probe
            print(
                f"\nstage probe ({state}): probe sweep of {', '.join(job.tasks)} / drqv2: rollouts of "
                f"{job.scale.record.episodes} episodes from the best well-performing seed, then every snapshot of "
                f"the well- and poorly performing seeds (at most {job.seeds} per task), layers "
                f"{' '.join(probe.layers or ('cnn0..mlp2',))}, max_tau {probe.max_tau}; writes "
                f"{SWEEP_DIR}/{SWEEP_PROBE_DIR.format(task='<task>', variant='drqv2')}/"
            )
        elif stage == "film":
            print(
                f"\nstage film ({state}): Figures 6 and 7, {' and '.join(PAPER.film_tasks)}: the best well-performing "
                f"and the worst poorly performing DrQ-v2 seed, {job.scale.film_frames} frames at "
                f"{job.scale.film_size}x{job.scale.film_size}; writes {FILMS_DIR}/figure<6|7>_<task>/"
            )
        else:
            print(f"\nstage report ({state}): every figure and table into {REPORT_DIR}/, and {PAPER_MD}")
    print(
        f"\nin all: {planned['trial_hours']:,.1f} trial-hours to train; disk at the peak "
        f"{size_text(planned['disk_peak_bytes'])}, at the end {size_text(planned['disk_end_bytes'])} (final models and "
        "snapshots; the probe, films and report add a few MB)"
    )
    return 0


# --- the command line ------------------------------------------------------------------------------------------------


@declared
@dataclass
class ReproduceFlags:
    """The reproduction's own flags (beside the sweep's :class:`~sb3_collapse.commands.sweep.ResourceFlags`),
    declared once: parser, help, range checks and the table in docs/reproduce.md."""

    out: str | None = setting(cli=RUN, required=True)
    """the folder of every output: a new or empty one, or one this command started with the same --scale, --tasks,
    --seeds and --transplant-seeds"""
    scale: str = setting("paper", cli=RUN, choices=tuple(SCALES))
    """paper: the paper's counts and budgets; tiny: the same stages at CPU sizes, in minutes (docs/reproduce.md)"""
    stages: tuple[str, ...] | None = setting(cli=RUN, nargs="+", metavar="STAGE", choices=STAGES)
    """the stages to run, in their order (default: all); a stage whose inputs are neither done nor in --stages is
    refused"""
    tasks: tuple[str, ...] | None = setting(
        cli=RUN,
        nargs="+",
        help=f"Figure 5's tasks (default: {' '.join(PAPER.figure5_tasks)}; {PAPER.transplant_task} is required: Study "
        "2's grid, Figure 2 and the report read it)",
    )
    seeds: int | None = setting(
        cli=RUN,
        minimum=1,
        help=f"seeds per task and variant (default: {PAPER.figure5_seeds}; tiny: {TINY_SCALE.seeds})",
    )
    transplant_seeds: int | None = setting(
        cli=RUN,
        minimum=1,
        help=f"seeds per transplant cell (default: {PAPER.transplant_seeds}; tiny: {TINY_SCALE.transplant_seeds})",
    )
    dry_run: bool = setting(False, cli=RUN)
    """print every stage's plan (trials, frames, GPU-hours, RAM, disk, trials at once); write nothing"""
    frames_per_second: float | None = setting(
        cli=RUN,
        metavar="FPS",
        above=0,
        help=f"one trial's training frames/s, for the GPU-hours (default: {REFERENCE_FPS:g}, {REFERENCE_FPS_SOURCE})",
    )


COMMANDS: dict[str, tuple[type, ...]] = {"": (ReproduceFlags, ResourceFlags)}
"""The flags, by the dataclasses that declare them (the parser, the help, the range checks and the table in
``docs/reproduce.md`` are generated from it)."""


def build_parser() -> argparse.ArgumentParser:
    """The command line of ``python -m sb3_collapse.reproduce``, its flags generated from :data:`COMMANDS`."""
    parser = CommandLine(
        prog=prog_name("sb3_collapse.reproduce"),
        description="The action-collapse paper's protocol as stages, each started when its inputs exist and "
        "skipped when done (rerun the same command to resume): "
        + "; ".join(f"{stage}: {what}" for stage, what in STAGE_HELP.items())
        + ". Frames = agent steps x action repeat; docs/reproduce.md.",
    )
    add_setting_arguments(parser, declaration=ReproduceFlags)
    resources = parser.add_argument_group("resources (those of python -m sb3_collapse.sweep)")
    add_setting_arguments(resources, declaration=ResourceFlags)
    return parser


def check_out(parser: argparse.ArgumentParser, job: Reproduction) -> None:
    """``--out``: new, empty, or a reproduction started with the same settings (else one line naming the flag)."""
    out = job.out
    if out.exists() and not out.is_dir():
        parser.error(f"--out {out} is a file: give a folder.")
    if not out.is_dir() or not any(out.iterdir()):
        return
    path = out / SETTINGS_JSON
    if not path.is_file():
        held = ", ".join(sorted(p.name for p in out.iterdir())[:3])
        parser.error(f"--out {out} holds other files ({held}...), not a reproduction: give a new or empty folder.")
    before = read_json(path)
    for name, value in job.settings().items():
        if before.get(name) != value:
            flag = "--" + name.replace("_", "-")
            parser.error(
                f"{flag}: {out} is a reproduction with {flag} {before.get(name)}, not {value}: give the same "
                "settings to resume it, or another --out."
            )


def check_stages(parser: argparse.ArgumentParser, job: Reproduction, stages: Sequence[str]) -> None:
    """``--stages`` (each one of :data:`STAGES`, as argparse checked): each stage's inputs done or scheduled before
    it."""
    for stage in stages:
        for needed in INPUTS[stage]:
            if needed not in stages and job.done(needed) is None:
                parser.error(
                    f"--stages: {stage} reads the outputs of {needed}, which {job.out} does not hold and --stages "
                    f"does not run: add {needed}."
                )


@report_unwritable_outputs
def main(argv: list[str] | None = None) -> int:
    """
    :param argv: command-line arguments (``sys.argv[1:]`` when ``None``)
    :return: exit status: 0 when every stage is done, 1 when a stage could not finish (named; the others went on),
        2 for bad input, :data:`~sb3_collapse.protocol.EXIT_INTERRUPTED` when interrupted (run it again to resume)
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    check_arguments(parser, args, *COMMANDS[""])
    scale = SCALES[args.scale]
    try:
        from sb3_collapse.sweep.trials import canonical_task

        tasks = tuple(canonical_task(task) for task in args.tasks or scale.tasks)
    except InputError as error:
        parser.error(f"--tasks: {error}")
    if PAPER.transplant_task not in tasks:
        parser.error(f"--tasks must hold {PAPER.transplant_task}: Study 2's grid, Figure 2 and the report read it.")
    job = Reproduction(
        Path(args.out),
        scale,
        tasks,
        args.seeds or scale.seeds,
        args.transplant_seeds or scale.transplant_seeds,
        args.address,
        args.cpus_per_trial,
        args.gpus_per_trial,
        args.connect_timeout_s,
        args.progress_bar,
    )
    stages = [stage for stage in STAGES if stage in (args.stages or STAGES)]
    check_stages(parser, job, args.stages or STAGES)
    check_out(parser, job)
    stopped = (
        f"\nStopped: run the same command again to resume (the finished stages and trials in {job.out} are kept; "
        f"exit status {EXIT_INTERRUPTED})."
    )
    return run_command(parser, lambda: run(job, stages, args.dry_run, args.frames_per_second), lambda _: stopped)


def run(job: Reproduction, stages: Sequence[str], plan_only: bool, frames_per_second: float | None) -> int:
    """Check the sweep stage's settings, then print the plan of ``stages`` (``plan_only``) or run them; :return: the
    exit status"""
    from sb3_collapse.sweep.runner import check_sweep

    check_sweep(
        job.sweep_trials(),
        job.sweep,
        dict(job.scale.training),
        {},
        job.cpus_per_trial,
        job.gpus_per_trial,
        job.connect_timeout_s,
    )
    if plan_only:
        fps = frames_per_second or REFERENCE_FPS
        source = "--frames-per-second" if frames_per_second else REFERENCE_FPS_SOURCE
        return dry_run(job, stages, fps, source)
    return run_stages(job, stages)


def run_stages(job: Reproduction, stages: Sequence[str]) -> int:
    """Run ``stages`` in order: each skipped when done, started when its inputs are done; :return: the exit status"""
    job.out.mkdir(parents=True, exist_ok=True)
    if not (job.out / SETTINGS_JSON).is_file():
        write_json_atomically(job.out / SETTINGS_JSON, job.settings())
    started, failed = time.perf_counter(), []
    with job.resources:
        failed = _run_each(job, stages)
    took = f"{time.perf_counter() - started:.0f} s"
    if failed:
        print(f"Not finished: {', '.join(failed)} ({took}); run the same command again once the cause is fixed.")
        return 1
    print(f"Every stage done ({took}): {job.out / PAPER_MD} lists the paper's figures and tables.")
    return 0


def _run_each(job: Reproduction, stages: Sequence[str]) -> list[str]:
    """Run ``stages`` in order; :return: those not done"""
    failed = []
    for stage in stages:
        if job.done(stage) is not None:
            print(f"stage {stage}: done before ({job.marker(stage)}): skipped")
            continue
        lacking = [needed for needed in INPUTS[stage] if job.done(needed) is None]
        if lacking:
            print(f"stage {stage}: not started: {', '.join(lacking)} did not finish")
            failed.append(stage)
            continue
        print(f"stage {stage}: running")
        begin = time.perf_counter()
        record = STAGE_FUNCTIONS[stage](job)
        if NOT_DONE in record:
            print(f"stage {stage}: not finished: {record[NOT_DONE]}")
            failed.append(stage)
            continue
        job.finish(stage, {**record, "seconds": round(time.perf_counter() - begin, 1)})
        print(f"stage {stage}: done in {time.perf_counter() - begin:.0f} s")
    return failed


if __name__ == "__main__":
    sys.exit(main())
