"""Linear probing with a sparsity constraint (Section 4.1): how well each layer's activations predict each true-state
component, by OMP with the sparsity chosen on validation episodes (the steps: docs/probe.md)."""

from __future__ import annotations

import dataclasses
import hashlib
import math
import time
from collections.abc import Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
from stable_baselines3.common.utils import get_device

from sb3_collapse.common.layers import LAYER_NAMES
from sb3_collapse.common.progress import progress_bar
from sb3_collapse.drqv2.checks import check_device
from sb3_collapse.errors import InputError, ParameterError
from sb3_collapse.monitoring import collect_activations, layer_taps
from sb3_collapse.probe.checkpoints import Checkpoint, load_checkpoint
from sb3_collapse.probe.omp import omp_path, path_predictions
from sb3_collapse.probe.rollouts import Rollouts
from sb3_collapse.run.config import declared_problem, setting

MIN_EPISODES = 3
"""Episodes a probe needs at least: one each for training, validation and test."""

PROBE_LAYERS = LAYER_NAMES[: LAYER_NAMES.index("action")]
"""The layers of Figure 1 of the paper: every named layer before the action."""


@dataclass
class EpisodeSplit:
    """The sample indices ``order``: ``n_train`` train, then ``n_validation`` validation, then ``n_test`` test samples
    (each in recording order); ``episodes``: ``"train"``, ``"validation"``, ``"test"`` -> sorted episode ids."""

    order: np.ndarray
    n_train: int
    n_validation: int
    n_test: int
    episodes: dict[str, list[int]]


def check_fractions(fractions: Sequence[float]) -> None:
    """:raises InputError: unless ``fractions`` are 3 finite positive fractions (train, validation, test) summing
    to 1"""
    finite = len(fractions) == 3 and all(map(math.isfinite, fractions))
    if not finite or min(fractions) <= 0 or not np.isclose(sum(fractions), 1.0):
        raise InputError(
            f"fractions must be 3 positive fractions summing to 1 (train validation test), got {list(fractions)}.",
            parameter="fractions",
        )


def split_by_episode(
    episode_ids: np.ndarray, fractions: Sequence[float] = (0.6, 0.2, 0.2), seed: int | Sequence[int] = 0
) -> EpisodeSplit:
    """
    Shuffle the episodes: ``round(fraction x episodes)`` (at least one) go to validation and to test, the rest to train.

    :param episode_ids: ``(N,)`` episode of each sample
    :param fractions: train, validation, test fractions of the episodes (summing to 1)
    :param seed: seed of the shuffle (a sequence: ``numpy``'s seed of several entropy words, as :func:`agent_split`'s)
    :return: the split
    :raises InputError: with fewer than 3 episodes, or fractions that leave a set empty
    """
    check_fractions(fractions)
    episodes = np.unique(episode_ids)
    if len(episodes) < MIN_EPISODES:
        raise InputError(
            f"Probing needs at least {MIN_EPISODES} episodes (train, validation, test), the rollouts have "
            f"{len(episodes)}."
        )
    shuffled = np.random.default_rng(seed).permutation(episodes)
    n_val = max(1, round(fractions[1] * len(episodes)))
    n_test = max(1, round(fractions[2] * len(episodes)))
    n_train = len(episodes) - n_val - n_test
    if n_train < 1:
        raise InputError(f"The split {list(fractions)} of {len(episodes)} episodes leaves none for training.")
    bounds = {"train": (0, n_train), "validation": (n_train, n_train + n_val), "test": (n_train + n_val, None)}
    sets = {name: np.sort(shuffled[start:stop]) for name, (start, stop) in bounds.items()}
    parts = [np.flatnonzero(np.isin(episode_ids, ids)) for ids in sets.values()]
    return EpisodeSplit(np.concatenate(parts), *map(len, parts), {name: ids.tolist() for name, ids in sets.items()})


