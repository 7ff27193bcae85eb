"""Collapse monitoring: named activations of an actor, collapse metrics, the callbacks built on them (and the run's
periodic evaluation), and the interventions of the reset rule."""

from sb3_collapse.common.layers import layer_parameters, layer_taps
from sb3_collapse.monitoring.activations import collect_activations
from sb3_collapse.monitoring.callbacks import (
    ActivationLogger,
    CollapseMetrics,
    FrameScheduleCallback,
    MetricsBatchSampler,
    frames_of,
)
from sb3_collapse.monitoring.evaluation import PeriodicEvaluation
from sb3_collapse.monitoring.grad_norms import grad_norms_of, track_grad_norms
from sb3_collapse.monitoring.interventions import INTERVENTIONS, apply_intervention
from sb3_collapse.monitoring.metrics import dead_fraction, dormant_ratio, gradient_norm, layer_metrics, unit_count
from sb3_collapse.monitoring.redo import PeriodicReDo
from sb3_collapse.monitoring.reset import CollapseReset

__all__ = [
    "INTERVENTIONS",
    "ActivationLogger",
    "CollapseMetrics",
    "CollapseReset",
    "FrameScheduleCallback",
    "MetricsBatchSampler",
    "PeriodicEvaluation",
    "PeriodicReDo",
    "apply_intervention",
    "collect_activations",
    "dead_fraction",
    "dormant_ratio",
    "frames_of",
    "grad_norms_of",
    "gradient_norm",
    "layer_metrics",
    "layer_parameters",
    "layer_taps",
    "track_grad_norms",
    "unit_count",
]
