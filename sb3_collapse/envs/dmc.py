"""DeepMind Control Suite tasks as Gymnasium environments, preprocessed as in DrQ-v2.

Follows ``dmc.py`` of facebookresearch/drqv2: actions in [-1, 1] rescaled to the task's bounds,
action repeat (summing rewards), 84x84 renders (camera 2 for quadruped, 0 otherwise) stacked
channel-first, oldest frame first.

Units: a *frame* is one simulator control step of dm_control (one call to its ``step``);
an *agent step* is one call to :meth:`DMCEnv.step`, i.e. ``action_repeat`` frames.
"""

from __future__ import annotations

import difflib
from collections import OrderedDict, deque
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.utils import EzPickle

from sb3_collapse.envs.registration import DMC_TASKS, DOMAIN_ALIASES
from sb3_collapse.envs.rendering import ensure_rendering_backend
from sb3_collapse.errors import ParameterError

OBS_TYPES = ("pixels", "state")
# Camera used for pixel observations, per domain (DrQ-v2 zooms in on the quadruped); 0 otherwise.
DEFAULT_CAMERA_IDS: dict[str, int] = {"quadruped": 2}

# DrQ-v2 style names ("walker_walk", "cup_catch") -> (domain, task).
_UNDERSCORE_NAMES: dict[str, tuple[str, str]] = {f"{domain}_{task}": (domain, task) for domain, task in DMC_TASKS}
_UNDERSCORE_NAMES.update(
    {
        f"{alias}_{task}": (domain, task)
        for alias, domain in DOMAIN_ALIASES.items()
        for task_domain, task in DMC_TASKS
        if task_domain == domain
    }
)


@dataclass(frozen=True)
class RewardInput:
    """
    A quantity that a DeepMind Control task's reward function (``Task.get_reward``) reads from the simulator: the
    value of one of its ``Physics`` methods, or one element of it.

    :param name: the quantity's name (``"torso_height"``)
    :param method: the ``Physics`` method that the reward function calls (``"torso_height"``)
    :param index: the element of the method's output that the reward reads (quadruped's ``torso_velocity()[0]``);
        ``None``: the whole output, flattened
    :param args: the method's arguments (stacker's ``site_distance("grasp", "target")``)
    :param state: whether it is a component of the environment state (a probing target); ``False`` for the control
        (``Physics.control()``, the last action in the task's bounds), which rollouts record as the action
    :param doc: what it is
    """

    name: str
    method: str
    index: int | None = None
    args: tuple[str, ...] = ()
    state: bool = True
    doc: str = ""

    def value(self, physics: Any) -> np.ndarray:
        """
        :param physics: the task's ``Physics``
        :return: ``(size,)`` float64, what the reward function reads (a copy)
        """
        value = np.array(getattr(physics, self.method)(*self.args), dtype=np.float64).reshape(-1)
        return value[[self.index]] if self.index is not None else value


CONTROL = RewardInput("control", "control", state=False, doc="the control, i.e. the last action (small-control term)")
"""The control, read by the rewards that favour small actions (a reward input, not a state component)."""


def _site_distance(site1: str, site2: str) -> RewardInput:
    """:return: the distance between two sites (``Physics.site_distance(site1, site2)``)."""
    return RewardInput(f"{site1}_to_{site2}", "site_distance", args=(site1, site2), doc=f"{site1} to {site2} distance")


