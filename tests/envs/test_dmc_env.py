"""Tests of the DeepMind Control environments (sb3_collapse.envs), with the real dm_control."""

from __future__ import annotations

import os
import pickle
import subprocess
import sys
import warnings
from collections.abc import Callable, Iterator

import gymnasium as gym
import numpy as np
import pytest
from gymnasium import spaces
from gymnasium.utils.env_checker import check_env as gym_check_env
from stable_baselines3.common.env_checker import check_env as sb3_check_env
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

from sb3_collapse.envs import DMC_TASKS, DMCEnv, make_dmc_env, parse_task
from sb3_collapse.envs.dmc import REWARD_INPUTS, reward_inputs_of, scale_action

# Imported after sb3_collapse.envs, so that the OpenGL backend is chosen first.
from dm_control import suite  # isort: skip
from dm_control.suite.wrappers import action_scale  # isort: skip
from dm_control.utils import rewards as dm_rewards  # isort: skip

WALKER_STATE_SHAPES = {"orientations": 14, "height": 1, "velocity": 9}


@pytest.fixture
def make_env() -> Iterator[Callable[..., DMCEnv]]:
    """:return: ``make_dmc_env``, closing the environments it made after the test."""
    envs: list[DMCEnv] = []

    def _make(task: str = "walker-walk", **kwargs) -> DMCEnv:
        envs.append(make_dmc_env(task, **kwargs))
        return envs[-1]

    yield _make
    for env in envs:
        env.close()


def raw_dmc_env(domain: str, task: str, seed: int):
    """:return: The plain dm_control environment DMCEnv wraps, for comparisons."""
    return suite.load(domain, task, task_kwargs={"random": seed}, visualize_reward=False)


def flat_state(observation) -> np.ndarray:
    """:return: A dm_control observation flattened as DMCEnv's state observation."""
    return np.concatenate([np.asarray(v, dtype=np.float32).reshape(-1) for v in observation.values()])


# ---------------------------------------------------------------- task names and registration


@pytest.mark.parametrize(
    "name, expected",
    [
        ("walker-walk", ("walker", "walk")),
        ("ball_in_cup-catch", ("ball_in_cup", "catch")),
        ("finger-turn_easy", ("finger", "turn_easy")),
        ("humanoid_CMU-run", ("humanoid_CMU", "run")),
        ("walker_walk", ("walker", "walk")),
        ("finger_turn_easy", ("finger", "turn_easy")),
        ("point_mass_easy", ("point_mass", "easy")),
        ("ball_in_cup_catch", ("ball_in_cup", "catch")),
        ("cup_catch", ("ball_in_cup", "catch")),
        ("cup-catch", ("ball_in_cup", "catch")),
    ],
)
def test_parse_task(name: str, expected: tuple[str, str]) -> None:
    assert parse_task(name) == expected


@pytest.mark.parametrize("name", ["walker-wlak", "walker_wlak", "walkerwalk", "walker", "", "walker-walk-v0"])
def test_parse_task_unknown(name: str) -> None:
    with pytest.raises(ValueError) as error:
        parse_task(name)
    message = str(error.value)
    assert repr(name) in message
    assert "DMC_TASKS" in message


def test_parse_task_suggests_close_names() -> None:
    with pytest.raises(ValueError, match="Did you mean 'walker-walk'"):
        parse_task("walker_wlak")


def test_every_task_parses_in_both_forms() -> None:
    for domain, task in DMC_TASKS:
        assert parse_task(f"{domain}-{task}") == (domain, task)
        assert parse_task(f"{domain}_{task}") == (domain, task)


def test_task_list_matches_dm_control() -> None:
    assert DMC_TASKS == tuple(suite.ALL_TASKS)


def test_all_tasks_are_registered() -> None:
    for domain, task in DMC_TASKS:
        spec = gym.spec(f"sb3_collapse/{domain}-{task}-v0")
        assert spec.entry_point == "sb3_collapse.envs.dmc:DMCEnv"
        assert spec.kwargs == {"task": f"{domain}-{task}"}
        assert spec.max_episode_steps is None
    assert gym.spec("sb3_collapse/cup-catch-v0").kwargs == {"task": "ball_in_cup-catch"}


def test_registration_is_idempotent() -> None:
    from sb3_collapse.envs import register_dmc_envs

    assert register_dmc_envs() == []


