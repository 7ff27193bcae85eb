"""The health of saved models, offline (``python -m sb3_collapse.probe health``): the metrics of
:func:`~sb3_collapse.monitoring.health.measure_health` of each checkpoint's actor and critic on one observation set,
in training order, as the rows of a long table (the report draws them): docs/probe.md#network-health."""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3.common.utils import get_device

from sb3_collapse.common.progress import progress_bar
from sb3_collapse.drqv2.checks import check_device
from sb3_collapse.envs import parse_task
from sb3_collapse.errors import InputError, LayerMappingError, ParameterError
from sb3_collapse.monitoring.health import HEALTH_METRICS, NETWORKS, HealthMemory, measure_health, network_taps
from sb3_collapse.probe.checkpoints import Checkpoint, load_checkpoint, read_saved_data
from sb3_collapse.probe.fixed_inputs import FIXED_SAMPLES
from sb3_collapse.probe.pipeline import check_checkpoint_files, record
from sb3_collapse.probe.rollouts import RecordOptions, Rollouts
from sb3_collapse.protocol import snapshot_files
from sb3_collapse.run.config import declared_problem, setting
from sb3_collapse.run.snapshots import is_snapshot

OFFLINE_METRICS = tuple(name for name in HEALTH_METRICS if name != "grad_norm")
"""The metrics measured offline: every metric of ``measure_health`` but the gradient norm (a training-time value)."""
SERIES_METRICS = ("persistent_dormant_fraction", "weight_change")
"""The metrics that compare a checkpoint with the one before (``measure_health``'s memory): a time series only."""
HEALTH_COLUMNS = ("checkpoint", "algorithm", "num_timesteps", "frames", "network", "layer", "metric", "value")
"""The columns of ``health.csv``: one row per checkpoint, layer and metric (``num_timesteps`` in agent steps,
``frames`` = agent steps x action repeat)."""
SCALAR_LAYER = "action"
"""The ``layer`` of the actor's metrics of the whole action (``collapse/action_std``, ``action_saturation``)."""


@dataclass
class HealthSettings:
    """What ``health`` measures and how, each setting declared with its flag of ``python -m sb3_collapse.probe``."""

    metrics: Sequence[str] | None = setting(
        help="metrics to measure; default: all of them (those comparing with the previous checkpoint, "
        f"{' and '.join(SERIES_METRICS)}, only over checkpoints of distinct training steps)",
        unit=None,
        choices=OFFLINE_METRICS,
        nargs="+",
        metavar="METRIC",
    )
    networks: Sequence[str] | None = setting(
        help="networks to measure; default: actor and critic (the actor only when a checkpoint is a snapshot, which "
        "holds no critic)",
        unit=None,
        choices=NETWORKS,
        nargs="+",
        metavar="NETWORK",
    )
    samples: int = setting(
        FIXED_SAMPLES,
        help="observations drawn from the rollouts (without replacement; all when there are fewer)",
        unit="observations",
        minimum=2,
    )
    sample_seed: int = setting(0, help="seed of that draw", unit=None)
    batch_size: int = setting(256, help="observations per forward pass", unit="observations", minimum=1)
    device: str = setting("auto", help="auto (CUDA when available), cpu, cuda, ...", unit=None)
    progress: bool = setting(True, help="show the progress bars", unit=None)

    def validate(self) -> None:
        """:raises ParameterError: naming the setting out of its declared choices or range (each value of a list)"""
        for option in fields(self):
            value = getattr(self, option.name)
            if option.metadata["nargs"] is not None and value is not None and not len(value):
                raise ParameterError(option.name, f"{option.name} must hold at least one value, or be None.")
            for item in value if option.metadata["nargs"] is not None and value is not None else [value]:
                if (problem := declared_problem(option, item, integer=False)) is not None:
                    raise ParameterError(option.name, f"{option.name} {problem}")
        check_device(self.device)


def health_checkpoint_paths(paths: Sequence[str | Path]) -> list[Path]:
    """:return: ``paths`` with a run folder replaced by its snapshots (``<run>/snapshots/*.zip``, in training order)"""
    expanded: list[Path] = []
    for path in map(Path, paths):
        expanded += snapshot_files(path) if path.is_dir() and snapshot_files(path) else [path]
    return expanded


def is_time_series(steps: Sequence[int]) -> bool:
    """:return: whether the checkpoints of training ``steps`` are 2 or more of distinct steps (measured in order)"""
    return len(steps) >= 2 and len(set(steps)) == len(steps)