_WALKER_STAND = (
    RewardInput("torso_height", "torso_height", doc="height of the torso's frame (standing term)"),
    RewardInput("torso_upright", "torso_upright", doc="zz entry of the torso's rotation matrix (upright term)"),
)
_WALKER_MOVE = (
    *_WALKER_STAND,
    RewardInput("horizontal_velocity", "horizontal_velocity", doc="horizontal velocity of the centre of mass (move)"),
)
_HOPPER_HEIGHT = RewardInput("height", "height", doc="torso height above the foot (standing term)")
_CARTPOLE_SPARSE = (
    RewardInput("cart_position", "cart_position", doc="the cart's position on the rail (centred term)"),
    RewardInput("pole_angle_cosine", "pole_angle_cosine", doc="cosine of each pole's angle (upright term)"),
)
_CARTPOLE_SMOOTH = (
    *_CARTPOLE_SPARSE,
    CONTROL,
    RewardInput("angular_vel", "angular_vel", doc="each pole's angular velocity (small-velocity term)"),
)
_FINGER_TURN = (RewardInput("dist_to_target", "dist_to_target", doc="distance from the spinner's tip to the target"),)
_HUMANOID = (
    RewardInput("head_height", "head_height", doc="height of the head (standing term)"),
    RewardInput("torso_upright", "torso_upright", doc="zz entry of the torso's rotation matrix (upright term)"),
    CONTROL,
    RewardInput("com_velocity_x", "center_of_mass_velocity", 0, doc="centre-of-mass velocity along x (move term)"),
    RewardInput("com_velocity_y", "center_of_mass_velocity", 1, doc="centre-of-mass velocity along y (move term)"),
)
_HUMANOID_CMU = (
    _HUMANOID[0],
    RewardInput("thorax_upright", "thorax_upright", doc="zz entry of the thorax's rotation matrix (upright term)"),
    *_HUMANOID[2:],
)
_DOG_STAND = (
    RewardInput("torso_pelvis_height", "torso_pelvis_height", doc="heights of the torso and the pelvis"),
    RewardInput("upright", "upright", doc="zz entries of the skull's, torso's and pelvis's rotation matrices"),
    RewardInput("touch_sensors", "touch_sensors", doc="touch forces of the palms and soles (summed)"),
)
_DOG_MOVE = (*_DOG_STAND, RewardInput("com_forward_velocity", "com_forward_velocity", doc="forward velocity"))
_LQR = (RewardInput("position", "position", doc="the joints' positions (state cost)"), CONTROL)
_MANIPULATOR_BALL = (_site_distance("ball", "target_ball"),)
_MANIPULATOR_PEG = (
    _site_distance("peg_grasp", "grasp"),
    _site_distance("peg_pinch", "pinch"),
    _site_distance("peg", "target_peg"),
    _site_distance("target_peg_tip", "peg_tip"),
)
_POINT_MASS = (RewardInput("mass_to_target_dist", "mass_to_target_dist", doc="mass to target distance"), CONTROL)
_QUADRUPED_UPRIGHT = RewardInput("torso_upright", "torso_upright", doc="zz entry of the torso's rotation matrix")
_QUADRUPED_MOVE = (
    _QUADRUPED_UPRIGHT,
    RewardInput("torso_velocity_x", "torso_velocity", 0, doc="forward velocity of the torso (move term)"),
)
_REACHER = (RewardInput("finger_to_target_dist", "finger_to_target_dist", doc="finger to target distance"),)
_SWIMMER = (RewardInput("nose_to_target_dist", "nose_to_target_dist", doc="nose to target distance"),)
_ACROBOT = (RewardInput("to_target", "to_target", doc="distance from the tip to the target"),)
_FISH_UPRIGHT = RewardInput("upright", "upright", doc="zz entry of the torso's rotation matrix")


def _stacker(n_boxes: int) -> tuple[RewardInput, ...]:
    """:return: stacker's reward inputs with ``n_boxes`` boxes: each box to the target, then the hand to the target."""
    return (*(_site_distance(f"box{b}", "target") for b in range(n_boxes)), _site_distance("grasp", "target"))


