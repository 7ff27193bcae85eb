"""Multi-seed sweeps on Ray: ``python -m sb3_collapse.sweep --help``, docs/sweeps.md."""

from __future__ import annotations

import argparse
import inspect
import sys
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

from sb3_collapse.commands.cli import (
    CommandLine,
    add_setting_arguments,
    check_arguments,
    cli_message,
    prog_name,
    report_unwritable_outputs,
    run_command,
    setting_flags,
    training_arguments,
    training_settings,
)
from sb3_collapse.errors import InputError, MissingDependencyError
from sb3_collapse.paper import PAPER
from sb3_collapse.protocol import ERROR_TXT, EXIT_INTERRUPTED, SWEEP_LOCK
from sb3_collapse.run.config import RUN, declared, setting
from sb3_collapse.run.variants import BLANK_SOURCE, GRID_VARIANTS, VARIANT_FORMS, transplant_of
from sb3_collapse.runfolder import NOT_A_RUN, RunStatus, run_folder_owner
from sb3_collapse.sweep.cluster import CONNECT_TIMEOUT_S
from sb3_collapse.sweep.donors import (
    DONOR_KEYS,
    check_distinct_donors,
    donors_record,
    pick_donors,
)
from sb3_collapse.sweep.plan import check_disk, check_node, size_text, states_plan, trial_states
from sb3_collapse.sweep.runner import (
    Attempt,
    SweepSummary,
    check_sweep,
    prepare_sweep_folder,
    run_sweep,
    sweep_settings,
)
from sb3_collapse.sweep.trials import (
    expand_trials,
    parse_checkpoint_specs,
    trial_dir,
)

DEFAULT_VARIANTS = ("drqv2", "drqv2+reset")
THROUGHPUT_ROWS = "benchmarks/README.md#train-throughput-gpu (cuda), #train-throughput-cpu (cpu)"


@declared
@dataclass
class SweepFlags:
    """The sweep's own flags (beside every training flag of train), declared once: parser, help and range checks."""

    tasks: tuple[str, ...] | None = setting(cli=RUN, nargs="+", required=True)
    """dm_control tasks: walker-walk hopper-stand ..."""
    seeds: int | None = setting(cli=RUN, minimum=1)
    """number of seeds: N runs seeds 0 .. N-1"""
    seed_list: tuple[int, ...] | None = setting(cli=RUN, nargs="+")
    """explicit seeds, e.g. 3 7"""
    variants: tuple[str, ...] | None = setting(
        cli=RUN,
        nargs="+",
        help=f"{VARIANT_FORMS} (td3, sac: SB3's, from the same pixels; drqv2-leaky: Leaky-ReLU activations; "
        f"docs/interventions.md); default: {' '.join(DEFAULT_VARIANTS)} (only the grid with --transplant-grid)",
    )
    transplant_grid: bool = setting(False, cli=RUN)
    """add the 9 cells of the CNN x MLP transplant grid"""
    out: str | None = setting(cli=RUN, required=True)
    """the sweep folder (with --address: on storage every node sees)"""
    allow_changed_settings: bool = setting(False, cli=RUN)
    """run even if --out holds a sweep with other training settings (finished trials keep theirs)"""
    dry_run: bool = setting(False, cli=RUN)
    """list the trials and their status, then the plan (what the trials to train take: frames, updates, RAM, disk,
    time; docs/sweeps.md), run nothing"""
    list_limit: int | None = setting(cli=RUN, flag="--list", metavar="N", minimum=0)
    """with --dry-run: list only the first N trials (0: the counts and the plan only; default: all)"""
    frames_per_second: float | None = setting(cli=RUN, metavar="FPS", above=0)
    """one trial's training frames/s, measured on this device (benchmarks/README.md#train-throughput-gpu (cuda),
    #train-throughput-cpu (cpu)): the plan's time estimate; none without it"""


