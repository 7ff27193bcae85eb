"""DrQ-v2 (Yarats et al., 2021) as a Stable-Baselines3 off-policy algorithm."""

from __future__ import annotations

import contextlib
import io
import os
import pathlib
import time
import warnings
from collections.abc import Iterable, Iterator, Mapping
from typing import Any, ClassVar, TypeVar

import numpy as np
import torch as th
from stable_baselines3.common.buffers import NStepReplayBuffer, ReplayBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.noise import ActionNoise
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import (
    GymEnv,
    MaybeCallback,
    ReplayBufferSamples,
    RolloutReturn,
    Schedule,
    TrainFreq,
    TrainFrequencyUnit,
)
from stable_baselines3.common.utils import should_collect_more_steps
from stable_baselines3.common.vec_env import VecEnv

from sb3_collapse.drqv2.augmentation import draw_shifts
from sb3_collapse.drqv2.cpu_allocator import tune_cpu_allocator
from sb3_collapse.drqv2.divergence import DivergenceError, DivergenceGuard, all_finite
from sb3_collapse.drqv2.policies import (
    Actor,
    CnnPolicy,
    Critic,
    DrQv2Policy,
    MlpPolicy,
    MultiInputPolicy,
    PixelEncoder,
    StateEncoder,
    check_action_space,
    check_policy_kwargs,
    critic_mse,
    exploration_noise,
    min_q,
    noisy_action,
)
from sb3_collapse.drqv2.prefetch import ReplayPrefetcher
from sb3_collapse.drqv2.replay_buffer import (
    DEFAULT_MIN_EPISODE_LENGTH,
    FrameStackReplayBuffer,
    frame_stack_storage_bytes,
)
from sb3_collapse.drqv2.sb3_compat import (
    DictNStepReplayBuffer,
    action_noise_actions,
    check_optimize_memory_usage,
    combine_callbacks,
    dict_replay_buffer_class,
)
from sb3_collapse.drqv2.schedules import ScheduleSpec, StddevSchedule
from sb3_collapse.drqv2.timing import LearnTimings, PhaseTime, UpdateClock
from sb3_collapse.drqv2.transplant import (
    TransplantSpec,
    check_init_from,
    describe_init_from,
    load_sources,
    transplant,
)
from sb3_collapse.errors import AssertedParameterError, ParameterError
from sb3_collapse.monitoring.grad_norms import GradNormRecorder

SelfDrQv2 = TypeVar("SelfDrQv2", bound="DrQv2")

ENV_CONFIG_KEYS = ("task_id", "action_repeat", "frame_stack", "size", "camera_id", "obs_type")
"""Settings read from a ``make_dmc_env`` environment and saved with the model (``model.env_config``)."""


