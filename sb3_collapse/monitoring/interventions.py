"""
Interventions on an off-policy actor-critic whose actor is stuck in action collapse: what
:class:`~sb3_collapse.monitoring.reset.CollapseReset` does at the end of a window without escape.

Each is a function ``model -> InterventionResult`` (``reset``, ``reset_actor``, ``reset_mlp``, ``redo``,
``shrink_perturb``, ``shrink_perturb_noise``) that changes exactly the parameters and state it names, on a model
whose policy provides :class:`InterventionParts` (DrQv2) or on SB3's TD3, DDPG and SAC through this module's
adapters. What each one resets and keeps, and how new weights and optimizer state are drawn:
docs/interventions.md#the-interventions.
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
from sb3_collapse.common.layers import LayerParts, layer_taps, reinitialize, sequential_hidden_parts
from sb3_collapse.common.model import CollapseModel
from sb3_collapse.monitoring.callbacks import MetricsBatchSampler
from sb3_collapse.monitoring.grad_norms import grad_norm_recorder
from sb3_collapse.monitoring.metrics import DORMANT_TAU, dormant_units

SHRINK = 0.8
"""Shrink-and-perturb's shrink factor lambda (Ash & Adams, 2020)."""

PERTURB = 0.2
"""Shrink-and-perturb's weight of the fresh initialization, ``1 - SHRINK``: ``shrink_perturb`` interpolates."""

REDO_EVERY_UPDATES = 1000
"""ReDo's recycling period ``F`` by default, in updates (gradient steps), for
:class:`~sb3_collapse.monitoring.redo.PeriodicReDo`."""

NOISE_SHRINK = 0.8
"""The default shrink factor lambda of :func:`shrink_perturb_noise` (Ash and Adams choose lambda per problem)."""

NOISE_SCALE = 0.01
"""The default noise scale sigma of :func:`shrink_perturb_noise`, times a noise of each layer's initial scale (chosen
per problem by Ash and Adams too)."""


@dataclass(frozen=True)
class InterventionResult:
    """
    What an intervention did.

    :param name: the intervention (``"reset"``, ``"redo"``...)
    :param detail: one short line for people and for the rule's events file (what was reset or recycled)
    :param scalars: numbers logged to TensorBoard as ``collapse/intervention/<key>``: ``weights_changed`` (the
        parameter entries that got new values) for every intervention, ``transitions_dropped`` for ``reset``,
        ``units_recycled`` and ``units_total`` for ``redo``
    :param units: for ``redo``, hidden layer -> indices of its recycled units (every hidden layer listed)
    """

    name: str
    detail: str
    scalars: dict[str, float]
    units: dict[str, tuple[int, ...]] = field(default_factory=dict)


# ------------------------------------------------------------------------------------------------ the model's parts
@runtime_checkable
class InterventionParts(Protocol):
    """
    What a policy provides for the interventions to act on it, without this module knowing its algorithm
    (``DrQv2Policy`` provides it by duck typing). SB3's TD3, DDPG and SAC policies get an adapter of this module
    (:func:`intervention_parts`). A model whose policy provides it is reset from scratch by its own
    ``model.reset_from_scratch()``.
    """

    @property
    def optimizers(self) -> list[th.optim.Optimizer]:
        """The optimizers of the policy's networks (an entropy coefficient's excluded)."""
        ...

    def named_layers(self) -> dict[str, nn.Module]:
        """The modules that produce each named activation (``cnn0``..``action``), input to output: the details
        of ``reset_actor`` and ``reset_mlp`` name the first and the last they renew."""
        ...

    def initialize_weights(self, module: nn.Module) -> None:
        """New initial values, in place, for every parameter of ``module`` (a part of the policy), with the
        algorithm's initializer, from torch's global generator, submodule by submodule in ``module.modules()``
        order; a ``TypeError`` for a submodule it cannot initialize."""
        ...

    def online_networks(self) -> dict[str, nn.Module]:
        """The trained networks by name (e.g. ``encoder``, ``actor``, ``critic``): what shrink and perturb
        changes."""
        ...

    def target_networks(self) -> dict[str, nn.Module]:
        """The target networks by name (e.g. ``target critic``)."""
        ...

    def actor_modules(self) -> list[nn.Module]:
        """The modules that ``reset_actor`` renews: the actor, with a features extractor of its own."""
        ...

    def actor_mlp_modules(self) -> list[nn.Module]:
        """The modules that ``reset_mlp`` renews: the actor's layers after the encoder or features extractor."""
        ...

    def hidden_layer_parts(self) -> list[LayerParts]:
        """The actor's and the critic's hidden layers that ReDo may recycle, actor first (what
        :func:`hidden_layers` returns); each lists every consumer of its units, in any network."""
        ...

    def encoder_channel_parts(self) -> list[LayerParts]:
        """The encoder's convolutions as layers of channels that ReDo may recycle, input to output, each with every
        consumer of its channels, in any network (a target network that reads the online encoder included);
        ``[]`` when there are none."""
        ...

    def forward_hidden(self, observations: Any, actions: th.Tensor) -> None:
        """Run the layers of :meth:`hidden_layer_parts` and :meth:`encoder_channel_parts` on a batch of
        ``(n, ...)`` observations and ``(n, action_dim)`` actions, for forward hooks to read (the caller sets the
        mode and the gradient)."""
        ...