@declared
@dataclass
class ResourceFlags:
    """Where and with what the trials run: the flags of the sweep and of the reproduction (``python -m
    sb3_collapse.reproduce``), declared once."""

    address: str | None = setting(cli=RUN)
    """Ray cluster to run on ('auto', 'ray://head:10001', 'head:6379'); default: a new local Ray instance.
    sb3-collapse must be installed on every node and --out, the checkpoints on storage every node sees"""
    connect_timeout_s: float = setting(CONNECT_TIMEOUT_S, cli=RUN, flag="--connect-timeout", metavar="SECONDS")
    """with --address: give up, writing nothing, when the cluster does not answer within this time (exit status 1)"""
    cpus_per_trial: float = setting(1, cli=RUN)
    """CPUs per trial; also its torch threads"""
    gpus_per_trial: float = setting(0, cli=RUN)
    """GPUs Ray reserves per trial, fractions allowed (0.25: 4 trials per GPU); > 0 trains on cuda, 0 on cpu"""
    progress_bar: bool = setting(True, cli=RUN)
    """show the progress bar"""


@declared
@dataclass
class DonorFlags:
    """transplant donors (Study 2: the CNN and the MLP of a source from two different agents; docs/sweeps.md)"""

    good_cnn: tuple[str, ...] | None = setting(cli=RUN, nargs="+", metavar="[TASK=]PATH")
    """DrQv2 checkpoint(s) of the well performing agent that gives the good CNN: PATH for every task, TASK=PATH per
    task"""
    good_mlp: tuple[str, ...] | None = setting(cli=RUN, nargs="+", metavar="[TASK=]PATH")
    """DrQv2 checkpoint(s) of the well performing agent that gives the good MLP: PATH for every task, TASK=PATH per
    task"""
    bad_cnn: tuple[str, ...] | None = setting(cli=RUN, nargs="+", metavar="[TASK=]PATH")
    """DrQv2 checkpoint(s) of the poorly performing agent that gives the bad CNN: PATH for every task, TASK=PATH per
    task"""
    bad_mlp: tuple[str, ...] | None = setting(cli=RUN, nargs="+", metavar="[TASK=]PATH")
    """DrQv2 checkpoint(s) of the poorly performing agent that gives the bad MLP: PATH for every task, TASK=PATH per
    task"""
    donors_from: str | None = setting(
        cli=RUN,
        metavar="SWEEP",
        help="pick the donors at random from this finished sweep instead: per task, two different seeds with a final "
        f"return >= {PAPER.success_return:g} (good CNN, good MLP) and two < {PAPER.failure_return:g} (bad ones)",
    )
    donor_variant: str = setting("drqv2", cli=RUN)
    """the variant of `donors_from` giving parts"""
    donor_seed: int = setting(0, cli=RUN)
    """seed of the pick of `donors_from`"""


def build_parser() -> argparse.ArgumentParser:
    """The command line of ``python -m sb3_collapse.sweep``: the sweep's flags (:class:`SweepFlags`,
    :class:`ResourceFlags`, :class:`DonorFlags`) and every training flag of train."""
    p = CommandLine(
        prog=prog_name("sb3_collapse.sweep"),
        description="Run every (task, variant, seed) as an independent trial on Ray (DrQ-v2, or the TD3/SAC "
        "baselines that --variants names), each into <out>/<task>/<variant>/seed_<k> (the run folder of python -m "
        "sb3_collapse.train). Each task trains with its own DrQ-v2 preset (docs/presets.md); a DrQ-v2 flag given "
        "here overrides it for every task and is recorded. Rerun the same command to resume: finished trials are "
        "skipped, unfinished ones resume from their newest checkpoint. Frames = agent steps x action repeat.",
        parents=[training_arguments()],
    )
    g, first = p.add_argument_group("sweep"), ["tasks", "seeds", "seed_list", "variants", "transplant_grid"]
    add_setting_arguments(g, first[:1], SweepFlags)
    add_setting_arguments(g.add_mutually_exclusive_group(required=True), first[1:3], SweepFlags)
    add_setting_arguments(g, first[3:], SweepFlags)
    add_setting_arguments(p.add_argument_group(inspect.getdoc(DonorFlags)), declaration=DonorFlags)
    add_setting_arguments(g, [name for name in setting_flags(SweepFlags) if name not in first], SweepFlags)
    add_setting_arguments(g, declaration=ResourceFlags)
    return p


