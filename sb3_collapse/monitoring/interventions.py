"""
The interventions that ``CollapseReset`` applies at the end of a window without escape, each ``model ->
InterventionResult`` on the model policy's :class:`InterventionParts` (docs/interventions.md#the-interventions).
"""

from __future__ import annotations

import copy
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import torch as th
from stable_baselines3 import SAC, TD3
from stable_baselines3.common.base_class import BaseAlgorithm
from torch import nn

from sb3_collapse.baselines import collapse_model
from sb3_collapse.common.layers import LayerParts, LayerTap, layer_taps, reinitialize, sequential_hidden_parts
from sb3_collapse.common.model import CollapseModel
from sb3_collapse.monitoring.activations import reading
from sb3_collapse.monitoring.callbacks import MetricsBatchSampler
from sb3_collapse.monitoring.grad_norms import grad_norm_recorder
from sb3_collapse.monitoring.metrics import DORMANT_TAU, dormant_units

REDO_EVERY_UPDATES = 1000  # ReDo's recycling period F by default, in updates (PeriodicReDo)


@dataclass(frozen=True)
class InterventionResult:
    """
    :param name: the intervention (``"reset"``, ``"redo"``...)
    :param detail: one short line of what it did (for people and the rule's events file)
    :param scalars: logged as ``collapse/intervention/<key>``: ``weights_changed`` always, ``transitions_dropped``
        for ``reset``, ``units_recycled`` and ``units_total`` for ``redo``
    :param units: for ``redo``, hidden layer -> indices of its recycled units (every hidden layer listed)
    """

    name: str
    detail: str
    scalars: dict[str, float]
    units: dict[str, tuple[int, ...]] = field(default_factory=dict)


@runtime_checkable
class InterventionParts(Protocol):
    """
    What a policy provides for the interventions to act on it, ``DrQv2Policy`` by duck typing, SB3's TD3, DDPG and
    SAC policies through an adapter (:func:`intervention_parts`); each method: docs/interventions.md#the-interventions.
    """

    @property
    def optimizers(self) -> list[th.optim.Optimizer]: ...  # of the networks (an entropy coefficient's excluded)
    def named_layers(self) -> dict[str, nn.Module]: ...  # the module making each named activation, input to output
    def initialize_weights(self, module: nn.Module) -> None: ...  # new initial values in place, the algorithm's way
    def online_networks(self) -> dict[str, nn.Module]: ...  # the trained networks by name: what shrink-perturb changes
    def target_networks(self) -> dict[str, nn.Module]: ...  # by name; a "target actor" is kept a copy of "actor"
    def actor_modules(self) -> list[nn.Module]: ...  # what reset_actor renews
    def actor_mlp_modules(self) -> list[nn.Module]: ...  # what reset_mlp renews: the actor after the encoder
    def hidden_layer_parts(self) -> list[LayerParts]: ...  # the actor's, then the critic's, that ReDo may recycle
    def encoder_channel_parts(self) -> list[LayerParts]: ...  # the encoder's convolutions ReDo may recycle, or []
    def forward_hidden(self, observations: Any, actions: th.Tensor) -> None: ...  # run the layers of the two above


@dataclass
class _SB3Parts:
    """:class:`InterventionParts` of an SB3 TD3 or DDPG (``kind="td3"``) or SAC (``kind="sac"``) policy."""

    policy: Any
    kind: str

    @property
    def optimizers(self) -> list[th.optim.Optimizer]:
        return [self.policy.actor.optimizer, self.policy.critic.optimizer]

    def named_layers(self) -> dict[str, nn.Module]:
        return {name: tap.module for name, tap in layer_taps(self.policy).items()}

    def initialize_weights(self, module: nn.Module) -> None:
        reinitialize(module)

    def online_networks(self) -> dict[str, nn.Module]:
        return {"actor": self.policy.actor, "critic": self.policy.critic}

    def target_networks(self) -> dict[str, nn.Module]:
        targets = {"target actor": self.policy.actor_target} if self.kind == "td3" else {}
        return {**targets, "target critic": self.policy.critic_target}

    def actor_modules(self) -> list[nn.Module]:
        return [self.policy.actor]

    def actor_mlp_modules(self) -> list[nn.Module]:
        actor = self.policy.actor
        return [actor.mu] if self.kind == "td3" else [actor.latent_pi, actor.mu, actor.log_std]

    def hidden_layer_parts(self) -> list[LayerParts]:
        # SB3's target actor and critic have layers of their own: no hidden unit of the online ones is read there.
        actor = self.policy.actor
        if self.kind == "td3":
            parts = sequential_hidden_parts("", list(actor.mu))
        else:
            parts = sequential_hidden_parts("", list(actor.latent_pi), tail=(actor.mu, actor.log_std))
        for k, q_network in enumerate(self.policy.critic.q_networks, start=1):
            parts += sequential_hidden_parts(f"q{k}.", list(q_network))
        return parts

    def encoder_channel_parts(self) -> list[LayerParts]:
        return []

    def forward_hidden(self, observations: Any, actions: th.Tensor) -> None:
        self.policy._predict(observations, deterministic=True)  # the actor, without noise
        self.policy.critic(observations, actions)