def chosen_metrics(metrics: Sequence[str] | None, series: bool) -> tuple[str, ...]:
    """:return: the metrics to measure: ``metrics``, or all of :data:`OFFLINE_METRICS` (the :data:`SERIES_METRICS`
    only for a time series, ``series``); :raises InputError: for a series metric asked of no time series"""
    if metrics is None:
        return tuple(name for name in OFFLINE_METRICS if series or name not in SERIES_METRICS)
    asked = [name for name in metrics if name in SERIES_METRICS]
    if asked and not series:
        raise InputError(
            f"metrics {asked} compare each checkpoint with the one before: give checkpoints of distinct training "
            "steps (a run's snapshots), or leave them out.",
            parameter="metrics",
        )
    return tuple(dict.fromkeys(metrics))


def chosen_networks(networks: Sequence[str] | None, paths: Sequence[Path]) -> tuple[tuple[str, ...], str]:
    """:return: the networks to measure (``networks``, default actor and critic, the actor only when a checkpoint is a
    snapshot) and a note on what was left out (``""``: nothing); :raises InputError: the critic asked of a snapshot"""
    snapshot = next((path for path in paths if is_snapshot(path)), None)
    if networks is None:
        if snapshot is not None:
            return ("actor",), f"measuring the actor only: {snapshot} is a snapshot (encoder and actor, no critic)"
        return NETWORKS, ""
    if "critic" in networks and snapshot is not None:
        raise InputError(
            f"{snapshot} is a snapshot (encoder and actor, no critic): pass `networks` actor, or give full "
            "checkpoints.",
            parameter="networks",
        )
    return tuple(dict.fromkeys(networks)), ""


def tag_parts(tag: str) -> tuple[str, str, str]:
    """:return: ``(network, layer, metric)`` of a tag of ``measure_health``: ``collapse/q1.mlp1/srank`` ->
    ``("critic", "q1.mlp1", "srank")``; ``collapse/action_std`` -> ``("actor", "action", "action_std")``"""
    parts = tag.split("/")
    layer, metric = (SCALAR_LAYER, parts[1]) if len(parts) == 2 else (parts[1], parts[2])
    head = layer.split(".")[0]
    return ("critic" if head[:1] == "q" and head[1:].isdigit() else "actor"), layer, metric


def observations_of(
    rollouts: str | Path | None,
    first: Checkpoint,
    options: RecordOptions,
    samples: int,
    seed: int = 0,
    progress: bool = True,
) -> tuple[np.ndarray, str]:
    """
    The observations every checkpoint is measured on, and what they are (for captions).

    :param rollouts: a rollouts file (``python -m sb3_collapse.probe record``), or ``None``: the first checkpoint's own
        rollouts, recorded in its DeepMind Control pixel env (``options``), or, for a model of vector observations, in
        the gymnasium env ``options.env``
    :param first: the first checkpoint (whose rollouts are recorded without ``rollouts``)
    :param options: how to record them
    :param samples: observations drawn without replacement by ``numpy.random.default_rng(seed)`` (all when fewer)
    :param seed: seed of that draw
    :param progress: show the recording's progress bar
    :return: ``(n, *obs_shape)`` observations, in recorded order, and their description
    :raises InputError: for a rollouts file of another observation shape than the model's, or no env to record in
    """
    if rollouts is not None:
        observations, source = Rollouts.load(rollouts).observations, Path(rollouts).name
    elif _is_gymnasium(options.env):
        observations, source = gymnasium_observations(first, options, progress), f"{first.name}'s own rollouts"
        source += f" in {options.env}"
    else:
        recorded = record(first, options, progress)
        observations = recorded.observations
        source = f"{first.name}'s own rollouts in {recorded.env_config['task_id']}"
    shape = tuple(first.model.observation_space.shape or ())
    if tuple(observations.shape[1:]) != shape:
        raise InputError(
            f"{rollouts} holds observations of shape {tuple(observations.shape[1:])} but {first.path} takes {shape}: "
            "give rollouts recorded with the checkpoints' observations (image size and frame stack).",
            parameter="rollouts",
        )
    total = len(observations)
    if samples < total:
        observations = observations[np.sort(np.random.default_rng(seed).choice(total, size=samples, replace=False))]
    drawn = f"{len(observations)} of {total}" if len(observations) < total else f"all {total}"
    return observations, f"{drawn} observations of {source}"


def _is_gymnasium(env: str | None) -> bool:
    """:return: whether ``env`` is given and names no DeepMind Control task (then a gymnasium id)"""
    if env is None:
        return False
    try:
        parse_task(env)
    except ValueError:
        return True
    return False


