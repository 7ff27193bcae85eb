"""Probe checkpoints (encoder and actor only) from a real tiny training run, read by the probe like full ones."""

import numpy as np
import pytest
import torch as th

from sb3_collapse import DrQv2
from sb3_collapse.drqv2.probe_checkpoint import is_probe_checkpoint, load_probe_checkpoint, save_probe_checkpoint
from sb3_collapse.errors import ParameterError
from sb3_collapse.probe.__main__ import main as probe_main
from sb3_collapse.probe.checkpoints import load_checkpoint
from sb3_collapse.protocol import PROBE_CHECKPOINT, PROBE_CHECKPOINTS_DIR
from sb3_collapse.train import TrainConfig, train


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """800 frames (40 agent steps at action repeat 20: short evaluation episodes) at 48x48, evaluated every 400."""
    config = TrainConfig(
        env="walker-walk", frames=800, action_repeat=20, seed_frames=400, batch_size=16, hidden_dim=64, size=48,
        eval_every_frames=400, eval_episodes=1, logdir=str(tmp_path_factory.mktemp("probe_ckpt")), progress_bar=False,
        replay_sampling="sb3", collapse_metrics_every_frames=0, probe_checkpoints=True, torch_threads=1,
    )  # fmt: skip
    return train(config)


def test_one_probe_checkpoint_per_evaluation(run):
    folder = run.run_dir / PROBE_CHECKPOINTS_DIR
    names = sorted(p.name for p in folder.iterdir())
    assert names == [PROBE_CHECKPOINT.format(frames=f) for f in (0, 400, 800)] == [
        "probe_0000000000_frames.zip",
        "probe_0000000400_frames.zip",
        "probe_0000000800_frames.zip",
    ]
    assert [int(e["frame"]) for e in run.evaluations] == [0, 400, 800]
    final_size = run.model_path.stat().st_size
    for path in folder.iterdir():
        assert is_probe_checkpoint(path) and path.stat().st_size < final_size / 2
    assert not is_probe_checkpoint(run.model_path)


def test_probe_checkpoint_holds_the_final_encoder_and_actor(run):
    final = DrQv2.load(run.model_path, buffer_size=64)
    checkpoint = load_checkpoint(run.run_dir / PROBE_CHECKPOINTS_DIR / PROBE_CHECKPOINT.format(frames=800))
    assert checkpoint.algorithm == "DrQv2" and checkpoint.num_timesteps == 40 and checkpoint.frames == 800
    assert checkpoint.env_config == final.env_config
    saved, reference = checkpoint.model.policy.state_dict(), final.policy.state_dict()
    compared = [k for k in reference if k.startswith(("encoder.", "actor."))]
    assert len(compared) > 10
    for key in compared:
        assert th.equal(saved[key], reference[key]), key
    assert not th.equal(saved["critic.q1.0.weight"], reference["critic.q1.0.weight"])  # the critic is not saved
    observation = np.random.default_rng(0).integers(0, 256, size=(2, *final.observation_space.shape), dtype=np.uint8)
    np.testing.assert_array_equal(
        checkpoint.model.predict(observation, deterministic=True)[0], final.predict(observation, deterministic=True)[0]
    )
    # the earliest one differs from the final weights
    first = load_probe_checkpoint(run.run_dir / PROBE_CHECKPOINTS_DIR / PROBE_CHECKPOINT.format(frames=0))
    assert first.num_timesteps == 0
    assert not th.equal(first.policy.state_dict()["actor.mlp1.0.weight"], reference["actor.mlp1.0.weight"])


def test_probe_reads_probe_checkpoints_over_training(run, tmp_path):
    rollouts = tmp_path / "rollouts.npz"
    record = ["record", str(run.model_path), "--episodes", "5", "--max-steps", "4", "--out", str(rollouts)]
    assert probe_main([*record, "--no-progress"]) == 0
    checkpoints = sorted((run.run_dir / PROBE_CHECKPOINTS_DIR).glob("*.zip"))
    out = tmp_path / "probe"
    argv = [*map(str, checkpoints), "--rollouts", str(rollouts), "--out", str(out), "--max-tau", "4"]
    assert probe_main([*argv, "--layers", "cnn4", "mlp1", "--no-progress"]) == 0
    assert (out / "mse_over_training.png").exists() and (out / "probe.csv").exists()


def test_probe_checkpoints_need_drqv2_and_evaluations(tmp_path):
    with pytest.raises(ParameterError, match="probe_checkpoints"):
        train(TrainConfig(env="walker-walk", frames=80, eval_every_frames=0, probe_checkpoints=True, logdir=str(tmp_path)))
    with pytest.raises(TypeError, match="DrQv2 model"):
        save_probe_checkpoint(type("NotDrQ", (), {"policy": th.nn.Linear(2, 2)})(), tmp_path / "x.zip")
    assert not list(tmp_path.iterdir())