def intervention_parts(model: BaseAlgorithm) -> InterventionParts:
    """The policy's :class:`InterventionParts` (DrQv2), or an adapter for SB3's TD3, DDPG, SAC; else ``TypeError``."""
    if isinstance(model.policy, InterventionParts):
        return model.policy
    if isinstance(model, TD3):
        return _SB3Parts(model.policy, "td3")  # type: ignore[return-value]
    if isinstance(model, SAC):
        if getattr(model.policy.actor, "use_sde", False):
            raise TypeError("The interventions do not support SAC with gSDE (use_sde=True).")
        return _SB3Parts(model.policy, "sac")  # type: ignore[return-value]
    raise TypeError(
        f"The interventions work on DrQv2 and on SB3's TD3, DDPG and SAC; {type(model).__name__} is none of them."
    )


def _fresh_copy(module: nn.Module, parts: InterventionParts) -> nn.Module:
    """A copy of ``module`` with new initial values (contiguous memory, as the initializers need)."""
    fresh = copy.deepcopy(module).to(memory_format=th.contiguous_format)
    parts.initialize_weights(fresh)
    return fresh


def _count(params: Iterable[nn.Parameter]) -> int:
    return sum(param.numel() for param in {id(param): param for param in params}.values())


def _forget_grad_norms(model: BaseAlgorithm) -> None:
    recorder = grad_norm_recorder(model)
    if recorder is not None:
        recorder.clear()


def reset_from_scratch(model: BaseAlgorithm) -> InterventionResult:
    """
    The action-collapse paper's rule (Section 5.2), in the middle of ``learn()``: "the training would be reset",
    by the model's own ``reset_from_scratch()`` (new networks and optimizers, an empty replay buffer, the warm-up
    again; ``num_timesteps`` and the episode kept). See docs/interventions.md#reset-on-td3-ddpg-and-sac.

    :param model: a DrQv2, TD3, DDPG or SAC model
    :return: what was done
    """
    networks = intervention_parts(model)
    transitions = model.replay_buffer.size()  # type: ignore[union-attr]
    _check_resets_itself(model)
    model.reset_from_scratch()  # type: ignore[attr-defined]
    parts = ", ".join([*networks.online_networks(), *networks.target_networks()]) + " and their optimizers"
    if getattr(model, "ent_coef_optimizer", None) is not None:
        parts += ", entropy coefficient"
    return InterventionResult(
        "reset",
        f"new {parts}; replay buffer emptied ({transitions} transitions); warm-up restarted",
        {"weights_changed": float(_count(model.policy.parameters())), "transitions_dropped": float(transitions)},
    )


def _check_resets_itself(model: BaseAlgorithm) -> None:
    """A ``TypeError`` for a model without ``reset_from_scratch()`` (SB3's TD3, DDPG, SAC get it by collapse_model)."""
    if not isinstance(collapse_model(model), CollapseModel):
        raise TypeError(
            f"intervention='reset' needs {type(model).__name__}.reset_from_scratch(): its policy provides the parts of "
            "the other interventions only."
        )


def _reset_modules(model: BaseAlgorithm, modules: Sequence[nn.Module], name: str, what: str) -> InterventionResult:
    """New weights for ``modules`` in place, their optimizer state forgotten; a target actor copies them again."""
    parts = intervention_parts(model)
    for module in modules:
        parts.initialize_weights(module)
    params = [param for module in modules for param in module.parameters()]
    ids = {id(param) for param in params}
    for optimizer in parts.optimizers:  # Adam's moments and step start again at their next step
        for param in [state_param for state_param in optimizer.state if id(state_param) in ids]:
            del optimizer.state[param]
    changed = _count(params)
    target = parts.target_networks().get("target actor")
    if target is not None:  # TD3 and DDPG build their target actor as a copy of the actor
        with th.no_grad():
            for online, copied in zip(parts.online_networks()["actor"].parameters(), target.parameters()):
                if id(online) in ids:
                    copied.copy_(online)
                    changed += copied.numel()
    _forget_grad_norms(model)
    also = " and target actor" if target is not None else ""
    detail = f"new {what} ({_span(parts, modules)}){also}, its optimizer state"
    return InterventionResult(name, detail, {"weights_changed": float(changed)})