@report_unwritable_outputs
def main(argv: list[str] | None = None) -> int:
    """
    :param argv: command-line arguments (``sys.argv[1:]`` when ``None``)
    :return: exit status: 0 when every trial finished, 1 when some failed (or the cluster did not answer), 2 for
        bad arguments, :data:`~sb3_collapse.protocol.EXIT_INTERRUPTED` when a signal stopped the sweep or another
        process held a trial's folder (run the same command again once it ended)
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    check_arguments(parser, args, SweepFlags, ResourceFlags, DonorFlags)
    stopped = (
        f"\nStopped at once: the running trials resume from their last checkpoints; run the same command again to "
        f"resume (finished trials in {args.out} are kept; exit status {EXIT_INTERRUPTED})."
    )
    return run_command(
        parser, lambda: run(parser, args), lambda _: stopped, bad_input=(MissingDependencyError, ValueError)
    )


def run(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    """The sweep of the parsed ``args`` (its dry run with ``--dry-run``); :return: the exit status"""
    training = training_settings(args)
    seeds = range(args.seeds) if args.seeds is not None else args.seed_list
    variants = list(args.variants or ([] if args.transplant_grid else DEFAULT_VARIANTS))
    if args.transplant_grid:
        variants += GRID_VARIANTS
    trials = expand_trials(args.tasks, variants, seeds)
    checkpoints, donors = transplant_checkpoints(args, trials)
    check_sweep(
        trials, args.out, training, checkpoints, args.cpus_per_trial, args.gpus_per_trial, args.connect_timeout_s
    )
    states = trial_states(trials, args.out, training, checkpoints)
    plan = states_plan(states, args.cpus_per_trial, args.gpus_per_trial, args.frames_per_second, args.out)
    if args.address is None:  # this machine runs the trials: it must hold one
        check_node(plan)
    if (shortage := check_disk(plan)) is not None:  # one trial that cannot fit: refused (an InputError)
        print(f"warning: {cli_message(InputError(shortage), parser)}", file=sys.stderr)
    if args.dry_run:
        return dry_run(
            states, args.out, training, checkpoints, args.allow_changed_settings, donors, plan, args.list_limit
        )
    summary = run_sweep(
        trials, args.out, training, checkpoints, args.cpus_per_trial, args.gpus_per_trial, args.address,
        args.allow_changed_settings, args.progress_bar, donors, args.connect_timeout_s, plan,
    )  # fmt: skip
    return print_summary(summary, args.out)


def print_summary(summary: SweepSummary, out: str) -> int:
    """Print what the sweep did; return the exit status (0 all finished, 1 some failed, EXIT_INTERRUPTED stopped)."""
    stopped = sum(checkpoint is not None for checkpoint in summary.interrupted.values())
    print(
        f"{len(summary.trials)} trials in {out}: {len(summary.finished)} finished now "
        f"({len(summary.resumed)} resumed from a checkpoint), {len(summary.skipped)} finished before, "
        f"{len(summary.failed)} failed"
        + (f", {stopped} stopped at a checkpoint" if stopped else "")
        + (f", {len(summary.interrupted) - stopped} not started" if len(summary.interrupted) > stopped else "")
        + (f", {len(summary.in_use)} in use by another process" if summary.in_use else "")
        + "."
    )
    for trial, error_path in summary.failed.items():  # a damaged trial's line says the way out
        again = ", and would again at a rerun" if trial in summary.repeating and trial not in summary.damaged else ""
        why = f": {summary.damaged[trial]}" if trial in summary.damaged else f" (see {error_path})"
        if trial in summary.reasons and not error_path.is_file():  # its error file could not be written
            why = f": {summary.reasons[trial]}"
        print(f"  failed{again}: {trial}{why}")
    for trial, owner in summary.in_use.items():
        print(f"  in use: {trial}: its folder is held by {owner}; left as it is")
    if others := len(summary.failed) - len(summary.damaged):
        print(failure_advice(others, len(summary.repeating) - len(summary.damaged)))
    if summary.in_use:
        them = "it" if len(summary.in_use) == 1 else "them"
        print(
            f"Run the same command again once the process holding {them} has ended: the sweep trains {them} then"
            + ("." if summary.failed or summary.interrupted else f" (exit status {EXIT_INTERRUPTED}).")
        )
    if summary.failed:
        return 1
    if summary.in_use and not summary.interrupted:
        return EXIT_INTERRUPTED
    if summary.interrupted:
        print(
            f"Stopped by {summary.stopped_by or 'a signal to the trials'}: run the same command again to resume "
            f"(exit status {EXIT_INTERRUPTED})."
        )
        return EXIT_INTERRUPTED
    return 0


def failure_advice(failed: int, repeating: int) -> str:
    """One line: what to do about ``failed`` trials, ``repeating`` of them failing the same way at a rerun."""
    fix = (
        f"fix the cause first (their {ERROR_TXT} says it: bad settings, a diverging run, an error of the training code)"
    )
    if repeating == 0:
        return "Rerun the same command to retry the failed trials."
    if repeating == failed:
        return f"A rerun would fail {'this trial' if failed == 1 else 'these trials'} the same way: {fix}."
    return (
        f"Rerun the same command to retry the other {failed - repeating} failed trials; the {repeating} marked would "
        f"fail the same way: {fix}."
    )


def transplant_checkpoints(args: argparse.Namespace, trials: list) -> tuple[dict[str, dict[str, str]], dict | None]:
    """The grid cells' donors, given (``--good-cnn``...) or picked (``--donors-from``): key -> task -> path, record."""
    tasks = list(dict.fromkeys(trial.task for trial in trials))
    given = {key: getattr(args, key) for key in DONOR_KEYS if getattr(args, key) is not None}
    if args.donors_from is None:
        checkpoints = {
            key: parse_checkpoint_specs(specs, tasks, f"--{key.replace('_', '-')}") for key, specs in given.items()
        }
        check_distinct_donors(checkpoints)
        return checkpoints, None
    if given:
        flags = ", ".join(f"--{key.replace('_', '-')}" for key in given)
        raise InputError(f"--donors-from picks every donor: leave out {flags}.", parameter="donors_from")
    needed = {source for trial in trials for source in (transplant_of(trial.variant) or {}).values()} - {BLANK_SOURCE}
    grid_tasks = list(dict.fromkeys(trial.task for trial in trials if transplant_of(trial.variant)))
    picked = {
        task: pick_donors(args.donors_from, task, args.donor_seed, args.donor_variant, sorted(needed))
        for task in grid_tasks
    }
    checkpoints: dict[str, dict[str, str]] = {}
    for task, donors in picked.items():
        for key, donor in donors.items():
            checkpoints.setdefault(key, {})[task] = donor.path
    return checkpoints, donors_record(args.donors_from, args.donor_seed, args.donor_variant, picked)


