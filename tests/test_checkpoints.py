"""
Run checkpoints (sb3_collapse.run.checkpoints): a run stopped by SIGTERM, killed by SIGKILL, resumed from a damaged
newest checkpoint, ends exactly as the same run uninterrupted; locks, refusals and a full disk.

One chain keeps the cost to about two tiny runs: the reference run (in this process), and the same run killed by
SIGKILL (a subprocess), resumed and stopped by SIGTERM (in this process: exit status 75), its newest
checkpoint truncated, resumed to the end (in this process).
"""

from __future__ import annotations

import csv
import errno
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import torch as th
from stable_baselines3.common.callbacks import EveryNTimesteps, StopTrainingOnMaxEpisodes
from stable_baselines3.common.save_util import load_from_zip_file

from sb3_collapse import CollapseReset, DrQv2, make_dmc_env
from sb3_collapse.commands.train import main
from sb3_collapse.envs.replay import EpisodeReplay
from sb3_collapse.errors import CheckpointError, InputError, OutputError
from sb3_collapse.protocol import (
    CHECKPOINT_JSON,
    CHECKPOINT_MODEL,
    CHECKPOINTS_DIR,
    COLLAPSE_EVENTS_CSV,
    COLLAPSE_METRICS_CSV,
    EVAL_CSV,
    EXIT_INTERRUPTED,
    FINAL_MODEL,
    LOCK_FILE,
    PROGRESS_CSV,
    RESULT_JSON,
    SNAPSHOT_FILE,
    SNAPSHOTS_DIR,
)
from sb3_collapse.run.checkpoints import ResumableCheckpoints, checkpoint_folders, load_checkpoint
from sb3_collapse.run.lock import RunLock
from sb3_collapse.run.signals import stop_signals

# 100 agent steps of cartpole at action repeat 20 (episodes of 50 steps): checkpoints every 10 steps, most of them
# mid-episode; the reset rule resets at frames 800 and 1600; updates from step 20 on; ReDo every 7 updates.
FLAGS = [
    "--env", "cartpole-balance", "--frames", "2000", "--seed", "3", "--action-repeat", "20", "--size", "48",
    "--hidden-dim", "64", "--feature-dim", "16", "--batch-size", "16", "--seed-frames", "400",
    "--eval-every-frames", "1000", "--eval-episodes", "1", "--checkpoint-every-frames", "200",
    "--collapse-metrics-every-frames", "400", "--collapse-metrics-batch", "16", "--reset-rule",
    "--reset-window-frames", "800", "--torch-threads", "1", "--no-progress-bar", "--replay-sampling", "sb3",
    "--snapshots", "--redo-every-updates", "7",
]  # fmt: skip
REPEAT = 20


@pytest.fixture(autouse=True)
def _keep_torch_threads():
    threads = th.get_num_threads()
    yield
    th.set_num_threads(threads)


def _start(run_dir: Path) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "sb3_collapse.train", *FLAGS, "--run-dir", str(run_dir)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
    )


def _wait_for_checkpoint(process: subprocess.Popen, run_dir: Path, min_step: int, timeout: float = 240) -> None:
    deadline = time.time() + timeout
    while time.time() < deadline:
        folders = checkpoint_folders(run_dir / CHECKPOINTS_DIR)
        if folders and int(folders[0].name.split("_")[1]) >= min_step:
            return
        if process.poll() is not None:
            pytest.fail(f"the run ended before a checkpoint at step {min_step}:\n{process.stdout.read()}")
        time.sleep(0.05)
    process.kill()
    pytest.fail(f"no checkpoint at step >= {min_step} within {timeout} s")


def _rows(path: Path, drop: tuple[str, ...] = ()) -> list[dict[str, str]]:
    with path.open(newline="") as file:
        return [{k: v for k, v in row.items() if k not in drop} for row in csv.DictReader(file)]


def _weights(run_dir: Path) -> dict[str, th.Tensor]:
    _, params, _ = load_from_zip_file(run_dir / FINAL_MODEL)
    return {f"{part}.{name}": tensor for part, state in params.items() for name, tensor in _flat(state)}


