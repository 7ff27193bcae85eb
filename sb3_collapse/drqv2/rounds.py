"""The loop of ``DrQv2.learn()`` in rounds: DrQ-v2's update ratio on any number of environments
(``train_freq=(n, "transition")``), SB3's ``train_freq`` otherwise, and environments stepped during the updates:
docs/throughput.md."""

from __future__ import annotations

from enum import Enum
from typing import TypeVar

import numpy as np
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.noise import ActionNoise
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.type_aliases import MaybeCallback, RolloutReturn, TrainFreq, TrainFrequencyUnit
from stable_baselines3.common.utils import should_collect_more_steps
from stable_baselines3.common.vec_env import VecEnv

from sb3_collapse.common.model import CollapseModelBase
from sb3_collapse.errors import AssertedParameterError

SelfRoundsAlgorithm = TypeVar("SelfRoundsAlgorithm", bound="RoundsAlgorithm")


class TransitionUnit(Enum):
    """The unit of ``train_freq=(n, "transition")``: transitions summed over the environments (beside SB3's
    ``TrainFrequencyUnit``, an ``Enum`` as it so that a saved ``TrainFreq`` comes back as one)."""

    TRANSITION = "transition"


TRANSITION = TransitionUnit.TRANSITION
TRAIN_FREQ_UNITS = ("step", "episode", TRANSITION.value)


