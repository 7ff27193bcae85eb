"""
The paper's reproduction (``python -m sb3_collapse.reproduce``, docs/reproduce.md) below its command line: its stages
and folder, its sizes (:class:`Scale`: :data:`PAPER_SCALE`, :data:`TINY_SCALE`), the classes of agents by final return
(:class:`Classes`, :func:`split_classes`), the state of one reproduction folder (:class:`Reproduction`: its settings,
the stages' done-markers, its trials, the grid's donors, the filmed agents) and the plan of its training stages.
"""

from __future__ import annotations

import contextlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from sb3_collapse.errors import InputError
from sb3_collapse.paper import PAPER
from sb3_collapse.probe.film import FILM_FRAMES, FILM_SIZE
from sb3_collapse.probe.pipeline import RecordOptions
from sb3_collapse.probe.probing import ProbeSettings
from sb3_collapse.protocol import FINAL_MODEL, write_json_atomically
from sb3_collapse.run.variants import GRID_VARIANTS
from sb3_collapse.runfolder import final_return, read_json, trial_folders
from sb3_collapse.sweep.cluster import CONNECT_TIMEOUT_S
from sb3_collapse.sweep.donors import DONOR_KEYS, donors_record, pick_donors
from sb3_collapse.sweep.plan import states_plan, trial_states
from sb3_collapse.sweep.trials import Trial, expand_trials

STAGES = ("sweep", "transplant", "probe", "film", "report")
"""The stages, in the order they run."""
INPUTS: dict[str, tuple[str, ...]] = {
    "sweep": (),
    "transplant": ("sweep",),
    "probe": ("sweep",),
    "film": ("sweep",),
    "report": ("sweep", "transplant", "probe", "film"),
}
"""Stage -> the stages whose outputs it reads."""
TRAINING_STAGES = ("sweep", "transplant")
"""The stages that train (on Ray, into the sweep folder)."""
VARIANTS = ("drqv2", "drqv2+reset")
"""Figure 5's variants: DrQ-v2 and DrQ-v2 with the paper's rule."""
SNAPSHOT_VARIANTS = ("drqv2",)
"""The variants whose trials keep snapshots: Figure 2 probes the snapshots of every well- and poorly performing
DrQ-v2 trial, and Figures 4, 8, 9 those of three DrQ-v2 agents, picked only once every trial has finished. The rule's
trials and the grid cells keep none (the report draws their Figure 4 from the online metrics)."""
SWEEP_DIR, FILMS_DIR, REPORT_DIR, STAGES_DIR = "sweep", "films", "report", "stages"
SETTINGS_JSON = "reproduce.json"
"""What ``--out`` was started with (a rerun with other settings is refused)."""
PAPER_MD = "paper.md"
"""The paper's figures and tables, each with the file of this reproduction that holds it."""


@dataclass(frozen=True)
class Scale:
    """
    The sizes of a reproduction.

    :param name: ``paper`` or ``tiny``
    :param training: ``TrainConfig`` settings of every trial beyond the task presets (``{}``: the presets, the
        paper's budgets)
    :param seeds: seeds per task and variant of the sweep stage
    :param transplant_seeds: seeds per cell of the transplant grid
    :param tasks: the tasks of the sweep, probe and report stages
    :param probe: the probe's settings (Figure 2)
    :param record: the rollouts the probe records (and Figures 4, 8, 9 read)
    :param film_frames: environment frames per film (Figures 6-7)
    :param film_size: height and width of the film's renders, in pixels
    :param film_every_frames: frames between two pictures of a film strip
    :param trials_per_worker: trials a Ray worker process runs before a fresh one replaces it (``run_sweep``'s:
        ``1`` at the paper's scale, ``0`` no limit at the tiny one, where a process's start is most of a trial)
    :param paper_classes: the paper's classes of agents (``PAPER.success_return`` and ``PAPER.failure_return``);
        ``False``: thresholds that split the agents
    """

    name: str
    training: Mapping[str, Any]
    seeds: int
    transplant_seeds: int
    tasks: tuple[str, ...]
    probe: ProbeSettings = field(default_factory=ProbeSettings)
    record: RecordOptions = field(default_factory=RecordOptions)
    film_frames: int = FILM_FRAMES
    film_size: int = FILM_SIZE
    film_every_frames: int = 30
    trials_per_worker: int = 1
    paper_classes: bool = True


