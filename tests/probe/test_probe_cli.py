import csv
import json
import shutil
import subprocess
import sys
import zipfile

import gymnasium as gym
import numpy as np
import pytest
from stable_baselines3 import PPO, SAC

from sb3_collapse import DrQv2, make_dmc_env
from sb3_collapse.commands.probe import main
from sb3_collapse.commands.probe_pipelines import PROBE_FILES as OUTPUT_FILES
from sb3_collapse.probe import (
    ProbeSettings,
    Rollouts,
    load_checkpoint,
    probe_checkpoint,
    probe_each_checkpoint,
    split_by_episode,
)
from tests.random_env import RandomObservationEnv

FAST = ["--max-tau", "4", "--no-progress"]


def save_drqv2(path, size=32, num_timesteps=0):
    env = make_dmc_env("walker-walk", seed=0, action_repeat=8, size=size)
    model = DrQv2("CnnPolicy", env, buffer_size=10, policy_kwargs={"hidden_dim": 32}, seed=0, device="cpu")
    model.num_timesteps = num_timesteps  # as if trained that long
    model.save(path)
    env.close()
    return path


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("probe")
    early = save_drqv2(folder / "ckpt_100.zip", num_timesteps=100)
    late = save_drqv2(folder / "ckpt_200.zip", num_timesteps=200)
    rollouts = folder / "walker.npz"
    argv = ["record", str(early), "--episodes", "5", "--max-steps", "4", "--out", str(rollouts), "--no-progress"]
    assert main(argv) == 0
    return {"folder": folder, "early": early, "late": late, "rollouts": rollouts}


def assert_no_outputs(out):
    """A failed run leaves neither outputs nor its staging folder (nor the output folder it created)."""
    assert not out.exists(), sorted(p.name for p in out.rglob("*"))


def test_probe_checkpoints_with_recorded_rollouts(files, tmp_path):
    out = tmp_path / "probe"
    argv = [str(files["late"]), str(files["early"]), "--rollouts", str(files["rollouts"]), "--out", str(out), *FAST]
    assert main(argv) == 0  # no sub-command word: `run`
    assert sorted(p.name for p in out.iterdir()) == sorted(OUTPUT_FILES)
    rows = list(csv.DictReader((out / "probe.csv").open()))
    assert len(rows) == 2 * 8 * 27  # checkpoints x layers x components (24 state dimensions, 3 reward inputs)
    assert {
        "checkpoint",
        "layer",
        "component",
        "tau",
        "validation_mse",
        "test_mse",
        "test_mse_raw",
        "n_train",
        "n_validation",
        "n_test",
    } <= set(rows[0])
    assert [r["layer"] for r in rows[::27][:8]] == ["cnn0", "cnn1", "cnn2", "cnn3", "cnn4", "mlp0", "mlp1", "mlp2"]
    assert {r["checkpoint"] for r in rows} == {"ckpt_100", "ckpt_200"}
    assert all(1 <= int(r["tau"]) <= 4 for r in rows)
    assert (int(rows[0]["n_train"]), int(rows[0]["n_validation"]), int(rows[0]["n_test"])) == (12, 4, 4)
    row = rows[30]
    np.testing.assert_allclose(
        float(row["test_mse_raw"]), float(row["test_mse"]) * float(row["target_std"]) ** 2, rtol=1e-6
    )
    summary = json.loads((out / "summary.json").read_text())
    assert summary["complete"] and summary["mse_over_training"] == "written"
    assert [c["num_timesteps"] for c in summary["checkpoints"]] == [200, 100]
    assert summary["checkpoints"][0]["frames"] == 1600  # 200 agent steps x action repeat 8
    reused = [c["layers"]["cnn0"]["reused_from_an_earlier_checkpoint"] for c in summary["checkpoints"]]
    assert reused == [False, True]
    cnn0 = [
        [r["test_mse"] for r in rows if r["layer"] == "cnn0" and r["checkpoint"] == c] for c in ("ckpt_200", "ckpt_100")
    ]
    assert cnn0[0] == cnn0[1]
    assert set(summary["checkpoints"][0]["layers"]["cnn4"]["mean_test_mse"]) == {
        "orientations", "height", "velocity",
        "reward:torso_height", "reward:torso_upright", "reward:horizontal_velocity",
    }  # fmt: skip
    # The previous outputs are kept unless --overwrite.
    assert main(argv) == 2
    assert main([*argv, "--overwrite", "--layers", "mlp0", "cnn4"]) == 0
    assert len(list(csv.DictReader((out / "probe.csv").open()))) == 2 * 2 * 27


