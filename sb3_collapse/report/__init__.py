"""Every figure and table of the paper from a sweep or run folder (:func:`write_report`, :func:`probe_sweep`,
:func:`film_to_folder`, :func:`probe_to_folder`); each module's part: docs/layout.md."""

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