REWARD_INPUTS: dict[str, tuple[RewardInput, ...]] = {
    "acrobot-swingup": _ACROBOT,
    "acrobot-swingup_sparse": _ACROBOT,
    "ball_in_cup-catch": (
        RewardInput("ball_to_target", "ball_to_target", doc="x and z from the ball to the cup's target (in_target)"),
    ),
    "cartpole-balance": _CARTPOLE_SMOOTH,
    "cartpole-balance_sparse": _CARTPOLE_SPARSE,
    "cartpole-swingup": _CARTPOLE_SMOOTH,
    "cartpole-swingup_sparse": _CARTPOLE_SPARSE,
    "cartpole-two_poles": _CARTPOLE_SMOOTH,
    "cartpole-three_poles": _CARTPOLE_SMOOTH,
    "cheetah-run": (RewardInput("speed", "speed", doc="horizontal velocity of the centre of mass"),),
    "dog-stand": _DOG_STAND,
    "dog-walk": _DOG_MOVE,
    "dog-trot": _DOG_MOVE,
    "dog-run": _DOG_MOVE,
    "dog-fetch": (
        *_DOG_STAND,
        RewardInput("ball_to_mouth_distance", "ball_to_mouth_distance", doc="ball to mouth distance (reach term)"),
        RewardInput("ball_to_target_distance", "ball_to_target_distance", doc="ball to target distance (fetch)"),
    ),
    "finger-spin": (RewardInput("hinge_velocity", "hinge_velocity", doc="angular velocity of the spinner"),),
    "finger-turn_easy": _FINGER_TURN,
    "finger-turn_hard": _FINGER_TURN,
    "fish-upright": (_FISH_UPRIGHT,),
    "fish-swim": (
        RewardInput("mouth_to_target", "mouth_to_target", doc="mouth to target, in the mouth's frame (its norm)"),
        _FISH_UPRIGHT,
    ),
    "hopper-stand": (_HOPPER_HEIGHT, CONTROL),
    "hopper-hop": (_HOPPER_HEIGHT, RewardInput("speed", "speed", doc="horizontal velocity of the torso (hop term)")),
    "humanoid-stand": _HUMANOID,
    "humanoid-walk": _HUMANOID,
    "humanoid-run": _HUMANOID,
    "humanoid-run_pure_state": _HUMANOID,
    "humanoid_CMU-stand": _HUMANOID_CMU,
    "humanoid_CMU-walk": _HUMANOID_CMU,
    "humanoid_CMU-run": _HUMANOID_CMU,
    "lqr-lqr_2_1": _LQR,
    "lqr-lqr_6_2": _LQR,
    "manipulator-bring_ball": _MANIPULATOR_BALL,
    "manipulator-bring_peg": _MANIPULATOR_PEG,
    "manipulator-insert_ball": _MANIPULATOR_BALL,
    "manipulator-insert_peg": _MANIPULATOR_PEG,
    "pendulum-swingup": (RewardInput("pole_vertical", "pole_vertical", doc="zz entry of the pole's rotation matrix"),),
    "point_mass-easy": _POINT_MASS,
    "point_mass-hard": _POINT_MASS,
    "quadruped-walk": _QUADRUPED_MOVE,
    "quadruped-run": _QUADRUPED_MOVE,
    "quadruped-escape": (
        _QUADRUPED_UPRIGHT,
        RewardInput("origin_distance", "origin_distance", doc="distance of the torso from the origin (escape)"),
    ),
    "quadruped-fetch": (
        _QUADRUPED_UPRIGHT,
        RewardInput("self_to_ball_distance", "self_to_ball_distance", doc="workspace to ball distance (reach)"),
        RewardInput("ball_to_target_distance", "ball_to_target_distance", doc="ball to target distance (fetch)"),
    ),
    "reacher-easy": _REACHER,
    "reacher-hard": _REACHER,
    "stacker-stack_2": _stacker(2),
    "stacker-stack_4": _stacker(4),
    "swimmer-swimmer6": _SWIMMER,
    "swimmer-swimmer15": _SWIMMER,
    "walker-stand": _WALKER_STAND,
    "walker-walk": _WALKER_MOVE,
    "walker-run": _WALKER_MOVE,
}
"""
The paper chose Figure 2's state components "because all of them are the input to the reward function".
``<domain>-<task>`` (every task of ``dm_control.suite``) -> the quantities that the task's ``get_reward`` reads, in
the order it reads them, each computed by the ``Physics`` method it calls. Tasks of one domain differ: walker-stand
reads no velocity (walk and run add ``horizontal_velocity``); hopper-stand reads ``height`` and the control,
hopper-hop ``height`` and ``speed``; the sparse cartpole tasks read neither the control nor ``angular_vel``. The
control (:data:`CONTROL`) is a reward input but not a state component: :meth:`DMCEnv.reward_inputs` leaves it out.
"""