def _span(parts: InterventionParts, modules: Sequence[nn.Module]) -> str:
    """The named layers inside ``modules``, ``first..last`` (``mlp0..action``)."""
    inside = {id(sub) for module in modules for sub in module.modules()}
    names = [name for name, layer in parts.named_layers().items() if id(layer) in inside]
    if not names:
        return ", ".join(type(module).__name__ for module in modules)
    return names[0] if len(names) == 1 else f"{names[0]}..{names[-1]}"


def reset_actor(model: BaseAlgorithm) -> InterventionResult:
    """
    Reset the actor (Nikishin et al., ICML 2022): new weights for :meth:`InterventionParts.actor_modules` (and TD3's
    target actor), their optimizer state forgotten, the rest kept; SAC with ``share_features_extractor`` refused.

    :param model: a DrQv2, TD3, DDPG or SAC model
    :return: what was done
    """
    _check_own_extractor(model)
    return _reset_modules(model, intervention_parts(model).actor_modules(), "reset_actor", "actor")


def reset_mlp(model: BaseAlgorithm) -> InterventionResult:
    """
    Reset the actor's MLP after the encoder, where the paper's Figure 3 locates collapse (after Nikishin et al., ICML
    2022): new weights, their optimizer state forgotten; the encoder, the critic, the buffer and the counters kept.

    :param model: a DrQv2, TD3, DDPG or SAC model
    :return: what was done
    """
    return _reset_modules(model, intervention_parts(model).actor_mlp_modules(), "reset_mlp", "actor MLP")


def hidden_layers(model: BaseAlgorithm) -> list[LayerParts]:
    """The actor's then the critic's hidden layers of a DrQv2, TD3, DDPG or SAC model that :func:`redo` may recycle."""
    return intervention_parts(model).hidden_layer_parts()


def encoder_channels(model: BaseAlgorithm) -> list[LayerParts]:
    """A DrQv2 ``CnnPolicy``'s ``cnn1``..``cnn4`` as layers of channels :func:`redo` may recycle (else none)."""
    return intervention_parts(model).encoder_channel_parts()


def redo(
    model: BaseAlgorithm,
    tau: float = DORMANT_TAU,
    batch_size: int = 512,
    sampler: MetricsBatchSampler | None = None,
    samples: Any = None,
    conv_channels: bool = False,
) -> InterventionResult:
    """
    ReDo, "Recycling Dormant neurons" (Sokar et al., ICML 2023), once: each dormant unit of :func:`hidden_layers`
    (and :func:`encoder_channels`) gets new incoming weights, zero outgoing weights in every network that reads it
    and zero Adam moments for those entries, so no network's output changes.

    :param model: a DrQv2, TD3, DDPG or SAC model
    :param tau: the dormancy threshold, relative to the layer's mean
    :param batch_size: stored transitions of the batch the activations are measured on
    :param sampler: draws that batch (``None``: a new :class:`MetricsBatchSampler` seeded from the model's seed)
    :param samples: the batch itself (``observations``, ``actions``), instead of drawing one
    :param conv_channels: recycle the dormant channels of DrQ-v2's ``cnn1``..``cnn4`` too
    :return: what was done (nothing, and the detail says so, with fewer than ``batch_size`` stored transitions)
    """
    parts = intervention_parts(model)
    layers = (encoder_channels(model) if conv_channels else []) + hidden_layers(model)
    total = sum(layer.units for layer in layers)
    if samples is None:
        sampler = sampler or MetricsBatchSampler.for_model(model)
        drawn = sampler.sample_transitions(model, batch_size)
        if drawn is None:
            detail = f"nothing recycled: fewer than {batch_size} transitions in the replay buffer"
            scalars = {"weights_changed": 0.0, "units_recycled": 0.0, "units_total": float(total)}
            return InterventionResult("redo", detail, scalars, {layer.name: () for layer in layers})
        samples = drawn[0]
    taps = {layer.name: LayerTap(layer.activation, ()) for layer in layers}
    with reading(model.policy, taps, device=None) as outputs:  # eval mode, no gradient; each on its own device
        parts.forward_hidden(samples.observations, samples.actions)
    indices = {
        layer.name: dormant_units(outputs[layer.name][-1], tau).nonzero().flatten().to(layer.linear.weight.device)
        for layer in layers
    }
    units = {name: tuple(int(i) for i in index.tolist()) for name, index in indices.items()}
    recycling = [(layer, indices[layer.name]) for layer in layers if len(indices[layer.name]) > 0]
    changed = 0
    for layer, index in recycling:  # all incoming weights first...
        changed += _renew_incoming(layer, index, parts)
    for layer, index in recycling:  # ...then the outgoing ones: a recycled unit feeding another one stays silent
        changed += _zero_outgoing(layer, index, parts.optimizers)
    _forget_grad_norms(model)
    recycled = sum(len(indices) for indices in units.values())
    listed = ", ".join(f"{layer.name} {len(units[layer.name])}/{layer.units}" for layer in layers if units[layer.name])
    detail = f"{recycled} of {total} hidden units recycled (tau {tau:g})" + (f": {listed}" if listed else "")
    scalars = {"weights_changed": float(changed), "units_recycled": float(recycled), "units_total": float(total)}
    return InterventionResult("redo", detail, scalars, units)


