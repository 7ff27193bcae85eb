"""The layer names (what each is: docs/monitoring.md), where each is read in a DrQv2, TD3, DDPG or SAC actor
(:func:`layer_taps`), and the hidden layers whose units ReDo may recycle (:class:`LayerParts`)."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import NamedTuple

import torch as th
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.torch_layers import FlattenExtractor, NatureCNN
from torch import nn

from sb3_collapse.errors import LayerMappingError

LAYER_NAMES = ("cnn0", "cnn1", "cnn2", "cnn3", "cnn4", "mlp0", "mlp1", "mlp2", "action")  # input to output


class LayerParts(NamedTuple):
    """
    A hidden layer ``name`` (``mlp1``, ``q1.mlp1``, ``cnn1``...), ``activation(linear(x))`` read by the ``consumers``
    (every Linear or Conv2d that reads it, target networks included); a unit is an output feature or channel.

    :param positions: spatial positions per channel in the consumers' flattened input (``height x width`` for a last
        convolution read by Linear layers); 1 otherwise
    :param channels_last: the consumers' flattened input is (height, width, channel), else (channel, height, width)
    """

    name: str
    linear: nn.Linear | nn.Conv2d
    activation: nn.Module
    consumers: tuple[nn.Linear | nn.Conv2d, ...]
    positions: int = 1
    channels_last: bool = False

    @property
    def units(self) -> int:
        """Output features or channels."""
        return int(self.linear.weight.shape[0])

    def consumer_columns(self, index: th.Tensor) -> th.Tensor:
        """:return: the consumers' weight columns (dim 1) that read the units ``index`` ``(k,)``, on its device"""
        if self.positions == 1:
            return index
        where = th.arange(self.positions, device=index.device)
        if self.channels_last:  # column of (position p, channel c): p * channels + c
            return (where[:, None] * self.units + index[None, :]).flatten()
        return (index[:, None] * self.positions + where[None, :]).flatten()  # c * positions + p


def sequential_hidden_parts(
    prefix: str, modules: Sequence[nn.Module], tail: tuple[nn.Linear, ...] = (), first: int = 1
) -> list[LayerParts]:
    """:return: the hidden layers (``Linear, activation`` pairs) of ``modules`` run in sequence, named
    ``<prefix>mlp<k>`` from ``k = first``; ``tail``: the consumers of the last Linear's activation"""
    modules = list(modules)
    linears = [i for i, module in enumerate(modules) if isinstance(module, nn.Linear)]
    hidden = []
    for k, i in enumerate(linears):
        following = [modules[j] for j in linears if j > i]
        consumers = (following[0],) if following else tail
        if i + 1 < len(modules) and next(modules[i + 1].parameters(), None) is None and consumers:
            hidden.append(LayerParts(f"{prefix}mlp{k + first}", modules[i], modules[i + 1], consumers))  # type: ignore[arg-type]
    return hidden


def reinitialize(module: nn.Module, initializer: Callable[[nn.Module], None] | None = None) -> None:
    """New initial values for every parameter of ``module``, in place, in ``module.modules()`` order: ``initializer``
    for each Linear and Conv2d, ``reset_parameters()`` for the others (``TypeError`` for a module without one)."""
    for sub in module.modules():
        if next(sub.parameters(recurse=False), None) is None:
            continue
        if initializer is not None and isinstance(sub, (nn.Linear, nn.Conv2d)):
            initializer(sub)
        elif callable(getattr(sub, "reset_parameters", None)):
            sub.reset_parameters()  # type: ignore[operator]
        else:
            raise TypeError(f"Cannot draw new initial values for the parameters of {type(sub).__name__}.")


@dataclass(frozen=True)
class LayerTap:
    """Where a named activation is read: the output (``source="input"``: the first input) of ``module``, computed
    with ``parameters`` (none for ``cnn0``), then ``transform``-ed unless ``None`` (``tanh`` for SAC's action)."""

    module: nn.Module
    parameters: tuple[nn.Parameter, ...]
    source: str = "output"
    transform: Callable[[th.Tensor], th.Tensor] | None = None


def policy_of(model: BaseAlgorithm | BasePolicy) -> BasePolicy:
    """:return: the policy of an algorithm, or the policy itself"""
    policy = model.policy if isinstance(model, BaseAlgorithm) else model
    if not isinstance(policy, BasePolicy):
        raise LayerMappingError(f"Expected an SB3 algorithm or policy, got {type(model).__name__}.")
    return policy