def reward_inputs_of(domain: str, task: str) -> tuple[RewardInput, ...]:
    """
    :param domain: the domain (``"walker"``)
    :param task: the task (``"walk"``)
    :return: every quantity that the task's reward reads (:data:`REWARD_INPUTS`), the control included; empty for a
        task not in the suite
    """
    return REWARD_INPUTS.get(f"{domain}-{task}", ())


def parse_task(name: str) -> tuple[str, str]:
    """
    Split a DeepMind Control Suite task name into its domain and task.

    Accepted forms: ``"<domain>-<task>"`` (``"walker-walk"``, ``"ball_in_cup-catch"``, ``"finger-turn_easy"``),
    DrQ-v2's ``"<domain>_<task>"`` (``"walker_walk"``, ``"finger_turn_easy"``) and the domain alias
    ``cup`` for ``ball_in_cup`` (``"cup-catch"``, ``"cup_catch"``).

    :param name: The task name.
    :return: ``(domain, task)`` as in ``dm_control.suite.ALL_TASKS``, e.g. ``("ball_in_cup", "catch")``.
    :raises ValueError: if the name is not a task of the suite (the message suggests close names).
    """
    if "-" in name:
        domain, task = name.split("-", 1)
        domain = DOMAIN_ALIASES.get(domain, domain)
        if (domain, task) in DMC_TASKS:
            return domain, task
    elif name in _UNDERSCORE_NAMES:
        return _UNDERSCORE_NAMES[name]
    raise ValueError(_unknown_task_message(name))


def _unknown_task_message(name: str) -> str:
    """
    :param name: A name that is not a task of the suite.
    :return: Error message naming it, with close matches and how to list the tasks.
    """
    canonical = {f"{domain}-{task}": f"{domain}-{task}" for domain, task in DMC_TASKS}
    canonical.update({underscored: f"{domain}-{task}" for underscored, (domain, task) in _UNDERSCORE_NAMES.items()})
    matches = difflib.get_close_matches(name, list(canonical), n=6, cutoff=0.6)
    suggestions = list(dict.fromkeys(canonical[match] for match in matches))[:3]
    hint = f" Did you mean {', '.join(repr(s) for s in suggestions)}?" if suggestions else ""
    return (
        f"Unknown DeepMind Control task {name!r}.{hint} Tasks are named '<domain>-<task>', e.g. 'walker-walk' "
        "(DrQ-v2's 'walker_walk' also works); list them with `sb3_collapse.envs.DMC_TASKS`."
    )


