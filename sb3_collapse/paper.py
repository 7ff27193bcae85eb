"""The action-collapse paper's numbers, each with the passage it comes from (Chen, Zhu & Perrault, *Understanding
Learned Representations and Action Collapse in Visual Reinforcement Learning*): :data:`PAPER`, the protocol every
default comes from, :data:`PAPER_RESULTS` and :data:`PROPOSITION_1`."""

from __future__ import annotations

from dataclasses import dataclass

from sb3_collapse.common.schedule import due_counts


@dataclass(frozen=True)
class PaperProtocol:
    """
    The paper's protocol numbers, in frames (agent steps x action repeat).

    :param check_every_frames: frames between two evaluations and two computations of the collapse metrics
        (Section 4.1: "there is an evaluation every 1e4 frames"; the rule's "computations" of Section 5.2)
    :param window_frames: the rule's window (Section 5.2: "reset the training from scratch every 2e5 frames")
    :param threshold: a gradient norm above it is healthy (Section 5.2: "a gradient norm larger than 0.001")
    :param patience: consecutive healthy computations, an escape (Section 5.2: "of consecutive five computations")
    :param layer: the layer whose gradient norm the rule reads (Section 5.2: "the gradient norm of mlp1")
    :param success_return: final return of a well-performing agent, at least (Section 4.1: "more than 900
        rewards"; Figure 3: "successful (rewards >= 900)")
    :param failure_return: final return of a poorly performing agent, below (Section 4.1: "less than 30 rewards")
    :param last_evals: evaluations of the across-seed std (5.2: "the average standard deviation over the last ten
        evaluations")
    :param percentiles: the band of Figure 5, in percent ("the 5th percentile and the 95th percentile")
    :param figure5_seeds: seeds per task and variant of Figure 5 ("40 seeds")
    :param figure5_tasks: the tasks of Figure 5 (walker_walk, hopper_stand, finger_spin)
    :param train_frames: frames of a run (Section 4.1: "The total number of training frames is 1.1e6")
    :param stage_frames: the four training stages of Tables 1-7 (their columns "x = 0, 35, 70, 110"), in frames
    :param transplant_seeds: seeds per cell of Study 2's transplant grid (Figure 3: "out of 20 seeds")
    :param transplant_task: the task of Study 2 and of Figure 2 (Figure 6's walker_walk; Section 4's agents)
    :param film_tasks: the tasks filmed in Figures 6 and 7 ("in walker_walk", "in finger_spin")
    """

    check_every_frames: int = 10_000
    window_frames: int = 200_000
    threshold: float = 1e-3
    patience: int = 5
    layer: str = "mlp1"
    success_return: float = 900.0
    failure_return: float = 30.0
    last_evals: int = 10
    percentiles: tuple[float, float] = (5.0, 95.0)
    figure5_seeds: int = 40
    figure5_tasks: tuple[str, ...] = ("walker-walk", "hopper-stand", "finger-spin")
    train_frames: int = 1_100_000
    stage_frames: tuple[int, ...] = (0, 350_000, 700_000, 1_100_000)
    transplant_seeds: int = 20
    transplant_task: str = "walker-walk"
    film_tasks: tuple[str, ...] = ("walker-walk", "finger-spin")

    def stages(self, budget_frames: int | None = None) -> tuple[int, ...]:
        """:return: the training stages of Tables 1-7, :attr:`stage_frames` scaled to ``budget_frames`` (``None``: the
        paper's), rounded to whole frames"""
        budget = self.train_frames if budget_frames is None else budget_frames
        if budget <= 0:
            raise ValueError(f"budget_frames must be > 0, got {budget}.")
        return tuple(round(frame * budget / self.train_frames) for frame in self.stage_frames)

    @property
    def evaluations(self) -> int:
        """The evaluations of a run, the paper's x in [0, 109]: 110."""
        return len(evaluation_schedule(self.train_frames, self.check_every_frames))

    @property
    def collapse_tag(self) -> str:
        """The tag of the rule's metric (``collapse/mlp1/grad_norm``)."""
        return metric_tag(self.layer, "grad_norm")


PAPER = PaperProtocol()


@dataclass(frozen=True)
class PaperResult:
    """
    The paper's headline numbers of one task of Figure 5 (Section 5.2, "Results"): DrQ-v2 against DrQ-v2 + the rule.

    :param task: the task, ``<domain>-<task>``
    :param seeds: seeds per variant ("The performance comparison of 40 seeds", Figure 5)
    :param stuck_baseline: DrQ-v2's seeds stuck in action collapse ("we count the number of seeds stuck in action
        collapse continuously. There are 13, 8, and 7 seeds out of 40 respectively for DrQ-v2")
    :param never_escaped_rule: the rule's seeds that never escaped action collapse ("In comparison, all 40 seeds of
        ours escape action collapse")
    :param std_baseline: DrQ-v2's "average standard deviation over the last ten evaluations" ("drops a lot, from
        418.2 to 38.2, from 359.5 to 93.8, and from 362.7 to 116.2 for the three tasks, respectively")
    :param std_rule: the same with the rule
    """

    task: str
    seeds: int
    stuck_baseline: int
    never_escaped_rule: int
    std_baseline: float
    std_rule: float


PAPER_RESULTS: tuple[PaperResult, ...] = (
    PaperResult("walker-walk", 40, 13, 0, 418.2, 38.2),
    PaperResult("hopper-stand", 40, 8, 0, 359.5, 93.8),
    PaperResult("finger-spin", 40, 7, 0, 362.7, 116.2),
)
"""In the order of the paper's tasks (walker_walk, hopper_stand, finger_spin: Section 5.2)."""

PROPOSITION_1 = (
    "Supposing the number of training frames is n · m (m is the frames where the exploration decreases to the "
    "smallest) and the probability of getting stuck in action collapse is p, then the probability of escaping action "
    "collapse when applying our proposed rule is 1 - p^n."
)
"""Proposition 1 of the paper (Section 5.2), word for word."""


def evaluation_schedule(frames: int, every_frames: int, frames_per_step: int = 1) -> list[int]:
    """
    The frames of a run's scheduled evaluations, as facebookresearch/drqv2's ``train.py``: frame 0, then every
    ``every_frames`` frames, never at the budget's end ("x in [0, 109]", Section 4.1); not the final model's.

    :param frames: the run's budget, in frames
    :param every_frames: frames between two evaluations (> 0)
    :param frames_per_step: frames an agent step adds (action repeat x environments)
    :return: the frames, increasing, each the first agent step's at or after its target
    """
    if every_frames <= 0 or frames_per_step <= 0:
        raise ValueError(f"every_frames and frames_per_step must be > 0, got {every_frames} and {frames_per_step}.")
    return due_counts(frames, every_frames, frames_per_step, at_start=True)  # PeriodicEvaluation's own rule


def metric_tag(layer: str, metric: str) -> str:
    """:return: the TensorBoard and collapse-metrics tag of ``metric`` of ``layer``, ``collapse/<layer>/<metric>``"""
    return f"collapse/{layer}/{metric}"