class _SB3Parts:
    """
    :class:`InterventionParts` of SB3's TD3 and DDPG (``kind="td3"``) or SAC (``kind="sac"``) policies.

    :param policy: the model's policy
    :param kind: ``"td3"`` or ``"sac"``
    """

    def __init__(self, policy: Any, kind: str) -> None:
        self.policy = policy
        self.kind = kind

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
        # SB3 builds the target actor and critic with layers and features extractors of their own (shared, with
        # share_features_extractor, between the two targets only): every consumer of these units is listed here.
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
        if self.kind == "td3":
            self.policy.actor(observations)
        else:
            self.policy.actor.get_action_dist_params(observations)
        self.policy.critic(observations, actions)


def intervention_parts(model: BaseAlgorithm) -> InterventionParts:
    """
    What the interventions act on: the model's policy when it provides :class:`InterventionParts` (DrQv2), an
    adapter for SB3's TD3, DDPG and SAC.

    :param model: a model
    :return: its parts
    :raises TypeError: for any other model, and for SAC with gSDE
    """
    if isinstance(model.policy, InterventionParts):
        return model.policy
    return _SB3Parts(model.policy, _sb3_kind(model))  # type: ignore[return-value]


def _sb3_kind(model: BaseAlgorithm) -> str:
    """``"td3"`` (TD3 and DDPG) or ``"sac"``; a ``TypeError`` for any other model."""
    if isinstance(model, TD3):
        return "td3"
    if isinstance(model, SAC):
        if getattr(model.policy.actor, "use_sde", False):
            raise TypeError("The interventions do not support SAC with gSDE (use_sde=True).")
        return "sac"
    raise TypeError(
        f"The interventions work on DrQv2 and on SB3's TD3, DDPG and SAC; {type(model).__name__} is none of them."
    )


def _kind(parts: InterventionParts) -> str | None:
    """The SB3 adapter's kind, ``"td3"`` or ``"sac"``; ``None`` for a policy that provides the parts itself."""
    return parts.kind if isinstance(parts, _SB3Parts) else None


def _fresh_copy(module: nn.Module, parts: InterventionParts) -> nn.Module:
    """A copy of ``module`` with new initial values (contiguous memory, as the initializers need)."""
    fresh = copy.deepcopy(module).to(memory_format=th.contiguous_format)
    parts.initialize_weights(fresh)
    return fresh


def _forget_optimizer_state(optimizers: Iterable[th.optim.Optimizer], params: Iterable[nn.Parameter]) -> None:
    """Drop the optimizer state (Adam moments, step) of these parameters; it starts again at their next step."""
    ids = {id(param) for param in params}
    for optimizer in optimizers:
        for param in [state_param for state_param in optimizer.state if id(state_param) in ids]:
            del optimizer.state[param]


def _count(params: Iterable[nn.Parameter]) -> int:
    return sum(param.numel() for param in {id(param): param for param in params}.values())


def _forget_grad_norms(model: BaseAlgorithm) -> None:
    recorder = grad_norm_recorder(model)
    if recorder is not None:
        recorder.clear()