class RoundsAlgorithm(CollapseModelBase, OffPolicyAlgorithm):
    """SB3's off-policy loop in rounds: the environment steps up to the next update due (:meth:`updates_due`), then
    the updates due, with the next step sent to the environments first (``step_envs_during_updates``)."""

    step_envs_during_updates: bool = False
    no_env_step_this_round: bool = False  # set during a round: its updates step no environment
    _pending_step: tuple[np.ndarray, np.ndarray] | None = None

    @property
    def at_safe_point(self) -> bool:
        """Whether no environment step is in flight (see :meth:`request_safe_point`)."""
        return self._pending_step is None

    def request_safe_point(self) -> None:
        """The round in progress steps no environment during its updates: the next round starts at a safe point."""
        self.no_env_step_this_round = True

    def learn(
        self: SelfRoundsAlgorithm,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 4,
        tb_log_name: str = "run",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfRoundsAlgorithm:
        if self.env is None:  # before SB3's assertion in _setup_learn; also an AssertionError, as SB3's
            name = type(self).__name__
            message = (
                f"{name}.learn needs an environment: pass env= to {name}(...) or {name}.load(...), or call set_env."
            )
            raise AssertedParameterError("env", message)
        if reset_num_timesteps:
            self.reset_step = 0
        total_timesteps, callback = self._setup_learn(
            total_timesteps, callback, reset_num_timesteps, tb_log_name, progress_bar
        )
        callback.on_training_start(locals(), globals())
        try:
            while self.num_timesteps < total_timesteps:
                if not self._learning_round(callback, total_timesteps, log_interval):
                    break
        finally:
            self._finish_pending_step()  # only after an exception: a normal round leaves no step in flight
        callback.on_training_end()
        return self

    def _learning_round(self, callback: BaseCallback, total_timesteps: int, log_interval: int) -> bool:
        """One round of environment steps then updates; :return: whether to go on (a callback may stop it)"""
        start = self.num_timesteps
        rollout = self.collect_rollouts(
            self.env, callback, self._round_train_freq(), self.replay_buffer,  # type: ignore[arg-type]
            self.action_noise, self.learning_starts, log_interval,
        )  # fmt: skip
        updates = self.updates_due(start, self.num_timesteps) if rollout.continue_training else 0
        if updates > 0:
            stepping = self.step_envs_during_updates and not self.no_env_step_this_round
            if stepping and self.num_timesteps < total_timesteps:
                self._send_next_step()
            self.train(gradient_steps=updates, batch_size=self.batch_size)
        self.no_env_step_this_round = False
        return rollout.continue_training

    def in_warmup(self, learning_starts: int | None = None) -> bool:
        """:return: whether the next actions are uniformly random (in the ``learning_starts`` transitions, ``None``:
        the model's, since the last reset)"""
        warmup = self.learning_starts if learning_starts is None else learning_starts
        return self.num_timesteps - self.reset_step < warmup

    def collect_rollouts(
        self,
        env: VecEnv,
        callback: BaseCallback,
        train_freq: TrainFreq,
        replay_buffer: ReplayBuffer,
        action_noise: ActionNoise | None = None,
        learning_starts: int = 0,
        log_interval: int | None = None,
    ) -> RolloutReturn:
        """SB3's ``collect_rollouts``; the first step completes the step sent before the updates, if any."""
        self.policy.set_training_mode(False)
        if env.num_envs > 1 and train_freq.unit == TrainFrequencyUnit.EPISODE:
            raise ValueError(
                f"train_freq=({train_freq.frequency}, 'episode') counts episodes, which needs one environment, but the "
                f"VecEnv has {env.num_envs}. Use train_freq in steps (transitions), e.g. train_freq=2."
            )
        num_collected_steps, num_collected_episodes = 0, 0
        callback.on_rollout_start()
        while should_collect_more_steps(train_freq, num_collected_steps, num_collected_episodes):
            if self._pending_step is not None:  # sent before the updates: its actions predate them
                actions, buffer_actions = self._pending_step
                self._pending_step = None
                new_obs, rewards, dones, infos = env.step_wait()
            else:
                actions, buffer_actions = self._sample_action(learning_starts, action_noise, env.num_envs)
                new_obs, rewards, dones, infos = env.step(actions)
            self.num_timesteps += env.num_envs
            num_collected_steps += 1

            callback.update_locals(locals())
            if not callback.on_step():
                return RolloutReturn(num_collected_steps * env.num_envs, num_collected_episodes, False)
            self._update_info_buffer(infos, dones)
            self._store_transition(replay_buffer, buffer_actions, new_obs, rewards, dones, infos)  # type: ignore[arg-type]
            self._update_current_progress_remaining(self.num_timesteps, self._total_timesteps)
            self._on_step()
            for index, done in enumerate(dones):
                if done:
                    num_collected_episodes += 1
                    self._episode_num += 1
                    if action_noise is not None:
                        action_noise.reset(**(dict(indices=[index]) if env.num_envs > 1 else {}))
                    if log_interval is not None and self._episode_num % log_interval == 0:
                        self.dump_logs()
        callback.on_rollout_end()
        return RolloutReturn(num_collected_steps * env.num_envs, num_collected_episodes, continue_training=True)

    def _send_next_step(self) -> None:
        """Choose the next actions with the current weights and send them to the environments (``step_async``)."""
        assert self.env is not None
        actions, buffer_actions = self._sample_action(self.learning_starts, self.action_noise, self.env.num_envs)
        self.env.step_async(actions)
        self._pending_step = (actions, buffer_actions)

    def _finish_pending_step(self) -> None:
        """After an exception: wait for the step in flight and store its transition (dropped if the environments
        died)."""
        if self._pending_step is None or self.env is None:
            return
        _, buffer_actions = self._pending_step
        self._pending_step = None
        try:
            new_obs, rewards, dones, infos = self.env.step_wait()
        except Exception:  # noqa: BLE001 - the original exception is the one to report
            return
        self.num_timesteps += self.env.num_envs
        self._update_info_buffer(infos, dones)
        self._store_transition(self.replay_buffer, buffer_actions, new_obs, rewards, dones, infos)  # type: ignore[arg-type]

    def _convert_train_freq(self) -> None:
        """SB3's conversion of ``train_freq``, and of ``(n, "transition")`` to ``TrainFreq(n, TRANSITION)``."""
        freq = self.train_freq
        if isinstance(freq, (tuple, list)) and len(freq) == 2 and freq[1] in (TRANSITION, "transition"):
            self.train_freq = TrainFreq(freq[0], TRANSITION)  # type: ignore[arg-type]
        else:
            super()._convert_train_freq()

    def _round_train_freq(self) -> TrainFreq:
        """``env.step`` calls of the next rollout: with ``(n, "transition")``, up to the step in which the transition
        count reaches the next multiple of ``n`` or the budget of ``learn()``; SB3's ``train_freq`` as is."""
        if self.train_freq.unit != TRANSITION:
            return self.train_freq
        frequency = self.train_freq.frequency
        next_multiple = (self.num_timesteps // frequency + 1) * frequency
        stop = min(next_multiple, max(self._total_timesteps, self.num_timesteps + 1))
        return TrainFreq(-(-(stop - self.num_timesteps) // self.n_envs), TrainFrequencyUnit.STEP)

    def updates_due(self, start: int, end: int) -> int:
        """:return: the updates due when ``num_timesteps`` goes from ``start`` to ``end`` (with ``(n, "transition")``,
        ``gradient_steps`` per multiple of ``n`` past ``reset_step + learning_starts``; SB3's otherwise)"""
        first = self.reset_step + self.learning_starts  # no update at or before this transition count
        if self.train_freq.unit != TRANSITION:
            return 0 if end <= first else self.gradient_steps if self.gradient_steps >= 0 else end - start
        low, frequency = max(start, first), self.train_freq.frequency
        if end <= low:
            return 0
        return end - low if self.gradient_steps < 0 else self.gradient_steps * (end // frequency - low // frequency)