@pytest.mark.parametrize(
    "env_id, task_id",
    [
        ("sb3_collapse/walker-walk-v0", "walker-walk"),
        ("sb3_collapse/ball_in_cup-catch-v0", "ball_in_cup-catch"),
        ("sb3_collapse/cup-catch-v0", "ball_in_cup-catch"),
        ("sb3_collapse/finger-turn_easy-v0", "finger-turn_easy"),
    ],
)
def test_gymnasium_make(env_id: str, task_id: str) -> None:
    env = gym.make(env_id, obs_type="state", action_repeat=4)
    try:
        assert isinstance(env.unwrapped, DMCEnv)
        assert env.unwrapped.task_id == task_id
        assert env.unwrapped.action_repeat == 4
        assert not any(isinstance(wrapper, gym.wrappers.TimeLimit) for wrapper in _wrappers(env))
        obs, info = env.reset(seed=0)
        assert obs in env.observation_space
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        assert info["frames"] == 4
    finally:
        env.close()


def _wrappers(env: gym.Env) -> list[gym.Env]:
    chain = [env]
    while isinstance(chain[-1], gym.Wrapper):
        chain.append(chain[-1].env)
    return chain


IMPORT_CHECK = """
import os, sys
import sb3_collapse.envs
from sb3_collapse.envs import ensure_rendering_backend
loaded = [m for m in sys.modules if m.split(".")[0] in ("dm_control", "mujoco", "shimmy")]
assert not loaded, loaded
assert "MUJOCO_GL" not in os.environ, "the backend must not be checked at import"
from dm_control import suite  # the import hook chooses the backend first
if ensure_rendering_backend(required=False) is not None:
    assert os.environ["MUJOCO_GL"] in ("egl", "osmesa"), os.environ["MUJOCO_GL"]
    assert suite.load("cartpole", "balance").physics.render(8, 8).shape == (8, 8, 3)
"""


def test_import_is_lazy_and_chooses_the_backend_before_dm_control() -> None:
    env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM")}
    subprocess.run(
        [sys.executable, "-W", "error::RuntimeWarning", "-c", IMPORT_CHECK], env=env, check=True, timeout=120
    )


# ---------------------------------------------------------------- pixel observations


def test_pixel_spaces(make_env) -> None:
    env = make_env("walker-walk", seed=0)
    assert env.observation_space == spaces.Box(0, 255, (9, 84, 84), np.uint8)
    assert env.action_space == spaces.Box(-1.0, 1.0, (6,), np.float32)
    assert (env.domain, env.task_name, env.task_id) == ("walker", "walk", "walker-walk")
    assert (env.action_repeat, env.frame_stack, env.obs_type, env.camera_id) == (2, 3, "pixels", 0)
    obs, info = env.reset()
    assert obs.shape == (9, 84, 84) and obs.dtype == np.uint8
    assert obs in env.observation_space
    assert info == {"frames": 0}
    obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
    assert obs.shape == (9, 84, 84) and obs.dtype == np.uint8
    assert isinstance(reward, float)
    assert (terminated, truncated, info) == (False, False, {"frames": 2})


def test_non_default_sizes(make_env) -> None:
    env = make_env("cartpole-swingup", frame_stack=2, size=32, action_repeat=8)
    assert env.observation_space.shape == (6, 32, 32)
    obs, _ = env.reset(seed=0)
    assert obs.shape == (6, 32, 32)
    assert env.step(env.action_space.sample())[-1] == {"frames": 8}


def test_reset_fills_the_stack_with_the_first_frame(make_env) -> None:
    env = make_env("walker-walk", seed=0)
    obs, _ = env.reset()
    assert obs[:3].any()
    np.testing.assert_array_equal(obs[:3], obs[3:6])
    np.testing.assert_array_equal(obs[:3], obs[6:9])
    np.testing.assert_array_equal(obs[6:9], env.render().transpose(2, 0, 1))

    action = np.ones(env.action_space.shape, dtype=np.float32)
    next_obs = env.step(action)[0]
    next_next_obs = env.step(action)[0]
    # Oldest frame first: each step shifts the stack by one frame.
    np.testing.assert_array_equal(next_obs[:6], obs[3:])
    np.testing.assert_array_equal(next_next_obs[:6], next_obs[3:])
    np.testing.assert_array_equal(next_next_obs[6:], env.render().transpose(2, 0, 1))
    assert not np.array_equal(next_next_obs[6:], obs[6:])