def test_default_form_records_rollouts_first(files, tmp_path, capsys):
    out = tmp_path / "single"
    assert (
        main(
            [
                str(files["early"]),
                "--episodes",
                "3",
                "--max-steps",
                "3",
                "--layers",
                "cnn4",
                "mlp2",
                "--out",
                str(out),
                *FAST,
            ]
        )
        == 0
    )
    assert sorted(p.name for p in out.iterdir()) == ["mse_by_layer.png", "probe.csv", "rollouts.npz", "summary.json"]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["rollouts"]["samples"] == 9 and summary["rollouts"]["env_config"]["size"] == 32
    assert summary["mse_over_training"].startswith("skipped")
    # the paper records from a well-performing agent: said on screen and in the summary, with how to do it
    note = summary["rollouts"]["note"]
    assert "well-performing agent (final return >= 900)" in note and "--rollouts" in note
    assert note in capsys.readouterr().out.replace("\n", " ")


def test_bad_inputs_exit_with_a_message_and_no_outputs(files, tmp_path, capsys):
    folder, out = files["folder"], tmp_path / "out"
    (folder / "notes.txt").write_text("hello")
    with zipfile.ZipFile(folder / "other.zip", "w") as archive:
        archive.writestr("readme.txt", "not a model")
    PPO("MlpPolicy", RandomObservationEnv(gym.spaces.Box(-1, 1, (3,), np.float32)), n_steps=8, batch_size=8).save(
        folder / "ppo.zip"
    )
    bigger = save_drqv2(folder / "size40.zip", size=40)
    SAC("MlpPolicy", RandomObservationEnv(gym.spaces.Box(-1, 1, (3,), np.float32)), buffer_size=10, use_sde=True).save(
        folder / "sac_sde.zip"
    )
    cases = {
        "does not exist": [str(folder / "missing.zip")],
        "not a zip": [str(folder / "notes.txt")],
        "not an SB3 model": [str(folder / "other.zip")],
        "cannot probe a model whose policy comes from 'stable_baselines3.common.policies'": [str(folder / "ppo.zip")],
        "SAC with gSDE": [str(folder / "sac_sde.zip")],  # its layers cannot be mapped
        # checkpoints of two image sizes are refused before anything is recorded: nothing is written
        "of shape (9, 40, 40): the probe feeds every checkpoint the same rollouts": [str(files["early"]), str(bigger)],
        "not a rollouts file": [str(files["early"]), "--rollouts", str(folder / "notes.txt")],
    }
    for message, args in cases.items():
        rollouts = [] if "--rollouts" in args else ["--rollouts", str(files["rollouts"])]
        assert main([*args, *rollouts, "--out", str(out), "--no-progress"]) == 2, message
        assert message in capsys.readouterr().err
        assert_no_outputs(out)
    assert main(["record", str(folder / "ppo.zip"), "--out", str(tmp_path / "r.npz")]) == 2
    assert "cannot probe" in capsys.readouterr().err and not (tmp_path / "r.npz").exists()


def test_help_of_the_module_and_its_sub_commands():
    result = subprocess.run(
        [sys.executable, "-m", "sb3_collapse.probe", "--help"], capture_output=True, text=True, check=False
    )
    assert result.returncode == 0 and "record" in result.stdout and "run" in result.stdout
    for command, option in (("run", "--max-tau"), ("record", "--episodes")):
        with pytest.raises(SystemExit) as exit_info:
            main([command, "--help"])
        assert exit_info.value.code == 0


