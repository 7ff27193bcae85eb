"""
Offline linear probing of an actor's layers with OMP (Section 4.1 of the paper), and the other computations on fixed
inputs: rollouts, films and the collapse metrics of snapshots. It draws nothing (:mod:`sb3_collapse.report` does):
docs/probe.md.
"""

from sb3_collapse.probe.checkpoints import load_checkpoint
from sb3_collapse.probe.omp import OrthogonalMatchingPursuit, omp_path
from sb3_collapse.probe.pipeline import RecordOptions
from sb3_collapse.probe.probing import ProbeSettings, probe_checkpoint, probe_each_checkpoint, split_by_episode
from sb3_collapse.probe.rollouts import Rollouts, record_rollouts

__all__ = [
    "OrthogonalMatchingPursuit",
    "ProbeSettings",
    "RecordOptions",
    "Rollouts",
    "load_checkpoint",
    "omp_path",
    "probe_checkpoint",
    "probe_each_checkpoint",
    "record_rollouts",
    "split_by_episode",
]