def test_renders_once_per_agent_step(make_env) -> None:
    env = make_env("walker-walk", seed=0, action_repeat=4)
    render = env._dmc.render
    calls = []
    env._dmc.render = lambda: calls.append(1) or render()
    env.reset()
    assert len(calls) == 1
    for _ in range(5):
        env.step(env.action_space.sample())
    assert len(calls) == 6
    env.render()
    assert len(calls) == 6  # render() returns the last render


def test_quadruped_uses_camera_2(make_env) -> None:
    env = make_env("quadruped-walk", seed=0)
    assert env.camera_id == 2
    obs, _ = env.reset()
    physics = env._dmc._env.physics
    camera_2 = physics.render(height=84, width=84, camera_id=2).transpose(2, 0, 1)
    camera_0 = physics.render(height=84, width=84, camera_id=0).transpose(2, 0, 1)
    np.testing.assert_array_equal(obs[6:], camera_2)
    assert not np.array_equal(obs[6:], camera_0)
    assert make_env("quadruped-walk", camera_id=0, obs_type="state").camera_id == 0


def test_render(make_env) -> None:
    env = make_env("walker-walk", seed=0)
    obs, _ = env.reset()
    frame = env.render()
    assert frame.shape == (84, 84, 3) and frame.dtype == np.uint8
    frame[:] = 0  # a copy: the observation is not affected
    assert env.render().any()
    assert env.metadata["render_modes"] == ["rgb_array"]
    assert env.metadata["render_fps"] == pytest.approx(20.0)  # 0.025 s per frame, 2 frames per agent step


# ---------------------------------------------------------------- dynamics: rewards, actions, time limit


def test_rewards_are_summed_over_the_action_repeat(make_env) -> None:
    env = make_env("walker-walk", seed=3, action_repeat=3, obs_type="state")
    raw = raw_dmc_env("walker", "walk", seed=3)
    obs, _ = env.reset()
    np.testing.assert_array_equal(obs, flat_state(raw.reset().observation))
    rng = np.random.default_rng(0)
    for step in range(1, 11):
        action = rng.uniform(-1, 1, size=env.action_space.shape).astype(np.float32)
        obs, reward, terminated, truncated, info = env.step(action)
        raw_reward = 0.0
        for _ in range(3):
            timestep = raw.step(action.astype(np.float64))
            raw_reward += timestep.reward
        assert reward == pytest.approx(raw_reward, rel=1e-12)
        np.testing.assert_array_equal(obs, flat_state(timestep.observation))
        assert info["frames"] == 3 * step
    assert reward > 0


def test_scale_action() -> None:
    low, high = np.array([-1.0, 0.0, -0.8, -1e3]), np.array([1.0, 2.0, 0.8, 3e3])
    np.testing.assert_array_equal(scale_action(np.full(4, -1.0), low, high), low)
    np.testing.assert_array_equal(scale_action(np.full(4, 1.0), low, high), high)
    np.testing.assert_allclose(scale_action(np.zeros(4), low, high), (low + high) / 2)
    # Clipped to [-1, 1] first.
    np.testing.assert_array_equal(scale_action(np.array([5.0, -5.0, 2.0, -2.0]), low, high), [1.0, 0.0, 0.8, -1e3])
    scaled = scale_action(np.array([0.1, 0.1, 0.1, 0.1], dtype=np.float32), low, high)
    assert scaled.dtype == np.float64
    # Unit bounds leave actions exactly unchanged.
    action = np.random.default_rng(0).uniform(-1, 1, size=100)
    np.testing.assert_array_equal(scale_action(action, -np.ones(100), np.ones(100)), action)


