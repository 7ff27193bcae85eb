"""
Offline linear probing of an actor's layers with Orthogonal Matching Pursuit (Section 4.1 of the paper), and the
other computations on fixed inputs: rollouts, films and the collapse metrics of snapshots. It draws nothing: the
figures and tables are :mod:`sb3_collapse.report`'s. ``python -m sb3_collapse.probe --help`` for the command line;
each module's part: docs/layout.md.
"""

from sb3_collapse.probe.checkpoints import Checkpoint, load_checkpoint
from sb3_collapse.probe.omp import OMPPath, OrthogonalMatchingPursuit, omp_path, path_predictions
from sb3_collapse.probe.pipeline import RecordOptions, record_to_file
from sb3_collapse.probe.probing import (
    PROBE_LAYERS,
    ProbeSettings,
    probe_checkpoint,
    probe_each_checkpoint,
    probe_layer,
    split_by_episode,
)
from sb3_collapse.probe.rollouts import Rollouts, record_rollouts

__all__ = [
    "PROBE_LAYERS",
    "Checkpoint",
    "OMPPath",
    "OrthogonalMatchingPursuit",
    "ProbeSettings",
    "RecordOptions",
    "Rollouts",
    "load_checkpoint",
    "omp_path",
    "path_predictions",
    "probe_checkpoint",
    "probe_each_checkpoint",
    "probe_layer",
    "record_rollouts",
    "record_to_file",
    "split_by_episode",
]
