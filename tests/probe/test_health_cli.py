"""``python -m sb3_collapse.probe health``: the network health of saved DrQv2 and SB3 TD3 models (CNN and MLP policies),
one checkpoint or a time series over snapshots, all outputs or none."""

import csv
import json
import math

import gymnasium as gym
import numpy as np
import pytest
from stable_baselines3 import PPO, TD3

from sb3_collapse import DrQv2, make_dmc_env
from sb3_collapse.commands.probe import main
from sb3_collapse.errors import ParameterError
from sb3_collapse.probe.health import HEALTH_COLUMNS, OFFLINE_METRICS, SERIES_METRICS, HealthSettings, tag_parts
from sb3_collapse.run.snapshots import save_snapshot
from tests.random_env import RandomObservationEnv

QUICK = ["--no-progress", "--episodes", "1"]


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("health")
    env = make_dmc_env("walker-walk", seed=0, action_repeat=8, size=32)
    drqv2 = DrQv2("CnnPolicy", env, buffer_size=10, policy_kwargs={"hidden_dim": 32}, seed=0, device="cpu")
    drqv2.save(folder / "drqv2.zip")
    for steps in (100, 300):  # two snapshots of a run, the weights moved in between
        drqv2.num_timesteps = steps
        for parameter in drqv2.policy.parameters():
            parameter.data.add_(0.01)
        save_snapshot(drqv2, folder / "run" / "snapshots" / f"snapshot_{steps * 8:010d}_frames.zip")
    env.close()
    rollouts = folder / "walker.npz"
    assert main(["record", str(folder / "drqv2.zip"), "--max-steps", "6", "--out", str(rollouts), *QUICK]) == 0
    pixels = RandomObservationEnv(gym.spaces.Box(0, 255, (9, 40, 40), np.uint8))  # NatureCNN takes 36x36 and more
    TD3("CnnPolicy", pixels, buffer_size=10, policy_kwargs={"net_arch": [16, 16]}, seed=0, device="cpu").save(
        folder / "td3_cnn.zip"
    )
    mlp = TD3("MlpPolicy", "Pendulum-v1", buffer_size=100, learning_starts=10, policy_kwargs={"net_arch": [16, 16]})
    mlp.save(folder / "td3_mlp_0.zip")
    mlp.learn(30)  # 20 updates: the weights change
    mlp.save(folder / "td3_mlp_30.zip")
    PPO("MlpPolicy", "Pendulum-v1", n_steps=8, batch_size=8).save(folder / "ppo.zip")
    return folder


def read_rows(out):
    with (out / "health.csv").open() as file:
        reader = csv.DictReader(file)
        assert tuple(reader.fieldnames) == HEALTH_COLUMNS
        return list(reader)


def assert_nothing_written(out, capsys):
    """A refused command exits 2 with one line and leaves neither outputs nor the folder it would have created."""
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: "), err
    assert not out.exists(), sorted(p.name for p in out.rglob("*"))
    return err[0]


@pytest.mark.parametrize(
    ("checkpoint", "record"),
    [
        ("drqv2.zip", ["--max-steps", "6"]),
        ("td3_cnn.zip", ["--env", "walker-walk", "--size", "40", "--max-steps", "5"]),
    ],
)
def test_a_cnn_checkpoint_on_its_own_rollouts(files, tmp_path, checkpoint, record):
    out = tmp_path / "health"
    assert main(["health", str(files / checkpoint), *record, "--out", str(out), *QUICK]) == 0
    names = {"health.csv", "health.json", "health_actor.png", "health_critic.png"}
    assert {path.name for path in out.iterdir()} == names  # a PNG per network, no staging folder left
    assert all((out / name).stat().st_size > 10_000 for name in names if name.endswith(".png"))
    rows = read_rows(out)
    layers = {(row["network"], row["layer"]) for row in rows}
    assert {("actor", "mlp2"), ("actor", "action"), ("critic", "q1.mlp1"), ("critic", "q2"), ("critic", "q1")} <= layers
    assert {("actor", "cnn1")} <= layers  # the encoder's layers, read through the actor
    metrics = {row["metric"] for row in rows}
    assert {"numerical_rank", "dormant_ratio_tau0.1", "stable_rank", "q_mean", "action_std"} <= metrics
    assert not metrics & {*SERIES_METRICS, "grad_norm"}  # one checkpoint: no previous one; no update offline
    q_std = [float(row["value"]) for row in rows if row["metric"] == "q_std"]
    assert len(q_std) == 2 and all(value >= 0 for value in q_std)
    summary = json.loads((out / "health.json").read_text())
    assert summary["complete"] and not summary["series"] and summary["networks"] == ["actor", "critic"]
    assert "own rollouts in walker-walk" in summary["inputs"]