def test_actions_are_rescaled_to_the_task_bounds(make_env) -> None:
    # The quadruped is the suite task with bounds other than [-1, 1] (besides lqr's +-1e10).
    env = make_env("quadruped-walk", seed=0, obs_type="state", action_repeat=1)
    raw = raw_dmc_env("quadruped", "walk", seed=0)
    spec = raw.action_spec()
    assert not (np.all(spec.minimum == -1) and np.all(spec.maximum == 1))
    scaled_raw = action_scale.Wrapper(raw, minimum=-1.0, maximum=1.0)
    obs, _ = env.reset()
    np.testing.assert_array_equal(obs, flat_state(scaled_raw.reset().observation))
    rng = np.random.default_rng(0)
    for _ in range(5):
        action = rng.uniform(-1.5, 1.5, size=env.action_space.shape).astype(np.float32)
        obs, reward, *_ = env.step(action)
        timestep = scaled_raw.step(np.clip(action, -1.0, 1.0).astype(np.float64))
        np.testing.assert_allclose(obs, flat_state(timestep.observation), rtol=1e-5, atol=1e-5)
        assert reward == pytest.approx(timestep.reward, abs=1e-6)
    # The simulator receives the bounds for actions at (or beyond) -1 and 1.
    ctrl = env._dmc._env.physics.data.ctrl
    env.step(np.full(env.action_space.shape, 2.0, dtype=np.float32))
    np.testing.assert_array_equal(ctrl, spec.maximum)
    env.step(np.full(env.action_space.shape, -1.0, dtype=np.float32))
    np.testing.assert_array_equal(ctrl, spec.minimum)


def test_discounts_and_termination(make_env) -> None:
    """Rewards are weighted by the product of earlier discounts; an episode end stops the repeat early."""
    env = make_env("walker-walk", seed=0, obs_type="state", action_repeat=4)
    env.reset()
    observation = env._dmc_observation
    outcomes = iter([(False, 0.5), (False, 0.5), (True, 0.0)])

    def fake_step(action):
        terminated, discount = next(outcomes)
        return observation, 1.0, terminated, False, {"timestep.discount": discount}

    env._dmc.step = fake_step
    _, reward, terminated, truncated, info = env.step(np.zeros(6, dtype=np.float32))
    assert reward == 1.0 + 0.5 + 0.25
    assert (terminated, truncated, info) == (True, False, {"frames": 3})


@pytest.mark.parametrize("action_repeat, n_steps", [(2, 500), (3, 334)])
def test_truncation_at_the_time_limit(make_env, action_repeat: int, n_steps: int) -> None:
    env = make_env("walker-walk", seed=0, obs_type="state", action_repeat=action_repeat)
    env.reset()
    action = np.zeros(env.action_space.shape, dtype=np.float32)
    for step in range(1, n_steps + 1):
        obs, reward, terminated, truncated, info = env.step(action)
        assert not terminated
        assert truncated == (step == n_steps), step
    # walker's time limit is 1000 frames; with action_repeat=3 the last agent step stops after 1 frame.
    assert info["frames"] == 1000
    obs, info = env.reset()
    assert info == {"frames": 0}


def test_pixel_episode_through_gymnasium_make() -> None:
    env = gym.make("sb3_collapse/walker-walk-v0", action_repeat=8, size=48)
    try:
        env.reset(seed=0)
        for step in range(1, 126):
            obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
            assert obs.shape == (9, 48, 48)
            assert not terminated
            assert truncated == (step == 125)
        assert info["frames"] == 1000
    finally:
        env.close()


# ---------------------------------------------------------------- true state and state observations


def test_get_state_walker(make_env) -> None:
    env = make_env("walker-walk", seed=0)
    assert env.state_shapes == WALKER_STATE_SHAPES
    assert list(env.state_shapes) == ["orientations", "height", "velocity"]
    with pytest.raises(RuntimeError, match="reset"):
        env.get_state()
    env.reset()
    state = env.get_state()
    assert list(state) == list(WALKER_STATE_SHAPES)
    for name, dim in WALKER_STATE_SHAPES.items():
        assert state[name].shape == (dim,) and state[name].dtype == np.float32
    # Copies: changing them changes nothing.
    state["height"][:] = 123.0
    assert env.get_state()["height"][0] != 123.0
    physics = env._dmc._env.physics
    assert env.get_state()["height"][0] == pytest.approx(physics.torso_height(), rel=1e-6)
    env.step(env.action_space.sample())
    assert env.get_state()["height"][0] == pytest.approx(physics.torso_height(), rel=1e-6)


def test_state_corresponds_to_pixel_observation(make_env) -> None:
    """get_state() of a pixel env equals the state observation of a state env with the same seed and actions."""
    pixel_env = make_env("walker-walk", seed=7)
    state_env = make_env("walker-walk", seed=7, obs_type="state")
    pixel_env.reset()
    state_obs, _ = state_env.reset()
    np.testing.assert_array_equal(np.concatenate(list(pixel_env.get_state().values())), state_obs)
    rng = np.random.default_rng(1)
    for _ in range(5):
        action = rng.uniform(-1, 1, size=6).astype(np.float32)
        pixel_env.step(action)
        state_obs = state_env.step(action)[0]
        np.testing.assert_array_equal(np.concatenate(list(pixel_env.get_state().values())), state_obs)
        np.testing.assert_array_equal(np.concatenate(list(state_env.get_state().values())), state_obs)