# ------------------------------------------------------------------------------------------------ reset from scratch
def reset_from_scratch(model: BaseAlgorithm) -> InterventionResult:
    """
    The action-collapse paper's rule (Section 5.2): restart the training from scratch, in the middle of ``learn()``,
    through the model's own ``reset_from_scratch()`` (:class:`~sb3_collapse.common.model.CollapseModel`): new
    networks and optimizers, an empty replay buffer, the warm-up restarted; ``num_timesteps`` and the environment's
    episode kept. See docs/interventions.md#reset-on-td3-ddpg-and-sac.

    :param model: a DrQv2, TD3, DDPG or SAC model
    :return: what was done
    """
    networks = intervention_parts(model)
    kind = _kind(networks)
    transitions = model.replay_buffer.size()  # type: ignore[union-attr]
    _check_resets_itself(model)
    collapse_model(model).reset_from_scratch()  # type: ignore[attr-defined]
    if kind is None:
        parts = ", ".join([*networks.online_networks(), *networks.target_networks()]) + " and their optimizers"
    else:
        parts = (
            "actor, target actor, critic, target critic and their optimizers"
            if kind == "td3"
            else "actor, critic, target critic and their optimizers"
            + (", entropy coefficient" if model.ent_coef_optimizer is not None else "")  # type: ignore[attr-defined]
        )
    return InterventionResult(
        "reset",
        f"new {parts}; replay buffer emptied ({transitions} transitions); warm-up restarted",
        {"weights_changed": float(_count(model.policy.parameters())), "transitions_dropped": float(transitions)},
    )


def _check_resets_itself(model: BaseAlgorithm) -> None:
    """A ``TypeError`` for a model without the model interface's ``reset_from_scratch()`` (nor SB3's TD3, DDPG, SAC)."""
    if not isinstance(model, CollapseModel) and _kind(intervention_parts(model)) is None:
        raise TypeError(
            f"intervention='reset' needs {type(model).__name__}.reset_from_scratch(): its policy provides the parts of "
            "the other interventions only."
        )


# ------------------------------------------------------------------------------------------------ partial resets
def _reset_modules(model: BaseAlgorithm, modules: Sequence[nn.Module], name: str, detail: str) -> InterventionResult:
    """New weights for ``modules`` in place, their optimizer state forgotten; TD3's target actor follows."""
    parts = intervention_parts(model)
    kind = _kind(parts)
    for module in modules:
        parts.initialize_weights(module)
    params = [param for module in modules for param in module.parameters()]
    _forget_optimizer_state(parts.optimizers, params)
    changed = _count(params)
    if kind == "td3":  # TD3 builds its target actor as a copy of the actor: the new parts are copied again
        target = model.policy.actor_target  # type: ignore[union-attr]
        by_id = {id(module): module for module in modules}
        for (_, online), (_, copied) in zip(model.policy.actor.named_modules(), target.named_modules()):  # type: ignore[union-attr]
            if id(online) in by_id:
                copied.load_state_dict(online.state_dict())
                changed += _count(copied.parameters())
    _forget_grad_norms(model)
    return InterventionResult(name, detail, {"weights_changed": float(changed)})


def reset_actor(model: BaseAlgorithm) -> InterventionResult:
    """
    Reset the actor only (after Nikishin et al., "The Primacy Bias in Deep Reinforcement Learning", ICML 2022): new
    actor weights (TD3/DDPG: and target actor; SAC and TD3: with its own features extractor) and a fresh actor
    optimizer state; the critic, DrQv2's encoder, the replay buffer and the counters are kept. SAC with
    ``share_features_extractor=True`` is refused. See docs/interventions.md#the-interventions.

    :param model: a DrQv2, TD3, DDPG or SAC model
    :return: what was done
    """
    parts = intervention_parts(model)
    kind = _kind(parts)
    _check_own_extractor(model)
    modules = parts.actor_modules()
    layers = _span(parts, modules) if kind is None else "features extractor and " + ("mu" if kind == "td3" else "MLP")
    detail = f"new actor ({layers})" + (" and target actor" if kind == "td3" else "") + ", actor optimizer state"
    return _reset_modules(model, modules, "reset_actor", detail)


