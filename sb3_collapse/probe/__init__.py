"""
Offline linear probing of an actor's layers with Orthogonal Matching Pursuit (Section 4.1 of the paper), and the
other computations on fixed inputs: films and the collapse metrics of snapshots. It draws nothing: the figures and
tables are :mod:`sb3_collapse.report`'s.

``python -m sb3_collapse.probe --help`` for the command line; the library:

- :mod:`~sb3_collapse.probe.omp`: batched OMP in torch (:func:`omp_path`, :class:`OrthogonalMatchingPursuit`);
- :mod:`~sb3_collapse.probe.rollouts`: record, save and load :class:`Rollouts`;
- :mod:`~sb3_collapse.probe.probing`: split by episode, standardize, fit and evaluate per layer and checkpoint;
- :mod:`~sb3_collapse.probe.pipeline`: record rollouts from a checkpoint (:func:`record_to_file`);
- :mod:`~sb3_collapse.probe.fixed_inputs`: the collapse metrics of snapshots on one fixed observation set;
- :mod:`~sb3_collapse.probe.film`: film an agent's episode.
"""

from sb3_collapse.probe.checkpoints import Checkpoint, load_checkpoint
from sb3_collapse.probe.omp import OMPPath, OrthogonalMatchingPursuit, omp_path, path_predictions
from sb3_collapse.probe.pipeline import RecordOptions, record_to_file
from sb3_collapse.probe.probing import (
    PROBE_LAYERS,
    ProbeSettings,
    probe_checkpoint,
    probe_checkpoints,
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
    "probe_checkpoints",
    "probe_layer",
    "record_rollouts",
    "record_to_file",
    "split_by_episode",
]
