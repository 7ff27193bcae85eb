"""What the sweep tests share: a tiny trial's flags and readers of a sweep's outputs."""

import csv

# A tiny trial: 1000 frames = 50 agent steps of 20 frames (a whole DMC episode is then 50 agent steps, so that the
# evaluations at frames 0 and 1000 stay cheap: rendering is most of a trial's time), 32x32 images, learning from
# frame 600 (agent step 30), collapse checks at frames 500 and 1000, and with the reset rule a window of 500 frames
# (a reset at frame 500; none at frame 1000, the budget's end; the rule's runs never reach an update: their warm-up
# restarts at the reset).
TINY = [
    "--frames", "1000", "--action-repeat", "20", "--size", "32", "--seed-frames", "600", "--batch-size", "8",
    "--hidden-dim", "32", "--feature-dim", "16", "--eval-every-frames", "1000", "--eval-episodes", "1",
    "--collapse-metrics-every-frames", "500", "--collapse-metrics-batch", "8", "--reset-window-frames", "500",
    # The trial ends with its first episode: DrQ-v2's sampling (finished episodes only) would not update.
    "--replay-sampling", "sb3",
    "--snapshots",  # encoder + actor at frames 0 and 1000, for the probe's Figure 2
]  # fmt: skip


def read_csv(path):
    with open(path) as file:
        return list(csv.DictReader(file))


def own_lines(stdout):
    """The lines the CLI printed, without the trials' output that Ray forwards to the driver (it may arrive late)."""
    return [line for line in stdout.splitlines() if "(run_trial pid=" not in line]


def mtimes(folder):
    return {path: path.stat().st_mtime_ns for path in folder.rglob("*") if path.is_file()}