def test_state_observations(make_env) -> None:
    env = make_env("walker-walk", seed=0, obs_type="state", frame_stack=5)
    assert env.observation_space == spaces.Box(-np.inf, np.inf, (24,), np.float32)
    assert env.frame_stack == 5  # ignored
    env._dmc.render = lambda: pytest.fail("state observations must not render")
    obs, _ = env.reset()
    assert obs.shape == (24,) and obs.dtype == np.float32
    obs = env.step(env.action_space.sample())[0]
    assert obs.shape == (24,) and obs.dtype == np.float32


def test_state_mode_render_is_fresh(make_env) -> None:
    env = make_env("walker-walk", seed=0, obs_type="state", size=32)
    env.reset()
    frame = env.render()
    assert frame.shape == (32, 32, 3) and frame.dtype == np.uint8


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"obs_type": "rgb"}, "obs_type"),
        ({"action_repeat": 0}, "action_repeat"),
        ({"frame_stack": 0}, "frame_stack"),
        ({"size": 0}, "size"),
        ({"action_repeat": 1.5}, "action_repeat"),
        ({"camera_id": 10}, "camera_id"),
        ({"task": "walker-wlak"}, "walker-wlak"),
    ],
)
def test_invalid_arguments(kwargs: dict, match: str) -> None:
    kwargs = {"task": "walker-walk", "obs_type": "state", **kwargs}
    with pytest.raises(ValueError, match=match):
        make_dmc_env(**kwargs)


def test_step_checks(make_env) -> None:
    env = make_env("walker-walk", obs_type="state")
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.zeros(6, dtype=np.float32))
    env.reset(seed=0)
    with pytest.raises(ValueError, match="shape"):
        env.step(np.zeros(5, dtype=np.float32))


# ---------------------------------------------------------------- seeding, pickling, closing


def test_reset_seed_determinism(make_env) -> None:
    env = make_env("walker-walk")
    first, _ = env.reset(seed=42)
    other, _ = env.reset(seed=43)
    again, _ = env.reset(seed=42)
    np.testing.assert_array_equal(first, again)
    assert not np.array_equal(first, other)
    # Seeding at construction is the same as seeding the first reset.
    seeded_at_construction, _ = make_env("walker-walk", seed=42).reset()
    np.testing.assert_array_equal(first, seeded_at_construction)
    # The action space is seeded too.
    env.reset(seed=5)
    sample = env.action_space.sample()
    env.reset(seed=5)
    np.testing.assert_array_equal(sample, env.action_space.sample())


def test_pickle_round_trip(make_env) -> None:
    env = make_env("finger_turn_easy", seed=1, action_repeat=4, obs_type="state")
    clone = pickle.loads(pickle.dumps(env))
    try:
        assert isinstance(clone, DMCEnv)
        assert (clone.task_id, clone.action_repeat, clone.obs_type) == ("finger-turn_easy", 4, "state")
        np.testing.assert_array_equal(clone.reset()[0], env.reset()[0])
    finally:
        clone.close()


def test_close_twice(make_env) -> None:
    env = make_dmc_env("walker-walk", obs_type="state")
    env.reset()
    env.close()
    env.close()


# ---------------------------------------------------------------- API checkers and vectorized envs


def test_gymnasium_check_env() -> None:
    env = gym.make("sb3_collapse/walker-walk-v0")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            gym_check_env(env.unwrapped)
    finally:
        env.close()


def test_gymnasium_check_env_state() -> None:
    env = gym.make("sb3_collapse/cartpole-swingup-v0", obs_type="state")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            # Unbounded state observations are intended.
            warnings.filterwarnings("ignore", message=".*observation space (minimum|maximum) value is")
            gym_check_env(env.unwrapped)
    finally:
        env.close()


@pytest.mark.parametrize("obs_type", ["pixels", "state"])
def test_sb3_check_env(make_env, obs_type: str) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        sb3_check_env(make_env("walker-walk", seed=0, obs_type=obs_type))