def reset_mlp(model: BaseAlgorithm) -> InterventionResult:
    """
    Reset the actor's MLP after the encoder, where the action-collapse paper's Figure 3 locates collapse: new
    weights and a fresh optimizer state for those layers; the encoder (or features extractor), the critic, the
    replay buffer and the step counters are kept (after Nikishin et al., ICML 2022, "The Primacy Bias in Deep
    Reinforcement Learning": reset the last layers, keep the buffer).

    - DrQv2: ``mlp0``..``action`` (the whole DrQ-v2 actor: its encoder is the shared one, so this is the same as
      ``reset_actor``);
    - TD3, DDPG: the actor's ``mu`` (``mlp1``..``action``; the features extractor, ``mlp0`` included, is kept), and
      the target actor's ``mu`` (a copy of the new one);
    - SAC: ``latent_pi``, ``mu`` and ``log_std``.

    :param model: a DrQv2, TD3, DDPG or SAC model
    :return: what was done
    """
    parts = intervention_parts(model)
    kind = _kind(parts)
    modules = parts.actor_mlp_modules()
    if kind is None:
        layers = _span(parts, modules)
    elif kind == "td3":
        layers = "mu: mlp1..action, and the target actor's mu"
    else:
        layers = "latent_pi, mu, log_std: mlp1..action"
    return _reset_modules(model, modules, "reset_mlp", f"new actor MLP ({layers}), its optimizer state")


def _span(parts: InterventionParts, modules: Sequence[nn.Module]) -> str:
    """The named layers inside ``modules``, ``first..last`` (``mlp0..action``)."""
    inside = {id(sub) for module in modules for sub in module.modules()}
    names = [name for name, layer in parts.named_layers().items() if id(layer) in inside]
    if not names:
        return ", ".join(type(module).__name__ for module in modules)
    return names[0] if len(names) == 1 else f"{names[0]}..{names[-1]}"


# ------------------------------------------------------------------------------------------------ ReDo
def hidden_layers(model: BaseAlgorithm) -> list[LayerParts]:
    """
    The hidden layers of the actor and the critic that :func:`redo` considers
    (:meth:`InterventionParts.hidden_layer_parts`): the actor's ``mlp1``, ``mlp2``... (as named by
    :func:`~sb3_collapse.common.layers.layer_taps`) and each Q network's ``q<k>.mlp1``... The encoder (or
    features extractor), DrQ-v2's trunks (Linear, LayerNorm, Tanh) and the target networks are not.

    :param model: a DrQv2, TD3, DDPG or SAC model
    :return: the layers, actor first
    """
    return intervention_parts(model).hidden_layer_parts()


def encoder_channels(model: BaseAlgorithm) -> list[LayerParts]:
    """
    The convolutional layers of DrQ-v2's pixel encoder as layers of channels that ReDo may recycle, ``cnn1``..
    ``cnn4`` (:meth:`InterventionParts.encoder_channel_parts`): each output channel is a unit, its incoming weights
    the convolution's filter and bias for it, its outgoing weights the next convolution's input channel, or, for
    ``cnn4``, the columns of the actor's, the critic's and the target critic's trunk Linear that read that channel
    at every position (DrQ-v2's target critic reads the online encoder).
    Sokar et al. recycle convolutional channels so.

    :param model: a DrQv2 model (``CnnPolicy``); another model or ``MlpPolicy`` has none
    :return: the layers, input to output (empty when there are none)
    """
    return intervention_parts(model).encoder_channel_parts()