class DrQv2(OffPolicyAlgorithm):
    """
    DrQ-v2: DDPG with a twin critic, n-step returns, random-shift augmentation of the pixels and a scheduled
    exploration noise; the convolutional encoder is trained by the critic loss only.

    Paper: https://arxiv.org/abs/2107.09645 (reference code: https://github.com/facebookresearch/drqv2).

    **Units.** Step counts are **transitions**, summed over the environments: SB3's ``num_timesteps``, which
    one ``env.step`` of a ``VecEnv`` of ``n_envs`` environments advances by ``n_envs`` (with one environment,
    transitions are agent steps). ``learning_starts``, ``train_freq``, the ``stddev_schedule``'s durations,
    ``buffer_size`` and the budget of :meth:`learn` are all in transitions, whatever ``n_envs``. DrQ-v2 and the
    action-collapse paper count **frames**: transitions x action repeat (2 on DeepMind Control), so
    ``learning_starts=2000`` transitions are DrQ-v2's 4,000 seed frames; ``model.num_frames`` gives the frame
    count, and the callbacks of ``sb3_collapse.monitoring`` (collapse checks, the reset rule's window) read it.
    Frames therefore mean the same with 1 or 8 environments: 8 environments reach a frame budget in 8 times
    fewer ``env.step`` calls.

    **Update ratio.** DrQ-v2 makes one update every 2 transitions (``train_freq=2``, ``gradient_steps=1``), and
    so does this class on any number of environments: ``gradient_steps`` updates each time the transition count
    passes a multiple of ``train_freq`` beyond ``learning_starts`` (counted from the last
    :meth:`reset_from_scratch`). The updates are made at the end of the ``env.step`` in which they become due: one
    environment makes one update every second step; 2 environments one update per step; 3 environments 1 and 2
    updates on alternate steps (1.5 per step: the fractional part is carried exactly, as the count of multiples
    passed); 4 environments 2 per step. After ``T`` transitions a model has made exactly
    ``gradient_steps * (T // train_freq - (reset_step + learning_starts) // train_freq)`` updates (``T`` beyond
    ``reset_step + learning_starts``).

    **Overlapped environment steps** (``step_envs_during_updates=True``): the environments compute the next
    step (physics and rendering) while the learner updates. That step's actions come from the weights before
    the round of updates: a policy lag of one round (``n_envs / train_freq`` updates on average; one update with
    one environment) with respect to the sequential loop, which is the order of DrQ-v2's reference loop (act,
    update, then step the environment). See ``docs/throughput.md``.

    :param policy: ``"CnnPolicy"`` (pixels, e.g. ``make_dmc_env``'s 9x84x84 uint8), ``"MlpPolicy"``
        (state vectors, no encoder and no augmentation; ``Discrete``, ``MultiDiscrete`` and ``MultiBinary``
        observations one-hot encoded by SB3's ``preprocess_obs``) or ``"MultiInputPolicy"`` (``spaces.Dict``
        observations: DrQ-v2's encoder on the image keys, the other keys flattened and concatenated, the augmentation
        on the images only), or a ``DrQv2Policy`` subclass
    :param env: the environment (a ``VecEnv``, a gymnasium env, or a registered id such as
        ``"sb3_collapse/walker-walk-v0"``)
    :param learning_rate: Adam learning rate of the encoder, actor and critic (or an SB3 schedule of the
        remaining progress)
    :param buffer_size: replay buffer capacity, in transitions (summed over the environments). With ``CnnPolicy``
        on a frame-stacked env (``make_dmc_env``), the default ``FrameStackReplayBuffer`` stores each frame once:
        about 21.5 KB per 9x84x84 transition, ~21.5 GB for DrQ-v2's 1,000,000 (11.8 GB for the 550,000 agent
        steps of a 1.1M-frame run). SB3's buffers store obs and next_obs: about 127 KB per 9x84x84
        transition, ~127 GB for 1,000,000. A warning says so when the full buffer would not fit in RAM, and
        a ``MemoryError`` suggests a size when it cannot even be reserved.
    :param learning_starts: transitions (summed over the environments) of uniformly random actions before the
        first update
    :param batch_size: minibatch size of each gradient update
    :param tau: soft update coefficient of the target critic
    :param gamma: discount factor
    :param train_freq: transitions (summed over the environments) per ``gradient_steps`` updates, whatever the
        number of environments (see **Update ratio** above); or ``(n, "episode")``: ``gradient_steps`` updates
        after every ``n`` episodes (one environment only, SB3's rule)
    :param gradient_steps: updates per ``train_freq`` transitions (``-1``: one per transition; ``0``: collect
        transitions without updating, as SB3 allows)
    :param n_steps: length of the n-step returns, in agent steps of one environment (SB3's ``NStepReplayBuffer``
        when > 1)
    :param stddev_schedule: exploration standard deviation as a function of the transition count
        (``num_timesteps``, summed over the environments, counted from the last :meth:`reset_from_scratch`): a
        float, ``"linear(init,final,duration)"``, ``"step_linear(init,final1,duration1,final2,duration2)"``
        (durations in transitions; agent steps with one environment) or a callable ``step -> std``
    :param stddev_clip: clip of the exploration noise used in the updates (target action, actor loss)
    :param augmentation_pad: random-shift padding in pixels; ``0`` disables the augmentation
        (pixel policies only)
    :param step_envs_during_updates: step the environments while the learner updates (see **Overlapped
        environment steps** above): before each round of updates, the next actions are sent to the environments
        (``VecEnv.step_async``), and their results collected after it (``step_wait``). It saves time only where
        the environments run in other processes (``SubprocVecEnv``); with a ``DummyVecEnv`` they step after the
        updates, with the same outcome. Off by default: the default keeps SB3's sequential loop (every action
        from the latest weights), so seeded runs are those of earlier versions
    :param compile_update: compile the update's forward and backward passes with ``torch.compile``: ``True``
        for ``mode="reduce-overhead"`` (CUDA graphs) on CUDA and ``"default"`` elsewhere, or a ``torch.compile``
        mode (``"default"``, ``"reduce-overhead"``, ``"max-autotune"``, ``"max-autotune-no-cudagraphs"``).
        The random draws stay outside the compiled code, so the update is the uncompiled one up to float
        rounding (tested against ``reference_update``). Compilation happens at the first update (about a minute
        on a 2-core CPU with an empty inductor cache; see ``model.timings.first_round_s``) and again after a
        :meth:`reset_from_scratch` (new modules). Off by default: on the CPU it was no faster at batch 32 and 256 and
        ~10% faster per update at batch 512, too little to pay the compilation back in short runs; it was not
        measured on a GPU (``docs/throughput.md``)
    :param callback: callback(s) run at every ``learn()`` call, before those given to ``learn()``
        (e.g. ``CollapseReset()``): what SB3's ``learn(callback=...)`` takes (a ``BaseCallback``, a function
        ``(locals, globals) -> bool``, a list of these), each converted as SB3 converts it; saved with the model
        only for the ``ResumableCallback`` ones (``CollapseReset``, ``CollapseMetrics``)
    :param replay_buffer_class: replay buffer class; ``None``: ``FrameStackReplayBuffer`` (n-step, each frame
        stored once) for ``CnnPolicy`` on an env that reports a ``frame_stack`` > 1 (``make_dmc_env``), SB3's
        otherwise (``NStepReplayBuffer`` when ``n_steps > 1``). Pass ``NStepReplayBuffer`` to store whole
        observations (e.g. stacks that are not shifted frame by frame)
    :param replay_buffer_kwargs: keyword arguments of the replay buffer (``n_steps``, ``gamma`` and
        ``frame_stack`` of a ``FrameStackReplayBuffer`` default to the algorithm's and the env's). Its
        ``sampling`` is ``"sb3"`` by default (SB3's semantics: the episode in progress is sampled too);
        ``dict(sampling="drqv2")`` samples as DrQ-v2's reference does (finished episodes only, no n-step return
        started in an episode's last ``n_steps - 1`` steps; updates wait until an episode has finished), as
        ``python -m sb3_collapse.train``, the sweep and the rl_zoo3 config do by default
    :param stats_window_size: episodes averaged in the rollout logs
    :param tensorboard_log: TensorBoard log folder, ``None`` for none
    :param policy_kwargs: keyword arguments of the policy: ``feature_dim`` (50), ``hidden_dim`` (1024),
        ``encoder_kwargs`` (``channels``, ``channels_last``, ``fused_relu``), ``activation``, and SB3's, which mean
        what they mean for TD3: ``net_arch`` (a list, or ``dict(pi=[...], qf=[...])``: the hidden layers of the actor
        and of each Q head; DrQ-v2's ``[1024, 1024]``), ``n_critics`` (2; the minimum over the heads for any number),
        ``features_extractor_class`` / ``features_extractor_kwargs`` (a ``BaseFeaturesExtractor`` in place of
        DrQ-v2's encoder), ``normalize_images`` (``False``: float images taken as they are), ``activation_fn``
        (``nn.ReLU`` or ``nn.LeakyReLU``), ``optimizer_class`` / ``optimizer_kwargs``; ``share_features_extractor``
        is ``True`` only (one encoder trained by the critic loss, DrQ-v2's). See ``DrQv2Policy`` and
        ``docs/algorithm.md``
    :param verbose: 0 silent, 1 info, 2 debug
    :param seed: seed of the random generators
    :param device: ``"cpu"``, ``"cuda"``, ... or ``"auto"``. On the CPU, glibc's malloc is tuned to reuse large
        freed buffers (a process-wide setting, see ``sb3_collapse.drqv2.cpu_allocator``); on CUDA,
        ``torch.backends.cudnn.benchmark`` is turned on, as DrQ-v2 does, unless torch's deterministic algorithms are
        on (``torch.use_deterministic_algorithms(True)``, e.g. through ``sb3_collapse.backends.configure_backends``)
    :param init_from: layer transplant (the action-collapse paper's Study 2): group -> source, where a source
        is the path of a zip saved by ``DrQv2.save`` (``.zip`` may be left out) or a DrQv2 model, e.g.
        ``{"cnn": "good.zip", "mlp": "bad.zip"}``. Groups: ``"cnn"``, the encoder (conv layers ``cnn1``..``cnn4``,
        shared by the actor and the critic); ``"mlp"``, the actor (trunk ``mlp0``, layers ``mlp1``, ``mlp2`` and
        the ``action`` head); ``"critic"``, the critic (trunk and Q heads), also copied into the target critic
        (DrQ-v2 starts the target as a copy of the critic). Exactly the parameters and buffers of the named
        groups are copied, once, when the model is built; everything else is the model's own fresh (seeded)
        initialization: the other groups' weights, the optimizers (empty Adam state), the replay buffer (empty),
        ``num_timesteps`` (0) and the schedules. The shapes must match (same observation shape, action space,
        ``feature_dim``, ``hidden_dim`` and encoder channels where the group depends on them) and every source is
        checked before anything is copied; a mismatch raises a ``ValueError`` naming the parameter and the
        settings that differ. Stored as ``model.init_from`` (group -> path, as plain strings) and saved;
        ``DrQv2.load`` gives back the trained weights, it does not transplant again, and neither does
        :meth:`reset_from_scratch`. See ``sb3_collapse.drqv2.transplant``
    :param action_noise: an SB3 ``ActionNoise`` for exploration, in place of the ``stddev_schedule``'s Gaussian:
        after the warm-up (uniform actions), the actor's deterministic action plus a draw of the noise, clipped to
        the action bounds, as SB3's TD3 explores; the noise is reset at the end of each episode. The target-policy
        smoothing noise of the updates stays DrQ-v2's (``stddev_schedule``, clipped at ``stddev_clip``)
    :param optimize_memory_usage: SB3's keyword: passed on to SB3's ``ReplayBuffer`` (``n_steps=1``, not dict
        observations), where it works (with ``replay_buffer_kwargs=dict(handle_timeout_termination=False)``, as in
        SB3); ignored with a warning elsewhere: ``FrameStackReplayBuffer`` (``CnnPolicy`` on ``make_dmc_env``)
        already stores each frame once, and SB3's n-step and dict buffers do not support it
    :param _init_setup_model: build the networks and the buffer now
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {
        "CnnPolicy": CnnPolicy,
        "MlpPolicy": MlpPolicy,
        "MultiInputPolicy": MultiInputPolicy,
    }
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
        train_freq: int | tuple[int, str] = 2,
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
        _init_setup_model: bool = True,
    ) -> None:
        transplant_specs = check_init_from(init_from)  # before building anything: unknown keys, missing files
        check_hyperparameters(
            learning_rate=learning_rate,
            buffer_size=buffer_size,
            learning_starts=learning_starts,
            batch_size=batch_size,
            tau=tau,
            gamma=gamma,
            train_freq=train_freq,
            gradient_steps=gradient_steps,
            n_steps=n_steps,
            stddev_clip=stddev_clip,
            augmentation_pad=augmentation_pad,
            policy_kwargs=policy_kwargs,
            seed=seed,
            device=device,
        )
        check_compile_update(compile_update)
        self.stddev_schedule = StddevSchedule(stddev_schedule)
        super().__init__(
            policy,
            env,  # type: ignore[arg-type]
            learning_rate,
            buffer_size,
            learning_starts,
            batch_size,
            tau,
            gamma,
            train_freq,
            gradient_steps,
            action_noise=action_noise,
            replay_buffer_class=replay_buffer_class,
            replay_buffer_kwargs=replay_buffer_kwargs,
            optimize_memory_usage=optimize_memory_usage,
            n_steps=n_steps,
            policy_kwargs=policy_kwargs,
            stats_window_size=stats_window_size,
            tensorboard_log=tensorboard_log,
            verbose=verbose,
            device=device,
            seed=seed,
            sde_support=False,
            supported_action_spaces=None,  # checked in _setup_model, with a clearer message than SB3's assertion
            support_multi_env=True,
        )
        self.stddev_clip = stddev_clip
        self.augmentation_pad = augmentation_pad
        self.step_envs_during_updates = step_envs_during_updates
        self.compile_update = compile_update
        self.callback = callback
        self.replay_prefetcher = ReplayPrefetcher()  # replay batches for train(), see sb3_collapse.drqv2.prefetch
        self.timings = LearnTimings()
        """Where the time of the last (or current) :meth:`learn` call went (see ``sb3_collapse.drqv2.timing``)."""
        self._update_clock = UpdateClock()
        self._compiled_losses: tuple[Any, Any] | None = None
        self._pending_step: tuple[np.ndarray, np.ndarray] | None = None
        self.hold_next_step = False
        """Set during a round: this round's updates do not step the environments (a checkpoint follows it)."""
        self._round, self._round_used_policy = PhaseTime(), False
        self.env_config = _read_env_config(self.env) if self.env is not None else None
        self.grad_norm_recorder: GradNormRecorder | None = None
        """Records the gradient norm of each named layer at each update (see :attr:`last_grad_norms`)."""
        self._train_stats: dict[str, th.Tensor] = {}
        self._train_stats_count = 0
        self.divergence_guard = DivergenceGuard()
        """Stops training on a loss or weight that is not finite, warns once when a loss grows by orders of magnitude
        (read at each log dump; see ``sb3_collapse.drqv2.divergence``)."""
        self._warned_replay_not_ready = False
        self.reset_step = 0
        """Agent step (``num_timesteps``) of the last :meth:`reset_from_scratch`, 0 when none; saved with the model."""
        self.init_from = describe_init_from(transplant_specs)
        """Group -> source (plain strings) of the layer transplant this model was built with, ``None`` when none;
        saved with the model."""
        if _init_setup_model:
            # Read the sources first (a file that is no DrQv2 zip fails before the replay buffer is allocated);
            # reading them builds no model and touches no random generator.
            sources = load_sources(transplant_specs)
            self._setup_model()
            if sources:
                replaced = transplant(self.policy, sources)
                if self.verbose >= 1:
                    groups = ", ".join(f"{group} from {source}" for group, source in (self.init_from or {}).items())
                    print(f"DrQv2: transplanted {groups} ({len(replaced)} tensors)")

    # ------------------------------------------------------------------ setup
    def _setup_model(self) -> None:
        check_action_space(self.action_space)
        self._select_replay_buffer()
        self.optimize_memory_usage = check_optimize_memory_usage(
            self.optimize_memory_usage, self.replay_buffer_class, self._uses_frame_stack_buffer(), self.n_steps
        )
        self._check_replay_memory()
        try:
            with warnings.catch_warnings():
                if "n_steps" in self.replay_buffer_kwargs:
                    # A loaded model has its n-step buffer class and kwargs set already: SB3's warning that
                    # `n_steps` is ignored for a custom buffer class does not apply.
                    warnings.filterwarnings("ignore", message=r"`n_steps=\d+` is ignored")
                super()._setup_model()
        except MemoryError as error:
            raise MemoryError(
                f"Could not allocate a replay buffer of {self.buffer_size:,} transitions ({error}). "
                + self._replay_memory_advice()
            ) from None
        if self.device.type == "cpu" and tune_cpu_allocator() and self.verbose >= 1:
            print("sb3_collapse: glibc malloc tuned to reuse freed buffers (SB3_COLLAPSE_TUNE_MALLOC=0 to disable)")
        if self.device.type == "cuda" and not th.are_deterministic_algorithms_enabled():
            th.backends.cudnn.benchmark = True  # fixed input shapes: let cuDNN pick its fastest kernels
        self._create_aliases()
        self._index_grad_layers()
        self.policy.exploration_std = self.current_stddev

    def _index_grad_layers(self) -> None:
        """
        Hook a new :class:`~sb3_collapse.monitoring.grad_norms.GradNormRecorder` on the current optimizers (the
        previous one, if any, is removed): ``cnn1``..``cnn4`` are recorded when the encoder's optimizer steps,
        ``mlp0``..``action`` when the actor's does.
        """
        if self.grad_norm_recorder is not None:
            self.grad_norm_recorder.remove()
        layers = {name: list(module.parameters()) for name, module in self.policy.named_layers().items()}
        self.grad_norm_recorder = GradNormRecorder({k: v for k, v in layers.items() if v}, self.policy.optimizers)

    def _select_replay_buffer(self) -> None:
        """
        ``FrameStackReplayBuffer`` by default for ``CnnPolicy`` on an env reporting ``frame_stack > 1`` (pixel
        observations); a class given by the user (or saved with the model) is kept. The algorithm's
        ``n_steps`` and ``gamma`` (and the env's ``frame_stack``) fill in the kwargs of a
        ``FrameStackReplayBuffer`` or ``NStepReplayBuffer`` that the user did not give.
        """
        config = self.env_config or {}
        frame_stack = config.get("frame_stack")
        if self.replay_buffer_class is None:  # dict observations: SB3's DictReplayBuffer, n-step when n_steps > 1
            self.replay_buffer_class = dict_replay_buffer_class(self.observation_space, self.n_steps)
        if (
            self.replay_buffer_class is None
            and issubclass(self.policy_class, CnnPolicy)
            and issubclass(self.policy_kwargs.get("encoder_class", PixelEncoder), PixelEncoder)
            and config.get("obs_type") in (None, "pixels")
            and isinstance(frame_stack, (int, np.integer))
            and frame_stack > 1
        ):
            self.replay_buffer_class = FrameStackReplayBuffer
        defaults: dict[str, Any] = {}
        if self._uses_frame_stack_buffer():
            defaults = {"n_steps": self.n_steps, "gamma": self.gamma, "frame_stack": frame_stack}
        elif self.replay_buffer_class is not None and issubclass(
            self.replay_buffer_class, (NStepReplayBuffer, DictNStepReplayBuffer)
        ):
            defaults = {"n_steps": self.n_steps, "gamma": self.gamma}
        for key, value in defaults.items():
            if key not in self.replay_buffer_kwargs and value is not None:
                self.replay_buffer_kwargs[key] = value

    def _uses_frame_stack_buffer(self) -> bool:
        return self.replay_buffer_class is not None and issubclass(self.replay_buffer_class, FrameStackReplayBuffer)

    def _replay_bytes_per_transition(self) -> float:
        """
        Bytes per transition of the replay buffer: for SB3's, obs and next_obs, action, reward, done, timeout;
        for ``FrameStackReplayBuffer``, its arrays' bytes divided by ``buffer_size``.
        """
        if self._uses_frame_stack_buffer() and self.replay_buffer_kwargs.get("frame_stack") is not None:
            kwargs = self.replay_buffer_kwargs
            total = frame_stack_storage_bytes(
                self.buffer_size,
                self.observation_space,  # type: ignore[arg-type]
                self.action_space,
                kwargs["frame_stack"],
                self.n_envs,
                kwargs.get("min_episode_length", DEFAULT_MIN_EPISODE_LENGTH),
            )
            return total / self.buffer_size
        obs_bytes = int(np.prod(self.observation_space.shape)) * np.dtype(self.observation_space.dtype).itemsize
        action_bytes = int(np.prod(self.action_space.shape)) * 4
        return 2 * obs_bytes + action_bytes + 12

    def _replay_memory_advice(self) -> str:
        per_transition, ram = self._replay_bytes_per_transition(), physical_memory_bytes()
        fitting = int(0.7 * ram / per_transition)
        storage = (
            "FrameStackReplayBuffer stores each frame once"
            if self._uses_frame_stack_buffer()
            else "SB3's buffer stores obs and next_obs separately"
        )
        return (
            f"{storage}: {per_transition / 1e3:,.0f} KB per transition, "
            f"{self.buffer_size * per_transition / 1e9:,.1f} GB in all, and this machine has "
            f"{ram / 1e9:,.1f} GB of RAM. Pass a smaller buffer_size, e.g. "
            f"buffer_size={fitting:_} (70% of the RAM), or the number of agent steps of your run if smaller."
        )

    def _check_replay_memory(self) -> None:
        """Warn now, rather than be killed hours later, when the full replay buffer cannot fit in RAM."""
        known = (None, ReplayBuffer, NStepReplayBuffer)
        if (self.replay_buffer_class not in known and not self._uses_frame_stack_buffer()) or (
            self.observation_space is None
        ):
            return
        if self.buffer_size * self._replay_bytes_per_transition() > physical_memory_bytes():
            warnings.warn(
                f"The replay buffer of {self.buffer_size:,} transitions will not fit in memory once full. "
                + self._replay_memory_advice(),
                stacklevel=4,  # the user's DrQv2(...) call
            )

    def _create_aliases(self) -> None:
        self.encoder = self.policy.encoder
        self.actor = self.policy.actor
        self.critic = self.policy.critic
        self.critic_target = self.policy.critic_target

    # ------------------------------------------------------------------ properties
    @property
    def current_stddev(self) -> float:
        """
        Exploration standard deviation at the current agent step, counted from the last
        :meth:`reset_from_scratch` (``num_timesteps - reset_step``; ``num_timesteps`` when there was none).
        """
        return self.stddev_schedule(self.num_timesteps - self.reset_step)

    @property
    def action_repeat(self) -> int:
        """Frames per agent step, read from the environment (1 when it does not report an action repeat)."""
        return int((self.env_config or {}).get("action_repeat") or 1)

    @property
    def num_frames(self) -> int:
        """Environment frames so far: ``num_timesteps x action_repeat`` (the unit of DrQ-v2 and the paper)."""
        return self.num_timesteps * self.action_repeat

    @property
    def last_grad_norms(self) -> dict[str, float]:
        """
        L2 norm of the gradient of each named layer's parameters at the last update (``cnn1``..``cnn4``
        from the critic loss, ``mlp0``..``action`` from the actor loss); empty before the first update.
        Recorded by :attr:`grad_norm_recorder` when the optimizers step: reading it needs no extra backward pass.
        """
        return {} if self.grad_norm_recorder is None else self.grad_norm_recorder.last()

    # ------------------------------------------------------------------ acting
    def _in_warmup(self, learning_starts: int) -> bool:
        """Whether the next actions are uniformly random (``learning_starts`` transitions since the last reset)."""
        return self.num_timesteps - self.reset_step < learning_starts

    def _sample_action(
        self,
        learning_starts: int,
        action_noise: ActionNoise | None = None,
        n_envs: int = 1,
    ) -> tuple[np.ndarray, np.ndarray]:
        """
        Uniform actions during the warm-up (the first ``learning_starts`` transitions, counted from the last
        :meth:`reset_from_scratch` if any), then the actor's mean plus scheduled Gaussian noise.
        """
        if self._in_warmup(learning_starts):
            unscaled_action = np.array([self.action_space.sample() for _ in range(n_envs)])
        else:
            self.policy.exploration_std = self.current_stddev
            # With an SB3 action noise, it replaces the schedule's Gaussian (SB3's TD3 exploration).
            deterministic = action_noise is not None
            unscaled_action, _ = self.predict(self._last_obs, deterministic=deterministic)  # type: ignore[arg-type]
            if not np.isfinite(unscaled_action).all():  # on the host already: checking costs nothing
                raise DivergenceError(
                    f"training diverged: the actor's action is not finite after update {self._n_updates} "
                    f"(frame {self.num_frames:,})."
                )
        buffer_action = self.policy.scale_action(unscaled_action)
        if action_noise is not None and not self._in_warmup(learning_starts):
            buffer_action = action_noise_actions(buffer_action, action_noise)
        return self.policy.unscale_action(buffer_action), buffer_action

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
        """
        Step the environments ``train_freq`` times and store the transitions (SB3's ``collect_rollouts``), timing
        the waits for the environments. The first step completes the step sent before the last round of updates,
        if there is one (``step_envs_during_updates``), instead of choosing new actions.

        :param env: the training environments
        :param callback: called at every step, and at the start and end of the rollout
        :param train_freq: how many ``env.step`` calls (or episodes, one environment only) to collect
        :param replay_buffer: where the transitions go
        :param action_noise: optional additional action noise (DrQ-v2 uses none)
        :param learning_starts: transitions of uniformly random actions since the last reset
        :param log_interval: episodes between two log dumps
        :return: transitions (summed over the environments) and episodes collected, and whether to go on
        """
        self.policy.set_training_mode(False)
        if env.num_envs > 1 and train_freq.unit == TrainFrequencyUnit.EPISODE:
            raise ValueError(
                f"train_freq=({train_freq.frequency}, 'episode') counts episodes, which needs one environment, but the "
                f"VecEnv has {env.num_envs}. Use train_freq in steps (transitions), e.g. train_freq=2."
            )
        num_collected_steps, num_collected_episodes = 0, 0
        continue_training = True
        callback.on_rollout_start()
        while should_collect_more_steps(train_freq, num_collected_steps, num_collected_episodes):
            if self._pending_step is not None:  # sent before the updates: its actions predate them
                actions, buffer_actions = self._pending_step
                self._pending_step = None
                start = time.perf_counter()
                new_obs, rewards, dones, infos = env.step_wait()
            else:
                self._round_used_policy |= not self._in_warmup(learning_starts)
                actions, buffer_actions = self._sample_action(learning_starts, action_noise, env.num_envs)
                start = time.perf_counter()
                new_obs, rewards, dones, infos = env.step(actions)
            self._round.env_s += time.perf_counter() - start
            self._round.transitions += env.num_envs
            self.num_timesteps += env.num_envs
            num_collected_steps += 1

            callback.update_locals(locals())
            if not callback.on_step():
                return RolloutReturn(num_collected_steps * env.num_envs, num_collected_episodes, continue_training=False)
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
        return RolloutReturn(num_collected_steps * env.num_envs, num_collected_episodes, continue_training)

    def _send_next_step(self) -> None:
        """Choose the next actions with the current weights and send them to the environments (``step_async``)."""
        assert self.env is not None
        self._round_used_policy |= not self._in_warmup(self.learning_starts)
        actions, buffer_actions = self._sample_action(self.learning_starts, self.action_noise, self.env.num_envs)
        self.env.step_async(actions)
        self._pending_step = (actions, buffer_actions)

    def _finish_pending_step(self) -> None:
        """
        After an exception between :meth:`_send_next_step` and the next rollout: wait for the step in flight and
        store its transition, so that the model's last observation is the environments' again. A step that cannot
        be completed (the environments died) is dropped.
        """
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

    def _round_train_freq(self) -> TrainFreq:
        """
        ``env.step`` calls of the next rollout: up to the step in which the transition count reaches the next
        multiple of ``train_freq`` (``train_freq`` steps with one environment, one step when ``n_envs >= train_freq``);
        the episode count of an episodic ``train_freq`` as is.
        """
        if self.train_freq.unit != TrainFrequencyUnit.STEP:
            return self.train_freq
        frequency = self.train_freq.frequency
        next_multiple = (self.num_timesteps // frequency + 1) * frequency
        return TrainFreq(-(-(next_multiple - self.num_timesteps) // self.n_envs), TrainFrequencyUnit.STEP)

    def updates_due(self, start: int, end: int) -> int:
        """
        Updates that DrQ-v2's ratio asks for when the transition count goes from ``start`` to ``end``:
        ``gradient_steps`` for each multiple ``m`` of ``train_freq`` with ``start < m <= end`` and
        ``m > reset_step + learning_starts`` (one per transition ``t`` in that range with ``gradient_steps=-1``).
        With an episodic ``train_freq``: ``gradient_steps`` (``-1``: ``end - start``) when
        ``end > reset_step + learning_starts``, else 0.

        :param start: ``num_timesteps`` before the steps
        :param end: ``num_timesteps`` after them
        :return: the number of updates
        """
        first = self.reset_step + self.learning_starts  # no update at or before this transition count
        if self.train_freq.unit != TrainFrequencyUnit.STEP:
            if end <= first:
                return 0
            return self.gradient_steps if self.gradient_steps >= 0 else end - start
        low = max(start, first)
        if end <= low:
            return 0
        if self.gradient_steps < 0:
            return end - low
        frequency = self.train_freq.frequency
        return self.gradient_steps * (end // frequency - low // frequency)

    # ------------------------------------------------------------------ training
    def train(self, gradient_steps: int, batch_size: int = 256) -> None:
        """
        ``gradient_steps`` DrQ-v2 updates on minibatches of ``batch_size`` transitions.

        After a :meth:`reset_from_scratch` at transition ``reset_step > 0``, no update happens until
        ``learning_starts`` transitions were collected since the reset (``learn()`` asks for none, see
        :meth:`updates_due`; a direct call is skipped too, and a verbose model says so).

        The batches are ``replay_buffer.sample``'s, in the same order; ``self.replay_prefetcher`` makes them (on
        CUDA, one batch ahead through pinned buffers; see ``sb3_collapse.drqv2.prefetch``).
        """
        if self.reset_step > 0 and self.num_timesteps - self.reset_step <= self.learning_starts:
            if self.verbose >= 2:
                print(f"DrQv2: warm-up after the reset at transition {self.reset_step}, no update")
            return
        if not getattr(self.replay_buffer, "ready_to_sample", True):
            self._warn_replay_not_ready()
            return
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

    def _warn_replay_not_ready(self) -> None:
        """Say once per ``learn()`` why the updates wait (DrQ-v2's sampling: no finished episode stored yet)."""
        if self._warned_replay_not_ready:
            return
        self._warned_replay_not_ready = True
        warnings.warn(
            f"DrQv2: no update at transition {self.num_timesteps}: the replay buffer samples finished episodes only "
            "(replay_buffer_kwargs sampling='drqv2', DrQ-v2's rule) and no episode has finished yet. Updates start "
            "when the first episode ends. DrQ-v2 starts learning after 4,000 frames (several episodes); pass a "
            "larger learning_starts, or sampling='sb3' to sample the episode in progress too.",
            stacklevel=2,
        )

    def _update(self, data: ReplayBufferSamples, discounts: th.Tensor | float, std: float) -> None:
        """
        One DrQ-v2 update: augment, encode obs (with gradients) and next_obs (without), update the critic
        and the encoder, update the actor on the detached features, then soft-update the target critic.

        The random numbers (augmentation shifts, then the noise of the target action, then that of the actor's
        action) are drawn first, in the order of ``reference_update``, so that the loss functions are
        deterministic functions of their inputs: the same with ``compile_update`` or not.
        """
        batch_size, action_dim = data.actions.shape
        shifts = next_shifts = None
        if self.augmentation_pad > 0 and self.encoder.has_cnn:
            shifts = draw_shifts(batch_size, self.augmentation_pad, self.device)
            next_shifts = draw_shifts(batch_size, self.augmentation_pad, self.device)
        next_noise = exploration_noise((batch_size, action_dim), std, self.stddev_clip, self.device)
        actor_noise = exploration_noise((batch_size, action_dim), std, self.stddev_clip, self.device)

        critic_loss_fn, actor_loss_fn = self._loss_functions()
        if self._uses_cuda_graphs():
            th.compiler.cudagraph_mark_step_begin()
        critic_loss, features, q1, q2, target_q = critic_loss_fn(
            data.observations, data.next_observations, data.actions, data.rewards, data.dones, discounts,
            shifts, next_shifts, next_noise,
        )
        self._update_critic(critic_loss)
        with _frozen(self.critic):
            actor_loss = actor_loss_fn(features.detach(), actor_noise)
        self._update_actor(actor_loss)
        soft_update(self.critic.parameters(), self.critic_target.parameters(), self.tau)

        self._add_train_stat("critic_loss", critic_loss.detach())
        self._add_train_stat("q1_mean", q1.detach().mean())
        self._add_train_stat("q2_mean", q2.detach().mean())
        self._add_train_stat("target_q_mean", target_q.detach().mean())
        self._add_train_stat("actor_loss", actor_loss.detach())
        self._add_train_stat("batch_reward", data.rewards.mean())
        self._add_train_stat("grad_norms", self.grad_norm_recorder.norms)  # type: ignore[union-attr,arg-type]
        self._train_stats_count += 1

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
        """
        The critic loss ``MSE(Q1, y) + MSE(Q2, y)``, ``y = r + (1 - done) * discount * min(Q1', Q2')`` with the
        target critic at the actor's action plus ``next_noise`` on the next observations. No random draw, no
        side effect: this is what ``compile_update`` compiles.

        :param obs: observations
        :param next_obs: next observations (n steps later)
        :param actions: actions taken, in [-1, 1]
        :param rewards: (n-step) rewards
        :param dones: terminations
        :param discounts: discount of the next value (per sample, or a float)
        :param shifts: random-shift offsets of ``obs`` (:func:`draw_shifts`), ``None`` without augmentation
        :param next_shifts: those of ``next_obs``
        :param next_noise: clipped noise of the target action (:func:`exploration_noise`)
        :return: the loss, the encoder features of ``obs`` (with the encoder's graph: the encoder is trained by this
            loss, and only by it), ``Q1``, ``Q2`` and the target ``y``
        """
        if shifts is not None and next_shifts is not None:
            # Images only (the image keys of dict observations), in the layout the convolutions take.
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
        """
        The actor loss ``-min(Q1, Q2)`` at the actor's action plus ``noise``, on features detached from the
        encoder. :meth:`_update` calls it with the critic's parameters frozen (``requires_grad=False``), so that
        the backward pass computes the actor's gradients only (the reference computes the critic's too, then
        discards them). No random draw, no side effect: this is what ``compile_update`` compiles.

        :param features: encoder features, detached
        :param noise: clipped noise of the action (:func:`exploration_noise`)
        :return: the loss
        """
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

    def _loss_functions(self) -> tuple[Any, Any]:
        """:meth:`_critic_loss` and :meth:`_actor_loss`, compiled once (lazily) when ``compile_update`` says so."""
        if not self.compile_update:
            return self._critic_loss, self._actor_loss
        if self._compiled_losses is None:
            mode = compile_mode(self.compile_update, self.device)
            # Static shapes (the batch size is fixed during training): another batch size compiles its own code.
            self._compiled_losses = (
                th.compile(self._critic_loss, mode=mode, dynamic=False),
                th.compile(self._actor_loss, mode=mode, dynamic=False),
            )
        return self._compiled_losses

    def _uses_cuda_graphs(self) -> bool:
        """Whether the compiled update replays CUDA graphs (each update then starts a new graph step)."""
        return bool(self.compile_update) and self.device.type == "cuda" and compile_mode(
            self.compile_update, self.device
        ) in CUDA_GRAPH_MODES

    def _add_train_stat(self, name: str, value: th.Tensor) -> None:
        """Accumulate a statistic on the device; it is averaged and logged at the next ``dump_logs``."""
        self._train_stats[name] = self._train_stats[name] + value if name in self._train_stats else value.clone()

    def _record_train_stats(self) -> tuple[dict[str, float], bool] | None:
        """
        Write the averages of the statistics accumulated since the last dump to the logger.

        :return: the mean losses (and batch reward) and whether every weight is finite, for the divergence guard;
            ``None`` without updates
        """
        if self._train_stats_count == 0:
            return None
        n = self._train_stats_count
        finite = all_finite(self.policy.parameters())
        stats = {name: value.detach().cpu() for name, value in self._train_stats.items()}
        for name, value in stats.items():
            if name == "grad_norms":
                for layer, norm in zip(self.grad_norm_recorder.names, (value / n).tolist()):  # type: ignore[union-attr]
                    self.logger.record(f"train/grad_norm/{layer}", norm)
            else:
                self.logger.record(f"train/{name}", float(value) / n)
        self.logger.record("train/stddev", self.current_stddev)
        self._train_stats = {}
        self._train_stats_count = 0
        losses = {name: float(stats[name]) / n for name in ("critic_loss", "actor_loss", "batch_reward") if name in stats}
        return losses, bool(finite)

    def dump_logs(self) -> None:
        checked = self._record_train_stats()
        self.logger.record("time/frames", self.num_frames)
        if checked is not None:
            given = len(self.divergence_guard.warnings)
            try:
                self.divergence_guard.check(*checked, update=self._n_updates, frame=self.num_frames, gamma=self.gamma)
            except DivergenceError:
                super().dump_logs()  # the non-finite values reach the logs too
                raise
            if len(self.divergence_guard.warnings) > given:
                self.logger.record("train/divergence_warnings", len(self.divergence_guard.warnings))
        super().dump_logs()

    # ------------------------------------------------------------------ learn / save
    def learn(
        self: SelfDrQv2,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 4,
        tb_log_name: str = "DrQv2",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfDrQv2:
        """
        Train for ``total_timesteps`` transitions, summed over the environments (frames = transitions x action
        repeat). Each round steps the environments up to the next update due (see **Update ratio** in the class
        docstring), then makes those updates; ``model.timings`` says where the time went.

        :param total_timesteps: number of transitions (summed over the environments; agent steps with one
            environment) to train for; the last round may pass it by less than ``train_freq``
        :param callback: callback(s) for this call, run after those given to the constructor
        :param log_interval: episodes between two log dumps
        :param tb_log_name: name of the TensorBoard run
        :param reset_num_timesteps: restart the step count (and so the exploration schedule and the
            warm-up, and forget the step of the last :meth:`reset_from_scratch`); pass ``False`` to continue a
            loaded model where it stopped
        :param progress_bar: show a progress bar (tqdm and rich)
        :return: the trained model
        """
        if reset_num_timesteps:
            self.reset_step = 0
        self._warned_replay_not_ready = False
        if self.env is None:  # before SB3's assertion in _setup_learn; also an AssertionError, as SB3's
            raise AssertedParameterError(
                "env", "DrQv2.learn needs an environment: pass env= to DrQv2(...) or DrQv2.load(...), or call set_env."
            )
        total_timesteps, all_callbacks = self._setup_learn(
            total_timesteps, self._combined_callbacks(callback), reset_num_timesteps, tb_log_name, progress_bar
        )
        all_callbacks.on_training_start(locals(), globals())
        self.timings, self._update_clock = LearnTimings(), UpdateClock()
        try:
            while self.num_timesteps < total_timesteps:
                if not self._learning_round(all_callbacks, total_timesteps, log_interval):
                    break
        finally:
            self._finish_pending_step()  # only after an exception: a normal round leaves no step in flight
            self._update_clock.collect(wait=True)
        all_callbacks.on_training_end()
        return self

    def _learning_round(self, callback: BaseCallback, total_timesteps: int, log_interval: int) -> bool:
        """
        One round of :meth:`learn`: the environment steps up to the next update due, then the updates due (with
        ``step_envs_during_updates``, the next step is sent to the environments first). Timed into
        ``self.timings``.

        :return: whether to go on (``False`` when a callback stopped the training)
        """
        round_start, start = time.perf_counter(), self.num_timesteps
        self._round, self._round_used_policy = PhaseTime(rounds=1), False
        self._update_clock.collect()  # the device time of earlier rounds that has completed
        device_start = None
        rollout = self.collect_rollouts(
            self.env,  # type: ignore[arg-type]
            callback=callback,
            train_freq=self._round_train_freq(),
            replay_buffer=self.replay_buffer,  # type: ignore[arg-type]
            action_noise=self.action_noise,
            learning_starts=self.learning_starts,
            log_interval=log_interval,
        )
        updates = self.updates_due(start, self.num_timesteps) if rollout.continue_training else 0
        if updates > 0:
            if self.step_envs_during_updates and self.num_timesteps < total_timesteps and not self.hold_next_step:
                self._send_next_step()
            update_start, updates_before = time.perf_counter(), self._n_updates
            device_start = self._update_clock.start(self.device)
            self.train(gradient_steps=updates, batch_size=self.batch_size)
            self._round.update_s = time.perf_counter() - update_start
            self._round.updates = self._n_updates - updates_before  # train() makes none while the buffer cannot sample
            if self.timings.first_round_s is None and self._round.updates > 0:
                self.timings.first_round_s, self.timings.first_round_updates = self._round.update_s, self._round.updates
        self.hold_next_step = False
        self._round.total_s = time.perf_counter() - round_start
        learning = self._round_used_policy or self._round.updates > 0
        phase = self.timings.learning if learning else self.timings.warmup
        phase.add(self._round)
        self._update_clock.stop(device_start, phase, self._round.update_s)
        return rollout.continue_training

    def _combined_callbacks(self, callback: MaybeCallback) -> MaybeCallback:
        return combine_callbacks(self.callback, callback)  # each converted as SB3 converts it (functions, lists)

    def reset_from_scratch(self) -> None:
        """
        Restart the training from scratch in the middle of ``learn()``, as the action-collapse paper's rule does.

        Reset: the encoder, actor, critic and target critic get **new** random weights (DrQ-v2's
        initialization drawn from torch's global generator in its current state, which has advanced since
        the initial build: never reseeded, so the weights differ from the initial ones, and a seeded run
        stays reproducible), copied into the existing parameter tensors (a compiled update keeps its code and
        CUDA graphs); the optimizers are new (empty Adam state); the replay buffer is emptied
        (``replay_buffer.reset()``); the last gradient norms are forgotten (:attr:`last_grad_norms` is empty
        until the next update); ``reset_step`` becomes ``num_timesteps``, so the exploration schedule restarts
        from its first value, the first ``learning_starts`` agent steps after the reset take uniform random
        actions again, and no update happens before ``learning_starts`` agent steps were collected since the
        reset.

        Kept: ``num_timesteps`` (TensorBoard curves continue on one axis, and the budget of ``learn()`` is
        spent, not extended), the number of updates so far, the logger, the environment and its episode in
        progress (the paper resets the training, not the environment; the transition of the current step is
        the first one stored after the reset), the callbacks, the episode statistics, the hyperparameters and
        the learning-rate schedule (a function of the progress of ``learn()``).

        A model built with ``init_from`` is reset from scratch too: the transplanted groups get new random
        weights like the others, ``init_from`` is **not** applied again (the paper's reset is a restart from
        scratch). ``model.init_from`` still records how the model was first initialized.
        """
        was_training = self.policy.training
        kept = {name: getattr(self.policy, name) for name in ("encoder", "actor", "critic", "critic_target")}
        self.policy._build(self.lr_schedule)  # fresh weights and optimizers, drawn as the first build drew them
        with th.no_grad():
            for name, module in kept.items():
                fresh = getattr(self.policy, name)
                # Into the same tensors: a compiled update (its guards, its CUDA graphs' addresses) stays valid.
                module.load_state_dict(fresh.state_dict())
                optimizer = getattr(fresh, "optimizer", None)
                if optimizer is not None:
                    module.optimizer = type(optimizer)(module.parameters(), **optimizer.defaults)
                setattr(self.policy, name, module)
        self.policy.set_training_mode(was_training)
        self._create_aliases()
        self._index_grad_layers()  # a new recorder, on the new optimizers: no norm until the next update
        self.replay_buffer.reset()  # type: ignore[union-attr]
        self.reset_step = self.num_timesteps
        self.policy.exploration_std = self.current_stddev

    @classmethod
    def load(  # type: ignore[override]
        cls,
        path: str | pathlib.Path | io.BufferedIOBase,
        env: GymEnv | None = None,
        device: th.device | str = "auto",
        custom_objects: dict[str, Any] | None = None,
        print_system_info: bool = False,
        force_reset: bool = True,
        **kwargs: Any,
    ) -> DrQv2:
        """
        Load a model saved by :meth:`save`, with its trained weights (SB3's ``load``; see its documentation).

        A model built with ``init_from`` comes back with the weights it was saved with: the transplant happened
        once, when it was built, and is not done again (``model.init_from`` still names its sources).

        :param path: the zip
        :param env: environment to continue training on (``None``: predict only, or set it later)
        :param device: where the networks go
        :param custom_objects: saved attributes to replace instead of unpickling them
        :param print_system_info: print the system info of the saving machine
        :param force_reset: reset the environment before the next ``learn()``
        :param kwargs: saved attributes to override (e.g. ``buffer_size``; ``stddev_schedule`` takes the same
            specifications as the constructor, e.g. ``"linear(1.0,0.1,500000)"``, durations in agent steps)
        :return: the loaded model
        :raises TypeError: for ``init_from``: loading does not transplant; build a new model with it instead
        :raises FileNotFoundError: when neither ``path`` nor ``path.zip`` is a file, naming the path given
        """
        if "init_from" in kwargs:
            raise TypeError(
                "DrQv2.load does not transplant layers (init_from): it restores the saved weights. Build a new "
                "model with DrQv2(policy, env, init_from={...}) to start from the layers of saved models."
            )
        if isinstance(path, (str, os.PathLike)):
            given = pathlib.Path(path)
            zipped = given.with_name(given.name + ".zip")
            if not given.is_file() and not (given.suffix != ".zip" and zipped.is_file()):
                tried = f"{os.fspath(path)!r}" + ("" if given.suffix == ".zip" else f" (nor {os.fspath(zipped)!r})")
                raise FileNotFoundError(f"DrQv2.load: no model file {tried}; give the path of a zip saved by DrQv2.save.")
        if "stddev_schedule" in kwargs:  # SB3 sets kwargs as attributes: parse a specification as __init__ does
            kwargs["stddev_schedule"] = StddevSchedule(kwargs["stddev_schedule"])
        model = super().load(
            path,
            env=env,
            device=device,
            custom_objects=custom_objects,
            print_system_info=print_system_info,
            force_reset=force_reset,
            **kwargs,
        )
        specs = model.__dict__.pop("callback_specs", None) or []
        if "callback" not in kwargs and specs:
            from sb3_collapse.monitoring.callbacks import callback_from_spec

            callbacks = [callback_from_spec(spec) for spec in specs]
            lost = [spec["class"].rpartition(":")[2] for spec, built in zip(specs, callbacks) if built is None]
            if lost:
                warnings.warn(
                    f"DrQv2.load: the constructor callback(s) {', '.join(lost)} could not be saved and are not restored; "
                    "pass them again: DrQv2.load(path, callback=[...]).",
                    stacklevel=2,
                )
            kept = [callback for callback in callbacks if callback is not None]
            model.callback = kept[0] if len(kept) == 1 else kept or None
        return model

    def save(
        self,
        path: str | pathlib.Path | io.BufferedIOBase,
        exclude: Iterable[str] | None = None,
        include: Iterable[str] | None = None,
    ) -> None:
        """
        SB3's ``save``, keeping the constructor's callbacks (``callback=``) that can be built again: the
        :class:`~sb3_collapse.monitoring.callbacks.ResumableCallback` ones (``CollapseReset``, ``CollapseMetrics``),
        with their settings and their state (the reset rule's window, streak, resets...). :meth:`load` builds them
        again; a ``learn(..., reset_num_timesteps=False)`` after it continues with them as they were.
        """
        from sb3_collapse.monitoring.callbacks import callback_spec

        callbacks = self.callback if isinstance(self.callback, list) else [self.callback] if self.callback else []
        self.callback_specs = [callback_spec(callback) for callback in callbacks]
        try:
            super().save(path, exclude=exclude, include=include)
        finally:
            del self.callback_specs

    def set_env(self, env: GymEnv, force_reset: bool = True) -> None:
        super().set_env(env, force_reset=force_reset)
        self.env_config = _read_env_config(self.env) or self.env_config

    def _excluded_save_params(self) -> list[str]:
        return [
            *super()._excluded_save_params(),
            "encoder",
            "actor",
            "critic",
            "critic_target",
            "callback",
            "grad_norm_recorder",
            "_train_stats",
            "_train_stats_count",
            "_warned_replay_not_ready",
            "timings",
            "_update_clock",
            "_compiled_losses",
            "_pending_step",
            "_round",
            "_round_used_policy",
            "hold_next_step",
            "replay_prefetcher",
        ]

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        state_dicts = ["policy", "actor.optimizer", "critic.optimizer"]
        if self.policy.encoder.optimizer is not None:
            state_dicts.append("encoder.optimizer")
        return state_dicts, []


def check_hyperparameters(
    *,
    learning_rate: float | Schedule = 1e-4,
    buffer_size: int = 1,
    learning_starts: int = 0,
    batch_size: int = 1,
    tau: float = 0.01,
    gamma: float = 0.99,
    train_freq: int | tuple[int, str] = 1,
    gradient_steps: int = 1,
    n_steps: int = 1,
    stddev_clip: float = 0.3,
    augmentation_pad: int = 0,
    policy_kwargs: Mapping[str, Any] | None = None,
    seed: int | None = None,
    device: th.device | str = "auto",
) -> None:
    """
    Check :class:`DrQv2`'s hyperparameters (the constructor calls it; ``TrainConfig.validate`` too, before a run
    folder is created), so that a bad value fails before anything is built, with its name.

    :raises ParameterError: naming the first bad parameter, what it must be and what it got
    """

    def integer(name: str, value: Any, minimum: int) -> None:
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
            raise ParameterError(name, f"{name} must be an integer >= {minimum}, got {value!r}.")

    def number(name: str, value: Any, low: float, high: float = np.inf, low_open: bool = False) -> None:
        valid = isinstance(value, (int, float, np.number)) and not isinstance(value, bool) and np.isfinite(value)
        if not valid or value < low or (low_open and value == low) or value > high:
            bounds = f"{'>' if low_open else '>='} {low:g}" + ("" if high == np.inf else f" and <= {high:g}")
            raise ParameterError(name, f"{name} must be a finite number {bounds}, got {value!r}.")

    if not callable(learning_rate):
        number("learning_rate", learning_rate, 0.0, low_open=True)
    integer("buffer_size", buffer_size, 1)
    integer("learning_starts", learning_starts, 0)
    integer("batch_size", batch_size, 1)
    number("tau", tau, 0.0, 1.0)
    number("gamma", gamma, 0.0, 1.0)
    integer("train_freq", train_freq[0] if isinstance(train_freq, tuple) else train_freq, 1)
    if gradient_steps != -1:
        integer("gradient_steps", gradient_steps, 0)  # 0: collect without updating, as SB3 allows
    integer("n_steps", n_steps, 1)
    number("stddev_clip", stddev_clip, 0.0)
    integer("augmentation_pad", augmentation_pad, 0)
    for name in ("feature_dim", "hidden_dim"):
        if name in (policy_kwargs or {}):
            integer(f"policy_kwargs['{name}']", policy_kwargs[name], 1)  # type: ignore[index]
    check_policy_kwargs(policy_kwargs)  # SB3's keywords: net_arch, n_critics, share_features_extractor...
    if seed is not None:
        integer("seed", seed, 0)
    check_device(device)


def check_device(device: th.device | str, name: str = "device") -> None:
    """
    :param device: a torch device, or ``"auto"``
    :param name: the parameter's name, for the message
    :raises ParameterError: for a device torch does not know, or CUDA without a GPU (instead of SB3's silent
        fallback to the CPU)
    """
    if device == "auto":
        return
    try:
        parsed = th.device(device)
    except (RuntimeError, TypeError) as error:
        message = f"{name} must be 'auto', 'cpu', 'cuda', 'cuda:N'..., got {device!r} ({error})."
        raise ParameterError(name, message) from None
    if parsed.type == "cuda" and not th.cuda.is_available():
        raise ParameterError(
            name,
            f"{name}={str(device)!r} asks for a CUDA GPU, but torch sees none (torch.cuda.is_available() is False): "
            "use device='cpu' or 'auto', or a CUDA build of torch on a machine with a GPU.",
        )

COMPILE_MODES = ("default", "reduce-overhead", "max-autotune", "max-autotune-no-cudagraphs")
"""The ``torch.compile`` modes that ``compile_update`` takes."""

CUDA_GRAPH_MODES = ("reduce-overhead", "max-autotune")
"""The modes among them that replay CUDA graphs on a CUDA device."""


def check_compile_update(compile_update: bool | str) -> None:
    """
    :param compile_update: the ``compile_update`` argument of ``DrQv2``
    :raises ParameterError: unless it is a bool or one of :data:`COMPILE_MODES`
    """
    if isinstance(compile_update, bool) or compile_update in COMPILE_MODES:
        return
    raise ParameterError(
        "compile_update",
        f"compile_update must be True, False or a torch.compile mode {COMPILE_MODES}, got {compile_update!r}.",
    )


def compile_mode(compile_update: bool | str, device: th.device) -> str:
    """
    :param compile_update: ``True`` or a mode (see ``DrQv2``)
    :param device: the model's device
    :return: the ``torch.compile`` mode: the given one, or for ``True`` ``"reduce-overhead"`` (CUDA graphs) on CUDA
        and ``"default"`` elsewhere
    """
    if isinstance(compile_update, str):
        return compile_update
    return "reduce-overhead" if device.type == "cuda" else "default"


@contextlib.contextmanager
def _frozen(module: th.nn.Module) -> Iterator[None]:
    """Parameters of ``module`` with ``requires_grad=False`` inside the block (the ones that required it before, after)."""
    params = [p for p in module.parameters() if p.requires_grad]
    for p in params:
        p.requires_grad_(False)
    try:
        yield
    finally:
        for p in params:
            p.requires_grad_(True)


def soft_update(params: Iterable[th.Tensor], target_params: Iterable[th.Tensor], tau: float) -> None:
    """
    SB3's ``polyak_update`` (``target = target * (1 - tau) + tau * param``, in place, the same operations and values)
    as two ``torch._foreach`` calls instead of two per tensor.

    :param params: parameters of the trained network
    :param target_params: parameters of its target network, updated in place
    :param tau: soft update coefficient
    """
    targets = list(target_params)
    with th.no_grad():
        th._foreach_mul_(targets, 1 - tau)
        th._foreach_add_(targets, list(params), alpha=tau)


def physical_memory_bytes() -> int:
    """Total RAM of this machine, in bytes."""
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def _read_env_config(env: VecEnv) -> dict[str, Any] | None:
    """The ``make_dmc_env`` settings of the (first) environment, or ``None`` for other environments."""
    config = {}
    for key in ENV_CONFIG_KEYS:
        # has_attr first: a SubprocVecEnv's worker dies on get_attr of a missing attribute.
        config[key] = env.get_attr(key, indices=[0])[0] if env.has_attr(key) else None
    if config["task_id"] is None and config["action_repeat"] is None:
        return None
    return config
