"""Offline OMP probing of an actor's layers (Section 4.1), the network health of saved models and the other
computations on fixed inputs: docs/probe.md."""

from sb3_collapse.probe.checkpoints import Checkpoint, load_checkpoint
from sb3_collapse.probe.health import HealthSettings, checkpoint_health
from sb3_collapse.probe.omp import OMPPath, OrthogonalMatchingPursuit, omp_path, path_predictions
from sb3_collapse.probe.probing import (
    PROBE_LAYERS,
    ProbeSettings,
    probe_checkpoint,
    probe_each_checkpoint,
    probe_layer,
    split_by_episode,
)
from sb3_collapse.probe.rollouts import RecordOptions, Rollouts, record_rollouts

__all__ = [
    "PROBE_LAYERS",
    "Checkpoint",
    "HealthSettings",
    "OMPPath",
    "OrthogonalMatchingPursuit",
    "ProbeSettings",
    "RecordOptions",
    "Rollouts",
    "checkpoint_health",
    "load_checkpoint",
    "omp_path",
    "path_predictions",
    "probe_checkpoint",
    "probe_each_checkpoint",
    "probe_layer",
    "record_rollouts",
    "split_by_episode",
]
