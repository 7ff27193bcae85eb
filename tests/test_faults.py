"""
Faults around a run's end and its folder: a full disk at the final save, a read-only folder, a diverging run.
"""

from __future__ import annotations

import errno
import json
import math
import warnings
from pathlib import Path

import pytest
import torch as th
from stable_baselines3.common.save_util import load_from_zip_file

from sb3_collapse import DrQv2
from sb3_collapse.drqv2.divergence import DivergenceError, DivergenceGuard, all_finite
from sb3_collapse.errors import report_unwritable_outputs, unwritable_message
from sb3_collapse.protocol import (
    CHECKPOINT_MODEL,
    CHECKPOINTS_DIR,
    CONFIG_JSON,
    FINAL_MODEL,
    RESULT_JSON,
    atomic_output,
)
from sb3_collapse.run.checkpoints import checkpoint_folders
from sb3_collapse.sweep.__main__ import main as sweep_main
from sb3_collapse.train import main


def _flags(run_dir: Path, frames: int = 800) -> list[str]:
    return [
        "--env", "cartpole-balance", "--frames", str(frames), "--action-repeat", "20", "--size", "36",
        "--hidden-dim", "16",
        "--feature-dim", "8", "--batch-size", "8", "--seed-frames", "200", "--eval-every-frames", "0",
        "--checkpoint-every-frames", "200", "--collapse-metrics-every-frames", "0", "--no-progress-bar",
        "--replay-sampling", "sb3", "--torch-threads", "1", "--run-dir", str(run_dir),
    ]  # fmt: skip


@pytest.fixture(autouse=True)
def _keep_torch_threads():
    threads = th.get_num_threads()
    yield
    th.set_num_threads(threads)


def test_atomic_output_leaves_nothing_under_the_final_name_after_an_error(tmp_path):
    target = tmp_path / "final_model.zip"
    target.write_text("previous")
    with pytest.raises(OSError, match="No space"), atomic_output(target) as temporary:
        assert temporary.suffix == ".zip" and temporary.parent == tmp_path
        temporary.write_text("half")
        raise OSError(errno.ENOSPC, "No space left on device")
    assert target.read_text() == "previous" and [p.name for p in tmp_path.iterdir()] == ["final_model.zip"]
    with atomic_output(target) as temporary:
        temporary.write_text("new")
    assert target.read_text() == "new" and [p.name for p in tmp_path.iterdir()] == ["final_model.zip"]


def test_unwritable_messages():
    assert unwritable_message(ValueError("x")) is None
    assert unwritable_message(OSError(errno.ENOENT, "No such file", "a")) is None
    full = unwritable_message(OSError(errno.ENOSPC, "No space left on device", "/runs/x/final_model.zip"))
    assert (
        full
        == "could not write /runs/x/final_model.zip (No space left on device): free space, then run the same "
           "command again."
    )
    assert "cannot write /ro (Read-only file system): choose a folder you can write to" in unwritable_message(
        OSError(errno.EROFS, "Read-only file system", "/ro")
    )


def test_full_disk_at_the_final_save_is_one_line_and_the_rerun_finishes(tmp_path, monkeypatch, capsys):
    run_dir = tmp_path / "run"
    original = DrQv2.save

    def full_disk(self, path, *args, **kwargs):
        if "final_model" not in str(path):  # the checkpoints fit
            return original(self, path, *args, **kwargs)
        with open(path, "wb") as file:
            file.write(b"PK\x03\x04 truncated")  # what a full disk leaves behind
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(DrQv2, "save", full_disk)
    assert main(_flags(run_dir, frames=810)) == 1
    printed = capsys.readouterr()
    assert (
        "the budget of 810 frames is not a multiple of the action repeat 20: the run trains 800 frames" in printed.out
    )
    error = printed.err.strip().splitlines()
    assert len(error) == 1 and error[0].startswith("error: could not write ") and "No space left on device" in error[0]
    assert "free space, then run the same command again" in error[0] and "resumes from the checkpoint step_" in error[0]
    assert not (run_dir / FINAL_MODEL).exists() and not (run_dir / RESULT_JSON).exists()
    assert not [path for path in run_dir.iterdir() if path.name.startswith(".")]  # no partial file left
    assert checkpoint_folders(run_dir / CHECKPOINTS_DIR)

    monkeypatch.setattr(DrQv2, "save", original)
    assert main(_flags(run_dir, frames=810)) == 0  # the same command finishes from the checkpoint
    assert "Resuming" in capsys.readouterr().out
    assert (run_dir / RESULT_JSON).is_file() and load_from_zip_file(run_dir / FINAL_MODEL)[1]