def standardize_features_(
    features: th.Tensor, n_train: int, min_std: float = 1e-6, chunk_rows: int = 256
) -> tuple[th.Tensor, th.Tensor]:
    """Standardize the ``(N, d)`` contiguous ``features`` in place with the mean and std of their first ``n_train``
    rows, ``chunk_rows`` at a time; :return: the ``(N, d_kept)`` result (a view of ``features``' memory), without the
    columns of train std ``<= min_std``, and the ``(d,)`` bool mask of the kept columns"""
    if not features.is_contiguous():
        raise ValueError("standardize_features_ needs a contiguous tensor.")
    n_rows, n_columns = features.shape
    train = [features[start : min(start + chunk_rows, n_train)] for start in range(0, n_train, chunk_rows)]  # views
    zeros = th.zeros(n_columns, dtype=th.float64, device=features.device)  # sum's start, not changed by it
    mean = sum((block.sum(0, dtype=th.float64) for block in train), zeros) / n_train
    squares = sum((((block.to(th.float64) - mean) ** 2).sum(0) for block in train), zeros)
    std = (squares / n_train).sqrt()
    keep = std > min_std
    columns = th.nonzero(keep).flatten()
    kept = len(columns)
    mean32, std32 = mean[columns].to(features.dtype), std[columns].to(features.dtype)
    flat = features.view(-1)
    # Row block [start, stop) is written to flat[start * kept : stop * kept], which ends before the next
    # block's first unread value (at stop * n_columns >= stop * kept): compaction in place is safe.
    for start in range(0, n_rows, chunk_rows):
        stop = min(start + chunk_rows, n_rows)
        block = (features[start:stop].index_select(1, columns) - mean32) / std32
        flat[start * kept : stop * kept] = block.reshape(-1)
    return flat[: n_rows * kept].view(n_rows, kept), keep