def hidden_activations(model: BaseAlgorithm, layers: Sequence[LayerParts], samples: Any) -> dict[str, th.Tensor]:
    """
    The activations of hidden layers on a batch of stored transitions (observations for the actor, observations
    and stored actions for the critic), in eval mode, without gradient; the mode is restored afterwards.

    :param model: a DrQv2, TD3, DDPG or SAC model
    :param layers: from :func:`hidden_layers`
    :param samples: replay samples (``observations``, ``actions``), e.g. from
        :meth:`~sb3_collapse.monitoring.callbacks.MetricsBatchSampler.sample_transitions`
    :return: layer name -> ``(n, units)`` float tensor (``(n, channels, height, width)`` for a convolution)
    """
    parts = intervention_parts(model)
    policy = model.policy
    outputs: dict[str, th.Tensor] = {}

    def hook(name: str) -> Callable[..., None]:
        def store(_module: nn.Module, _args: Any, output: th.Tensor) -> None:
            outputs[name] = output.detach().float().clone()

        return store

    handles = [layer.activation.register_forward_hook(hook(layer.name)) for layer in layers]
    was_training = policy.training
    policy.set_training_mode(False)
    try:
        with th.no_grad():
            parts.forward_hidden(samples.observations, samples.actions)
    finally:
        for handle in handles:
            handle.remove()
        policy.set_training_mode(was_training)
    return outputs


def redo(
    model: BaseAlgorithm,
    tau: float = DORMANT_TAU,
    batch_size: int = 512,
    sampler: MetricsBatchSampler | None = None,
    samples: Any = None,
    conv_channels: bool = False,
) -> InterventionResult:
    """
    ReDo, "Recycling Dormant neurons" (Sokar et al., ICML 2023), **once**, on the actor's and the critic's hidden
    layers (:func:`hidden_layers`), and with ``conv_channels`` on DrQ-v2's convolution channels
    (:func:`encoder_channels`). A unit is dormant when its mean absolute activation on the batch, divided by its
    layer's mean, is at most ``tau`` (:func:`~sb3_collapse.monitoring.metrics.dormant_units`). Each dormant unit gets
    new incoming weights, zero outgoing weights in every network that reads it (targets included) and zero Adam
    moments for those entries, so no network's output changes. The periodic form is
    :class:`~sb3_collapse.monitoring.redo.PeriodicReDo`. See docs/interventions.md#the-interventions.

    :param model: a DrQv2, TD3, DDPG or SAC model
    :param tau: the dormancy threshold, relative to the layer's mean (0.025: ReDo's, and ``dormant_ratio``'s)
    :param batch_size: stored transitions of the batch the activations are measured on
    :param sampler: draws the batch from the replay buffer (``None``: a new :class:`MetricsBatchSampler`, seeded
        from the model's seed)
    :param samples: the batch itself (``observations``, ``actions``), instead of drawing one
    :param conv_channels: recycle the dormant channels of DrQ-v2's ``cnn1``..``cnn4`` too (a channel's score is its
        mean absolute activation over the batch and the positions)
    :return: what was done; with fewer than ``batch_size`` stored transitions nothing is recycled and the detail
        says so
    """
    parts = intervention_parts(model)
    layers = (encoder_channels(model) if conv_channels else []) + hidden_layers(model)
    total = sum(layer.units for layer in layers)
    if samples is None:
        sampler = sampler or MetricsBatchSampler(None if model.seed is None else int(model.seed) + 1_000_003)
        drawn = sampler.sample_transitions(model, batch_size)
        if drawn is None:
            detail = f"nothing recycled: fewer than {batch_size} transitions in the replay buffer"
            scalars = {"weights_changed": 0.0, "units_recycled": 0.0, "units_total": float(total)}
            return InterventionResult("redo", detail, scalars, {layer.name: () for layer in layers})
        samples = drawn[0]
    activations = hidden_activations(model, layers, samples)
    masks = {layer.name: dormant_units(activations[layer.name], tau) for layer in layers}
    optimizers = parts.optimizers
    indices = {layer.name: masks[layer.name].nonzero().flatten().to(layer.linear.weight.device) for layer in layers}
    units = {name: tuple(int(i) for i in index.tolist()) for name, index in indices.items()}
    recycling = [(layer, indices[layer.name]) for layer in layers if len(indices[layer.name]) > 0]
    changed = 0
    for layer, index in recycling:  # all incoming weights first...
        changed += _renew_incoming(layer, index, parts, optimizers)
    for layer, index in recycling:  # ...then the outgoing ones: a recycled unit feeding another one stays silent
        changed += _zero_outgoing(layer, index, optimizers)
    _forget_grad_norms(model)
    recycled = sum(len(indices) for indices in units.values())
    listed = ", ".join(f"{layer.name} {len(units[layer.name])}/{layer.units}" for layer in layers if units[layer.name])
    detail = f"{recycled} of {total} hidden units recycled (tau {tau:g})" + (f": {listed}" if listed else "")
    scalars = {"weights_changed": float(changed), "units_recycled": float(recycled), "units_total": float(total)}
    return InterventionResult("redo", detail, scalars, units)