def test_cnn0_probe_is_reused_across_checkpoints(files):
    """cnn0 (normalized pixels) is the same for every DrQv2: probed once, with the same result as a fresh fit."""
    rollouts = Rollouts.load(files["rollouts"])
    split = split_by_episode(rollouts.episode_ids)
    settings = ProbeSettings(layers=["cnn0", "cnn4"], max_tau=4, device="cpu", progress=False)
    reuse = {}
    first = probe_checkpoint(load_checkpoint(files["early"]), rollouts, split, settings, reuse)
    second = probe_checkpoint(load_checkpoint(files["late"]), rollouts, split, settings, reuse)
    fresh = probe_checkpoint(load_checkpoint(files["late"]), rollouts, split, settings)
    assert [p.reused for p in first.layers] == [False, False] and [p.reused for p in second.layers] == [True, False]
    assert len(reuse) == 1
    for reused, fitted in zip(second.layers, fresh.layers):
        np.testing.assert_array_equal(reused.test_mse, fitted.test_mse)
        np.testing.assert_array_equal(reused.tau, fitted.tau)
    # many checkpoints at once: each one's rows as probe_checkpoint gives them, in the given order, labelled
    paths, labels = [files["late"], files["early"], files["late"]], ["a/late", "b/early", "c/late"]
    for jobs in (1, 2):
        results = probe_each_checkpoint(paths, labels, rollouts, split, settings, jobs)
        assert [{r["checkpoint"] for r in rows} for rows in results] == [{label} for label in labels]
        for rows, expected in zip(results, (second, first, second)):
            assert [(r["layer"], r["component"], r["tau"], r["test_mse"]) for r in rows] == [
                (r["layer"], r["component"], r["tau"], r["test_mse"]) for r in expected.rows
            ]


def test_bad_layers_and_split_are_refused_before_any_rollout(files, tmp_path, monkeypatch, capsys):
    """--layers mlp9 and --split 0.5 0.5 0.5 are refused before a checkpoint is loaded or a rollout recorded: both
    would fail the test here if called."""

    def never(*args, **kwargs):
        raise AssertionError("called before the flags were checked")

    from sb3_collapse.commands import probe_pipelines

    for name in ("record_rollouts", "record", "load_checkpoint", "load_sweep"):
        monkeypatch.setattr(probe_pipelines, name, never)
    out = tmp_path / "out"
    for command in ([str(files["early"])], ["sweep", str(tmp_path), "--task", "walker-walk"]):
        with pytest.raises(SystemExit) as exit_info:
            main([*command, "--layers", "mlp9", "--out", str(out)])
        assert exit_info.value.code == 2 and "invalid choice: 'mlp9'" in capsys.readouterr().err
        with pytest.raises(SystemExit) as exit_info:
            main([*command, "--split", "0.5", "0.5", "0.5", "--out", str(out), "--no-progress"])
        assert (
            exit_info.value.code == 2 and "--split must be 3 positive fractions summing to 1" in capsys.readouterr().err
        )
        assert_no_outputs(out)