def standardize_targets(targets: np.ndarray, n_train: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:return: the ``(N, K)`` ``targets`` standardized (float64) with the mean and std of the first ``n_train`` rows,
    the ``mean`` and the ``scale`` (the std, or 1 for a target constant on those rows: then only centred)"""
    train = targets[:n_train].astype(np.float64)
    mean, std = train.mean(0), train.std(0)
    scale = np.where(std > 0, std, 1.0)
    return (targets.astype(np.float64) - mean) / scale, mean, scale


def plan_passes(dimensions: dict[str, int], n_samples: int, memory_bytes: float) -> list[list[str]]:
    """Group layers (name -> flattened activation size) into forward passes of ``n_samples`` observations whose
    float32 activations take at most ``memory_bytes`` each (first fit, largest layer first; a layer larger than the
    budget gets a pass of its own); each pass lists its layers in the order of ``dimensions``."""
    order, passes = list(dimensions), []  # [bytes used, layers] of each pass
    for name in sorted(order, key=lambda layer: -dimensions[layer]):
        size = 4.0 * dimensions[name] * n_samples
        fit = next((fit for fit in passes if fit[0] + size <= memory_bytes), None)  # first fit
        if fit is None:
            passes.append(fit := [0.0, []])
        fit[0] += size
        fit[1].append(name)
    layer_passes = [sorted(layers, key=order.index) for _, layers in passes]
    return sorted(layer_passes, key=lambda layers: order.index(layers[0]))


def _extract_activations(
    model: object, observations: np.ndarray, order: np.ndarray, layers: Sequence[str], settings: ProbeSettings
) -> dict[str, th.Tensor]:
    """:return: layer -> the ``(len(order), d)`` float32 flattened activations of ``observations[order]``"""
    out: dict[str, th.Tensor] = {}
    device, size = get_device(settings.device), settings.batch_size
    for start in progress_bar(
        range(0, len(order), size), f"extracting {'+'.join(layers)}", "block", settings.progress, leave=False
    ):
        batch = observations[order[start : start + size]]
        for name, value in collect_activations(model, batch, layers, size, device).items():
            if name not in out:
                out[name] = th.empty(len(order), value[0].numel(), dtype=th.float32, device=device)
            out[name][start : start + len(batch)] = value.reshape(len(batch), -1)
    return out


@dataclass
class LayerProbe:
    """
    OMP probe of one layer for the ``K`` targets, MSE in standardized units: ``max_tau`` is the largest sparsity fitted
    (at most ``n_features_kept``, the columns not constant on the train set), ``tau`` ``(K,)`` the one chosen on the
    validation set, ``n_active`` ``(K,)`` the atoms selected before an early stop, ``validation_curve``
    ``(K, max_tau)`` the validation MSE of each sparsity; ``reused``: copied from an earlier checkpoint (``cnn0``).
    """

    layer: str
    n_features: int
    n_features_kept: int
    max_tau: int
    tau: np.ndarray
    n_active: np.ndarray
    validation_curve: np.ndarray
    validation_mse: np.ndarray
    test_mse: np.ndarray
    fit_seconds: float = 0.0
    reused: bool = False


def probe_layer(
    layer: str,
    features: th.Tensor,
    targets: np.ndarray,
    split: EpisodeSplit,
    max_tau: int = 64,
    min_std: float = 1e-6,
    progress: bool = False,
) -> LayerProbe:
    """
    Probe one layer (docs/probe.md, steps 2 to 4); ``features`` is standardized in place.

    :param layer: its name (for the result and the progress bar)
    :param features: ``(N, d)`` float32 activations, rows in ``split.order``
    :param targets: ``(N, K)`` standardized targets, rows in ``split.order``
    :param split: the split
    :param max_tau: the largest sparsity
    :param min_std: train std at or below which a feature column is dropped
    :param progress: show a progress bar over the OMP iterations
    :return: the probe
    """
    start_time = time.perf_counter()
    n_features = features.shape[1]
    features, _ = standardize_features_(features, split.n_train, min_std=min_std)
    n_kept, k = features.shape[1], targets.shape[1]
    n_train, n_val = split.n_train, split.n_validation
    Y = th.as_tensor(targets, dtype=th.float64, device=features.device)
    y_val, y_test = Y[n_train : n_train + n_val], Y[n_train + n_val :]
    tau_max = min(max_tau, n_kept)
    if tau_max == 0:  # nothing varies: the prediction is the train mean, 0 in standardized units
        val_mse, test_mse, zeros = (y_val**2).mean(0).cpu().numpy(), (y_test**2).mean(0).cpu().numpy(), np.zeros(k, int)
        elapsed = time.perf_counter() - start_time
        return LayerProbe(layer, n_features, 0, 0, zeros, zeros, np.empty((k, 0)), val_mse, test_mse, elapsed)
    path = omp_path(features[:n_train], Y[:n_train], tau_max, progress=progress, desc=f"fitting {layer}")
    val_pred = path_predictions(features[n_train : n_train + n_val], path)  # (n_val, K, tau_max)
    curve = ((val_pred - y_val[:, :, None]) ** 2).mean(0)  # (K, tau_max)
    best = curve.argmin(1)  # first minimum: the smallest tau on ties
    rows = th.arange(k, device=curve.device)
    test_pred = path_predictions(features[n_train + n_val :], path)[:, rows, best]
    tau, validation_mse = (best + 1).cpu().numpy(), curve[rows, best].cpu().numpy()
    test_mse = ((test_pred - y_test) ** 2).mean(0).cpu().numpy()
    n_active, elapsed = path.n_active.cpu().numpy(), time.perf_counter() - start_time
    return LayerProbe(
        layer, n_features, n_kept, tau_max, tau, n_active, curve.cpu().numpy(), validation_mse, test_mse, elapsed
    )


@dataclass
class ProbeSettings:
    """The probe's settings, each declared with its flag of ``python -m sb3_collapse.probe`` (:func:`setting`)."""

    layers: Sequence[str] | None = setting(
        help=f"layers to probe; default: those of {' '.join(PROBE_LAYERS)} the model has",
        unit=None,
        choices=PROBE_LAYERS,
        nargs="+",
        metavar="LAYER",
    )
    max_tau: int = setting(64, help="largest sparsity; every tau in 1..`max_tau` is validated", unit=None, minimum=1)
    fractions: Sequence[float] = setting(
        (0.6, 0.2, 0.2),
        help="fractions of the episodes for training, validation and test, summing to 1",
        unit=None,
        flag="--split",
        nargs=3,
        metavar=("TRAIN", "VAL", "TEST"),
        above=0,
        maximum=1,
    )
    split_seed: int = setting(0, help="seed of the episode shuffle", unit=None)
    split_per_agent: bool = setting(
        False,
        help="probe sweep: split the episodes of each agent's probe by its own shuffle, seeded by `split_seed` and the "
        "agent's seed (default: one split for every agent)",
        unit=None,
    )
    batch_size: int = setting(256, help="observations per forward pass", unit="observations", minimum=1)
    memory_gb: float = setting(
        4.0, help="activations held at once, in GB; layers share a forward pass while they fit", unit="GB", above=0
    )
    min_std: float = setting(
        1e-6,
        help="feature columns of a smaller train std are dropped as constant; targets are warned",
        unit=None,
        minimum=0,
    )
    target_std_ratio: float = setting(
        0.1,
        help="warn for a target whose train std is at most this fraction of its std over all the rollouts",
        unit=None,
        minimum=0,
        maximum=1,
    )
    device: str = setting("auto", help="auto (CUDA when available), cpu, cuda, ...", unit=None)
    progress: bool = setting(True, help="show the progress bars", unit=None)

    def validate(self) -> None:
        """:raises InputError: naming the bad setting (out of its declared range, for those of one value)"""
        for option in (option for option in fields(self) if option.metadata["nargs"] is None):
            if (problem := declared_problem(option, getattr(self, option.name), integer=False)) is not None:
                raise ParameterError(option.name, f"{option.name} {problem}")
        check_fractions(self.fractions)
        check_device(self.device)


def agent_split(episode_ids: np.ndarray, settings: ProbeSettings, agent: int | None = None) -> EpisodeSplit:
    """
    The episode split of one agent's probe: :func:`split_by_episode` seeded by ``settings.split_seed``, or with
    ``settings.split_per_agent`` by ``(split_seed, agent)`` (each agent its own shuffle of the same episodes).

    :param episode_ids: ``(N,)`` episode of each sample
    :param settings: the probe's ``fractions``, ``split_seed`` and ``split_per_agent``
    :param agent: the agent's seed (``None``: the shared split)
    :return: the split
    """
    seed = [settings.split_seed, agent] if settings.split_per_agent and agent is not None else settings.split_seed
    return split_by_episode(episode_ids, settings.fractions, seed)


@dataclass
class CheckpointProbe:
    """A checkpoint's probe: one :class:`LayerProbe` per layer, one row of :data:`ROW_COLUMNS` per (layer, target)."""

    checkpoint: Checkpoint
    layers: list[LayerProbe] = field(default_factory=list)
    rows: list[dict] = field(default_factory=list)
    extract_seconds: float = 0.0


ROW_COLUMNS = (
    "checkpoint", "algorithm", "num_timesteps", "frames", "layer", "component", "group", "tau", "max_tau",
    "validation_mse", "test_mse", "validation_mse_raw", "test_mse_raw", "target_std", "n_train", "n_validation",
    "n_test", "n_features", "n_features_kept",
)  # fmt: skip
"""The rows' columns: ``num_timesteps`` in agent steps, ``*_mse`` standardized, ``*_mse_raw`` in state units squared."""


def _select_layers(checkpoint: Checkpoint, layers: Sequence[str] | None) -> list[str]:
    """:return: ``layers`` (``None``: the paper's that the model has) in the model's order; :raises InputError: for
    a requested name the model lacks"""
    available = list(layer_taps(checkpoint.model))
    missing = [name for name in layers or () if name not in available]
    if missing:
        raise InputError(f"{checkpoint.path}: no layer(s) {missing}; this {checkpoint.algorithm} has {available}.")
    names = [name for name in available if name in (PROBE_LAYERS if layers is None else layers)]
    if layers is None and not names:
        raise InputError(f"{checkpoint.path}: none of the layers {list(PROBE_LAYERS)}; it has {available}.")
    return names


def probe_checkpoint(
    checkpoint: Checkpoint,
    rollouts: Rollouts,
    split: EpisodeSplit,
    settings: ProbeSettings,
    reuse: dict[str, LayerProbe] | None = None,
) -> CheckpointProbe:
    """
    Probe every layer of a checkpoint for every state component of the rollouts.

    :param checkpoint: the loaded checkpoint (on ``settings.device``)
    :param rollouts: the recorded observations and states
    :param split: the episode split of the rollouts
    :param settings: the probe's settings
    :param reuse: probes of ``cnn0`` of earlier checkpoints on the same rollouts and split, reused (updated here)
    :return: the results, one row per (layer, target)
    :raises InputError: when the rollouts' observations do not fit the model
    """
    model, observations = checkpoint.model, rollouts.observations
    model_shape = tuple(model.observation_space.shape or ())
    if tuple(observations.shape[1:]) != model_shape:
        raise InputError(
            f"{checkpoint.path} takes observations of shape {model_shape}, the rollouts hold "
            f"{tuple(observations.shape[1:])}: record rollouts with this model's env settings (size, frame stack)."
        )
    layers = _select_layers(checkpoint, settings.layers)
    names, groups, raw_targets = rollouts.targets()
    targets, _, target_scale = standardize_targets(raw_targets[split.order], split.n_train)
    train_std = raw_targets[split.order[: split.n_train]].std(0, dtype=np.float64)
    dims = {name: value[0].numel() for name, value in collect_activations(model, observations[:1], layers).items()}
    result, probes, pixel_key = CheckpointProbe(checkpoint), {}, None
    if reuse is not None and "cnn0" in layers:  # the exact values of cnn0 on a few observations
        pixels = collect_activations(model, observations[split.order[:16]], layers=["cnn0"])["cnn0"]
        # The pixels as this model normalizes them, and the split: a probe is reused on the same samples and sets.
        pixel_key = hashlib.sha1(pixels.cpu().numpy().tobytes() + split.order.tobytes()).hexdigest()
        if pixel_key in reuse:
            probes["cnn0"] = dataclasses.replace(reuse[pixel_key], fit_seconds=0.0, reused=True)
    wanted = {name: dim for name, dim in dims.items() if name not in probes}
    for layer_pass in plan_passes(wanted, len(split.order), settings.memory_gb * 1e9):
        start = time.perf_counter()
        activations = _extract_activations(model, observations, split.order, layer_pass, settings)
        result.extract_seconds += time.perf_counter() - start
        for layer in layer_pass:  # each layer's activations freed once probed
            probes[layer] = probe_layer(
                layer, activations.pop(layer), targets, split, settings.max_tau, settings.min_std, settings.progress
            )
    if pixel_key is not None:
        reuse.setdefault(pixel_key, probes["cnn0"])
    sizes = (split.n_train, split.n_validation, split.n_test)
    for layer in layers:
        probe = probes[layer]
        result.layers.append(probe)
        for j, (name, group) in enumerate(zip(names, groups)):
            mse = (float(probe.validation_mse[j]), float(probe.test_mse[j]))
            values = (checkpoint.name, checkpoint.algorithm, checkpoint.num_timesteps, checkpoint.frames, layer, name)
            values += (group, int(probe.tau[j]), probe.max_tau, *mse, *(m * float(target_scale[j]) ** 2 for m in mse))
            values += (float(train_std[j]), *sizes, probe.n_features, probe.n_features_kept)
            result.rows.append(dict(zip(ROW_COLUMNS, values)))
    return result


REMEDY = (
    "record rollouts from a well-performing agent, as the paper's protocol does (Section 4.1; "
    "`python -m sb3_collapse.probe record GOOD.zip`), with enough episodes (--episodes)"
)
"""The way out that every probe warning names."""


def probe_warnings(
    rollouts: Rollouts, split: EpisodeSplit, rows: Sequence[dict[str, Any]], settings: ProbeSettings
) -> list[dict[str, Any]]:
    """:return: where the probe's ``rows`` mean little (docs/probe.md#warnings), one dict per kind (``kind``,
    ``targets`` or ``layers``, ``message``): targets that barely vary on the train episodes, layers of fewer test
    samples than ``max_tau``"""
    names, _, raw = rollouts.targets()
    train_std = raw[split.order[: split.n_train]].std(0, dtype=np.float64)
    limit = np.maximum(settings.min_std, settings.target_std_ratio * raw.std(0, dtype=np.float64))
    flat = [name for name, std, most in zip(names, train_std, limit) if std <= most]
    layers = list(dict.fromkeys(row["layer"] for row in rows if row["n_test"] < row["max_tau"]))
    warnings = []
    if flat:
        message = (
            f"target(s) {', '.join(flat)} barely vary on the train episodes (train std <= {settings.target_std_ratio:g}"
            " x their std over the rollouts): their standardized MSE divides by that small variance and means little"
        )
        warnings.append({"kind": "barely varying targets", "targets": flat, "message": f"{message}; {REMEDY}."})
    if layers:
        message = (
            f"layer(s) {', '.join(layers)}: the split leaves {split.n_test} test samples, fewer than the sparsity "
            "fitted (max_tau): their test MSE rests on fewer samples than a probe's coefficients"
        )
        warnings.append({"kind": "few test samples", "layers": layers, "message": f"{message}; {REMEDY}."})
    return warnings


def probe_each_checkpoint(
    paths: Sequence[str | Path],
    labels: Sequence[str],
    rollouts: Rollouts,
    split: EpisodeSplit | Sequence[EpisodeSplit],
    settings: ProbeSettings,
    jobs: int = 1,
) -> list[list[dict[str, Any]]]:
    """
    :func:`probe_checkpoint` of many checkpoints on the same rollouts, the first alone (the others reuse its ``cnn0``
    where they share its split).

    :param paths: the checkpoints
    :param labels: their names in the rows (``checkpoint``)
    :param rollouts: the recorded observations and states
    :param split: the episode split of the rollouts, or one per checkpoint (:func:`agent_split`)
    :param settings: the probe's settings; ``settings.progress`` shows one bar over the checkpoints
    :param jobs: checkpoints probed at once (threads, each with ``settings.memory_gb / jobs``); the results do not
        depend on it
    :return: each checkpoint's rows, in the order of ``paths``
    :raises InputError: for a checkpoint that cannot be loaded or does not fit the rollouts
    """
    device = get_device(settings.device)
    quiet = dataclasses.replace(settings, progress=False, memory_gb=settings.memory_gb / jobs)
    reuse: dict[str, LayerProbe] = {}

    splits = [split] * len(paths) if isinstance(split, EpisodeSplit) else list(split)
    if len(splits) != len(paths):
        raise ValueError(f"split: one split or one per checkpoint ({len(paths)}), got {len(splits)}.")

    def probe_one(item: tuple[str | Path, str, EpisodeSplit]) -> list[dict[str, Any]]:
        checkpoint = load_checkpoint(item[0], device=device)
        checkpoint.label = item[1]
        return probe_checkpoint(checkpoint, rollouts, item[2], quiet, reuse).rows

    def in_order(work: list[tuple[str | Path, str, EpisodeSplit]]) -> Iterator[list[dict[str, Any]]]:
        yield probe_one(work[0])  # alone: the others reuse its cnn0 probe
        with ThreadPoolExecutor(max_workers=jobs) as pool:
            yield from pool.map(probe_one, work[1:])  # in the order of work, whatever finishes first

    work = list(zip(paths, labels, splits))
    return list(progress_bar(in_order(work), "probing checkpoints", "checkpoint", settings.progress, len(work)))
