import json

import numpy as np
import pytest

from sb3_collapse import DrQv2, make_dmc_env
from sb3_collapse.errors import InputError
from sb3_collapse.probe import Rollouts, record_rollouts
from sb3_collapse.probe.rollouts import pool_rollouts, resolve_env_config

ENV = {"action_repeat": 8, "frame_stack": 3, "size": 32}


@pytest.fixture(scope="module")
def model():
    env = make_dmc_env("walker-walk", seed=0, **ENV)
    return DrQv2("CnnPolicy", env, buffer_size=10, policy_kwargs={"hidden_dim": 32}, seed=0, device="cpu")


@pytest.fixture(scope="module")
def rollouts(model):
    config = resolve_env_config(model.env_config)
    return record_rollouts(model, config, episodes=3, seed=5, max_steps=4, progress=False)


def test_recorded_arrays_and_walker_targets(rollouts):
    assert len(rollouts) == 12 and rollouts.n_episodes == 3
    assert rollouts.observations.shape == (12, 9, 32, 32) and rollouts.observations.dtype == np.uint8
    assert rollouts.episode_ids.tolist() == [0] * 4 + [1] * 4 + [2] * 4
    assert rollouts.steps.tolist() == [0, 1, 2, 3] * 3
    assert {k: v.shape for k, v in rollouts.states.items()} == {
        "orientations": (12, 14),
        "height": (12, 1),
        "velocity": (12, 9),
    }
    assert rollouts.env_config == {"task_id": "walker-walk", "camera_id": 0, **ENV}
    assert rollouts.actions.shape == (12, 6) and np.abs(rollouts.actions).max() <= 1
    assert {k: v.shape for k, v in rollouts.reward_inputs.items()} == {
        "torso_height": (12, 1),
        "torso_upright": (12, 1),
        "horizontal_velocity": (12, 1),
    }
    names, groups, values = rollouts.targets()
    assert names[:2] == ["orientations_0", "orientations_1"] and names[14] == "height" and names[23] == "velocity_8"
    assert names[24:] == ["reward:torso_height", "reward:torso_upright", "reward:horizontal_velocity"]
    assert groups[24:] == names[24:]
    assert len(names) == 27 and groups.count("velocity") == 9 and values.shape == (12, 27)
    # walker's observed height is the torso height its reward reads
    np.testing.assert_array_equal(values[:, 14], values[:, 24])


def test_rollouts_of_several_agents_are_pooled(model, rollouts):
    # Section 4.1: "All the samples in three sets are collected from well-performing agents".
    config = resolve_env_config(model.env_config)
    other = record_rollouts(model, config, episodes=2, seed=6, max_steps=3, progress=False)
    pooled = pool_rollouts([rollouts, other])
    assert len(pooled) == 12 + 6 and pooled.n_episodes == 5
    assert pooled.episode_ids.tolist() == [0] * 4 + [1] * 4 + [2] * 4 + [3] * 3 + [4] * 3  # never one mixed episode
    np.testing.assert_array_equal(pooled.observations[12:], other.observations)
    for name in rollouts.states:
        np.testing.assert_array_equal(pooled.states[name], np.concatenate([rollouts.states[name], other.states[name]]))
    assert pooled.reward_inputs.keys() == rollouts.reward_inputs.keys() and pooled.env_config == rollouts.env_config
    assert pooled.metadata["agents"] == 2 and [m["seed"] for m in pooled.metadata["pooled"]] == [5, 6]
    moved = Rollouts(**{**vars(other), "env_config": {**other.env_config, "size": 64}})
    with pytest.raises(InputError, match="pooled rollouts must share their env settings"):
        pool_rollouts([rollouts, moved])


def test_state_is_the_one_behind_each_observation(model, rollouts):
    """Replay the recorded actions in a fresh env: same observations, same states at the same steps."""
    env = make_dmc_env("walker-walk", seed=5, **ENV)
    obs, _ = env.reset(seed=5)
    for t in range(4):
        np.testing.assert_array_equal(obs, rollouts.observations[t])
        state = np.concatenate([*env.get_state().values(), *env.reward_inputs().values()])
        np.testing.assert_allclose(state, rollouts.targets()[2][t], rtol=1e-6)
        physics = env.physics  # the reward inputs are the reward function's Physics methods at that state
        expected = [physics.torso_height(), physics.torso_upright(), physics.horizontal_velocity()]
        np.testing.assert_array_equal(rollouts.targets()[2][t, 24:], np.float32(expected))
        obs, reward, *_ = env.step(rollouts.actions[t])
        assert reward == pytest.approx(rollouts.rewards[t])
    env.close()