def test_read_only_run_folder_is_one_line_and_exit_2(tmp_path, monkeypatch, capsys):
    run_dir = tmp_path / "read-only" / "run"
    original = Path.mkdir

    def read_only(self, *args, **kwargs):
        if str(self).startswith(str(tmp_path / "read-only")):
            raise OSError(errno.EROFS, "Read-only file system", str(self))
        return original(self, *args, **kwargs)

    monkeypatch.setattr(Path, "mkdir", read_only)
    with pytest.raises(SystemExit) as exit_info:
        main(_flags(run_dir))
    assert exit_info.value.code == 2
    error = capsys.readouterr().err.strip().splitlines()[-1]
    assert "error: run folder: cannot write " in error and "(Read-only file system)" in error
    assert not (tmp_path / "read-only").exists()


def test_divergence_guard_stops_on_non_finite_values_and_warns_once_on_growth():
    guard = DivergenceGuard(growth=100.0, reference_dumps=2)
    guard.check({"critic_loss": 3.0, "actor_loss": -0.5}, True, update=10, frame=100)
    guard.check({"critic_loss": 5.0, "actor_loss": -0.2}, True, update=20, frame=200)
    assert guard.scale == {"critic_loss": 5.0, "actor_loss": 1.0}
    guard.check({"critic_loss": 400.0, "actor_loss": -90.0}, True, update=30, frame=300)  # 80x and 90x: no warning
    with pytest.warns(RuntimeWarning, match=r"the critic_loss is 600 at update 40 \(frame 400\), over 100 times its"):
        guard.check({"critic_loss": 600.0, "actor_loss": -1.0}, True, update=40, frame=400)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        guard.check({"critic_loss": 1e6, "actor_loss": -1.0}, True, update=50, frame=500)  # once per loss
    assert len(guard.warnings) == 1
    with pytest.raises(DivergenceError, match=r"the critic_loss is nan at update 60 \(frame 600\)"):
        guard.check({"critic_loss": math.nan, "actor_loss": 0.0}, True, update=60, frame=600)
    with pytest.raises(DivergenceError, match="a weight is not finite after update 70"):
        guard.check({"critic_loss": 1.0}, False, update=70, frame=700)
    assert bool(all_finite([th.ones(2), th.zeros(3)])) and not bool(all_finite([th.ones(2), th.tensor([math.inf])]))


def test_divergence_guard_warns_on_losses_the_rewards_cannot_explain_from_the_first_dump():
    """A run diverging from its first updates: its losses are compared with what its rewards allow."""
    guard = DivergenceGuard()
    # Rewards of at most 2 and gamma 0.99: values up to 200, a critic loss up to 100 x 200^2 = 4e6 without a warning.
    guard.check({"critic_loss": 3.9e6, "actor_loss": -1.9e4, "batch_reward": 2.0}, True, 1, 10, gamma=0.99)
    assert guard.warnings == [] and guard.max_reward == 2.0
    with pytest.warns(RuntimeWarning, match=r"the critic_loss is 1.6e\+09 at update 2 .* rewards allow \(4e\+04\)"):
        guard.check({"critic_loss": 1.6e9, "actor_loss": -10.0, "batch_reward": 0.5}, True, 2, 20, gamma=0.99)
    with pytest.warns(RuntimeWarning, match=r"the actor_loss is -3e\+04 .* rewards allow \(200\)"):
        guard.check({"critic_loss": 1.0, "actor_loss": -3e4, "batch_reward": 0.5}, True, 3, 30, gamma=0.99)
    assert len(guard.warnings) == 2


def test_diverging_run_stops_with_one_line_and_keeps_its_last_finite_checkpoint(tmp_path, monkeypatch, capsys):
    run_dir = tmp_path / "run"
    original = DrQv2._update
    calls = []

    def diverging(self, *args, **kwargs):
        original(self, *args, **kwargs)
        calls.append(1)
        if len(calls) == 8:  # frame 520: after the checkpoint at frame 400
            with th.no_grad():
                next(self.critic.parameters()).fill_(math.nan)

    monkeypatch.setattr(DrQv2, "_update", diverging)
    assert main(_flags(run_dir)) == 1
    error = capsys.readouterr().err.strip().splitlines()
    assert len(error) == 1 and error[0].startswith("error: training diverged: ")
    assert "its last checkpoint" in error[0] and "Try a smaller --lr" in error[0]
    kept = checkpoint_folders(run_dir / CHECKPOINTS_DIR)
    assert kept and not (run_dir / RESULT_JSON).exists()
    weights = load_from_zip_file(kept[0] / CHECKPOINT_MODEL)[1]["policy"]
    assert all(th.isfinite(tensor).all() for tensor in weights.values())


def test_command_lines_end_with_one_line_on_an_unwritable_output(capsys):
    def failing(error: OSError):
        @report_unwritable_outputs
        def main(argv: list[str] | None = None) -> int:
            raise error

        return main

    assert failing(OSError(errno.EROFS, "Read-only file system", "/ro/out"))([]) == 2
    assert failing(OSError(errno.ENOSPC, "No space left on device", "/full/out"))([]) == 1
    assert capsys.readouterr().err.splitlines() == [
        (
            "error: cannot write /ro/out (Read-only file system): choose a folder you can write to, or make this one "
            "writable."
        ),
        "error: could not write /full/out (No space left on device): free space, then run the same command again.",
    ]
    with pytest.raises(FileNotFoundError):
        failing(FileNotFoundError(errno.ENOENT, "No such file or directory", "/x"))([])