def _renew_incoming(layer: LayerParts, index: th.Tensor, parts: InterventionParts) -> int:
    """New initial values for the incoming weights and bias of units ``index``; returns the entries changed."""
    fresh = _fresh_copy(layer.linear, parts)
    incoming = [(layer.linear.weight, fresh.weight)]
    if layer.linear.bias is not None:
        incoming.append((layer.linear.bias, fresh.bias))
    with th.no_grad():
        for param, new in incoming:
            param[index] = new[index].to(param.dtype)
    for optimizer in parts.optimizers:
        for param, _ in incoming:
            _zero_moments(optimizer, param, 0, index)
    return len(index) * (layer.linear.weight[0].numel() + (layer.linear.bias is not None))


def _zero_outgoing(layer: LayerParts, index: th.Tensor, optimizers: Sequence[th.optim.Optimizer]) -> int:
    """Zero the outgoing weights of units ``index`` (the consumers' columns); returns the entries changed."""
    columns = layer.consumer_columns(index)
    with th.no_grad():
        for consumer in layer.consumers:
            consumer.weight[:, columns] = 0.0
    for optimizer in optimizers:
        for consumer in layer.consumers:
            _zero_moments(optimizer, consumer.weight, 1, columns)
    return sum(consumer.weight[:, columns].numel() for consumer in layer.consumers)


def _zero_moments(optimizer: th.optim.Optimizer, param: nn.Parameter, dim: int, index: th.Tensor) -> None:
    """Zero the entries ``index`` along ``dim`` of every per-entry optimizer state of ``param`` (Adam's moments)."""
    for value in (optimizer.state.get(param) or {}).values():
        if isinstance(value, th.Tensor) and value.shape == param.shape:
            with th.no_grad():
                value.index_fill_(dim, index, 0.0)


def shrink_perturb(model: BaseAlgorithm, shrink: float = 0.8, perturb: float = 0.2) -> InterventionResult:
    """
    Shrink and perturb toward a fresh initialization ``theta_0``: ``theta <- shrink * theta + perturb * theta_0`` on
    every parameter of the online networks; the targets, the optimizer state, the buffer and the counters kept.

    :param model: a DrQv2, TD3, DDPG or SAC model
    :param shrink: lambda, in ``(0, 1]``
    :param perturb: the weight of the fresh initialization, ``>= 0``
    :return: what was done
    """
    fresh = "theta_0 (toward a fresh init)"
    return _shrink_and_add(model, "shrink_perturb", shrink, perturb, "perturb", None, fresh)


def shrink_perturb_noise(model: BaseAlgorithm, shrink: float = 0.8, noise: float = 0.01) -> InterventionResult:
    """
    Ash and Adams' shrink and perturb (NeurIPS 2020): ``theta <- lambda * theta + sigma * noise`` on every parameter
    of the online networks (:func:`perturbation_noise`), the rest kept.

    :param model: a DrQv2, TD3, DDPG or SAC model
    :param shrink: lambda, in ``(0, 1]``
    :param noise: sigma, ``>= 0``
    :return: what was done
    """
    what = "noise (Ash & Adams; noise at each layer's initial scale, biases and normalization parameters included)"
    return _shrink_and_add(model, "shrink_perturb_noise", shrink, noise, "noise", perturbation_noise, what)