PAPER_SCALE = Scale("paper", {}, PAPER.figure5_seeds, PAPER.transplant_seeds, PAPER.figure5_tasks)
# CPU sizes: 1000 frames = 20 agent steps of 50 frames (a DMC episode is then 20 agent steps, 20 renders: rendering is
# most of a tiny trial's time on a CPU, its evaluations most of that), 32x32 images, small networks, learning from frame
# 500, evaluations (and snapshots) at frames 0 and 500 and of the final model at 1000, collapse checks every 250 frames
# on batches of 4 (a check finds at least 5 transitions stored, after a reset too) and the rule's window of 500 frames.
# Four seeds: the grid's donors are two good and two bad walker-walk agents. A Ray worker runs trial after trial
# (trials_per_worker=0): a process's start (imports, the rendering check) would be most of a tiny trial.
TINY_SCALE = Scale(
    "tiny",
    dict(
        frames=1000,
        action_repeat=50,
        size=32,
        seed_frames=500,
        batch_size=8,
        hidden_dim=32,
        feature_dim=16,
        eval_every_frames=500,
        eval_episodes=1,
        collapse_metrics_every_frames=250,
        collapse_metrics_batch=4,
        reset_window_frames=500,
        replay_sampling="sb3",
    ),
    seeds=4,
    transplant_seeds=1,
    tasks=PAPER.figure5_tasks,
    probe=ProbeSettings(max_tau=4, progress=False, device="cpu"),
    record=RecordOptions(episodes=3, max_steps=10),
    film_frames=250,
    film_size=64,
    film_every_frames=50,
    trials_per_worker=0,
    paper_classes=False,
)
SCALES = {scale.name: scale for scale in (PAPER_SCALE, TINY_SCALE)}


@dataclass(frozen=True)
class Classes:
    """
    The classes of agents by final return: well-performing ``>= success_return``, poorly performing
    ``< failure_return``; ``source`` says where the numbers come from.
    """

    success_return: float
    failure_return: float
    source: str

    def line(self, what: str) -> str:
        """:return: one line for the output"""
        return (
            f"{what}: well-performing >= {self.success_return:g}, poorly performing < {self.failure_return:g} "
            f"({self.source})"
        )


PAPER_CLASSES = Classes(PAPER.success_return, PAPER.failure_return, "the paper's, Section 4.1")