def test_a_folder_given_as_a_checkpoint_is_named_for_what_it_is(files, tmp_path, capsys):
    """A folder where a checkpoint is expected: a sweep folder points at `probe sweep`, a run folder at its model
    files, any other folder at a .zip in it."""
    from sb3_collapse.protocol import CONFIG_JSON, FINAL_MODEL, SNAPSHOTS_DIR

    run = tmp_path / "sweep" / "walker-walk" / "drqv2" / "seed_0"
    (run / SNAPSHOTS_DIR).mkdir(parents=True)
    (run / CONFIG_JSON).write_text("{}")
    bare = tmp_path / "bare"
    bare.mkdir()
    expected = {
        tmp_path / "sweep": f"is a sweep folder, not a checkpoint: probe its trials with `python -m sb3_collapse.probe "
        f"sweep {tmp_path / 'sweep'} --task walker-walk`, or give a trial's model, e.g. {run / FINAL_MODEL}.",
        run: "is a run folder, not a checkpoint: give a model file (it has none yet).",
        bare: "is a folder, not a checkpoint: give an SB3 .zip.",
        files["folder"]: f"is a folder, not a checkpoint: give an SB3 .zip, e.g. {files['early']}.",
    }
    for folder, message in expected.items():
        for command in ([str(folder)], ["record", str(folder)], ["film", str(folder)]):
            assert main([*command, "--out", str(tmp_path / "out"), "--no-progress"]) == 2
            assert capsys.readouterr().err == f"error: {folder} {message}\n", command
    shutil.copy(files["early"], run / FINAL_MODEL)
    shutil.copy(files["late"], run / SNAPSHOTS_DIR / "snapshot_0000000200_frames.zip")
    assert main([str(run), "--out", str(tmp_path / "out")]) == 2
    assert capsys.readouterr().err == (
        f"error: {run} is a run folder, not a checkpoint: give its model, {run / FINAL_MODEL} or "
        f"{run / SNAPSHOTS_DIR}/*.zip.\n"
    )


def assert_no_bar_frames(text):
    """No tqdm or rich redraw ('\\r') nor bar characters."""
    assert "\r" not in text and "%|" not in text and "it/s" not in text and "━" not in text, text


def test_commands_draw_no_progress_bar_into_a_captured_stderr_and_the_summary_holds_the_warnings(
    files, tmp_path, capfd
):
    rollouts = tmp_path / "r.npz"
    record = ["record", str(files["early"]), "--episodes", "3", "--max-steps", "3", "--out", str(rollouts)]
    assert main(record) == 0  # the progress is on (the default), stderr is not a terminal
    captured = capfd.readouterr()
    assert_no_bar_frames(captured.err + captured.out)
    assert captured.err.splitlines() == ["recording: 9 steps"]
    out = tmp_path / "probe"
    probe = [str(files["early"]), "--rollouts", str(rollouts), "--layers", "cnn4", "mlp2", "--max-tau", "4"]
    assert main([*probe, "--out", str(out)]) == 0
    captured = capfd.readouterr()
    assert_no_bar_frames(captured.err + captured.out)
    assert "extracting cnn4+mlp2: 1 blocks" in captured.err.splitlines()
    assert "fitting cnn4: 4 atoms" in captured.err.splitlines()
    # 3 episodes of 3 steps: 3 test samples, fewer than max_tau 4; said on screen and in the summary
    warnings = json.loads((out / "summary.json").read_text())["warnings"]
    few = next(warning for warning in warnings if warning["kind"] == "few test samples")
    assert few["layers"] == ["cnn4", "mlp2"] and f"Warning: {few['message']}" in captured.err
    assert "well-performing agent" in few["message"]


@pytest.mark.parametrize("split", [("0.5", "0.5", "0.5"), ("nan", "0.5", "0.5"), ("2", "0", "0"), ("x", "0.5", "0.5")])
@pytest.mark.parametrize("command", ["run", "sweep"])
def test_every_split_error_is_one_line_with_the_same_prefix(tmp_path, capsys, command, split):
    """A sum other than 1, a NaN (once "must be <= 1"), a fraction out of range, a word: each is the sub-command's
    `<prog> <command>: error: --split ...` line, exit status 2, before any file is read."""
    where = ["sweep", str(tmp_path), "--task", "walker-walk"] if command == "sweep" else [str(tmp_path / "a.zip")]
    with pytest.raises(SystemExit) as exit_info:
        main([*where, "--split", *split, "--out", str(tmp_path / "out")])
    lines = capsys.readouterr().err.strip().splitlines()
    assert exit_info.value.code == 2 and lines[-1].startswith(f"python -m sb3_collapse.probe {command}: error: ")
    expected = "argument --split: invalid float value: 'x'" if split[0] == "x" else (
        f"--split must be 3 positive fractions summing to 1 (train validation test), got {[float(v) for v in split]}."
    )  # fmt: skip
    assert lines[-1].endswith(expected) and "<= 1" not in lines[-1]