def test_an_mlp_policy_over_two_checkpoints_is_a_time_series(files, tmp_path):
    out = tmp_path / "health"
    late, early = files / "td3_mlp_30.zip", files / "td3_mlp_0.zip"  # given out of order
    argv = ["health", str(late), str(early), "--env", "Pendulum-v1", "--max-steps", "40", "--out", str(out)]
    assert main([*argv, *QUICK]) == 0
    rows = read_rows(out)
    assert rows[0]["checkpoint"] == "td3_mlp_0"  # measured in training order
    change = {
        r["checkpoint"]: float(r["value"]) for r in rows if r["layer"] == "mlp1" and r["metric"] == "weight_change"
    }
    assert change["td3_mlp_0"] == 0.0 and change["td3_mlp_30"] > 0  # from the first checkpoint's weights
    persistent = {r["checkpoint"]: float(r["value"]) for r in rows if r["metric"] == "persistent_dormant_fraction"}
    assert math.isnan(persistent["td3_mlp_0"]) and 0 <= persistent["td3_mlp_30"] <= 1
    assert {row["metric"] for row in rows} == set(OFFLINE_METRICS) - {"dormant_ratios"} | {
        f"dormant_ratio_tau{tau:g}" for tau in (0, 0.025, 0.1)
    }
    summary = json.loads((out / "health.json").read_text())
    assert summary["series"] and "all 40 observations of td3_mlp_0's own rollouts in Pendulum-v1" in summary["inputs"]


def test_a_run_folder_is_its_snapshots_actor_only(files, tmp_path, capsys):
    out = tmp_path / "health"
    argv = ["health", str(files / "run"), "--rollouts", str(files / "walker.npz"), *QUICK]
    assert main([*argv, "--out", str(out)]) == 0
    assert "measuring the actor only" in capsys.readouterr().out  # a snapshot holds no critic: said, not silent
    assert {path.name for path in out.iterdir()} == {"health.csv", "health.json", "health_actor.png"}
    rows = read_rows(out)
    assert {row["frames"] for row in rows} == {"800", "2400"} and {row["network"] for row in rows} == {"actor"}
    change = [float(r["value"]) for r in rows if r["layer"] == "mlp1" and r["metric"] == "weight_change"]
    assert change[0] == 0.0 and change[1] > 0
    # the critic asked of a snapshot is refused in one line, nothing written
    other = tmp_path / "other"
    assert main([*argv, "--out", str(other), "--networks", "critic"]) == 2
    assert "is a snapshot (encoder and actor, no critic)" in assert_nothing_written(other, capsys)


def test_refusals_say_what_to_do_in_one_line_and_write_nothing(files, tmp_path, capsys):
    out = tmp_path / "health"
    rollouts = ["--rollouts", str(files / "walker.npz")]
    ppo = ["health", str(files / "ppo.zip"), "--out", str(out), *QUICK]
    assert main(ppo) == 2  # another algorithm: one line that says which are supported
    refusal = assert_nothing_written(out, capsys)
    assert all(name in refusal for name in ("ppo.zip", "DrQv2", "TD3", "DDPG", "SAC")), refusal
    cases = {
        "compare each checkpoint with the one before": [
            str(files / "drqv2.zip"),
            *rollouts,
            "--metrics",
            "weight_change",
        ],
        # found once the checkpoint is loaded (after the staging folder was made): still nothing written
        "holds observations of shape (9, 32, 32) but": [str(files / "td3_cnn.zip"), *rollouts],
        "neither a DeepMind Control task nor a gymnasium id": [str(files / "td3_mlp_0.zip"), "--env", "NoSuchEnv-v0"],
        "gives observations of shape (3,)": [str(files / "td3_cnn.zip"), "--env", "Pendulum-v1"],
    }
    for message, args in cases.items():
        assert main(["health", *args, "--out", str(out), *QUICK]) == 2, message
        assert message in assert_nothing_written(out, capsys), message
    with pytest.raises(SystemExit) as exited:  # refused by the parser: the gradient norm is a training-time value
        main(["health", str(files / "drqv2.zip"), "--metrics", "grad_norm", "--out", str(out)])
    assert exited.value.code == 2 and "invalid choice: 'grad_norm'" in capsys.readouterr().err and not out.exists()


@pytest.mark.parametrize(
    ("settings", "parameter"),
    [
        ({"metrics": ("grad_norm",)}, "metrics"),  # a training-time value
        ({"networks": ()}, "networks"),
        ({"networks": ("value",)}, "networks"),
        ({"samples": 1}, "samples"),
        ({"device": "tpu"}, "device"),
    ],
)
def test_the_library_names_the_bad_setting(settings, parameter):
    with pytest.raises(ParameterError) as raised:
        HealthSettings(**settings).validate()
    assert raised.value.parameter == parameter


def test_tags_split_into_network_layer_and_metric():
    assert tag_parts("collapse/q1.mlp1/srank") == ("critic", "q1.mlp1", "srank")
    assert tag_parts("collapse/q2/q_mean") == ("critic", "q2", "q_mean")
    assert tag_parts("collapse/mlp1/dormant_ratio_tau0.1") == ("actor", "mlp1", "dormant_ratio_tau0.1")
    assert tag_parts("collapse/action_std") == ("actor", "action", "action_std")