def split_classes(finals: Sequence[float], what: str, parts: int = 2) -> Classes:
    """
    Thresholds that split ``finals`` (the tiny scale's agents, which never reach the paper's
    ``PAPER.success_return``): ``parts=2``, one cut
    at the median (``success_return == failure_return``: every agent in one of the two classes); ``parts=3``, the
    cuts at the thirds (the middle third between). A cut lies midway between two distinct sorted values, moved to the
    nearest gap where values tie; with one distinct value every agent is well-performing.

    :param finals: the final returns
    :param what: the agents, for :attr:`Classes.source`
    :param parts: 2 or 3
    """
    values = sorted(finals)
    gaps = [k for k in range(1, len(values)) if values[k - 1] < values[k]]

    def cut(k: int) -> float:
        if not gaps:
            return values[0] if values else 0.0
        nearest = min(gaps, key=lambda gap: (abs(gap - k), gap))
        return (values[nearest - 1] + values[nearest]) / 2

    low, high = (cut(len(values) // 2),) * 2 if parts == 2 else (cut(len(values) // 3), cut(2 * len(values) // 3))
    paper = f"{PAPER.success_return:g}/{PAPER.failure_return:g}"
    source = f"tiny scale: the {parts}-way split of the {len(values)} final returns of {what}, not the paper's {paper}"
    return Classes(max(low, high) if parts == 2 else high, min(low, high), source)


def drqv2_finals(sweep: Path, task: str, variant: str = "drqv2") -> dict[int, float]:
    """:return: seed -> final return of the finished trials of ``task`` and ``variant`` with a final model"""
    finals = {}
    for *names, seed, folder in trial_folders(sweep):
        value = final_return(folder) if names == [task, variant] else None
        if value is not None and (folder / FINAL_MODEL).is_file():
            finals[seed] = value
    return finals


@dataclass
class Reproduction:
    """
    One reproduction: its folder, scale, counts, resources.

    :param out: the folder of every output
    :param scale: its sizes
    :param tasks: the tasks of the sweep, probe and report stages
    :param seeds: seeds per task and variant of the sweep stage
    :param transplant_seeds: seeds per cell of the transplant grid
    :param address: Ray cluster, ``None`` for a local instance
    :param cpus_per_trial: CPUs per trial
    :param gpus_per_trial: GPUs per trial
    :param connect_timeout_s: seconds to wait for the cluster at ``address``
    :param progress: progress bars
    :param resources: what the stages hold until the end (the Ray session of the training stages)
    """

    out: Path
    scale: Scale
    tasks: tuple[str, ...]
    seeds: int
    transplant_seeds: int
    address: str | None = None
    cpus_per_trial: float = 1
    gpus_per_trial: float = 0
    connect_timeout_s: float = CONNECT_TIMEOUT_S
    progress: bool = True
    resources: contextlib.ExitStack = field(default_factory=contextlib.ExitStack)

    @property
    def sweep(self) -> Path:
        """The sweep folder of both training stages (the report reads one folder)."""
        return self.out / SWEEP_DIR

    @property
    def transplant_task(self) -> str:
        """Study 2's task."""
        return PAPER.transplant_task

    def settings(self) -> dict[str, Any]:
        """What ``reproduce.json`` records (a rerun must match)."""
        return {
            "scale": self.scale.name,
            "tasks": list(self.tasks),
            "seeds": self.seeds,
            "transplant_seeds": self.transplant_seeds,
        }

    def marker(self, stage: str) -> Path:
        """The done-marker of ``stage``, written last."""
        return self.out / STAGES_DIR / f"{stage}.json"

    def done(self, stage: str) -> dict[str, Any] | None:
        """:return: what ``stage`` recorded when it finished, ``None`` when it has not"""
        path = self.marker(stage)
        return read_json(path) if path.is_file() else None

    def finish(self, stage: str, record: Mapping[str, Any]) -> None:
        """Write the done-marker of ``stage`` (after all its outputs)."""
        path = self.marker(stage)
        path.parent.mkdir(parents=True, exist_ok=True)
        write_json_atomically(path, {"stage": stage, **record})

    def sweep_trials(self) -> list[Trial]:
        """Figure 5's trials."""
        return expand_trials(self.tasks, VARIANTS, range(self.seeds))

    def grid_trials(self) -> list[Trial]:
        """Study 2's trials: the nine cells on its task."""
        return expand_trials([self.transplant_task], GRID_VARIANTS, range(self.transplant_seeds))

    def classes(self, task: str, parts: int = 2) -> Classes:
        """The classes of ``task``'s DrQ-v2 agents (the paper's, or at the tiny scale a split of its finals)."""
        if self.scale.paper_classes:
            return PAPER_CLASSES
        return split_classes(list(drqv2_finals(self.sweep, task).values()), f"{task}/drqv2", parts)

    def report_classes(self) -> Classes:
        """The report's classes: one pair for every task (the paper's, or at the tiny scale the split of every final
        return of Study 2's task: its DrQ-v2, rule and grid trials, so that some grid cells succeed)."""
        if self.scale.paper_classes:
            return PAPER_CLASSES
        task = self.transplant_task
        finals = [
            v for variant in (*VARIANTS, *GRID_VARIANTS) for v in drqv2_finals(self.sweep, task, variant).values()
        ]
        median = split_classes(finals, f"every {task} trial (Figure 5's and the grid's)")
        third = split_classes(finals, f"every {task} trial", 3)
        failure = min(third.failure_return, median.success_return)
        return Classes(median.success_return, failure, median.source + "; poorly performing: the lowest third")


def pick_grid_donors(job: Reproduction) -> tuple[dict[str, dict[str, str]], dict[str, Any], Classes]:
    """:return: the grid's donor checkpoints (key -> task -> path), their record, and the classes they were drawn by
    (:raises InputError: a class of fewer than two agents)"""
    task, classes = job.transplant_task, job.classes(job.transplant_task)
    picked = pick_donors(
        job.sweep, task, 0, "drqv2", success_return=classes.success_return, failure_return=classes.failure_return
    )
    checkpoints = {key: {task: donor.path} for key, donor in picked.items()}
    record = donors_record(job.sweep, 0, "drqv2", {task: picked}, classes.success_return, classes.failure_return)
    return checkpoints, record, classes


def film_agents(job: Reproduction, task: str) -> tuple[tuple[int, float], tuple[int, float], Classes, str]:
    """:return: the good and the poor agent filmed of ``task`` (seed, final return): the best well-performing and
    the worst poorly performing DrQ-v2 seeds, their classes and a note when a class is empty (then the best and the
    worst seed; :raises InputError: fewer than two finished seeds)"""
    finals = drqv2_finals(job.sweep, task)
    if len(finals) < 2:
        raise InputError(f"{task}/drqv2 has {len(finals)} finished trial(s) with a final model; a film needs 2")
    classes = job.classes(task)
    ranked = sorted(finals.items(), key=lambda item: (-item[1], item[0]))
    good = [item for item in ranked if item[1] >= classes.success_return]
    poor = [item for item in ranked if item[1] < classes.failure_return]
    note = ""
    if not good or not poor:
        note = f"no {'well' if not good else 'poorly'}-performing seed: the best and the worst seed instead"
        good, poor = ranked[:1], ranked[-1:]
    return good[0], poor[-1], classes, note


def training_plan(job: Reproduction, stage: str, fps: float) -> tuple[list[Trial], dict[str, Any]]:
    """
    :param stage: ``sweep`` or ``transplant``
    :param fps: one trial's training frames per second
    :return: the stage's trials and :func:`~sb3_collapse.sweep.plan.sweep_plan` of them (their folders read, nothing
        written; the transplant's donors, drawn by the sweep stage, a placeholder path), each trial keeping snapshots
        as the stage has it (:data:`SNAPSHOT_VARIANTS`)
    """
    trials = job.sweep_trials() if stage == "sweep" else job.grid_trials()
    placeholder = str(job.sweep / "<donor drawn from the sweep stage>")
    checkpoints = {} if stage == "sweep" else {key: {job.transplant_task: placeholder} for key in DONOR_KEYS}
    states = trial_states(trials, job.sweep, dict(job.scale.training), checkpoints, SNAPSHOT_VARIANTS)
    plan = states_plan(states, job.cpus_per_trial, job.gpus_per_trial, fps, job.sweep)
    return trials, plan


def reproduction_plan(job: Reproduction, stages: Sequence[str], fps: float) -> dict[str, Any]:
    """
    :param stages: the stages to run
    :param fps: one trial's training frames per second
    :return: the plan of the training stages among ``stages``: ``stages`` (stage -> its ``trials``, its ``plan``
        (:func:`training_plan`) and its ``trial_hours`` at ``fps``), the ``trial_hours`` of them all, the disk at the
        peak (``disk_peak_bytes``: what the stages before hold at the end, then this stage's pending trials at most)
        and at the end (``disk_end_bytes``)
    """
    planned, total_hours, disk_end, disk_peak = {}, 0.0, 0, 0
    for stage in (stage for stage in stages if stage in TRAINING_STAGES):
        trials, plan = training_plan(job, stage, fps)
        hours = plan["frames"] / fps / 3600
        total_hours += hours
        disk_peak = max(disk_peak, disk_end + plan["disk_needed_bytes"])
        disk_end += plan["disk_at_end_bytes"]
        planned[stage] = {"trials": len(trials), "plan": plan, "trial_hours": hours}
    return {"stages": planned, "trial_hours": total_hours, "disk_peak_bytes": disk_peak, "disk_end_bytes": disk_end}
