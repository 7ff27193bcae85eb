"""
The health of a model's networks on a batch of observations, in one place: :func:`measure_health` gives the
metrics of :mod:`sb3_collapse.monitoring.metrics` of the actor's and the critic's named layers as tags,
``collapse/<layer>/<metric>`` (what :class:`~sb3_collapse.monitoring.callbacks.CollapseMetrics` logs at each check);
:class:`HealthMemory` carries what one measurement needs of the previous (the dormant units, the weights at the last
reset). See docs/monitoring.md.
"""

from __future__ import annotations

import math
from collections.abc import Collection, Iterable, Sequence
from dataclasses import dataclass, field

import torch as th
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.policies import BasePolicy

from sb3_collapse.common.layers import LayerTap, critic_layer_taps, layer_taps, policy_of
from sb3_collapse.errors import ParameterError
from sb3_collapse.monitoring.activations import Observations, collect_activations
from sb3_collapse.monitoring.grad_norms import grad_norms_of
from sb3_collapse.monitoring.metrics import (
    DORMANT_TAU,
    DORMANT_TAUS,
    EXTRA_LAYER_METRICS,
    LAYER_METRICS,
    SATURATION_LIMIT,
    SRANK_DELTA,
    action_spread,
    dormant_units,
    layer_metrics,
    persistent_dormant_fraction,
    saturated_fraction,
    weight_change,
    weight_magnitude,
)
from sb3_collapse.paper import metric_tag

DEFAULT_METRICS = (*LAYER_METRICS, "grad_norm", "action_std", "action_saturation")
"""What :class:`CollapseMetrics` measures by default: the paper's metrics and those it has always logged."""
EXTRA_METRICS = (
    *EXTRA_LAYER_METRICS,
    "persistent_dormant_fraction",
    "weight_magnitude",
    "weight_change",
    "q_mean",
    "q_std",
)
"""The plasticity literature's other metrics (docs/monitoring.md#metrics)."""
HEALTH_METRICS = DEFAULT_METRICS + EXTRA_METRICS
"""Every metric :func:`measure_health` can measure."""
NETWORKS = ("actor", "critic")
"""The networks :func:`measure_health` can measure."""
_MEMORY_METRICS = ("persistent_dormant_fraction", "weight_change")  # need a HealthMemory


@dataclass
class HealthMemory:
    """
    What :func:`measure_health` carries from one measurement to the next, on the model's device.

    :param dormant: layer -> ``(units,)`` mask of its dormant units at the last measurement (at ``tau``)
    :param reference: layer -> copies of its parameters at the last reset (the reference of ``weight_change``)
    """

    dormant: dict[str, th.Tensor] = field(default_factory=dict)
    reference: dict[str, tuple[th.Tensor, ...]] = field(default_factory=dict)

    def remember_weights(self, model: BaseAlgorithm | BasePolicy, networks: Iterable[str] = NETWORKS) -> None:
        """Take the parameters of every layer of ``networks`` now as the reference of ``weight_change``, and forget
        the dormant units (those of the weights before)."""
        self.reference = {
            name: tuple(p.detach().clone() for p in tap.parameters)
            for name, tap in network_taps(model, networks).items()
            if tap.parameters
        }
        self.dormant = {}


def check_health_arguments(metrics: Iterable[str], networks: Iterable[str], taus: Sequence[float]) -> None:
    """:raises ParameterError: naming ``metrics``, ``networks`` or ``taus`` for an unknown name or a bad threshold"""
    unknown = [name for name in metrics if name not in HEALTH_METRICS]
    if unknown:
        raise ParameterError("metrics", f"metrics: unknown {unknown}; choose among {list(HEALTH_METRICS)}.")
    bad = [name for name in networks if name not in NETWORKS]
    if bad or not list(networks):
        raise ParameterError("networks", f"networks must be some of {list(NETWORKS)}, got {list(networks)}.")
    if not len(taus) or any(not isinstance(t, (int, float)) or not math.isfinite(t) or t < 0 for t in taus):
        raise ParameterError("taus", f"taus must be finite thresholds >= 0, at least one, got {list(taus)}.")


def network_taps(model: BaseAlgorithm | BasePolicy, networks: Iterable[str] = NETWORKS) -> dict[str, LayerTap]:
    """:return: name -> :class:`LayerTap` of the named layers of ``networks``: the actor's (``cnn0``..``action``),
    then the critic's (``q1.mlp0``, ``q1.mlp1``.., ``q1``, ``q2.mlp0``..)"""
    networks = list(networks)
    taps = dict(layer_taps(model)) if "actor" in networks else {}
    return {**taps, **critic_layer_taps(model)} if "critic" in networks else taps


