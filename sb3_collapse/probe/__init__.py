"""Offline OMP probing of an actor's layers (Section 4.1) and the other computations on fixed inputs: docs/probe.md."""

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