def test_dummy_vec_env() -> None:
    vec_env = make_vec_env("sb3_collapse/walker-walk-v0", n_envs=2, seed=0, vec_env_cls=DummyVecEnv)
    try:
        obs = vec_env.reset()
        assert obs.shape == (2, 9, 84, 84) and obs.dtype == np.uint8
        assert not np.array_equal(obs[0], obs[1])  # seeds 0 and 1
        for _ in range(3):
            obs, _, _, infos = vec_env.step(np.stack([vec_env.action_space.sample() for _ in range(2)]))
        assert obs.shape == (2, 9, 84, 84)
        assert [info["frames"] for info in infos] == [6, 6]
        states = vec_env.env_method("get_state")
        assert [{k: v.shape for k, v in s.items()} for s in states] == [
            {"orientations": (14,), "height": (1,), "velocity": (9,)}
        ] * 2
    finally:
        vec_env.close()


def test_subproc_vec_env_default_start_method() -> None:
    """The plain registered id works in forkserver workers (the forkserver preloads sb3_collapse.envs)."""
    vec_env = make_vec_env("sb3_collapse/walker-walk-v0", n_envs=2, seed=0, vec_env_cls=SubprocVecEnv)
    try:
        obs = vec_env.reset()
        assert obs.shape == (2, 9, 84, 84) and obs.dtype == np.uint8
        for _ in range(3):
            obs, _, _, infos = vec_env.step(np.stack([vec_env.action_space.sample() for _ in range(2)]))
        assert [info["frames"] for info in infos] == [6, 6]
        states = vec_env.env_method("get_state")
        assert [list(s) for s in states] == [list(WALKER_STATE_SHAPES)] * 2
        assert vec_env.get_attr("task_id") == ["walker-walk"] * 2
    finally:
        vec_env.close()


def test_subproc_vec_env_spawn_with_module_prefix() -> None:
    """With "spawn", workers import nothing by themselves: "module:id" makes gymnasium import the registering module."""
    vec_env = make_vec_env(
        "sb3_collapse.envs:sb3_collapse/cheetah-run-v0",
        n_envs=2,
        seed=0,
        vec_env_cls=SubprocVecEnv,
        vec_env_kwargs={"start_method": "spawn"},
        env_kwargs={"obs_type": "state"},
    )
    try:
        obs = vec_env.reset()
        assert obs.shape == (2, 17)
        obs, *_ = vec_env.step(np.stack([vec_env.action_space.sample() for _ in range(2)]))
        assert obs.shape == (2, 17)
    finally:
        vec_env.close()


def test_subproc_vec_env_with_callables() -> None:
    vec_env = SubprocVecEnv([lambda rank=rank: make_dmc_env("walker-walk", seed=rank, size=32) for rank in range(2)])
    try:
        assert vec_env.reset().shape == (2, 9, 32, 32)
    finally:
        vec_env.close()


# ---------------------------------------------------------------- reward inputs (the paper's Figure 2 columns)


def _tol(x, **kwargs) -> float:
    return float(np.asarray(dm_rewards.tolerance(np.asarray(x, dtype=np.float64), **kwargs)).reshape(-1)[0])