def _renew_incoming(
    layer: LayerParts, index: th.Tensor, parts: InterventionParts, optimizers: Sequence[th.optim.Optimizer]
) -> int:
    """New initial values for the incoming weights and bias of units ``index``; returns the entries changed."""
    fresh = _fresh_copy(layer.linear, parts)
    incoming = [(layer.linear.weight, fresh.weight)]
    if layer.linear.bias is not None:
        incoming.append((layer.linear.bias, fresh.bias))
    with th.no_grad():
        for param, new in incoming:
            param[index] = new[index].to(param.dtype)
    for optimizer in optimizers:
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
    state = optimizer.state.get(param)
    for value in (state or {}).values():
        if isinstance(value, th.Tensor) and value.shape == param.shape:
            with th.no_grad():
                value.index_fill_(dim, index, 0.0)


# ------------------------------------------------------------------------------------------------ shrink and perturb
def shrink_perturb(model: BaseAlgorithm, shrink: float = SHRINK, perturb: float = PERTURB) -> InterventionResult:
    """
    Shrink and perturb as an **interpolation toward a fresh initialization**: ``theta <- shrink * theta + perturb *
    theta_0``, with ``theta_0`` a fresh initialization (the algorithm's initializer, drawn now), on every parameter
    of the online networks: DrQv2's encoder, actor and critic; the actor and the critic of TD3, DDPG and SAC (with
    their features extractors). With the defaults (``shrink + perturb = 1``) every weight moves a fifth of the way
    to a new initial value: ``theta + 0.2 (theta_0 - theta)``. Kept: the target networks (they follow by Polyak
    averaging), the optimizer state, SAC's entropy coefficient, the replay buffer and the step counters. Ash and
    Adams' own form, a shrink and a small noise, is :func:`shrink_perturb_noise`.

    :param model: a DrQv2, TD3, DDPG or SAC model
    :param shrink: lambda, in ``(0, 1]`` (0.8)
    :param perturb: the weight of the fresh initialization, ``>= 0`` (0.2)
    :return: what was done
    """
    changed, names = _shrink_and_add(model, shrink, perturb, "perturb", _fresh_values)
    detail = (
        f"theta <- {shrink:g} theta + {perturb:g} theta_0 (toward a fresh init) on the {', '.join(names)}; "
        "optimizer state kept"
    )
    return InterventionResult("shrink_perturb", detail, {"weights_changed": float(changed)})


def shrink_perturb_noise(
    model: BaseAlgorithm, shrink: float = NOISE_SHRINK, noise: float = NOISE_SCALE
) -> InterventionResult:
    """
    Shrink and perturb in Ash and Adams' form ("On Warm-Starting Neural Network Training", NeurIPS 2020):
    ``theta <- lambda * theta + sigma * noise`` on every parameter of the online networks, the noise at each
    layer's initial scale (:func:`perturbation_noise`). Kept: the target networks, the optimizer state, SAC's
    entropy coefficient, the replay buffer and the counters. See docs/interventions.md#the-interventions.

    :param model: a DrQv2, TD3, DDPG or SAC model
    :param shrink: lambda, in ``(0, 1]``
    :param noise: sigma, ``>= 0``
    :return: what was done
    """
    changed, names = _shrink_and_add(model, shrink, noise, "noise", perturbation_noise)
    detail = (
        f"theta <- {shrink:g} theta + {noise:g} noise (Ash & Adams; noise at each layer's initial scale, biases and "
        f"normalization parameters included) on the {', '.join(names)}; optimizer state kept"
    )
    return InterventionResult("shrink_perturb_noise", detail, {"weights_changed": float(changed)})