def test_save_load_roundtrip_and_bad_files(rollouts, tmp_path):
    path = rollouts.save(tmp_path / "walker.npz")
    assert path.exists() and not (tmp_path / "walker.npz.partial").exists()
    loaded = Rollouts.load(path)
    np.testing.assert_array_equal(loaded.observations, rollouts.observations)
    assert list(loaded.states) == list(rollouts.states) and loaded.env_config == rollouts.env_config
    assert loaded.metadata["deterministic"] is True and loaded.metadata["max_steps"] == 4
    assert list(loaded.reward_inputs) == list(rollouts.reward_inputs)
    for name, value in rollouts.reward_inputs.items():
        np.testing.assert_array_equal(loaded.reward_inputs[name], value)
    # a file of another format is refused in one line
    with np.load(path) as data:
        arrays = {key: data[key] for key in data.files}
    meta = json.loads(str(arrays["meta"]))
    meta["format_version"] = 1
    arrays["meta"] = np.array(json.dumps(meta))
    np.savez_compressed(tmp_path / "old.npz", **arrays)
    with pytest.raises(
        InputError, match=r"not a rollouts file this version .* reads \(ValueError: format 1, not 2\)"
    ) as error:
        Rollouts.load(tmp_path / "old.npz")
    assert "\n" not in str(error.value)
    # a recorded quantity that the task's reward does not read is no reward input: walker-stand reads no velocity
    with np.load(path) as data:
        arrays = {key: data[key] for key in data.files}
    meta = json.loads(str(arrays["meta"]))
    meta["env_config"]["task_id"] = "walker-stand"
    arrays["meta"] = np.array(json.dumps(meta))
    np.savez_compressed(tmp_path / "stand.npz", **arrays)
    stand = Rollouts.load(tmp_path / "stand.npz")
    assert list(stand.reward_inputs) == ["torso_height", "torso_upright"]
    assert stand.targets()[0][24:] == ["reward:torso_height", "reward:torso_upright"]
    with pytest.raises(InputError, match="does not exist"):
        Rollouts.load(tmp_path / "missing.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a numpy file")
    with pytest.raises(InputError, match="not a rollouts file"):
        Rollouts.load(tmp_path / "junk.npz")


def test_noise_and_env_settings(model):
    with pytest.raises(InputError, match="pass `env`"):
        resolve_env_config(None)
    config = resolve_env_config(None, task_id="walker-walk", size=40)
    assert config == {"task_id": "walker-walk", "action_repeat": 2, "frame_stack": 3, "size": 40, "camera_id": None}
    with pytest.raises(InputError, match="`size` and `frame_stack` the model was trained with"):
        record_rollouts(model, config, episodes=1, max_steps=1, progress=False)
    config = resolve_env_config(model.env_config)
    noisy = record_rollouts(model, config, episodes=1, seed=5, noise_std=0.5, max_steps=3, progress=False)
    clean = record_rollouts(model, config, episodes=1, seed=5, max_steps=3, progress=False)
    assert not np.allclose(noisy.actions, clean.actions)


def test_figure2_columns_are_the_reward_inputs_then_the_state_groups(rollouts):
    from sb3_collapse.report.figure2 import figure2_columns

    names, groups, _ = rollouts.targets()
    columns = dict(figure2_columns("walker-walk", names, groups))
    assert list(columns) == [
        "torso velocity", "orientation (torso upright)", "torso height", "root velocities (state)",
        "leg orientations (state)",
    ]  # fmt: skip
    assert columns["orientation (torso upright)"] == ("reward:torso_upright",)
    assert columns["torso velocity"] == ("reward:horizontal_velocity",)
    # rollouts without reward inputs keep the state columns only
    assert list(dict(figure2_columns("walker-walk", names[:24], groups[:24]))) == [
        "root velocities (state)", "leg orientations (state)"
    ]  # fmt: skip
    # hopper-stand's reward reads no speed: its rollouts hold no reward:speed, and Figure 2 has no torso velocity
    hopper = ["position_0", "velocity_0", "velocity_1", "velocity_2", "reward:height"]
    assert [title for title, _ in figure2_columns("hopper-stand", hopper, [n.split("_")[0] for n in hopper])] == [
        "torso height", "root velocities (state)", "rootz (state)"
    ]  # fmt: skip
    # another domain: one column per reward input first, then one per state component
    generic = figure2_columns(
        "cheetah-run", ["position_0", "velocity_0", "reward:speed"], ["position", "velocity", "reward:speed"]
    )
    assert generic == [
        ("reward:speed", ("reward:speed",)),
        ("position", ("position_0",)),
        ("velocity", ("velocity_0",)),
    ]
