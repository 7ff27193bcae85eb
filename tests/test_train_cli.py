import csv
import json
import subprocess
import sys

import numpy as np
import pytest
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from sb3_collapse import DrQv2
from sb3_collapse.train import TrainConfig, main, train


def test_train_end_to_end(tmp_path):
    config = TrainConfig(
        env="walker-walk", frames=800, action_repeat=8, seed_frames=400, batch_size=8, hidden_dim=64,
        eval_every_frames=400, eval_episodes=1, logdir=str(tmp_path), progress_bar=False,
    )
    result = train(config)
    assert result.run_dir == tmp_path / "walker-walk_s0"
    with open(result.run_dir / "eval.csv") as file:
        rows = list(csv.DictReader(file))
    assert [int(row["frame"]) for row in rows] == [0, 400, 800]
    assert [int(row["step"]) for row in rows] == [0, 50, 100]
    assert all(np.isfinite(float(row["mean_reward"])) for row in rows)
    assert json.loads((result.run_dir / "config.json").read_text())["frames"] == 800

    model = DrQv2.load(result.model_path)
    assert model.num_timesteps == 100 and model.num_frames == 800
    assert model.env_config["task_id"] == "walker-walk" and model.env_config["action_repeat"] == 8
    assert model.learning_starts == 50 and model._n_updates == 25

    events = list(result.run_dir.glob("events.out.tfevents.*"))
    accumulator = EventAccumulator(str(events[0]))
    accumulator.Reload()
    assert [e.step for e in accumulator.Scalars("eval/mean_reward")] == [0, 50, 100]

    # A second run with the same name gets its own folder.
    second = train(TrainConfig(**{**config.__dict__, "frames": 80, "eval_every_frames": 0}))
    assert second.run_dir == tmp_path / "walker-walk_s0_2"
    assert second.evaluations == []


def test_train_with_collapse_metrics_and_reset_rule(tmp_path):
    config = TrainConfig(
        env="walker-walk", frames=800, action_repeat=8, seed_frames=160, batch_size=8, hidden_dim=32,
        eval_every_frames=0, logdir=str(tmp_path), progress_bar=False, collapse_metrics_every_frames=400,
        collapse_probe_batch=16, reset_rule=True, reset_window_frames=400,
    )
    result = train(config)
    accumulator = EventAccumulator(str(next(result.run_dir.glob("events.out.tfevents.*"))))
    accumulator.Reload()
    tags = set(accumulator.Tags()["scalars"])
    assert {"collapse/mlp1/numerical_rank", "collapse/mlp1/grad_norm", "collapse/action_std"} <= tags
    # One check per window of 400 frames: 5 healthy checks in a row cannot happen before the window ends.
    assert [e.value for e in accumulator.Scalars("collapse/resets")][-1] >= 1


def test_help_documents_units():
    out = subprocess.run([sys.executable, "-m", "sb3_collapse.train", "--help"], capture_output=True, text=True, check=True).stdout
    for flag in ("--frames", "--eval-every-frames", "--seed-frames", "--stddev-schedule", "--buffer-size", "--logdir"):
        assert flag in out
    assert "in frames" in out and "agent steps" in out


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--env", "walker-wlak"], "walker-walk"),
        (["--frames", "0"], "--frames must be >= 1"),
        (["--stddev-schedule", "linear(1,0.1)"], "stddev schedule"),
        (["--eval-episodes", "0"], "--eval-episodes must be >= 1"),
    ],
)
def test_bad_arguments_exit_with_a_message(argv, message, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 2
    assert message in capsys.readouterr().err