def _shrink_and_add(
    model: BaseAlgorithm,
    name: str,
    shrink: float,
    scale: float,
    scale_name: str,
    draw: Callable[[nn.Module, nn.Module], Iterable[tuple[nn.Parameter, th.Tensor]]] | None,
    what: str,
) -> InterventionResult:
    """``theta <- shrink * theta + scale * value`` on the online networks, ``draw(network, fresh copy)`` giving
    ``(parameter, value)`` pairs (``None``: the fresh copy's values); ``what`` names the values in the detail."""
    if not 0.0 < shrink <= 1.0:
        raise ValueError(f"shrink must be in (0, 1], got {shrink}.")
    if not scale >= 0.0:
        raise ValueError(f"{scale_name} must be >= 0, got {scale}.")
    parts = intervention_parts(model)
    networks = parts.online_networks()
    seen: set[int] = set()
    for module in networks.values():
        fresh = _fresh_copy(module, parts)
        with th.no_grad():
            for param, new in zip(module.parameters(), fresh.parameters()) if draw is None else draw(module, fresh):
                if id(param) not in seen:  # a features extractor shared by the actor and the critic: once
                    seen.add(id(param))
                    param.mul_(shrink).add_(new, alpha=scale)
    _forget_grad_norms(model)
    changed = _count(param for module in networks.values() for param in module.parameters())
    detail = f"theta <- {shrink:g} theta + {scale:g} {what} on the {', '.join(networks)}; optimizer state kept"
    return InterventionResult(name, detail, {"weights_changed": float(changed)})


def perturbation_noise(module: nn.Module, fresh: nn.Module) -> list[tuple[nn.Parameter, th.Tensor]]:
    """
    ``(parameter, noise)`` pairs of :func:`shrink_perturb_noise`: ``fresh``'s (a new copy of ``module``) weight for a
    Linear or a convolution, else ``U(-1/sqrt(fan_in), 1/sqrt(fan_in))``, ``fan_in`` a unit's inputs (LayerNorm: its
    features); each on its parameter's device and dtype.
    """
    noise = []
    for sub, fresh_sub in zip(module.modules(), fresh.modules()):
        drawn = dict(fresh_sub.named_parameters(recurse=False))
        weighted = isinstance(sub, (nn.Linear, nn.Conv2d))
        for name, param in sub.named_parameters(recurse=False):
            if weighted and name == "weight":
                noise.append((param, drawn[name]))
            else:
                bound = (sub.weight[0].numel() if weighted else param.numel()) ** -0.5  # type: ignore[index]
                noise.append((param, th.empty_like(param).uniform_(-bound, bound)))
    return noise


INTERVENTIONS: dict[str, Callable[..., InterventionResult]] = {
    "reset": reset_from_scratch,
    "reset_actor": reset_actor,
    "reset_mlp": reset_mlp,
    "redo": redo,
    "shrink_perturb": shrink_perturb,
    "shrink_perturb_noise": shrink_perturb_noise,
}
"""The interventions by name, the values of ``CollapseReset(intervention=...)``."""

INTERVENTION_LABELS = {
    "reset": "reset from scratch",
    "reset_actor": "actor reset",
    "reset_mlp": "actor MLP reset",
    "redo": "ReDo, one-shot at the rule's trigger",
    "shrink_perturb": "shrink & perturb, interpolation to a fresh init",
    "shrink_perturb_noise": "shrink & perturb, Ash & Adams (lambda theta + sigma noise)",
    "redo_periodic": f"ReDo every {REDO_EVERY_UPDATES} updates, whole run",
}
"""Each intervention's name in figures, and the periodic ReDo of the variants ``<algorithm>+redo_periodic``."""


def check_intervention(name: str, model: BaseAlgorithm | None = None) -> None:
    """A ``ValueError`` for an unknown name or a ``model`` it cannot change as it says; ``TypeError``: no support."""
    if name not in INTERVENTIONS:
        raise ValueError(f"intervention must be one of {', '.join(INTERVENTIONS)}; got {name!r}.")
    if model is not None:
        intervention_parts(model)
        if name == "reset":
            _check_resets_itself(model)
        if name == "reset_actor":
            _check_own_extractor(model)


def _check_own_extractor(model: BaseAlgorithm) -> None:
    if isinstance(intervention_parts(model), _SB3Parts) and getattr(model.policy, "share_features_extractor", False):
        raise ValueError(
            f"intervention='reset_actor' on a {type(model).__name__} with share_features_extractor=True would reset "
            "the critic's features extractor too: use 'reset_mlp' (the actor after the extractor)."
        )


def apply_intervention(model: BaseAlgorithm, name: str, **kwargs: Any) -> InterventionResult:
    """
    :param model: a DrQv2, TD3, DDPG or SAC model
    :param name: one of :data:`INTERVENTIONS`
    :param kwargs: the intervention's own parameters (e.g. ``tau`` for ``redo``)
    :return: what was done
    """
    check_intervention(name, model)
    return INTERVENTIONS[name](model, **kwargs)