def _flat(state: dict, prefix: str = ""):
    for key, value in state.items():
        if isinstance(value, dict):
            yield from _flat(value, f"{prefix}{key}.")
        elif isinstance(value, th.Tensor):
            yield f"{prefix}{key}", value


def _scalars(run_dir: Path) -> dict[str, list[tuple[int, float]]]:
    """Every TensorBoard scalar of a run folder as TensorBoard reads it (several event files, purges applied)."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(run_dir))
    events.Reload()
    return {
        tag: [(event.step, repr(event.value)) for event in events.Scalars(tag)]  # repr: nan == nan
        for tag in events.Tags()["scalars"]
        if tag not in ("time/fps", "time/time_elapsed")
    }


def _newest_step(run_dir: Path) -> int:
    return int(checkpoint_folders(run_dir / CHECKPOINTS_DIR)[0].name.split("_")[1])


def test_killed_stopped_and_resumed_run_ends_as_the_uninterrupted_one(tmp_path, capsys):
    reference, resumed = tmp_path / "reference", tmp_path / "resumed"
    assert main([*FLAGS, "--run-dir", str(reference)]) == 0

    # 1. Another process trains into the folder: a second one is refused; then SIGKILL, after its second checkpoint.
    process = _start(resumed)
    _wait_for_checkpoint(process, resumed, 20)
    with pytest.raises(InputError, match=rf"in use by pid {process.pid} on host"):
        with RunLock(resumed):
            pass
    process.kill()
    process.communicate(timeout=60)
    killed_at = _newest_step(resumed)

    # 2. The same command resumes from it (mid-episode); SIGTERM after two checkpoints of its own writes one more
    # and ends with exit status 75, the folder not marked failed.
    def stop_later() -> None:
        deadline = time.time() + 240
        while time.time() < deadline:
            folders = checkpoint_folders(resumed / CHECKPOINTS_DIR)
            if folders and int(folders[0].name.split("_")[1]) >= killed_at + 20:
                os.kill(os.getpid(), signal.SIGTERM)
                return
            time.sleep(0.02)

    capsys.readouterr()
    watcher = threading.Thread(target=stop_later, daemon=True)
    watcher.start()
    assert main([*FLAGS, "--run-dir", str(resumed)]) == EXIT_INTERRUPTED
    watcher.join()
    printed = capsys.readouterr()
    assert f"Resuming {resumed} from its checkpoint at frame {killed_at * REPEAT:,}" in printed.out
    assert "SIGTERM: writing a checkpoint" in printed.out and "run the same command again to resume" in printed.err
    assert not (resumed / "error.txt").exists() and not (resumed / RESULT_JSON).exists()

    # 3. The newest checkpoint is damaged (truncated model): the resume falls back to the one before, and says so.
    newest, previous = checkpoint_folders(resumed / CHECKPOINTS_DIR)[:2]
    model_zip = newest / CHECKPOINT_MODEL
    model_zip.write_bytes(model_zip.read_bytes()[:1000])
    assert main([*FLAGS, "--run-dir", str(resumed)]) == 0
    printed = capsys.readouterr().out
    assert f"Checkpoint {newest} is damaged ({CHECKPOINT_MODEL} has 1000 bytes" in printed
    assert f"from its checkpoint at frame {int(previous.name.split('_')[1]) * REPEAT:,}" in printed

    # Same weights, evaluations, reset-rule events and collapse checks; no duplicated or missing log row.
    a, b = _weights(reference), _weights(resumed)
    assert a.keys() == b.keys() and all(th.equal(a[name], b[name]) for name in a)
    assert _rows(reference / EVAL_CSV, drop=("wall_time_s",)) == _rows(resumed / EVAL_CSV, drop=("wall_time_s",))
    events = _rows(resumed / COLLAPSE_EVENTS_CSV)
    assert [row["frame"] for row in events] == ["800", "1600"] and events == _rows(reference / COLLAPSE_EVENTS_CSV)
    assert _rows(reference / COLLAPSE_METRICS_CSV) == _rows(resumed / COLLAPSE_METRICS_CSV)
    timing = ("time/fps", "time/time_elapsed")
    assert _rows(reference / PROGRESS_CSV, drop=timing) == _rows(resumed / PROGRESS_CSV, drop=timing)
    recycles = [row["redo/recycles"] for row in _rows(resumed / PROGRESS_CSV) if row.get("redo/recycles")]
    assert len(recycles) >= 2  # PeriodicReDo (every 7 updates) recycled, at the same steps as the uninterrupted run
    assert _scalars(reference) == _scalars(resumed)  # TensorBoard, the events after each checkpoint purged
    result = json.loads((resumed / RESULT_JSON).read_text())
    assert result["resumes"] == 2 and result["resets"] == 2  # the lineage of the final weights: two resumptions
    assert {k: v for k, v in result.items() if k not in ("wall_time_s", "timings", "resumes")} == {
        k: v
        for k, v in json.loads((reference / RESULT_JSON).read_text()).items()
        if k not in ("wall_time_s", "timings", "resumes")
    }
    assert not (resumed / CHECKPOINTS_DIR).exists() and not (resumed / LOCK_FILE).exists()  # deleted once finished
    # The snapshots' schedule resumed with the run: the same files, the same encoder and actor weights.
    snapshots = [sorted((run / SNAPSHOTS_DIR).iterdir()) for run in (reference, resumed)]
    assert (
        [p.name for p in snapshots[0]]
        == [p.name for p in snapshots[1]]
        == [SNAPSHOT_FILE.format(frames=frames) for frames in (0, 1000, 2000)]
    )
    for a_zip, b_zip in zip(*snapshots):
        a, b = load_from_zip_file(a_zip)[1]["policy"], load_from_zip_file(b_zip)[1]["policy"]
        assert a.keys() == b.keys() and all(th.equal(a[name], b[name]) for name in a)


def test_resume_with_other_settings_is_refused_with_the_differences(tmp_path, capsys):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "config.json").write_text(json.dumps({"env": "cartpole-balance", "learning_rate": 0.0001}))
    with pytest.raises(SystemExit) as exit_info:
        main([*FLAGS, "--lr", "0.001", "--run-dir", str(run_dir)])
    assert exit_info.value.code == 2
    error = capsys.readouterr().err
    assert "holds an unfinished run with other settings" in error and "--lr 0.001 (the run folder has 0.0001)" in error


def _tiny_model(run_dir: Path) -> tuple[DrQv2, EpisodeReplay]:
    env = EpisodeReplay(make_dmc_env("cartpole-balance", seed=0, action_repeat=8, size=36))
    model = DrQv2(
        "CnnPolicy", env, learning_starts=1000, batch_size=4, buffer_size=200, seed=0,
        policy_kwargs=dict(hidden_dim=16, feature_dim=4), replay_buffer_kwargs=dict(sampling="sb3"),
    )  # fmt: skip
    return model, env


def test_full_disk_keeps_the_previous_checkpoint(tmp_path, monkeypatch):
    model, _ = _tiny_model(tmp_path)
    checkpoints = ResumableCheckpoints(tmp_path / CHECKPOINTS_DIR, every_frames=80)
    model.learn(12, callback=checkpoints)  # checkpoints at steps 10 (frame 80)
    first = checkpoint_folders(tmp_path / CHECKPOINTS_DIR)
    assert [folder.name for folder in first] == ["step_000000000010"]

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr("sb3_collapse.run.checkpoints.pickle.dump", full)
    with pytest.raises(
        OutputError,
        match=rf"into {tmp_path / CHECKPOINTS_DIR} \(No space left on device\); the "
        r"previous checkpoint step_000000000010 is intact",
    ):
        model.learn(12, callback=checkpoints, reset_num_timesteps=False)
    monkeypatch.undo()
    assert checkpoint_folders(tmp_path / CHECKPOINTS_DIR) == first  # no partial folder listed, the old one whole
    assert load_checkpoint(tmp_path / CHECKPOINTS_DIR).folder == first[0]
    assert [path.name for path in (tmp_path / CHECKPOINTS_DIR).iterdir() if path.name.startswith(".")] == []


def test_checkpoint_of_another_version_is_refused(tmp_path):
    model, _ = _tiny_model(tmp_path)
    model.learn(12, callback=ResumableCheckpoints(tmp_path, every_frames=80))
    info_path = checkpoint_folders(tmp_path)[0] / CHECKPOINT_JSON
    info = json.loads(info_path.read_text())
    info_path.write_text(json.dumps({**info, "version": "0.0.1"}))
    with pytest.raises(CheckpointError, match="written by sb3-collapse 0.0.1, this is .*resume with the version"):
        load_checkpoint(tmp_path)


def test_episode_replay_rebuilds_the_episode_in_progress():
    env = EpisodeReplay(make_dmc_env("cartpole-swingup", seed=1, action_repeat=2, size=32))
    env.reset(seed=5)
    env.reset()  # an unseeded reset: the random state it started from is recorded
    rng = np.random.default_rng(0)
    for _ in range(7):
        observation, *_ = env.step(rng.uniform(-1, 1, size=1).astype(np.float32))
    record = env.episode_record()
    other = EpisodeReplay(make_dmc_env("cartpole-swingup", seed=99, action_repeat=2, size=32))
    assert np.array_equal(other.replay_episode(record), observation)
    action = np.array([0.3], dtype=np.float32)
    assert np.array_equal(other.step(action)[0], env.step(action)[0])


def test_drqv2_save_and_load_keep_the_reset_rule(tmp_path):
    env = make_dmc_env("cartpole-balance", seed=0, action_repeat=8, size=36)
    rule = CollapseReset(window_frames=160, check_every_frames=40, batch_size=4)
    model = DrQv2(
        "CnnPolicy", env, learning_starts=10, batch_size=4, buffer_size=200, seed=0, callback=rule,
        policy_kwargs=dict(hidden_dim=16, feature_dim=4), replay_buffer_kwargs=dict(sampling="sb3"),
    )  # fmt: skip
    model.learn(25)
    assert rule.resets == 1 and rule.window_start_frame == 160
    model.save(tmp_path / "model.zip")
    loaded = DrQv2.load(tmp_path / "model.zip", env=env)
    restored = loaded.callback
    assert isinstance(restored, CollapseReset) and restored is not rule
    assert (restored.window_frames, restored.check_every_frames, restored.batch_size) == (160, 40, 4)
    loaded.learn(20, reset_num_timesteps=False)  # frames 200..360: the window of frame 160 ends at 320
    assert restored.resets == 2 and restored.reset_frames == [160, 320] and restored.window_start_frame == 320


def test_a_callbacks_state_goes_through_the_same_functions_in_a_run_checkpoint_and_drqv2_save(tmp_path, monkeypatch):
    """The reset rule's state, kept by a run checkpoint and by DrQv2.save, is taken by ``callback_states`` and put back
    by ``load_callback_states`` (``sb3_collapse.common.saved_callbacks``) on both paths: the same state both ways."""
    from sb3_collapse.common.saved_callbacks import callback_states, load_callback_states

    callers = {"state_dict": [], "load_state_dict": []}

    def spy(name):
        original = getattr(CollapseReset, name)

        def method(self, *args):
            frame = sys._getframe(1)
            while frame.f_code.co_name.startswith("<"):  # a comprehension's frame: the function around it
                frame = frame.f_back
            callers[name].append(frame.f_code.co_name)  # the function that called it
            return original(self, *args)

        return method

    for name in callers:
        monkeypatch.setattr(CollapseReset, name, spy(name))

    def built(rule=None):
        rule = rule or CollapseReset(window_frames=160, check_every_frames=40, batch_size=4)
        env = EpisodeReplay(make_dmc_env("cartpole-balance", seed=0, action_repeat=8, size=36))
        model = DrQv2(
            "CnnPolicy", env, learning_starts=10, batch_size=4, buffer_size=200, seed=0, callback=rule,
            policy_kwargs=dict(hidden_dim=16, feature_dim=4), replay_buffer_kwargs=dict(sampling="sb3"),
        )  # fmt: skip
        return model, rule, ResumableCheckpoints(tmp_path / CHECKPOINTS_DIR, every_frames=0, callbacks=[rule])

    model, rule, checkpoints = built()
    model.learn(25, callback=checkpoints)  # a reset at frame 160, then the next window
    checkpoints.save()
    model.save(tmp_path / "model.zip")
    # The checkpoint's callback states, its model (saved by DrQv2.save, constructor callbacks included), the zip.
    assert callers["state_dict"] == [callback_states.__name__] * 3
    expected = rule.state_dict()
    assert expected["resets"] == 1 and expected["num_timesteps"] == 25

    resumed, resumed_rule, resumed_checkpoints = built()
    resumed_checkpoints.init_callback(resumed)
    resumed_checkpoints.resume(load_checkpoint(tmp_path / CHECKPOINTS_DIR))
    loaded = DrQv2.load(tmp_path / "model.zip")
    assert callers["load_state_dict"] == [load_callback_states.__name__] * 2
    assert resumed_rule._pending_state == loaded.callback._pending_state == expected
    with pytest.raises(ValueError, match=r"^the callbacks saved are \['CollapseReset'\], these are \[\]: use the"):
        load_callback_states([], callback_states([rule]))  # a run checkpoint resumed without its callbacks


def test_second_sigint_stops_at_once():
    with pytest.raises(ValueError, match="^every_frames must be >= 0, got -1"):
        ResumableCheckpoints("unused", every_frames=-1)
    checkpoints = ResumableCheckpoints("unused", every_frames=0)  # 0: checkpoints only at a stop request
    before = signal.getsignal(signal.SIGINT)
    with stop_signals(checkpoints):
        signal.raise_signal(signal.SIGINT)  # the first asks for a checkpoint and a stop
        assert checkpoints.stop_signal == "SIGINT"
        with pytest.raises(KeyboardInterrupt):
            signal.raise_signal(signal.SIGINT)
    assert signal.getsignal(signal.SIGINT) is before  # put back


def test_drqv2_load_warns_about_a_callback_it_cannot_rebuild(tmp_path):
    env = make_dmc_env("cartpole-balance", seed=0, action_repeat=8, size=36)
    model = DrQv2(
        "CnnPolicy", env, buffer_size=50, seed=0,
        callback=[CollapseReset(), EveryNTimesteps(10, StopTrainingOnMaxEpisodes(1))],
        policy_kwargs=dict(hidden_dim=16, feature_dim=4),
    )  # fmt: skip
    model.save(tmp_path / "model.zip")
    with pytest.warns(UserWarning, match=r"callback\(s\) EveryNTimesteps could not be saved .* pass them again"):
        loaded = DrQv2.load(tmp_path / "model.zip")
    assert isinstance(loaded.callback, CollapseReset)


def test_csv_files_are_written_back_as_the_checkpoint_holds_them(tmp_path):
    """Rows written after the checkpoint go without a word; a file shorter, cut mid-row or changed is rewritten from
    the checkpoint and named in one line; a file the checkpoint does not know is left alone."""
    from sb3_collapse.run.checkpoints import restore_csv_files

    saved = {"cut.csv": b"h\n1\n2\n", "short.csv": b"h\n1\n2\n", "changed.csv": b"h\n1\n", "after.csv": b"h\n1\n"}
    saved["new.csv"] = b""  # not written yet at the checkpoint
    found = {
        "cut.csv": b"h\n1",
        "short.csv": b"h\n",
        "changed.csv": b"h\n9\n",
        "after.csv": b"h\n1\n2\n3",
        "new.csv": b"x\n",
    }
    for name, content in {**found, "other.csv": b"kept"}.items():
        (tmp_path / name).write_bytes(content)
    paths = [tmp_path / name for name in (*found, "other.csv", "missing.csv")]
    assert restore_csv_files(paths, saved, 600) == (
        "cut.csv (cut mid-row), short.csv (2 line(s) short), changed.csv (changed) did not hold what the checkpoint "
        "at frame 600 recorded: rewritten from it (the rows after it are written again as the run goes on)."
    )
    assert {name: (tmp_path / name).read_bytes() for name in saved} == saved
    assert (tmp_path / "other.csv").read_bytes() == b"kept" and not (tmp_path / "missing.csv").exists()
    assert restore_csv_files(paths, saved, 600) is None  # all as the checkpoint holds them
    assert sorted(path.name for path in tmp_path.iterdir() if path.name.startswith(".")) == []  # nothing partial