def _shrink_and_add(
    model: BaseAlgorithm,
    shrink: float,
    scale: float,
    scale_name: str,
    draw: Callable[[nn.Module, nn.Module], Iterable[tuple[nn.Parameter, th.Tensor]]],
) -> tuple[int, list[str]]:
    """
    ``theta <- shrink * theta + scale * value`` on every parameter of the online networks, the values drawn network by
    network (:meth:`InterventionParts.online_networks`: encoder, actor, critic for DrQv2; actor, critic otherwise)
    from torch's global generator.

    :param scale_name: the Python parameter that ``scale`` is, for the error message
    :param draw: ``(network, a fresh initialization of it) -> (parameter, value)`` pairs: :func:`_fresh_values` or
        :func:`perturbation_noise`
    :return: the parameter entries changed and the networks' names
    """
    if not 0.0 < shrink <= 1.0:
        raise ValueError(f"shrink must be in (0, 1], got {shrink}.")
    if not scale >= 0.0:
        raise ValueError(f"{scale_name} must be >= 0, got {scale}.")
    parts = intervention_parts(model)
    networks = parts.online_networks()
    seen: set[int] = set()
    changed = 0
    for module in networks.values():
        with th.no_grad():
            for param, new in draw(module, _fresh_copy(module, parts)):
                if id(param) in seen:  # a features extractor shared by the actor and the critic: once
                    continue
                seen.add(id(param))
                param.mul_(shrink).add_(new, alpha=scale)
                changed += param.numel()
    _forget_grad_norms(model)
    return changed, list(networks)


def _fresh_values(module: nn.Module, fresh: nn.Module) -> Iterable[tuple[nn.Parameter, th.Tensor]]:
    """``(parameter, its fresh initial value)`` pairs of :func:`shrink_perturb`'s interpolation."""
    return zip(module.parameters(), fresh.parameters())


def perturbation_noise(module: nn.Module, fresh: nn.Module) -> list[tuple[nn.Parameter, th.Tensor]]:
    """
    The noise of :func:`shrink_perturb_noise` for every parameter of ``module``, drawn from torch's global generator
    on each parameter's device, in its dtype: the weight of a Linear or a convolution is ``fresh``'s (a fresh
    initialization of ``module``); any other parameter (a bias, a LayerNorm's gain and shift) is drawn from
    ``U(-1/sqrt(fan_in), 1/sqrt(fan_in))``, ``fan_in`` the inputs of one of the layer's units (a Linear's
    ``in_features``, a convolution's input channels times its kernel area, else the parameter's entries: a
    LayerNorm's normalized features).

    :param module: the module whose parameters get the noise
    :param fresh: a copy of ``module`` with new initial values (same structure)
    :return: ``(parameter, noise)`` pairs, each noise of its parameter's shape, in ``module.modules()`` order
    """
    noise = []
    for sub, fresh_sub in zip(module.modules(), fresh.modules()):
        drawn = dict(fresh_sub.named_parameters(recurse=False))
        for name, param in sub.named_parameters(recurse=False):
            weighted = isinstance(sub, (nn.Linear, nn.Conv2d))
            if weighted and name == "weight":
                noise.append((param, drawn[name]))
                continue
            fan_in = sub.weight[0].numel() if weighted else param.numel()  # type: ignore[index]
            bound = fan_in**-0.5
            noise.append((param, th.empty_like(param).uniform_(-bound, bound)))
    return noise


# ------------------------------------------------------------------------------------------------ by name
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
"""What each intervention is called in figures (e.g. the report's legend), and the periodic ReDo of the variants
``<algorithm>+redo_periodic`` (a callback, not an intervention of the rule)."""


def check_intervention(name: str, model: BaseAlgorithm | None = None) -> None:
    """
    :param name: an intervention name
    :param model: the model it will be applied to (``None``: check the name only)
    :raises ValueError: for an unknown name, or a model the intervention cannot change as it says
    :raises TypeError: for a model that no intervention supports
    """
    if name not in INTERVENTIONS:
        raise ValueError(f"intervention must be one of {', '.join(INTERVENTIONS)}; got {name!r}.")
    if model is None:
        return
    intervention_parts(model)
    if name == "reset":
        _check_resets_itself(model)
    if name == "reset_actor":
        _check_own_extractor(model)


def _check_own_extractor(model: BaseAlgorithm) -> None:
    if _kind(intervention_parts(model)) is not None and getattr(model.policy, "share_features_extractor", False):
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