def gymnasium_observations(checkpoint: Checkpoint, options: RecordOptions, progress: bool = True) -> np.ndarray:
    """:return: the ``(n, *obs_shape)`` observations of ``options.episodes`` episodes of ``checkpoint``'s agent in the
    gymnasium env ``options.env`` (each capped at ``options.max_steps`` agent steps, else by the env's time limit;
    ``options``' seed, deterministic actions and noise); :raises InputError: an unknown id, an env of other
    observations"""
    try:
        env = gym.make(options.env)
    except gym.error.Error as error:
        raise InputError(
            f"env {options.env!r} is neither a DeepMind Control task nor a gymnasium id ({error}).", parameter="env"
        ) from error
    observations: list[np.ndarray] = []
    try:
        if env.observation_space.shape != checkpoint.model.observation_space.shape:
            raise InputError(
                f"{options.env} gives observations of shape {env.observation_space.shape} but {checkpoint.path} takes "
                f"{checkpoint.model.observation_space.shape}: give the env the model was trained on.",
                parameter="env",
            )
        rng = np.random.default_rng(options.seed)
        low, high = env.action_space.low, env.action_space.high
        for episode in progress_bar(range(options.episodes), "recording", "episode", progress):
            obs, _ = env.reset(seed=options.seed + episode)
            for _ in range(options.max_steps) if options.max_steps is not None else itertools.count():
                observations.append(obs)
                action, _ = checkpoint.model.predict(obs, deterministic=options.deterministic)
                if options.noise_std > 0:
                    action = np.clip(action + rng.normal(0.0, options.noise_std, np.shape(action)), low, high)
                obs, _, terminated, truncated, _ = env.step(action)
                if terminated or truncated:
                    break
    finally:
        env.close()
    return np.stack(observations)


def checkpoint_health(
    paths: Sequence[str | Path],
    settings: HealthSettings,
    rollouts: str | Path | None = None,
    record_options: RecordOptions | None = None,
    labels: Sequence[str] | None = None,
) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """
    Measure every checkpoint on one observation set, one checkpoint in memory at a time; over checkpoints of distinct
    training steps (a run's snapshots) in training order, with one
    :class:`~sb3_collapse.monitoring.health.HealthMemory` carried from the first (whose weights are the reference of
    ``weight_change``).

    :param paths: SB3 zips of DrQv2, TD3, DDPG or SAC (CNN or MLP policies), or DrQv2 snapshots
    :param settings: the metrics, networks, observations and device
    :param rollouts: a rollouts file, or ``None``: record the first checkpoint's own (:func:`observations_of`)
    :param record_options: how to record them (``None``: the defaults)
    :param labels: the checkpoints' names in the rows (``None``: their file names)
    :return: the rows of :data:`HEALTH_COLUMNS` (in training order for a time series) and what was measured
        (``series``, ``networks``, ``metrics``, ``inputs``, ``notes``, ``checkpoints``)
    :raises InputError: for bad input (what can be checked without a model, before any is loaded)
    """
    settings.validate()
    record_options = record_options or RecordOptions()
    record_options.check()
    paths = [Path(path) for path in paths]
    check_checkpoint_files(paths)  # SB3 zips of probe-able algorithms, of one observation shape
    names = list(labels) if labels is not None else [path.name.removesuffix(".zip") for path in paths]
    steps = [int(read_saved_data(path)[1].get("num_timesteps", 0)) for path in paths]
    series = is_time_series(steps)
    order = sorted(range(len(paths)), key=steps.__getitem__) if series else list(range(len(paths)))
    metrics = chosen_metrics(settings.metrics, series)
    networks, note = chosen_networks(settings.networks, paths)
    if note:
        print(f"Note: {note}.", flush=True)
    device = get_device(settings.device)
    memory, observations, inputs = HealthMemory(), None, ""
    rows: list[dict[str, Any]] = []
    measured: list[dict[str, Any]] = []
    for index in progress_bar(order, "measuring", "checkpoint", settings.progress):
        checkpoint = load_checkpoint(paths[index], device=device)
        checkpoint.label = names[index]
        try:
            network_taps(checkpoint.model, networks)
        except LayerMappingError as error:
            raise InputError(f"{checkpoint.path}: {error}", parameter="networks") from error
        if observations is None:
            observations, inputs = observations_of(
                rollouts, checkpoint, record_options, settings.samples, settings.sample_seed, settings.progress
            )
        values = measure_health(
            checkpoint.model,
            observations,
            metrics=metrics,
            networks=networks,
            batch_size=settings.batch_size,
            device=device,
            memory=memory if series else HealthMemory(),
        )
        about = {"checkpoint": checkpoint.name, "algorithm": checkpoint.algorithm}
        about |= {"num_timesteps": checkpoint.num_timesteps, "frames": checkpoint.frames}
        for tag, value in values.items():
            network, layer, metric = tag_parts(tag)
            rows.append(about | {"network": network, "layer": layer, "metric": metric, "value": float(value)})
        measured.append(about | {"path": str(checkpoint.path)})
        del checkpoint  # one model in memory at a time
    summary = {"series": series, "networks": list(networks), "metrics": list(metrics), "inputs": inputs}
    return rows, summary | {"notes": [note] if note else [], "checkpoints": measured}