def dry_run(
    states: dict, out: str, training: dict, checkpoints: dict, allow_changed_settings: bool, donors: dict | None,
    plan: dict, list_limit: int | None = None,
) -> int:  # fmt: skip
    """Print the first ``list_limit`` trials' status and folder (all: ``None``), the ``plan`` and the counts, after
    checking the sweep's settings file; return 0."""
    if donors is not None:
        for task, picked in donors["tasks"].items():
            for key, donor in picked.items():
                final = donor["final_return"]
                print(f"donor {task} {key}: seed {donor['seed']} (final return {final:.1f}) {donor['path']}")
    settings = sweep_settings(list(states), training, checkpoints, resources={}, donors=donors, plan=plan)
    prepare_sweep_folder(Path(out), settings, allow_changed_settings, write=False)
    listed = list(states.items())[:list_limit]
    for trial, (status, left, config, done) in listed:
        folder = trial_dir(out, trial)
        if left is not None and left[0] == Attempt.IN_USE:  # not run now, nothing written into it: a rerun once it ends
            print(f"{status:<10} in use {folder}: held by {left[1]}; left as it is, run the same command once it ends")
            continue
        if left is not None:  # not run: a rerun would not repair it
            print(f"{status:<10} keep   {folder}: {left[1]}")
            continue
        action = "skip" if status == RunStatus.FINISHED else "resume" if done else "run"
        print(f"{status:<10} {action:<6} {done:>10,} of {config.frames:,} frames  {folder}")
    if len(listed) < len(states):
        print(f"... {len(states) - len(listed)} more trials (--list)")
    if plan["trials_pending"]:
        print("\n".join(plan_lines(plan)))
    counts = Counter(status for status, *_ in states.values())
    as_is = Counter(reason[0] for _, reason, *_ in states.values() if reason is not None)
    print(
        f"{len(states)} trials: "
        + ", ".join(f"{counts[status]} {status}" for status in (*RunStatus, NOT_A_RUN) if counts[status])
        + f"; {plan['trials_pending']} would run (frames done: the newest checkpoint of an unfinished trial)"
        + (f"; {as_is[Attempt.IN_USE]} in use by another process (run once it ends)" if as_is[Attempt.IN_USE] else "")
        + "".join(f"; {number} kept as they are ({kind})" for kind, number in as_is.items() if kind != Attempt.IN_USE)
        + "."
    )
    owner = run_folder_owner(out, SWEEP_LOCK)
    if owner is not None:  # the command itself would be refused now
        print(
            f"Note: sweep folder {out} is in use by {owner}: without --dry-run this command is refused until it ends; "
            "wait for it to end (or stop it), or give this sweep another --out."
        )
    return 0