# Each task's reward, rebuilt from the recorded reward inputs alone (the formulas of dm_control's get_reward), and
# what its Physics methods give at the same state. A reward input the reward does not read, or a wrong one, makes
# the rebuilt reward differ from get_reward's.
INF = float("inf")
REWARD_FROM_INPUTS = {
    "walker-walk": lambda r, p: (3 * _tol(r["torso_height"], bounds=(1.2, INF), margin=0.6)
                                 + (1 + r["torso_upright"][0]) / 2) / 4
    * (5 * _tol(r["horizontal_velocity"], bounds=(1, INF), margin=0.5, value_at_margin=0.5, sigmoid="linear") + 1) / 6,
    "hopper-hop": lambda r, p: _tol(r["height"], bounds=(0.6, 2))
    * _tol(r["speed"], bounds=(2, INF), margin=1, value_at_margin=0.5, sigmoid="linear"),
    "cheetah-run": lambda r, p: _tol(r["speed"], bounds=(10, INF), margin=10, value_at_margin=0, sigmoid="linear"),
    "cartpole-balance_sparse": lambda r, p: _tol(r["cart_position"], bounds=(-0.25, 0.25))
    * _tol(r["pole_angle_cosine"], bounds=(0.995, 1)),
    "finger-spin": lambda r, p: float(r["hinge_velocity"][0] <= -15),
    "finger-turn_easy": lambda r, p: float(r["dist_to_target"][0] <= 0),
    "reacher-easy": lambda r, p: _tol(
        r["finger_to_target_dist"], bounds=(0, p.named.model.geom_size[["target", "finger"], 0].sum())
    ),
    "ball_in_cup-catch": lambda r, p: float(
        all(abs(r["ball_to_target"]) < p.named.model.site_size["target", [0, 2]] - p.named.model.geom_size["ball", 0])
    ),
    "quadruped-walk": lambda r, p: _tol(r["torso_upright"], bounds=(1, INF), sigmoid="linear", margin=2,
                                        value_at_margin=0)
    * _tol(r["torso_velocity_x"], bounds=(0.5, INF), margin=0.5, value_at_margin=0.5, sigmoid="linear"),
    "acrobot-swingup": lambda r, p: _tol(r["to_target"], bounds=(0, p.named.model.site_size["target", 0]), margin=1),
    "pendulum-swingup": lambda r, p: _tol(r["pole_vertical"], bounds=(np.cos(np.deg2rad(8)), 1)),
}
PHYSICS_VALUES = {
    "walker": lambda p: {
        "torso_height": p.torso_height(), "torso_upright": p.torso_upright(),
        "horizontal_velocity": p.horizontal_velocity(),
    },
    "hopper": lambda p: {"height": p.height(), "speed": p.speed()},
    "cheetah": lambda p: {"speed": p.speed()},
    "cartpole": lambda p: {
        "cart_position": p.cart_position(), "pole_angle_cosine": p.pole_angle_cosine(), "angular_vel": p.angular_vel()
    },
    "finger-spin": lambda p: {"hinge_velocity": p.hinge_velocity()},
    "finger": lambda p: {"dist_to_target": p.dist_to_target()},
    "reacher": lambda p: {"finger_to_target_dist": p.finger_to_target_dist()},
    "ball_in_cup": lambda p: {"ball_to_target": p.ball_to_target()},
    "quadruped": lambda p: {"torso_upright": p.torso_upright(), "torso_velocity_x": p.torso_velocity()[0]},
    "acrobot": lambda p: {"to_target": p.to_target()},
    "pendulum": lambda p: {"pole_vertical": p.pole_vertical()},
    "humanoid": lambda p: {
        "head_height": p.head_height(), "torso_upright": p.torso_upright(),
        "com_velocity_x": p.center_of_mass_velocity()[0], "com_velocity_y": p.center_of_mass_velocity()[1],
    },
}  # fmt: skip


@pytest.mark.parametrize("task", [*REWARD_FROM_INPUTS, "humanoid-walk"])
def test_reward_inputs_are_what_the_reward_reads(make_env, task: str) -> None:
    """At every step: the reward inputs equal the task's Physics methods at that state, and (but for humanoid, whose
    reward also reads the control) dm_control's get_reward equals the reward rebuilt from them alone."""
    env = make_env(task, seed=3, obs_type="state", action_repeat=1)
    domain, name = parse_task(task)
    expected_of = PHYSICS_VALUES.get(f"{domain}-{name}", PHYSICS_VALUES.get(domain))
    env.reset(seed=3)
    rng = np.random.default_rng(0)
    for _ in range(12):
        inputs = env.reward_inputs()
        physics = env.physics
        expected = {key: np.asarray(value, dtype=np.float32).reshape(-1) for key, value in expected_of(physics).items()}
        assert list(inputs) == list(expected)
        for key in inputs:
            assert inputs[key].dtype == np.float32
            np.testing.assert_array_equal(inputs[key], expected[key])
        if task in REWARD_FROM_INPUTS:
            inputs64 = {item.name: item.value(physics) for item in reward_inputs_of(domain, name)}  # float64
            assert REWARD_FROM_INPUTS[task](inputs64, physics) == pytest.approx(
                float(env._dmc._env.task.get_reward(physics)), abs=1e-9
            )
        env.step(rng.uniform(-1, 1, env.action_space.shape).astype(np.float32))


def test_reward_inputs_cover_the_preset_tasks() -> None:
    from sb3_collapse.presets import PRESETS

    domains = {parse_task(task)[0] for task in PRESETS}
    assert domains <= {key.split("-")[0] for key in REWARD_INPUTS}
    assert REWARD_INPUTS["finger-spin"] != REWARD_INPUTS["finger"]
