"""An environment's episode in progress rebuilt bit for bit in a new process (its reset's random state and its
actions, taken again), to resume a run from a checkpoint. See docs/checkpoints.md#what-is-in-one."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3.common.vec_env import VecEnv


class EpisodeReplay(gym.Wrapper):
    """Records the episode in progress (the reset's seed or random state, the actions since) for
    :meth:`replay_episode`; ``env.unwrapped`` must have ``get_rng_state`` and ``set_rng_state``."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        for name in ("get_rng_state", "set_rng_state"):
            if not callable(getattr(env.unwrapped, name, None)):
                raise TypeError(f"EpisodeReplay needs an environment with {name}(); {env.unwrapped} has none.")
        self._record: dict[str, Any] | None = None  # None before the first reset
        self._actions: list[np.ndarray] = []

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict]:
        rng = None if seed is not None else self.env.unwrapped.get_rng_state()
        self._record = {"seed": seed, "rng": rng, "options": options}
        self._actions = []
        return self.env.reset(seed=seed, options=options)

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict]:
        self._actions.append(np.array(action, copy=True))
        return self.env.step(action)

    def episode_record(self) -> dict[str, Any] | None:
        """:return: a picklable record of the episode in progress (:meth:`replay_episode`); ``None`` before a reset"""
        if self._record is None:
            return None
        return {**self._record, "actions": [action.copy() for action in self._actions]}

    def replay_episode(self, record: dict[str, Any] | None) -> Any:
        """Reset as the :meth:`episode_record` ``record`` was, then take its actions again (``RuntimeError`` if the
        episode ends before). :return: the observation after the last action; ``None`` for a ``None`` record"""
        if record is None:
            return None
        if record["seed"] is None:
            self.env.unwrapped.set_rng_state(record["rng"])
        observation, _ = self.reset(seed=record["seed"], options=record["options"])
        for index, action in enumerate(record["actions"]):
            observation, _, terminated, truncated, _ = self.step(action)
            if (terminated or truncated) and index < len(record["actions"]) - 1:
                raise RuntimeError(f"the replayed episode ended after {index + 1} of {len(record['actions'])} actions.")
        return observation


def episode_records(venv: VecEnv) -> list[dict[str, Any] | None]:
    """:return: the :meth:`EpisodeReplay.episode_record` of each environment of ``venv``"""
    return list(venv.env_method("episode_record"))


def replay_episodes(venv: VecEnv, records: list[dict[str, Any] | None]) -> list[Any]:
    """:return: each environment's observation after replaying its record of :func:`episode_records`' ``records``"""
    if len(records) != venv.num_envs:
        raise ValueError(f"{len(records)} episode records for {venv.num_envs} environments.")
    return [venv.env_method("replay_episode", record, indices=[index])[0] for index, record in enumerate(records)]