def measure_health(
    model: BaseAlgorithm | BasePolicy,
    observations: Observations,
    metrics: Collection[str] = DEFAULT_METRICS,
    networks: Collection[str] = ("actor",),
    layers: Iterable[str] | None = None,
    tau: float = DORMANT_TAU,
    taus: Sequence[float] = DORMANT_TAUS,
    delta: float = SRANK_DELTA,
    saturation_limit: float = SATURATION_LIMIT,
    batch_size: int = 256,
    device: th.device | str | None = None,
    memory: HealthMemory | None = None,
) -> dict[str, float]:
    """
    The health metrics of a model's networks on a batch of observations, as :class:`CollapseMetrics` logs them.

    The actor runs deterministically on ``observations``; the critic on them and the actor's actions, ``Q(s, mu(s))``;
    both in eval mode without gradient (restored after). Each layer's metrics come from one pass
    (:func:`~sb3_collapse.monitoring.metrics.layer_metrics`), on ``device``.

    :param model: a DrQv2, TD3, DDPG or SAC model, or its policy (the gradient norms need the model)
    :param observations: ``(n, ...)`` observations as stored by the env (e.g. uint8 pixels), or a dict of them
    :param metrics: which, of :data:`HEALTH_METRICS` (:data:`DEFAULT_METRICS`: the tags logged by default)
    :param networks: which, of ``"actor"`` and ``"critic"``
    :param layers: the layers to measure (names of either network), ``None`` for every layer of ``networks``
    :param tau: threshold of ``dormant_ratio`` and of the dormant units of ``persistent_dormant_fraction``
    :param taus: thresholds of ``dormant_ratios`` (one tag ``dormant_ratio_tau<tau>`` each)
    :param delta: threshold of ``srank``
    :param saturation_limit: ``|a|`` above which an action component counts as saturated
    :param batch_size: observations per forward pass
    :param device: where the activations and the metrics are computed, ``None``: the policy's device
    :param memory: the previous measurement's, updated in place; needed by ``persistent_dormant_fraction`` (NaN at
        the first measurement) and ``weight_change`` (0 at the first, whose weights become the reference)
    :return: tag -> value, ``collapse/<layer>/<metric>`` for a layer's metrics, ``collapse/q<k>/q_mean`` and
        ``q_std`` for each Q network, ``collapse/action_std`` and ``collapse/action_saturation``
    :raises ParameterError: naming ``metrics``, ``networks``, ``taus`` or ``memory``
    :raises KeyError: for a layer name the model does not have
    """
    check_health_arguments(metrics, networks, taus)
    needs_memory = [name for name in _MEMORY_METRICS if name in metrics]
    if needs_memory and memory is None:
        raise ParameterError(
            "memory", f"memory: {needs_memory} compare with the previous measurement; pass a HealthMemory."
        )
    policy = policy_of(model)
    device = policy.device if device is None else device
    actor_taps = layer_taps(policy) if "actor" in networks else {}
    critic_taps = critic_layer_taps(policy) if "critic" in networks else {}
    wanted = None if layers is None else set(layers)
    unknown = [] if wanted is None else sorted(wanted.difference(actor_taps, critic_taps))
    if unknown:
        raise KeyError(f"Unknown layer(s) {unknown}; the networks {list(networks)} have {[*actor_taps, *critic_taps]}.")
    chosen = [name for name in {**actor_taps, **critic_taps} if wanted is None or name in wanted]
    q_values = [name for name in critic_taps if "." not in name]  # q1, q2: a Q network's value (n, 1)
    q_stats = [name for name in ("q_mean", "q_std") if name in metrics]
    activations = collect_activations(
        policy,
        observations,
        [name for name in chosen if name in actor_taps],
        batch_size=batch_size,
        device=device,
        critic_layers=[
            name for name in critic_taps if name in chosen and name not in q_values or q_stats and name in q_values
        ],
    )
    activation_metrics = [name for name in metrics if name in LAYER_METRICS + EXTRA_LAYER_METRICS]
    values: dict[str, float] = {}
    for layer, acts in activations.items():
        if layer in q_values:
            continue  # a Q value: its statistics below
        for name, value in layer_metrics(acts, tau, delta, activation_metrics, taus).items():
            values[metric_tag(layer, name)] = value
        if "persistent_dormant_fraction" in metrics:
            assert memory is not None  # needs_memory
            dormant = dormant_units(acts, tau)
            previous = memory.dormant.get(layer)
            persistent = math.nan if previous is None else persistent_dormant_fraction(dormant, previous)
            values[metric_tag(layer, "persistent_dormant_fraction")] = persistent
            memory.dormant[layer] = dormant
    for layer in chosen:  # the weights of each layer that has some
        values.update(_weight_metrics(layer, {**actor_taps, **critic_taps}[layer].parameters, metrics, memory))
    if "grad_norm" in metrics and "actor" in networks and isinstance(model, BaseAlgorithm):
        for layer, norm in grad_norms_of(model).items():  # the actor's, recorded at its last update
            if wanted is None or layer in wanted:
                values[metric_tag(layer, "grad_norm")] = norm
    for q_name in q_values if q_stats else ():
        q = activations[q_name].double().flatten()
        if "q_mean" in metrics:
            values[metric_tag(q_name, "q_mean")] = float(q.mean())
        if "q_std" in metrics:
            values[metric_tag(q_name, "q_std")] = float(q.std(correction=0))
    if "action" in activations:
        if "action_std" in metrics:
            values["collapse/action_std"] = action_spread(activations["action"])
        if "action_saturation" in metrics:
            values["collapse/action_saturation"] = saturated_fraction(activations["action"], saturation_limit)
    return values


def _weight_metrics(
    layer: str, parameters: Sequence[th.Tensor], metrics: Collection[str], memory: HealthMemory | None
) -> dict[str, float]:
    """``weight_magnitude`` and ``weight_change`` of a layer with parameters (the reference taken if it has none)."""
    values: dict[str, float] = {}
    if not parameters:
        return values
    if "weight_magnitude" in metrics:
        values[metric_tag(layer, "weight_magnitude")] = weight_magnitude(parameters)
    if "weight_change" in metrics:
        assert memory is not None  # needs_memory
        reference = memory.reference.setdefault(layer, tuple(p.detach().clone() for p in parameters))
        values[metric_tag(layer, "weight_change")] = weight_change(parameters, reference)
    return values