def scale_action(action: np.ndarray, low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """
    Clip an action to [-1, 1] and map it linearly onto [low, high] (as dm_control's ``action_scale`` wrapper).

    Bounds of exactly [-1, 1] leave the (clipped) action unchanged, bit for bit.

    :param action: Action with components in [-1, 1] (values outside are clipped).
    :param low: Lower bounds of the task's actions.
    :param high: Upper bounds of the task's actions.
    :return: The rescaled action, as float64 (the dtype dm_control expects).
    """
    action = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
    scale = (high - low) / 2.0
    offset = (high + low) / 2.0
    return scale * action + offset


class DMCEnv(gym.Env[np.ndarray, np.ndarray], EzPickle):
    """
    A DeepMind Control Suite task with DrQ-v2 preprocessing: observations ``uint8`` ``(3 * frame_stack, size,
    size)``, the last ``frame_stack`` renders, channel-first, oldest first (``obs_type="state"``: the float32 state
    vector, nothing rendered); actions in [-1, 1] rescaled to the task's bounds and repeated ``action_repeat``
    frames, rewards summed; the time limit gives ``truncated=True``; ``info["frames"]`` counts frames since the
    reset; :meth:`get_state` the true state. See docs/environments.md.

    :param task: Task name, e.g. "walker-walk" (see :func:`parse_task` for the accepted forms).
    :param seed: Seed of the task's random initial states (and of the action space); None for a random one.
        ``reset(seed=...)`` reseeds both.
    :param action_repeat: Frames (simulator control steps) per agent step, each with the same action.
    :param frame_stack: Number of renders (one per agent step) stacked in a pixel observation; ignored for states.
    :param size: Height and width of the renders, in pixels.
    :param camera_id: Camera of the renders; None for DrQ-v2's choice (2 for quadruped, 0 otherwise).
    :param obs_type: "pixels" for stacked renders, "state" for the vectorized true state.
    :param render_mode: "rgb_array" (:meth:`render` returns the last render) or None (:meth:`render` returns None).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 20}

    def __init__(
        self,
        task: str,
        seed: int | None = None,
        action_repeat: int = 2,
        frame_stack: int = 3,
        size: int = 84,
        camera_id: int | None = None,
        obs_type: str = "pixels",
        render_mode: str | None = "rgb_array",
    ) -> None:
        EzPickle.__init__(
            self,
            task=task,
            seed=seed,
            action_repeat=action_repeat,
            frame_stack=frame_stack,
            size=size,
            camera_id=camera_id,
            obs_type=obs_type,
            render_mode=render_mode,
        )
        check_env_arguments(action_repeat, frame_stack, size, obs_type, render_mode)
        self.domain, self.task_name = parse_task(task)
        self.task_id = f"{self.domain}-{self.task_name}"
        self.action_repeat = action_repeat
        self.frame_stack = frame_stack
        self.size = size
        self.obs_type = obs_type
        self.render_mode = render_mode
        self.camera_id = DEFAULT_CAMERA_IDS.get(self.domain, 0) if camera_id is None else camera_id

        self._dmc = self._load(seed)
        n_cameras = self._dmc._env.physics.model.ncam
        if not -1 <= self.camera_id < n_cameras:
            self.close()
            raise ValueError(
                f"camera_id={self.camera_id} does not exist in {self.task_id}, which has {n_cameras} cameras "
                "(ids 0 to ncam - 1, or -1 for the free camera)."
            )

        action_spec = self._dmc._env.action_spec()
        self._action_low = np.broadcast_to(action_spec.minimum, action_spec.shape).astype(np.float64)
        self._action_high = np.broadcast_to(action_spec.maximum, action_spec.shape).astype(np.float64)
        self.action_space = spaces.Box(-1.0, 1.0, shape=action_spec.shape, dtype=np.float32, seed=seed)

        self._state_shapes = OrderedDict(
            (name, int(np.prod(spec.shape))) for name, spec in self._dmc._env.observation_spec().items()
        )
        if obs_type == "pixels":
            self.observation_space = spaces.Box(0, 255, shape=(3 * frame_stack, size, size), dtype=np.uint8)
        else:
            dim = sum(self._state_shapes.values())
            self.observation_space = spaces.Box(-np.inf, np.inf, shape=(dim,), dtype=np.float32)

        agent_step_s = self._dmc._env.control_timestep() * action_repeat
        self.metadata = {"render_modes": ["rgb_array"], "render_fps": 1.0 / agent_step_s}

        self._frames: deque[np.ndarray] = deque(maxlen=frame_stack)  # CHW renders, oldest first
        self._last_render: np.ndarray | None = None  # HWC
        self._dmc_observation: dict[str, np.ndarray] | None = None  # of the current timestep
        self._elapsed_frames = 0

    def _load(self, seed: int | None) -> Any:
        """
        Build the dm_control environment, wrapped by shimmy.

        :param seed: Seed of the task's random number generator, or None.
        :return: The ``DmControlCompatibilityV0`` wrapper.
        """
        # The OpenGL backend must be chosen before dm_control is imported.
        ensure_rendering_backend(required=self.obs_type == "pixels")
        from dm_control import suite
        from shimmy.dm_control_compatibility import DmControlCompatibilityV0

        dm_env = suite.load(self.domain, self.task_name, task_kwargs={"random": seed}, visualize_reward=False)
        render_kwargs = {"height": self.size, "width": self.size, "camera_id": self.camera_id}
        return DmControlCompatibilityV0(dm_env, render_mode="rgb_array", render_kwargs=render_kwargs)

    @property
    def state_shapes(self) -> OrderedDict[str, int]:
        """Names of the true state components (dm_control's order) and their flattened sizes."""
        return OrderedDict(self._state_shapes)

    def get_state(self) -> dict[str, np.ndarray]:
        """
        Return the true state behind the current observation.

        :return: The dm_control observation of the current timestep (the last one of the last agent step,
            or the reset one), as components named as in :attr:`state_shapes`, each a flattened float32 copy.
        """
        if self._dmc_observation is None:
            raise RuntimeError("get_state() needs a current timestep: call reset() first.")
        return {name: np.array(value, dtype=np.float32).reshape(-1) for name, value in self._dmc_observation.items()}

    @property
    def physics(self) -> Any:
        """The dm_control ``Physics`` of the task (its simulator state)."""
        return self._dmc._env.physics

    def reward_inputs(self) -> dict[str, np.ndarray]:
        """
        The state components that the task's reward function reads (:data:`REWARD_INPUTS` but the control, which is
        the action), at the current timestep (the same one as :meth:`get_state`), computed by the task's ``Physics``
        methods as ``get_reward`` computes them.

        :return: name -> ``(size,)`` float32 (size 1 but for per-pole, per-body or vector quantities such as
            cartpole's ``pole_angle_cosine`` or ball_in_cup's ``ball_to_target``)
        """
        if self._dmc_observation is None:
            raise RuntimeError("reward_inputs() needs a current timestep: call reset() first.")
        physics = self.physics
        inputs = reward_inputs_of(self.domain, self.task_name)
        return {item.name: item.value(physics).astype(np.float32) for item in inputs if item.state}

    def get_rng_state(self) -> dict[str, Any]:
        """
        The state of the environment's random generators: the task's (initial states) and the action space's.
        With :meth:`set_rng_state`, a checkpoint can make the next :meth:`reset` give the same episode again.

        :return: a picklable state
        """
        return {
            "task": self._dmc._env.task.random.get_state(),
            "action_space": self.action_space.np_random.bit_generator.state,
        }

    def set_rng_state(self, state: dict[str, Any]) -> None:
        """
        Put the random generators back in a state of :meth:`get_rng_state`.

        :param state: what :meth:`get_rng_state` returned
        """
        self._dmc._env.task.random.set_state(state["task"])
        self.action_space.np_random.bit_generator.state = state["action_space"]

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        """
        Start a new episode.

        :param seed: If given, reseed the task's random initial states and the action space with it,
            so that resets with the same seed give the same first observation.
        :param options: Unused.
        :return: The first observation, and info with ``frames`` = 0.
        """
        super().reset(seed=seed)
        if seed is not None:
            self._dmc._env.task._random = np.random.RandomState(seed)
            self.action_space.seed(seed)
        self._dmc_observation, _ = self._dmc.reset()
        self._elapsed_frames = 0
        if self.obs_type == "pixels":
            frame = self._render_frame()
            for _ in range(self.frame_stack):
                self._frames.append(frame)
        return self._observation(), {"frames": 0}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        """
        Apply an action for ``action_repeat`` frames (fewer if the episode ends before).

        :param action: Action in [-1, 1] (clipped), of shape ``action_space.shape``.
        :return: observation, reward (sum over the frames, each weighted by the product of the previous
            frames' discounts), terminated, truncated, and info with ``frames``: frames since the last reset.
        """
        if self._dmc_observation is None:
            raise RuntimeError("Call reset() before step().")
        action = np.asarray(action)
        if action.shape != self.action_space.shape:
            raise ValueError(f"Expected an action of shape {self.action_space.shape}, got {action.shape}.")
        dmc_action = scale_action(action, self._action_low, self._action_high)

        reward, discount = 0.0, 1.0
        terminated = truncated = False
        for _ in range(self.action_repeat):
            self._dmc_observation, frame_reward, terminated, truncated, info = self._dmc.step(dmc_action)
            self._elapsed_frames += 1
            reward += float(frame_reward) * discount
            discount *= float(info["timestep.discount"])
            if terminated or truncated:
                break

        if self.obs_type == "pixels":
            self._frames.append(self._render_frame())
        return self._observation(), reward, terminated, truncated, {"frames": self._elapsed_frames}

    def render(self) -> np.ndarray | None:
        """
        :return: With ``render_mode="rgb_array"``, an RGB image of shape ``(size, size, 3)`` (uint8):
            the last render of the observation for pixels, a fresh render for states. None otherwise.
        """
        if self.render_mode is None:
            return None
        if self.obs_type == "pixels" and self._last_render is not None:
            return self._last_render.copy()
        return self._dmc.render()

    def close(self) -> None:
        """Free the simulator (calling it again does nothing)."""
        if getattr(self, "_dmc", None) is not None:
            self._dmc.close()
            self._dmc = None

    def _render_frame(self) -> np.ndarray:
        """
        Render the current simulator state.

        :return: The render, channel-first: shape ``(3, size, size)``, uint8.
        """
        self._last_render = self._dmc.render()
        return self._last_render.transpose(2, 0, 1)

    def _observation(self) -> np.ndarray:
        """:return: The current observation (a new array), as described in the class docstring."""
        if self.obs_type == "pixels":
            return np.concatenate(list(self._frames), axis=0)
        return np.concatenate(list(self.get_state().values()))


def check_env_arguments(
    action_repeat: int, frame_stack: int, size: int, obs_type: str = "pixels", render_mode: str | None = None
) -> None:
    """
    Raise a ``ParameterError`` (a ``ValueError``) for invalid :class:`DMCEnv` arguments (see its docstring for their
    meaning), before any environment is built.

    :param action_repeat: Frames per agent step, at least 1.
    :param frame_stack: Renders per observation, at least 1.
    :param size: Render height and width in pixels, at least 1.
    :param obs_type: One of ``OBS_TYPES``.
    :param render_mode: "rgb_array" or None.
    """
    for name, value in (("action_repeat", action_repeat), ("frame_stack", frame_stack), ("size", size)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise ParameterError(name, f"{name} must be an integer >= 1, got {value!r}.")
    if obs_type not in OBS_TYPES:
        raise ParameterError("obs_type", f"obs_type must be one of {OBS_TYPES}, got {obs_type!r}.")
    if render_mode not in (None, "rgb_array"):
        raise ParameterError("render_mode", f"render_mode must be 'rgb_array' or None, got {render_mode!r}.")


def make_dmc_env(
    task: str,
    seed: int | None = None,
    action_repeat: int = 2,
    frame_stack: int = 3,
    size: int = 84,
    camera_id: int | None = None,
    obs_type: str = "pixels",
) -> DMCEnv:
    """
    Create a DeepMind Control Suite task with DrQ-v2 preprocessing (see :class:`DMCEnv`).

    :param task: Task name, e.g. "walker-walk", "walker_walk" or "cup-catch" (see :func:`parse_task`).
    :param seed: Seed of the task's random initial states (and of the action space); None for a random one.
    :param action_repeat: Frames (simulator control steps) per agent step, each with the same action.
    :param frame_stack: Number of renders (one per agent step) stacked in a pixel observation; ignored for states.
    :param size: Height and width of the renders, in pixels.
    :param camera_id: Camera of the renders; None for DrQ-v2's choice (2 for quadruped, 0 otherwise).
    :param obs_type: "pixels" for stacked renders, "state" for the vectorized true state.
    :return: The environment.
    """
    return DMCEnv(
        task=task,
        seed=seed,
        action_repeat=action_repeat,
        frame_stack=frame_stack,
        size=size,
        camera_id=camera_id,
        obs_type=obs_type,
    )
