"""DrQ-v2 (Yarats et al., 2021) as a Stable-Baselines3 off-policy algorithm: ``docs/algorithm.md``."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any, ClassVar, TypeVar

import numpy as np
import torch as th
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.noise import ActionNoise
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, ReplayBufferSamples, Schedule

from sb3_collapse.common.grad_norms import GradNormRecorder
from sb3_collapse.common.model import read_env_config
from sb3_collapse.drqv2 import replay_memory
from sb3_collapse.drqv2.augmentation import draw_shifts
from sb3_collapse.drqv2.checks import (
    check_compile_update,
    check_hyperparameters,
    check_replay_buffer_kwargs,
    compile_losses,
    uses_cuda_graphs,
)
from sb3_collapse.drqv2.divergence import DivergenceGuard, all_finite
from sb3_collapse.drqv2.encoders import PixelEncoder, StateEncoder
from sb3_collapse.drqv2.policies import (
    Actor,
    CnnPolicy,
    Critic,
    DrQv2Policy,
    MlpPolicy,
    MultiInputPolicy,
    check_action_space,
    critic_mse,
    exploration_noise,
    frozen,
    min_q,
    noisy_action,
    soft_update,
)
from sb3_collapse.drqv2.prefetch import ReplayPrefetcher
from sb3_collapse.drqv2.replay_buffer import refuse_non_finite
from sb3_collapse.drqv2.rounds import RoundsAlgorithm
from sb3_collapse.drqv2.sb3_compat import ConstructorCallbacks, combine_callbacks
from sb3_collapse.drqv2.schedules import ScheduleSpec, StddevSchedule
from sb3_collapse.drqv2.transplant import TransplantSpec, check_init_from, describe_source, load_sources, transplant
from sb3_collapse.drqv2.update_stats import UpdateStats
from sb3_collapse.errors import DivergenceError

SelfDrQv2 = TypeVar("SelfDrQv2", bound="DrQv2")


class DrQv2(ConstructorCallbacks, RoundsAlgorithm):
    """
    DrQ-v2: Mastering Visual Continuous Control (https://arxiv.org/abs/2107.09645): DDPG with a twin critic, n-step
    returns, random-shift augmentation and a scheduled exploration noise. ``docs/algorithm.md``.

    Step counts are transitions summed over the environments (SB3's ``num_timesteps``), not frames.

    :param policy: ``"CnnPolicy"``, ``"MlpPolicy"``, ``"MultiInputPolicy"`` or a ``DrQv2Policy`` subclass
    :param env: the environment (a ``VecEnv``, a gymnasium env or a registered id)
    :param learning_rate: Adam learning rate of the encoder, actor and critic, or an SB3 schedule
    :param buffer_size: replay capacity, in transitions (a warning when it cannot fit in RAM)
    :param learning_starts: transitions of uniformly random actions before the first update (DrQ-v2's 4,000 frames)
    :param batch_size: minibatch size of each update
    :param tau: soft update coefficient of the target critic
    :param gamma: discount factor
    :param train_freq: ``(n, "transition")``: updates every ``n`` transitions summed over the envs; or SB3's forms
    :param gradient_steps: updates per ``train_freq`` (``-1``: one per transition; ``0``: none)
    :param n_steps: length of the n-step returns, in agent steps
    :param stddev_schedule: exploration std of the transitions since the last reset (:class:`StddevSchedule`)
    :param stddev_clip: clip of the exploration noise in the updates (target action, actor loss)
    :param augmentation_pad: random-shift padding in pixels; ``0``: no augmentation
    :param step_envs_during_updates: step the environments while the learner updates (a policy lag of one round)
    :param compile_update: ``torch.compile`` the losses: ``True`` or a ``torch.compile`` mode
    :param callback: callback(s) run at every ``learn()`` before its own, saved with the model where possible
    :param replay_buffer_class: ``None``: ``FrameStackReplayBuffer`` on a frame-stacked env, SB3's otherwise
    :param replay_buffer_kwargs: its keyword arguments (``dict(sampling="drqv2")``: finished episodes only, with
        ``FrameStackReplayBuffer``); copied, not changed
    :param stats_window_size: episodes averaged in the rollout logs
    :param tensorboard_log: TensorBoard log folder, ``None`` for none
    :param policy_kwargs: keyword arguments of the policy (``DrQv2Policy``): DrQ-v2's and SB3's
    :param verbose: 0 silent, 1 info, 2 debug
    :param seed: seed of the random generators
    :param device: ``"cpu"``, ``"cuda"``, ... or ``"auto"``; CUDA without a GPU is refused
    :param init_from: the paper's layer transplant: group (``"cnn"``, ``"mlp"``, ``"critic"``) -> a DrQv2 zip or model
    :param action_noise: an SB3 ``ActionNoise`` in place of the ``stddev_schedule``'s Gaussian when acting
    :param optimize_memory_usage: SB3's, where SB3's ``ReplayBuffer`` is used with ``n_steps=1`` (else a warning)
    :param cudnn_benchmark: turn cuDNN's autotuner on when built on CUDA (a process-wide flag); saved with the model
    :param _init_setup_model: build the networks and the buffer now
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {
        "CnnPolicy": CnnPolicy, "MlpPolicy": MlpPolicy, "MultiInputPolicy": MultiInputPolicy
    }  # fmt: skip
    load_parsers: ClassVar[dict[str, Callable[[Any], Any]]] = {"stddev_schedule": StddevSchedule}  # as __init__
    policy: DrQv2Policy
    encoder: PixelEncoder | StateEncoder
    actor: Actor
    critic: Critic
    critic_target: Critic

    def __init__(
        self,
        policy: str | type[DrQv2Policy],
        env: GymEnv | str | None,
        learning_rate: float | Schedule = 1e-4,
        buffer_size: int = 1_000_000,
        learning_starts: int = 2000,
        batch_size: int = 256,
        tau: float = 0.01,
        gamma: float = 0.99,
        train_freq: int | tuple[int, str] = (2, "transition"),
        gradient_steps: int = 1,
        n_steps: int = 3,
        stddev_schedule: ScheduleSpec = "linear(1.0,0.1,100000)",
        stddev_clip: float = 0.3,
        augmentation_pad: int = 4,
        step_envs_during_updates: bool = False,
        compile_update: bool | str = False,
        callback: MaybeCallback = None,
        replay_buffer_class: type[ReplayBuffer] | None = None,
        replay_buffer_kwargs: dict[str, Any] | None = None,
        stats_window_size: int = 100,
        tensorboard_log: str | None = None,
        policy_kwargs: dict[str, Any] | None = None,
        verbose: int = 0,
        seed: int | None = None,
        device: th.device | str = "auto",
        init_from: Mapping[str, TransplantSpec] | None = None,
        action_noise: ActionNoise | None = None,
        optimize_memory_usage: bool = False,
        cudnn_benchmark: bool = False,
        _init_setup_model: bool = True,
    ) -> None:
        transplant_specs = check_init_from(init_from)  # before building anything: unknown keys, missing files
        check_hyperparameters(
            learning_rate=learning_rate, buffer_size=buffer_size, learning_starts=learning_starts,
            batch_size=batch_size, tau=tau, gamma=gamma, train_freq=train_freq, gradient_steps=gradient_steps,
            n_steps=n_steps, stddev_clip=stddev_clip, augmentation_pad=augmentation_pad, policy_kwargs=policy_kwargs,
            seed=seed, device=device, cudnn_benchmark=cudnn_benchmark,
        )  # fmt: skip
        check_compile_update(compile_update)
        self.stddev_schedule = StddevSchedule(stddev_schedule)
        super().__init__(
            policy, env, learning_rate, buffer_size, learning_starts, batch_size, tau, gamma,  # type: ignore[arg-type]
            train_freq, gradient_steps, action_noise=action_noise, optimize_memory_usage=optimize_memory_usage,
            replay_buffer_class=replay_buffer_class,
            replay_buffer_kwargs=dict(replay_buffer_kwargs or {}),  # a copy: _setup_model fills in its defaults
            n_steps=n_steps, policy_kwargs=policy_kwargs,
            stats_window_size=stats_window_size, tensorboard_log=tensorboard_log, verbose=verbose, device=device,
            seed=seed, sde_support=False, support_multi_env=True,
            supported_action_spaces=None,  # checked in _setup_model, with a clearer message than SB3's assertion
        )  # fmt: skip
        self.stddev_clip = stddev_clip
        self.augmentation_pad = augmentation_pad
        self.step_envs_during_updates = step_envs_during_updates
        self.compile_update = compile_update
        self.cudnn_benchmark = cudnn_benchmark
        self.callback = callback
        self.replay_prefetcher = ReplayPrefetcher()  # train()'s batches, drawn ahead
        self._compiled_losses: tuple[Any, Any] | None = None
        self._pending_step: tuple[np.ndarray, np.ndarray] | None = None
        self.no_env_step_this_round = False
        self.env_config = read_env_config(self.env) if self.env is not None else None
        self.grad_norm_recorder: GradNormRecorder | None = None  # the gradient norm of each named layer
        self.update_stats = UpdateStats()
        self.divergence_guard = DivergenceGuard()  # read at each log dump
        self._warned_replay_not_ready = False
        self.reset_step = 0
        self.init_from = {key: describe_source(spec) for key, spec in transplant_specs.items()} or None  # saved
        if _init_setup_model:
            sources = load_sources(transplant_specs)  # before the replay buffer; no random generator touched
            self._setup_model()
            if sources:
                transplant(self.policy, sources, verbose=self.verbose)

    def _setup_model(self) -> None:
        check_action_space(self.action_space)
        with replay_memory.replay_buffer_setup(self):  # the buffer chosen; a MemoryError suggests a size
            check_replay_buffer_kwargs(self.replay_buffer_class, self.replay_buffer_kwargs, self.policy_class)
            super()._setup_model()
        if self.cudnn_benchmark and self.device.type == "cuda" and not th.are_deterministic_algorithms_enabled():
            th.backends.cudnn.benchmark = True  # fixed input shapes: let cuDNN pick its fastest kernels
        self._create_aliases()
        self._index_grad_layers()
        self.policy.exploration_std = self.current_stddev

    def _create_aliases(self) -> None:
        self.encoder = self.policy.encoder
        self.actor = self.policy.actor
        self.critic = self.policy.critic
        self.critic_target = self.policy.critic_target

    def _index_grad_layers(self) -> None:
        """A new gradient-norm recorder on the current optimizers, the previous one removed."""
        if self.grad_norm_recorder is not None:
            self.grad_norm_recorder.remove()
        self.grad_norm_recorder = GradNormRecorder.of_modules(self.policy.named_layers(), self.policy.optimizers)

    @property
    def current_stddev(self) -> float:
        """Exploration standard deviation: the schedule at ``num_timesteps - reset_step`` transitions."""
        return self.stddev_schedule(self.num_timesteps - self.reset_step)

    @property
    def action_repeat(self) -> int:
        """Frames per agent step, read from the environment (1 when it reports none)."""
        return int((self.env_config or {}).get("action_repeat") or 1)

    @property
    def last_grad_norms(self) -> dict[str, float]:
        """L2 norm of each named layer's gradient at the last update; empty before the first update."""
        return {} if self.grad_norm_recorder is None else self.grad_norm_recorder.last()

    def _sample_action(
        self, learning_starts: int, action_noise: ActionNoise | None = None, n_envs: int = 1
    ) -> tuple[np.ndarray, np.ndarray]:
        """Uniform actions during the warm-up (since the last reset), then the actor's mean plus scheduled noise."""
        if self.in_warmup(learning_starts):
            unscaled_action = np.array([self.action_space.sample() for _ in range(n_envs)])
        else:
            self.policy.exploration_std = self.current_stddev
            deterministic = action_noise is not None  # an SB3 action noise replaces the schedule's Gaussian
            unscaled_action, _ = self.predict(self._last_obs, deterministic=deterministic)  # type: ignore[arg-type]
            if not np.isfinite(unscaled_action).all():  # on the host already: checking costs nothing
                observations = self._last_obs.values() if isinstance(self._last_obs, dict) else [self._last_obs]
                for values in observations:  # an env's NaN (a reset's: not stored yet) is not a divergence
                    if np.issubdtype(np.asarray(values).dtype, np.floating):
                        refuse_non_finite(values, n_envs, "observation")
                raise DivergenceError(
                    f"training diverged: the actor's action is not finite after update {self._n_updates} "
                    f"(frame {self.num_frames:,})."
                )
        buffer_action = self.policy.scale_action(unscaled_action)
        if action_noise is not None and not self.in_warmup(learning_starts):
            buffer_action = np.clip(buffer_action + action_noise(), -1, 1)  # TD3's exploration
        return self.policy.unscale_action(buffer_action), buffer_action

    def train(self, gradient_steps: int, batch_size: int = 256) -> None:
        """``gradient_steps`` updates on minibatches of ``batch_size`` transitions (none in the ``learning_starts``
        transitions after a :meth:`reset_from_scratch`)."""
        if self.reset_step > 0 and self.num_timesteps - self.reset_step <= self.learning_starts:
            if self.verbose >= 2:
                print(f"DrQv2: warm-up after the reset at transition {self.reset_step}, no update")
            return
        if not getattr(self.replay_buffer, "ready_to_sample", True):
            if not self._warned_replay_not_ready:  # once per learn()
                replay_memory.warn_not_ready(self.num_timesteps)
                self._warned_replay_not_ready = True
            return
        if self._n_updates == 0 and self.verbose >= 1:
            print(
                f"DrQv2: updates start at transition {self.num_timesteps:,} (learning_starts={self.learning_starts:,})"
            )
        self.policy.set_training_mode(True)
        self._update_learning_rate(self.policy.optimizers)
        std = self.current_stddev
        buffer, env = self.replay_buffer, self._vec_normalize_env
        assert buffer is not None
        with self.replay_prefetcher.batches(buffer, gradient_steps, batch_size, env) as batches:
            for replay_data in batches:
                self._n_updates += 1
                discounts = replay_data.discounts if replay_data.discounts is not None else self.gamma
                self._update(replay_data, discounts, std)
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")

    def _update(self, data: ReplayBufferSamples, discounts: th.Tensor | float, std: float) -> None:
        """One DrQ-v2 update (the reference's ``update``); the random draws come first, in the reference's order, so
        that the losses are pure functions, compiled or not."""
        batch_size, action_dim = data.actions.shape
        shifts = next_shifts = None
        if self.augmentation_pad > 0 and self.encoder.has_cnn:
            shifts = draw_shifts(batch_size, self.augmentation_pad, self.device)
            next_shifts = draw_shifts(batch_size, self.augmentation_pad, self.device)
        next_noise = exploration_noise((batch_size, action_dim), std, self.stddev_clip, self.device)
        actor_noise = exploration_noise((batch_size, action_dim), std, self.stddev_clip, self.device)

        if self._compiled_losses is None:  # compile_update: compiled once, at the first update
            self._compiled_losses = compile_losses(
                self._critic_loss, self._actor_loss, self.compile_update, self.device
            )
        critic_loss_fn, actor_loss_fn = self._compiled_losses
        if uses_cuda_graphs(self.compile_update, self.device):
            th.compiler.cudagraph_mark_step_begin()
        critic_loss, features, q1, q2, target_q = critic_loss_fn(
            data.observations, data.next_observations, data.actions, data.rewards, data.dones, discounts,
            shifts, next_shifts, next_noise,
        )  # fmt: skip
        self._update_critic(critic_loss)
        with frozen(self.critic):  # the actor's backward computes the actor's gradients only
            actor_loss = actor_loss_fn(features.detach(), actor_noise)
        self._update_actor(actor_loss)
        soft_update(self.critic.parameters(), self.critic_target.parameters(), self.tau)

        self.update_stats.add(
            critic_loss=critic_loss, q1_mean=q1.mean(), q2_mean=q2.mean(), target_q_mean=target_q.mean(),
            actor_loss=actor_loss, batch_reward=data.rewards.mean(), grad_norms=self.grad_norm_recorder.norms,  # type: ignore[union-attr]
        )  # fmt: skip

    def _critic_loss(
        self,
        obs: th.Tensor,
        next_obs: th.Tensor,
        actions: th.Tensor,
        rewards: th.Tensor,
        dones: th.Tensor,
        discounts: th.Tensor | float,
        shifts: th.Tensor | None,
        next_shifts: th.Tensor | None,
        next_noise: th.Tensor,
    ) -> tuple[th.Tensor, th.Tensor, th.Tensor, th.Tensor, th.Tensor]:
        """``MSE(Q1, y) + MSE(Q2, y)``, ``y = r + (1 - done) * discount * min(Q1', Q2')`` at the actor's next action
        plus ``next_noise``. :return: the loss, the features of ``obs`` (with graph), ``Q1``, ``Q2``, ``y``"""
        if shifts is not None and next_shifts is not None:
            obs = self.encoder.augment(obs, self.augmentation_pad, shifts)
            next_obs = self.encoder.augment(next_obs, self.augmentation_pad, next_shifts)
        features = self.encoder(obs)
        with th.no_grad():
            next_features = self.encoder(next_obs)
            next_action = noisy_action(self.actor(next_features), next_noise)
            target_q = rewards + (1.0 - dones) * discounts * min_q(self.critic_target(next_features, next_action))
        q_values = self.critic(features, actions)  # n_critics heads, DrQ-v2's 2
        critic_loss = critic_mse(q_values, target_q)
        return critic_loss, features, q_values[0], q_values[min(1, len(q_values) - 1)], target_q

    def _actor_loss(self, features: th.Tensor, noise: th.Tensor) -> th.Tensor:
        """``-min(Q1, Q2)`` at the actor's action plus ``noise`` on detached ``features``."""
        action = noisy_action(self.actor(features), noise)
        return -min_q(self.critic(features, action)).mean()

    def _update_critic(self, critic_loss: th.Tensor) -> None:
        """Critic and encoder step on ``critic_loss`` (from :meth:`_critic_loss`)."""
        for optimizer in (self.encoder.optimizer, self.critic.optimizer):
            if optimizer is not None:
                optimizer.zero_grad(set_to_none=True)
        critic_loss.backward()
        self.critic.optimizer.step()
        if self.encoder.optimizer is not None:
            self.encoder.optimizer.step()

    def _update_actor(self, actor_loss: th.Tensor) -> None:
        """Actor step on ``actor_loss`` (from :meth:`_actor_loss`): the encoder and the critic do not change."""
        self.actor.optimizer.zero_grad(set_to_none=True)
        actor_loss.backward(inputs=list(self.actor.parameters()))
        self.actor.optimizer.step()

    def dump_logs(self) -> None:
        """SB3's log dump, with the means of the updates since the last dump, checked by the divergence guard."""
        means = self.update_stats.dump(self.logger, self.grad_norm_recorder.names)  # type: ignore[union-attr]
        self.logger.record("time/frames", self.num_frames)
        if means is not None:
            self.logger.record("train/stddev", self.current_stddev)
            finite = bool(all_finite(self.policy.parameters()))
            try:
                self.divergence_guard.check_dump(
                    means, finite, self._n_updates, self.num_frames, self.gamma, self.logger
                )
            except DivergenceError:
                super().dump_logs()  # the non-finite values reach the logs too
                raise
        super().dump_logs()

    def learn(
        self: SelfDrQv2,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 4,
        tb_log_name: str = "DrQv2",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfDrQv2:
        """SB3's ``learn`` for ``total_timesteps`` transitions, the constructor's callbacks before ``callback``
        (``reset_num_timesteps=True`` also restarts the exploration schedule and the warm-up)."""
        self._warned_replay_not_ready = False
        if self.replay_buffer is not None:  # a loaded model's batch drawn ahead, from its restored replay buffer
            self.replay_prefetcher.restore(self.replay_buffer, self._vec_normalize_env)
        if self.verbose >= 1:
            start = 0 if reset_num_timesteps else self.num_timesteps - self.reset_step
            if start < self.learning_starts:
                print(
                    f"DrQv2: updates start after {self.learning_starts:,} transitions of uniform random actions "
                    f"(learning_starts), {self.learning_starts - start:,} from now"
                )
        callbacks = combine_callbacks(self.callback, callback)
        return super().learn(total_timesteps, callbacks, log_interval, tb_log_name, reset_num_timesteps, progress_bar)

    def reset_from_scratch(self) -> None:
        """The paper's reset in the middle of ``learn()``: new weights, empty optimizers and replay buffer, the
        schedule and the warm-up from ``num_timesteps`` (``docs/interventions.md``)."""
        self.policy.renew_networks(self.lr_schedule)
        self._create_aliases()
        self._index_grad_layers()  # a new recorder, on the new optimizers: no norm until the next update
        self.replay_buffer.reset()  # type: ignore[union-attr]
        self.replay_prefetcher.discard()  # drawn from the old transitions
        self.reset_step = self.num_timesteps
        self.policy.exploration_std = self.current_stddev

    def set_env(self, env: GymEnv, force_reset: bool = True) -> None:
        super().set_env(env, force_reset=force_reset)
        self.env_config = read_env_config(self.env) or self.env_config

    def _excluded_save_params(self) -> list[str]:
        return [
            *super()._excluded_save_params(), "encoder", "actor", "critic", "critic_target", "grad_norm_recorder",
            "update_stats", "_warned_replay_not_ready", "_compiled_losses", "_pending_step", "no_env_step_this_round",
        ]  # fmt: skip

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        encoder = ["encoder.optimizer"] if self.policy.encoder.optimizer is not None else []
        return ["policy", "actor.optimizer", "critic.optimizer", *encoder], []
