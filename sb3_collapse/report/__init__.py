"""
Reports of a sweep folder: the paper's Figure 5, the per-variant table and the layer-transplant grid
(Figure 3(a)). ``python -m sb3_collapse.report --help`` for the command line; the library:

- :mod:`~sb3_collapse.report.loading`: read ``<sweep>/<task>/<variant>/seed_<k>/`` folders (:func:`load_sweep`);
- :mod:`~sb3_collapse.report.statistics`: aligned curves, percentile bands, "stuck in action collapse", the table
  and the grid;
- :mod:`~sb3_collapse.report.reference`: the published DrQ-v2 curves shipped with the package;
- :mod:`~sb3_collapse.report.tables` and :mod:`~sb3_collapse.report.plots`: CSV, Markdown and PNG outputs;
- :mod:`~sb3_collapse.report.collapse_figure`: Figures 4, 8, 9 (the three agents, their metrics on the fixed probing
  set and online);
- :mod:`~sb3_collapse.report.pipeline`: :func:`build_report` and :func:`write_report`;
- the outputs of ``python -m sb3_collapse.probe``, from the probe's computations: :mod:`~sb3_collapse.report.figure2`
  (Figure 2 and Tables 1-6, :func:`probe_sweep`), :mod:`~sb3_collapse.report.film` (Figures 6-7,
  :func:`film_to_folder`), :mod:`~sb3_collapse.report.probe_outputs` (a probe's plots, :func:`probe_to_folder`).
"""

from sb3_collapse.report.collapse_figure import FixedInputSettings
from sb3_collapse.report.figure2 import probe_sweep
from sb3_collapse.report.film import film_to_folder
from sb3_collapse.report.loading import Sweep, Trial, load_sweep
from sb3_collapse.report.pipeline import Report, build_report, write_report
from sb3_collapse.report.probe_outputs import probe_to_folder
from sb3_collapse.report.reference import ReferenceCurves, load_reference_curves, reference_task_name
from sb3_collapse.report.statistics import (
    BandCurve,
    GridCell,
    ReportSettings,
    VariantSummary,
    aligned_returns,
    last_evals_std_mean,
    percentile_band,
    stuck_in_collapse,
    summarize,
    transplant_grid,
)

__all__ = [
    "BandCurve",
    "FixedInputSettings",
    "GridCell",
    "ReferenceCurves",
    "Report",
    "ReportSettings",
    "Sweep",
    "Trial",
    "VariantSummary",
    "aligned_returns",
    "build_report",
    "film_to_folder",
    "last_evals_std_mean",
    "load_reference_curves",
    "load_sweep",
    "percentile_band",
    "probe_sweep",
    "probe_to_folder",
    "reference_task_name",
    "stuck_in_collapse",
    "summarize",
    "transplant_grid",
    "write_report",
]