def test_sweep_into_a_read_only_folder_is_one_line_and_exit_2(tmp_path, monkeypatch, capsys):
    out = tmp_path / "read-only" / "sweep"
    original = Path.mkdir

    def read_only(self, *args, **kwargs):
        if "read-only" in str(self):
            raise OSError(errno.EROFS, "Read-only file system", str(self))
        return original(self, *args, **kwargs)

    monkeypatch.setattr(Path, "mkdir", read_only)
    flags = ["--frames", "800", "--action-repeat", "20", "--size", "36", "--eval-every-frames", "400"]
    status = sweep_main(["--tasks", "cartpole-balance", "--seeds", "1", "--out", str(out), *flags])
    assert status == 2
    error = capsys.readouterr().err.strip().splitlines()
    assert error == [
        (
            f"error: cannot write {out} (Read-only file system): choose a folder you can write to, or make this "
            "one writable."
        )
    ]
    assert not (tmp_path / "read-only").exists()


def test_resume_after_the_learning_rate_was_edited_in_the_settings_file_is_refused(tmp_path, monkeypatch, capsys):
    run_dir = tmp_path / "run"
    original = DrQv2._update
    calls = []

    def crashing(self, *args, **kwargs):
        original(self, *args, **kwargs)
        calls.append(1)
        if len(calls) == 8:  # frame 520: after the checkpoint at frame 400
            raise RuntimeError("a crash")

    monkeypatch.setattr(DrQv2, "_update", crashing)
    with pytest.raises(RuntimeError, match="a crash"):
        main(_flags(run_dir))
    monkeypatch.setattr(DrQv2, "_update", original)
    config = json.loads((run_dir / CONFIG_JSON).read_text())
    trained_with = config["learning_rate"]
    (run_dir / CONFIG_JSON).write_text(json.dumps({**config, "learning_rate": 0.001}))  # edited by hand
    capsys.readouterr()
    with pytest.raises(SystemExit) as exit_info:
        main([*_flags(run_dir), "--lr", "0.001"])
    assert exit_info.value.code == 2
    error = capsys.readouterr().err.strip().splitlines()[-1]
    (kept,) = checkpoint_folders(run_dir / CHECKPOINTS_DIR)[:1]
    assert error.endswith(
        f"error: --run-dir {run_dir} holds an unfinished run with other settings: --lr 0.001 (its checkpoint "
        f"{kept.name} trained with {trained_with:g}). Run it with the settings it trained with (and its config.json "
        "as it wrote it) to resume it, or train into another folder."
    )
    assert checkpoint_folders(run_dir / CHECKPOINTS_DIR)[0] == kept  # nothing changed
    (run_dir / CONFIG_JSON).write_text(json.dumps(config))  # the settings file as the run wrote it: it resumes
    assert main(_flags(run_dir)) == 0
    assert json.loads((run_dir / RESULT_JSON).read_text())["resumes"] == 1


def test_run_folder_turning_read_only_while_training_is_one_line_exit_1_and_the_rerun_resumes(
    tmp_path, monkeypatch, capsys
):
    from stable_baselines3.common.logger import CSVOutputFormat

    run_dir = tmp_path / "run"
    original = CSVOutputFormat.write

    def read_only_after_a_checkpoint(self, *args, **kwargs):
        if checkpoint_folders(run_dir / CHECKPOINTS_DIR):  # the file system was remounted read-only
            raise OSError(errno.EROFS, "Read-only file system", self.file.name)
        return original(self, *args, **kwargs)

    monkeypatch.setattr(CSVOutputFormat, "write", read_only_after_a_checkpoint)
    flags = _flags(run_dir, frames=1200)  # the first episode ends at frame 1000: SB3 logs, into progress.csv
    assert main(flags) == 1
    error = capsys.readouterr().err.strip().splitlines()
    (kept,) = checkpoint_folders(run_dir / CHECKPOINTS_DIR)[:1]
    assert len(error) == 1 and error[0].startswith(f"error: could not write {run_dir / 'progress.csv'} (Read-only file")
    assert error[0].endswith(
        f": the run stops. Make the folder writable again, then run the same command again: it resumes from the "
        f"checkpoint {kept.name}, which is intact."
    )
    assert not (run_dir / RESULT_JSON).exists()
    frames = json.loads((kept / "checkpoint.json").read_text())["frames"]
    monkeypatch.setattr(CSVOutputFormat, "write", original)  # writable again
    assert main(flags) == 0
    assert f"from its checkpoint at frame {frames:,} ({kept.name})" in capsys.readouterr().out
    assert json.loads((run_dir / RESULT_JSON).read_text())["resumes"] == 1