def plan_lines(plan: dict) -> list[str]:
    """:return: the plan as the dry run prints it (a short table)"""
    columns = ("replay_ram", "checkpoints_peak", "snapshots", "model")
    row = "  {:<32} {:>12} {:>17} {:>12} {:>12}".format
    total = f"{plan['frames']:,} frames ({plan['agent_steps']:,} agent steps), {plan['updates']:,} updates in all"
    lines = [
        f"plan of the {plan['trials_pending']} trials to train: {total}",
        row("per trial", "replay RAM", "checkpoints peak", "snapshots", "final model"),
    ]
    lines += [row(group, *(size_text(sizes[name]) for name in columns)) for group, sizes in plan["bytes"].items()]
    node, limits = plan["node"], plan["limits"]
    lines.append(f"  disk at the end: {size_text(plan['disk_at_end_bytes'])} (final models and snapshots)")
    if plan.get("out_free_bytes") is not None:
        lines.append(
            f"  disk to write: up to {size_text(plan['disk_needed_bytes'])} (final models, snapshots, the checkpoints "
            f"of the trials at once); {size_text(plan['out_free_bytes'])} free at --out"
        )
    lines.append(
        f"  at once on this machine: {plan['trials_at_once']} trials (by RAM {limits['ram']:,} of "
        f"{node['ram_bytes'] / 1e9:,.1f} GB; by CPUs {limits['cpus']} of {node['cpus']}"
        + (f"; by GPUs {limits['gpus']} of {node['gpus']}" if "gpus" in limits else "")
        + ")"
    )
    if plan["hours"] is None:
        lines.append(f"  time: no estimate: pass --frames-per-second (one trial's, measured: {THROUGHPUT_ROWS})")
    else:
        lines.append(
            f"  time (estimate): {plan['hours']:,.1f} h at {plan['frames_per_second']:g} frames/s per trial "
            f"(--frames-per-second), {plan['trials_at_once']} at once"
        )
    return lines
