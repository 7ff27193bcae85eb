"""Every figure and table of the paper from a sweep or run folder (:func:`write_report`, :func:`probe_sweep`,
:func:`film_to_folder`, :func:`probe_to_folder`, :func:`health_to_folder`); each module's part: docs/layout.md."""

from sb3_collapse.report.collapse_figure import FixedInputSettings
from sb3_collapse.report.figure2 import probe_sweep
from sb3_collapse.report.film import film_to_folder
from sb3_collapse.report.headline import escape_probability
from sb3_collapse.report.health import health_to_folder
from sb3_collapse.report.loading import Sweep, Trial, load_sweep
from sb3_collapse.report.pipeline import Report, build_report, write_report
from sb3_collapse.report.probe_outputs import probe_to_folder
from sb3_collapse.report.reference import load_reference_curves, reference_task_name
from sb3_collapse.report.statistics import ReportSettings, stuck_in_collapse

__all__ = [
    "FixedInputSettings",
    "Report",
    "ReportSettings",
    "Sweep",
    "Trial",
    "build_report",
    "escape_probability",
    "film_to_folder",
    "health_to_folder",
    "load_reference_curves",
    "load_sweep",
    "probe_sweep",
    "probe_to_folder",
    "reference_task_name",
    "stuck_in_collapse",
    "write_report",
]
