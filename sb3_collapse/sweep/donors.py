"""
The donors of the transplant grid (the paper's Study 2, Section 4.2): "We extract the CNN and MLP from two random
well-performing agents, which we regard as "good" CNN and MLP. We also extract "bad" CNN and MLP from two poorly
performing agents." Given as checkpoints or picked from a finished sweep: docs/sweeps.md.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sb3_collapse.errors import InputError
from sb3_collapse.paper import PAPER
from sb3_collapse.protocol import FINAL_MODEL
from sb3_collapse.run.variants import BASELINE_VARIANT, BLANK_SOURCE, TRANSPLANT_SOURCES
from sb3_collapse.runfolder import final_return, trial_folders
from sb3_collapse.sweep.trials import canonical_task, donor_key

DONOR_PARTS = ("cnn", "mlp")  # in the order a pick assigns them: the first agent drawn gives the CNN
DONOR_SOURCES = tuple(s for s in TRANSPLANT_SOURCES if s != BLANK_SOURCE)  # good, bad: the classes of donors
DONOR_KEYS = tuple(donor_key(source, part) for source in DONOR_SOURCES for part in DONOR_PARTS)  # good_cnn...


@dataclass(frozen=True)
class Donor:
    """
    An agent of a finished sweep that gives a transplanted part.

    :param seed: its seed
    :param final_return: its last scheduled evaluation's mean return (:func:`~sb3_collapse.runfolder.final_return`)
    :param path: its saved model (:data:`~sb3_collapse.protocol.FINAL_MODEL`), absolute
    """

    seed: int
    final_return: float
    path: str


def donor_candidates(
    sweep: str | Path,
    task: str,
    variant: str = BASELINE_VARIANT,
    success_return: float = PAPER.success_return,
    failure_return: float = PAPER.failure_return,
) -> dict[str, list[Donor]]:
    """
    The finished seeds of a task and variant of a sweep, by class.

    :param sweep: a sweep folder
    :param task: the task (any form of :func:`~sb3_collapse.sweep.trials.canonical_task`)
    :param variant: the variant whose seeds may give parts
    :param success_return: a final return at least this is a well-performing agent
    :param failure_return: a final return below this is a poorly performing agent
    :return: ``{"good": [...], "bad": [...]}``, each by seed; the seeds in between are in neither
    """
    task = canonical_task(task)
    classes: dict[str, list[Donor]] = {"good": [], "bad": []}
    for *names, seed, child in trial_folders(sweep):
        value = final_return(child) if names == [task, variant] else None
        if value is None or not (child / FINAL_MODEL).is_file():
            continue
        donor = Donor(seed=seed, final_return=value, path=str((child / FINAL_MODEL).resolve()))
        if value >= success_return:
            classes["good"].append(donor)
        elif value < failure_return:
            classes["bad"].append(donor)
    return classes


def pick_donors(
    sweep: str | Path,
    task: str,
    seed: int = 0,
    variant: str = BASELINE_VARIANT,
    sources: Sequence[str] = DONOR_SOURCES,
    success_return: float = PAPER.success_return,
    failure_return: float = PAPER.failure_return,
) -> dict[str, Donor]:
    """
    Pick the donors of one task at random: for each source, two different agents of its class ("from two random
    well-performing agents"), the first for the CNN, the second for the MLP; the same ``seed`` gives the same donors.

    :param sweep: a finished sweep folder
    :param task: the task
    :param seed: the seed of the draw (recorded in the sweep's settings file)
    :param variant: the variant whose seeds may give parts
    :param sources: the classes to pick (``"good"``, ``"bad"``)
    :param success_return: a final return at least this is a well-performing agent
    :param failure_return: a final return below this is a poorly performing agent
    :return: :func:`donor_key` -> donor, for each source and part (``InputError``: a class of fewer than two agents)
    """
    candidates = donor_candidates(sweep, task, variant, success_return, failure_return)
    rng = np.random.default_rng(seed)
    picked: dict[str, Donor] = {}
    for source in (source for source in DONOR_SOURCES if source in sources):
        pool = candidates[source]
        if len(pool) < 2:
            what = f"final return >= {success_return:g}" if source == "good" else f"final return < {failure_return:g}"
            raise InputError(
                f"--donors-from {sweep}: {canonical_task(task)}/{variant} has {len(pool)} finished seed(s) with a "
                f"{what} and a {FINAL_MODEL}; the {source} CNN and MLP need two different agents: pass "
                f"--{source}-cnn PATH --{source}-mlp PATH instead.",
                parameter="donors_from",
            )
        first, second = rng.choice(len(pool), size=2, replace=False)
        for part, index in zip(DONOR_PARTS, (first, second)):
            picked[donor_key(source, part)] = pool[int(index)]
    return picked


def check_distinct_donors(checkpoints: Mapping[str, Mapping[str, str]]) -> None:
    """An ``InputError`` when a source's CNN and MLP come from the same file for a task (one agent, not two)."""
    for source in DONOR_SOURCES:
        cnn, mlp = checkpoints.get(donor_key(source, "cnn"), {}), checkpoints.get(donor_key(source, "mlp"), {})
        for task in sorted(set(cnn) & set(mlp)):
            if Path(cnn[task]).resolve() == Path(mlp[task]).resolve():
                raise InputError(
                    f"--{source}-cnn and --{source}-mlp give the same checkpoint {cnn[task]} for {task}: the paper "
                    f"takes the {source} CNN and MLP from two different agents; pass another agent's checkpoint to "
                    "one of them.",
                    parameter=donor_key(source, "mlp"),
                )


def donors_record(
    sweep: str | Path,
    seed: int,
    variant: str,
    picked: Mapping[str, Mapping[str, Donor]],
    success_return: float = PAPER.success_return,
    failure_return: float = PAPER.failure_return,
) -> dict[str, Any]:
    """What the sweep's settings file records of a draw (key ``donors``), ``picked``: task -> :func:`pick_donors`
    (with ``success_return`` and ``failure_return``, its classes)."""
    return {
        "from": str(Path(sweep).resolve()),
        "seed": int(seed),
        "variant": variant,
        "success_return": float(success_return),
        "failure_return": float(failure_return),
        "tasks": {task: {key: asdict(donor) for key, donor in donors.items()} for task, donors in picked.items()},
    }
