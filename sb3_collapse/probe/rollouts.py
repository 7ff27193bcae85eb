"""Rollouts: an agent's pixel observations with the true state and the reward's inputs behind each ("all of them are
the input to the reward function"), saved as compressed ``.npz`` files: docs/probe.md."""

from __future__ import annotations

import inspect
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np
from stable_baselines3.common.base_class import BaseAlgorithm

from sb3_collapse.common.progress import progress_bar
from sb3_collapse.envs import make_dmc_env, parse_task
from sb3_collapse.envs.dmc import reward_inputs_of
from sb3_collapse.errors import InputError, ParameterError
from sb3_collapse.protocol import REWARD_PREFIX, atomic_output
from sb3_collapse.run.config import declared_problem, setting

FORMAT_VERSION = 2
"""The format of the rollouts files written and read (a file of another is refused)."""
ENV_SETTINGS = ("task_id", "action_repeat", "frame_stack", "size", "camera_id")
"""``make_dmc_env`` settings stored with the rollouts (``obs_type`` is always ``"pixels"``)."""
ARRAYS = ("observations", "actions", "rewards", "episode_ids", "steps")
"""The arrays of every recorded step, besides the states and reward inputs."""


@dataclass
class Rollouts:
    """
    Recorded agent steps, ``N`` in all (not the final observation of an episode, on which no action is taken).

    :param observations: ``(N, *obs_shape)`` observations as the env gives them (``uint8`` ``(N, 9, 84, 84)``)
    :param states: true-state component name -> ``(N, size)`` float32 at each observation, in dm_control's order
    :param actions: ``(N, action_dim)`` float32 actions taken, in [-1, 1]
    :param rewards: ``(N,)`` float32 reward received for each action (summed over the action repeat)
    :param episode_ids: ``(N,)`` int64 episode of each step, ``0..episodes - 1``
    :param steps: ``(N,)`` int64 agent step of each observation within its episode (0: the reset observation)
    :param env_config: ``make_dmc_env`` settings (:data:`ENV_SETTINGS`)
    :param metadata: how they were recorded (``checkpoint``, ``deterministic``, ``noise_std``, ``seed``, ...)
    :param reward_inputs: reward input name -> ``(N, size)`` float32 that the task's reward reads at each observation
    """

    observations: np.ndarray
    states: dict[str, np.ndarray]
    actions: np.ndarray
    rewards: np.ndarray
    episode_ids: np.ndarray
    steps: np.ndarray
    env_config: dict[str, Any]
    metadata: dict[str, Any] = field(default_factory=dict)
    reward_inputs: dict[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        n = len(self.observations)
        arrays = {name: getattr(self, name) for name in ARRAYS[1:]}
        arrays.update({f"state {name!r}": value for name, value in self.states.items()})
        arrays.update({f"reward input {name!r}": value for name, value in self.reward_inputs.items()})
        wrong = {name: len(value) for name, value in arrays.items() if len(value) != n}
        if wrong:
            raise InputError(f"Rollouts arrays must all have {n} rows (one per observation); got {wrong}.")

    def __len__(self) -> int:
        return len(self.observations)

    @property
    def n_episodes(self) -> int:
        """Number of distinct episodes."""
        return len(np.unique(self.episode_ids))

    def targets(self) -> tuple[list[str], list[str], np.ndarray]:
        """:return: the scalar probing targets, one per dimension of each state component then reward input: ``names``
        (``"orientations_0"``, ``"height"``, ``"reward:torso_height"``), ``groups`` and the ``(N, K)`` float32 values"""
        names, groups, columns = [], [], []
        for prefix, components in (("", self.states), (REWARD_PREFIX, self.reward_inputs)):
            for component, values in components.items():
                values = values.reshape(len(values), -1)
                for i in range(values.shape[1]):
                    names.append(prefix + (component if values.shape[1] == 1 else f"{component}_{i}"))
                    groups.append(prefix + component)
                    columns.append(values[:, i])
        if not columns:
            raise InputError("The rollouts hold no state components to probe.")
        return names, groups, np.stack(columns, axis=1).astype(np.float32)

    def save(self, path: str | Path) -> Path:
        """:param path: the compressed ``.npz`` to write (atomically); :return: the path written"""
        meta = {"format_version": FORMAT_VERSION, "env_config": self.env_config, "metadata": self.metadata}
        meta |= {"state_components": list(self.states), "reward_inputs": list(self.reward_inputs)}
        arrays = {name: getattr(self, name) for name in ARRAYS} | {"meta": np.array(json.dumps(meta))}
        arrays.update({f"state/{name}": value for name, value in self.states.items()})
        arrays.update({f"reward_input/{name}": value for name, value in self.reward_inputs.items()})
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        with atomic_output(path) as temporary, temporary.open("wb") as file:
            np.savez_compressed(file, **arrays)
        return Path(path)

    @classmethod
    def load(cls, path: str | Path) -> Rollouts:
        """
        :param path: a file written by :meth:`save`
        :return: the rollouts, with the recorded reward inputs that the task's reward reads (others left out)
        :raises InputError: for a missing file, one that is not a rollouts file or one of another format
        """
        path = Path(path)
        if not path.is_file():
            raise InputError(
                f"Rollouts file {path} does not exist; record one with `python -m sb3_collapse.probe record`."
            )
        try:
            with np.load(path, allow_pickle=False) as data:
                meta = json.loads(str(data["meta"]))
                if meta["format_version"] != FORMAT_VERSION:
                    raise ValueError(f"format {meta['format_version']}, not {FORMAT_VERSION}")
                task = parse_task(meta["env_config"]["task_id"])
                read = {item.name for item in reward_inputs_of(*task) if item.state}
                arrays = {key: data[key] for key in ARRAYS}
                arrays["states"] = {name: data[f"state/{name}"] for name in meta["state_components"]}
                inputs = [name for name in meta["reward_inputs"] if name in read]
                arrays["reward_inputs"] = {name: data[f"reward_input/{name}"] for name in inputs}
        except (OSError, ValueError, KeyError, json.JSONDecodeError) as error:
            raise InputError(
                f"{path} is not a rollouts file this version of sb3_collapse.probe reads ({type(error).__name__}: "
                f"{error}); record one with `python -m sb3_collapse.probe record`."
            ) from error
        return cls(env_config=meta["env_config"], metadata=meta.get("metadata", {}), **arrays)


def resolve_env_config(model_env_config: dict[str, Any] | None, **overrides: Any) -> dict[str, Any]:
    """The :data:`ENV_SETTINGS` for recording: ``overrides`` not ``None``, else a DrQv2 checkpoint's
    ``model_env_config``, else ``make_dmc_env``'s defaults."""
    parameters = inspect.signature(make_dmc_env).parameters
    defaults = {"task_id": None} | {key: parameters[key].default for key in ENV_SETTINGS[1:]}
    saved = {key: value for key, value in (model_env_config or {}).items() if key in defaults and value is not None}
    given = {key: value for key, value in overrides.items() if value is not None}
    config = {**defaults, **saved, **given}
    if config["task_id"] is None:
        raise InputError(
            "The checkpoint does not say which environment it was trained on: pass `env`, e.g. walker-walk."
        )
    if (model_env_config or {}).get("obs_type") not in (None, "pixels"):
        raise InputError(
            f"The checkpoint was trained on {model_env_config['obs_type']!r} observations; probing needs pixels."
        )
    return config


@dataclass
class RecordOptions:
    """How to record rollouts, each option declared with its flag of ``python -m sb3_collapse.probe``
    (:func:`setting`); ``None`` ones come from the checkpoint, else ``make_dmc_env``'s defaults."""

    env: str | None = setting(help="dm_control task, e.g. walker-walk; default: the checkpoint's", unit=None)
    episodes: int = setting(20, help="episodes to record", unit="episodes", minimum=1)
    max_steps: int | None = setting(
        help="cap on agent steps per episode; default: the task's time limit (500 agent steps for walker at action "
        "repeat 2)",
        unit="agent steps",
        minimum=1,
    )
    seed: int = setting(0, help="seed of the env's initial states and the action noise", unit=None)
    deterministic: bool = setting(
        True,
        help="use the policy's deterministic action (off: sample its own exploration)",
        unit=None,
        flag="--stochastic",
    )
    noise_std: float = setting(
        0.0, help="std of Gaussian noise added to each action (actions in [-1, 1])", unit=None, minimum=0
    )
    action_repeat: int | None = setting(help="frames per agent step", unit="frames", minimum=1)
    frame_stack: int | None = setting(help="stacked RGB frames per observation", unit=None, minimum=1)
    size: int | None = setting(help="image height and width", unit="pixels", minimum=1)
    camera_id: int | None = setting(help="camera of the renders", unit=None)
    pool_agents: int = setting(
        1,
        help="probe sweep: pool the rollouts of this many well-performing seeds (the best first), `episodes` in all "
        'divided among them, each recorded with `seed` + its rank (Section 4.1: the samples are "collected from '
        'well-performing agents"); the other commands record one checkpoint',
        unit=None,
        minimum=1,
    )

    def check(self, pooled: bool = False) -> None:
        """
        :param pooled: whether the caller records from several agents (``probe sweep``); else ``pool_agents`` must be 1
        :raises ParameterError: for an option out of its declared range, before anything is loaded or recorded
        """
        for option in fields(self):
            if (problem := declared_problem(option, getattr(self, option.name), integer=False)) is not None:
                raise ParameterError(option.name, f"{option.name} {problem}")
        if not pooled and self.pool_agents != 1:
            message = "pools the rollouts of a sweep's best seeds (probe sweep); here they come from one checkpoint"
            raise ParameterError("pool_agents", f"pool_agents={self.pool_agents} {message}: leave it at 1.")
        if self.pool_agents > self.episodes:
            message = (
                f"pool_agents={self.pool_agents} needs at least one of the `episodes` per agent, got {self.episodes}."
            )
            raise ParameterError("pool_agents", message)

    def shares(self) -> list[int]:
        """:return: the episodes each of the ``pool_agents`` agents records, ``episodes`` in all (the first get the
        remainder)"""
        share, remainder = divmod(self.episodes, self.pool_agents)
        return [share + (rank < remainder) for rank in range(self.pool_agents)]


def pool_rollouts(parts: Sequence[Rollouts]) -> Rollouts:
    """
    The rollouts of several agents as one set: the samples in order, each part's episodes numbered after the
    previous part's (a split by episode never mixes two agents' episodes in one episode).

    :param parts: rollouts of the same task and env settings, with the same state components and reward inputs
    :return: the pooled rollouts; ``metadata["pooled"]``: each part's metadata, ``metadata["agents"]``: their number
    :raises InputError: when the parts were recorded in different envs or hold different components
    """
    if not parts:
        raise InputError("pool_rollouts needs at least one Rollouts.", parameter="parts")
    first = parts[0]
    for part in parts[1:]:
        same = (part.env_config, list(part.states), list(part.reward_inputs))
        if same != (first.env_config, list(first.states), list(first.reward_inputs)):
            raise InputError(
                f"pooled rollouts must share their env settings and components: {part.env_config} vs "
                f"{first.env_config}; record them with the same task, size and frame stack.",
                parameter="parts",
            )
    offsets = np.cumsum([0] + [int(part.episode_ids.max()) + 1 if len(part) else 0 for part in parts[:-1]])
    arrays = {name: np.concatenate([getattr(part, name) for part in parts]) for name in ARRAYS if name != "episode_ids"}
    arrays["episode_ids"] = np.concatenate([part.episode_ids + offset for part, offset in zip(parts, offsets)])

    def joined(kind: str) -> dict[str, np.ndarray]:
        return {name: np.concatenate([getattr(part, kind)[name] for part in parts]) for name in getattr(first, kind)}

    metadata = {"agents": len(parts), "pooled": [part.metadata for part in parts]}
    return Rollouts(
        states=joined("states"),
        reward_inputs=joined("reward_inputs"),
        env_config=dict(first.env_config),
        metadata=metadata,
        **arrays,
    )


def record_rollouts(
    model: BaseAlgorithm,
    env_config: dict[str, Any],
    episodes: int,
    seed: int = 0,
    deterministic: bool = True,
    noise_std: float = 0.0,
    max_steps: int | None = None,
    progress: bool = True,
    metadata: dict[str, Any] | None = None,
) -> Rollouts:
    """
    Run an agent in a DeepMind Control pixel env and record what probing needs.

    :param model: the agent (its observation space must be the env's)
    :param env_config: ``make_dmc_env`` settings (:data:`ENV_SETTINGS`)
    :param episodes: episodes to record
    :param seed: seed of the env's initial states and of the action noise
    :param deterministic: the policy's deterministic action (else the model's own exploration)
    :param noise_std: std of the Gaussian noise added to each action (in action units), then clipped to [-1, 1]
    :param max_steps: cap on agent steps per episode (``None``: the task's time limit)
    :param progress: show a progress bar over agent steps
    :param metadata: extra entries of :attr:`Rollouts.metadata`
    :return: the rollouts
    :raises InputError: when the env's observations do not fit the model
    """
    RecordOptions(episodes=episodes, max_steps=max_steps, noise_std=noise_std).check()
    try:
        env = make_dmc_env(
            env_config["task_id"], seed=seed, obs_type="pixels", **{k: env_config[k] for k in ENV_SETTINGS[1:]}
        )
    except ValueError as error:
        raise InputError(str(error)) from error
    model_shape = tuple(model.observation_space.shape or ())
    if env.observation_space.shape != model_shape:
        env.close()
        raise InputError(
            f"The env gives observations of shape {env.observation_space.shape} but the model takes {model_shape}: "
            "pass the `size` and `frame_stack` the model was trained with."
        )
    rng = np.random.default_rng(seed)
    recorded: dict[str, list] = {name: [] for name in ARRAYS}
    states: dict[str, list] = {name: [] for name in env.state_shapes}
    reward_inputs: dict[str, list] = {}
    per_episode = min(env._dmc._env._step_limit / env.action_repeat, max_steps or math.inf)  # the time limit's cap
    total = episodes * math.ceil(per_episode) if math.isfinite(per_episode) else None
    bar = progress_bar(None, "recording", "step", progress, total)
    try:
        for episode in range(episodes):
            obs, _ = env.reset(seed=seed if episode == 0 else None)
            step, done = 0, False
            while not done and (max_steps is None or step < max_steps):
                action, _ = model.predict(obs, deterministic=deterministic)
                action = np.asarray(action, dtype=np.float32).reshape(env.action_space.shape)
                if noise_std > 0:
                    action = np.clip(action + rng.normal(0.0, noise_std, action.shape), -1.0, 1.0).astype(np.float32)
                for name, value in env.get_state().items():
                    states[name].append(value)
                for name, value in env.reward_inputs().items():
                    reward_inputs.setdefault(name, []).append(value)
                next_obs, reward, terminated, truncated, _ = env.step(action)
                for name, value in zip(ARRAYS, (obs, action, reward, episode, step)):
                    recorded[name].append(value)
                obs, step, done = next_obs, step + 1, terminated or truncated
                bar.update(1)
    finally:
        bar.close()
        env.close()
    dtypes = (None, np.float32, np.float32, np.int64, np.int64)
    arrays = {name: np.asarray(values, dtype) for (name, values), dtype in zip(recorded.items(), dtypes)}
    info = dict(seed=seed, episodes=episodes, deterministic=deterministic, noise_std=noise_std, max_steps=max_steps)
    return Rollouts(
        states={name: np.stack(values).astype(np.float32) for name, values in states.items()},
        reward_inputs={name: np.stack(values).astype(np.float32) for name, values in reward_inputs.items()},
        env_config={key: env_config[key] for key in ENV_SETTINGS},
        metadata={**info, **(metadata or {})},
        **arrays,
    )
