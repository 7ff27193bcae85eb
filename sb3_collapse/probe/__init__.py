"""
Offline linear probing of an actor's layers with Orthogonal Matching Pursuit (Section 4.1 of the paper).

``python -m sb3_collapse.probe --help`` for the command line; the library:

- :mod:`~sb3_collapse.probe.omp`: batched OMP in torch (:func:`omp_path`, :class:`OrthogonalMatchingPursuit`);
- :mod:`~sb3_collapse.probe.rollouts`: record, save and load :class:`Rollouts`;
- :mod:`~sb3_collapse.probe.probing`: split by episode, standardize, fit and evaluate per layer;
- :mod:`~sb3_collapse.probe.report`: ``probe.csv``, ``summary.json`` and plots;
- :mod:`~sb3_collapse.probe.pipeline`: the two commands as functions.
"""

from sb3_collapse.errors import ProbeError
from sb3_collapse.probe.checkpoints import Checkpoint, load_checkpoint
from sb3_collapse.probe.omp import OMPPath, OrthogonalMatchingPursuit, omp_path, path_predictions
from sb3_collapse.probe.pipeline import RecordOptions, probe_to_folder, record_to_file
from sb3_collapse.probe.probing import PROBE_LAYERS, ProbeSettings, probe_checkpoint, probe_layer, split_by_episode
from sb3_collapse.probe.rollouts import Rollouts, record_rollouts

__all__ = [
    "PROBE_LAYERS",
    "Checkpoint",
    "OMPPath",
    "OrthogonalMatchingPursuit",
    "ProbeError",
    "ProbeSettings",
    "RecordOptions",
    "Rollouts",
    "load_checkpoint",
    "omp_path",
    "path_predictions",
    "probe_checkpoint",
    "probe_layer",
    "probe_to_folder",
    "record_rollouts",
    "record_to_file",
    "split_by_episode",
]
