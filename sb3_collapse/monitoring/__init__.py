"""Collapse monitoring: named activations, collapse metrics, the callbacks built on them, the interventions."""

from sb3_collapse.common.layers import LayerTap, layer_parameters, layer_taps
from sb3_collapse.monitoring.activations import collect_activations
from sb3_collapse.monitoring.callbacks import (
    ActivationLogger,
    CollapseMetrics,
    FrameScheduleCallback,
    MetricsBatchSampler,
    action_repeat_of,
    frames_of,
)
from sb3_collapse.monitoring.evaluation import PeriodicEvaluation
from sb3_collapse.monitoring.grad_norms import grad_norm_recorder, grad_norms_of, track_grad_norms
from sb3_collapse.monitoring.interventions import (
    INTERVENTIONS,
    InterventionResult,
    apply_intervention,
    redo,
    reset_actor,
    reset_from_scratch,
    reset_mlp,
    shrink_perturb,
    shrink_perturb_noise,
)
from sb3_collapse.monitoring.metrics import (
    action_spread,
    dead_fraction,
    dead_units,
    dormant_ratio,
    dormant_units,
    effective_rank,
    gradient_norm,
    input_correlation,
    layer_metrics,
    numerical_rank,
    saturated_fraction,
    singular_values,
    unit_correlation,
    unit_count,
    zero_fraction,
)
from sb3_collapse.monitoring.periodic_redo import PeriodicReDo
from sb3_collapse.monitoring.reset import CollapseReset

__all__ = [
    "INTERVENTIONS",
    "ActivationLogger",
    "CollapseMetrics",
    "CollapseReset",
    "FrameScheduleCallback",
    "InterventionResult",
    "LayerTap",
    "MetricsBatchSampler",
    "PeriodicEvaluation",
    "PeriodicReDo",
    "action_repeat_of",
    "action_spread",
    "apply_intervention",
    "collect_activations",
    "dead_fraction",
    "dead_units",
    "dormant_ratio",
    "dormant_units",
    "effective_rank",
    "frames_of",
    "grad_norm_recorder",
    "grad_norms_of",
    "gradient_norm",
    "input_correlation",
    "layer_metrics",
    "layer_parameters",
    "layer_taps",
    "numerical_rank",
    "redo",
    "reset_actor",
    "reset_from_scratch",
    "reset_mlp",
    "saturated_fraction",
    "shrink_perturb",
    "shrink_perturb_noise",
    "singular_values",
    "track_grad_norms",
    "unit_correlation",
    "unit_count",
    "zero_fraction",
]