def layer_taps(model: BaseAlgorithm | BasePolicy) -> dict[str, LayerTap]:
    """:return: name -> :class:`LayerTap` of the named layers of a DrQv2, TD3, DDPG or SAC actor (algorithm or
    policy), input to output (docs/monitoring.md); ``LayerMappingError`` for an unknown layout"""
    policy = policy_of(model)
    named_layers = getattr(policy, "named_layers", None)
    if callable(named_layers):  # DrQv2Policy names its own layers
        return {name: LayerTap(module, tuple(module.parameters())) for name, module in named_layers().items()}
    actor = getattr(policy, "actor", None)
    if actor is None or not hasattr(actor, "features_extractor"):
        raise LayerMappingError(
            f"Cannot map the layers of {type(policy).__name__}: named layers are defined for DrQv2 and for "
            "SB3's TD3, DDPG and SAC policies (an `actor` with a features extractor)."
        )
    taps = _extractor_taps(actor.features_extractor)
    if hasattr(actor, "latent_pi"):  # SAC: latent_pi = hidden layers, mu = mean action before the tanh squash
        if getattr(actor, "use_sde", False):
            raise LayerMappingError("SAC with gSDE (use_sde=True) has no deterministic tanh(mu) action to name.")
        taps.update(_activation_taps(actor.latent_pi, nn.Linear, "mlp"))
        taps["action"] = LayerTap(actor.mu, tuple(actor.mu.parameters()), transform=th.tanh)
    elif isinstance(getattr(actor, "mu", None), nn.Sequential):  # TD3 / DDPG: mu = hidden layers, Linear, Tanh
        linears = [i for i, m in enumerate(actor.mu) if isinstance(m, nn.Linear)]
        if not linears or linears[-1] + 1 >= len(actor.mu):
            raise LayerMappingError(
                f"Cannot map the layers of {type(policy).__name__}: unexpected actor.mu {actor.mu}."
            )
        last = linears[-1]
        taps.update(_activation_taps(actor.mu[:last], nn.Linear, "mlp"))
        taps["action"] = LayerTap(actor.mu[last + 1], tuple(actor.mu[last].parameters()))
    else:
        raise LayerMappingError(f"Cannot map the layers of {type(policy).__name__}: its actor has no `mu` network.")
    return taps


def _extractor_taps(extractor: nn.Module) -> dict[str, LayerTap]:
    """``cnn0``..``cnnK`` and ``mlp0`` of SB3's ``NatureCNN`` or ``FlattenExtractor``."""
    if isinstance(extractor, NatureCNN):
        taps = {"cnn0": LayerTap(extractor.cnn, (), source="input")}
        taps.update(_activation_taps(extractor.cnn, nn.Conv2d, "cnn"))
        taps["mlp0"] = LayerTap(extractor.linear, tuple(extractor.linear.parameters()))
        return taps
    if isinstance(extractor, FlattenExtractor):
        return {"mlp0": LayerTap(extractor, ())}
    raise LayerMappingError(
        f"Cannot map the layers of the features extractor {type(extractor).__name__}: "
        "NatureCNN (CnnPolicy) and FlattenExtractor (MlpPolicy) are supported."
    )


def _activation_taps(layers: Iterable[nn.Module], kind: type[nn.Module], prefix: str) -> dict[str, LayerTap]:
    """``<prefix>1``..``<prefix>K``: the activation after each ``kind`` module of a ``kind, activation, ...`` list."""
    modules = list(layers)
    taps: dict[str, LayerTap] = {}
    for k, index in enumerate((i for i, m in enumerate(modules) if isinstance(m, kind)), start=1):
        if index + 1 >= len(modules) or isinstance(modules[index + 1], (nn.Linear, nn.Conv2d, nn.Flatten)):
            raise LayerMappingError(f"{kind.__name__} {k} of the actor ({prefix}{k}) has no activation after it.")
        taps[f"{prefix}{k}"] = LayerTap(modules[index + 1], tuple(modules[index].parameters()))
    return taps


def layer_parameters(model: BaseAlgorithm | BasePolicy) -> dict[str, tuple[nn.Parameter, ...]]:
    """:return: name -> the parameters of the layer that computes it, input to output (``cnn0`` left out)"""
    return {name: tap.parameters for name, tap in layer_taps(model).items() if tap.parameters}


def critic_layer_taps(model: BaseAlgorithm | BasePolicy) -> dict[str, LayerTap]:
    """
    :return: name -> :class:`LayerTap` of each Q network ``q<k>`` of a DrQv2, TD3, DDPG or SAC critic (algorithm or
        policy), named as the actor's (docs/monitoring.md#the-critic): ``q<k>.mlp0`` the network's input (the
        critic's features and the action, concatenated), ``q<k>.mlp1``.. after each hidden Linear + activation,
        ``q<k>`` the Q value ``(n, 1)``; ``LayerMappingError`` for an unknown layout
    """
    policy = policy_of(model)
    heads = getattr(getattr(policy, "critic", None), "q_networks", None)
    if not heads:
        raise LayerMappingError(
            f"Cannot map the critic of {type(policy).__name__}: critic layers are defined for DrQv2 and for SB3's "
            "TD3, DDPG and SAC policies (a `critic` with `q_networks`)."
        )
    taps: dict[str, LayerTap] = {}
    for k, head in enumerate(heads, start=1):
        modules = list(head)
        linears = [i for i, module in enumerate(modules) if isinstance(module, nn.Linear)]
        if not linears or linears[-1] != len(modules) - 1:
            raise LayerMappingError(
                f"Cannot map the layers of Q network q{k}: expected Linear, activation, ... Linear."
            )
        taps[f"q{k}.mlp0"] = LayerTap(modules[0], (), source="input")
        taps.update(_activation_taps(modules[: linears[-1]], nn.Linear, f"q{k}.mlp"))
        taps[f"q{k}"] = LayerTap(modules[-1], tuple(modules[-1].parameters()))
    return taps
