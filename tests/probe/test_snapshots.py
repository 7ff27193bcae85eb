"""Snapshots (encoder and actor only) from a real tiny training run, read by the probe like full ones."""

import csv
import dataclasses
import json
import re
import shutil
import sys
import zipfile
from pathlib import Path

import matplotlib.image
import numpy as np
import pytest
import torch as th
from PIL import Image

from sb3_collapse import DrQv2
from sb3_collapse.commands.probe import main as probe_main
from sb3_collapse.commands.report import main as report_main
from sb3_collapse.commands.report_pipelines import FixedInputSettings, fixed_agent_rows, write_report, write_run_report
from sb3_collapse.errors import InputError, ParameterError
from sb3_collapse.monitoring import collect_activations, layer_metrics
from sb3_collapse.probe.checkpoints import load_checkpoint
from sb3_collapse.probe.film import film_episode
from sb3_collapse.probe.fixed_inputs import fixed_metrics
from sb3_collapse.probe.pipeline import RecordOptions, record
from sb3_collapse.probe.rollouts import record_rollouts, resolve_env_config
from sb3_collapse.protocol import (
    FIGURE2_PNG,
    SNAPSHOT_FILE,
    SNAPSHOTS_DIR,
    SWEEP_PROBE_DIR,
    TABLES_1_6_CSV,
    snapshot_files,
)
from sb3_collapse.report.pipeline import (
    COLLAPSE_AGENTS_CSV,
    COLLAPSE_FIXED_CSV,
    COLLAPSE_ONLINE_PNG,
    COLLAPSE_PNG,
    RUN_COLLAPSE_FIXED_CSV,
    RUN_COLLAPSE_FIXED_PNG,
    RUN_COLLAPSE_PNG,
)
from sb3_collapse.run.config import TrainConfig
from sb3_collapse.run.runner import train
from sb3_collapse.run.snapshots import MARKER, is_snapshot, load_snapshot, save_snapshot

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "report"))
from fabricated_sweep import write_probe_sweep


@pytest.fixture(scope="module")
def run(tiny_walker_run):
    """800 frames (40 agent steps at action repeat 20: short evaluation episodes) at 48x48, evaluated every 400: the
    session's run (tests/conftest.py), which test_train_cli.py reads too."""
    return tiny_walker_run


def test_one_snapshot_per_evaluation(run):
    folder = run.run_dir / SNAPSHOTS_DIR
    names = sorted(p.name for p in folder.iterdir())
    assert (
        names
        == [SNAPSHOT_FILE.format(frames=f) for f in (0, 400, 800)]
        == [
            "snapshot_0000000000_frames.zip",
            "snapshot_0000000400_frames.zip",
            "snapshot_0000000800_frames.zip",
        ]
    )
    assert [int(e["frame"]) for e in run.evaluations] == [0, 400]  # scheduled; 800: the final model's, apart
    assert run.saved_model_evaluation["frame"] == 800
    final_size = run.model_path.stat().st_size
    for path in folder.iterdir():
        assert is_snapshot(path) and path.stat().st_size < final_size / 2
    assert not is_snapshot(run.model_path)


def test_a_snapshot_of_another_version_is_refused(run, tmp_path):
    """A zip whose marker is not :data:`MARKER` (another version's) is not a snapshot: loading it is refused in one
    line naming the file, and only the snapshots folder of this version is listed."""
    names = [SNAPSHOT_FILE.format(frames=frames) for frames in (0, 400)]
    (tmp_path / SNAPSHOTS_DIR).mkdir()
    other = tmp_path / SNAPSHOTS_DIR / names[0]
    with zipfile.ZipFile(run.run_dir / SNAPSHOTS_DIR / names[0]) as source, zipfile.ZipFile(other, "w") as target:
        for member in source.namelist():
            target.writestr("probe_checkpoint.json" if member == MARKER else member, source.read(member))
    shutil.copy(run.run_dir / SNAPSHOTS_DIR / names[1], tmp_path / SNAPSHOTS_DIR / names[1])
    (tmp_path / "probe_checkpoints").mkdir()
    shutil.copy(run.run_dir / SNAPSHOTS_DIR / names[1], tmp_path / "probe_checkpoints" / names[1])
    assert [path.name for path in snapshot_files(tmp_path)] == names
    assert not is_snapshot(other) and is_snapshot(tmp_path / SNAPSHOTS_DIR / names[1])
    with pytest.raises(ValueError, match=rf"^{re.escape(str(other))} is not a snapshot \(no {MARKER}\)"):
        load_snapshot(other)


def test_snapshot_holds_the_final_encoder_and_actor(run):
    final = DrQv2.load(run.model_path, buffer_size=64)
    checkpoint = load_checkpoint(run.run_dir / SNAPSHOTS_DIR / SNAPSHOT_FILE.format(frames=800))
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
    first = load_snapshot(run.run_dir / SNAPSHOTS_DIR / SNAPSHOT_FILE.format(frames=0))
    assert first.num_timesteps == 0
    assert not th.equal(first.policy.state_dict()["actor.mlp1.0.weight"], reference["actor.mlp1.0.weight"])


def test_snapshots_need_drqv2_and_evaluations(tmp_path):
    with pytest.raises(ParameterError, match="snapshots"):
        train(TrainConfig(env="walker-walk", frames=80, eval_every_frames=0, snapshots=True, logdir=str(tmp_path)))
    with pytest.raises(TypeError, match="DrQv2 model"):
        save_snapshot(type("NotDrQ", (), {"policy": th.nn.Linear(2, 2)})(), tmp_path / "x.zip")
    assert not list(tmp_path.iterdir())


def test_probe_sweep_draws_figure2_and_tables(run, tmp_path, capsys):
    root = write_probe_sweep(tmp_path / "sweep", run.run_dir, {0: 950.0, 1: 920.0, 2: 20.0, 3: 10.0, 4: 500.0})
    damaged = root / "walker-walk" / "drqv2" / "seed_5"  # a truncated result file: listed, the rest probed
    shutil.copytree(root / "walker-walk" / "drqv2" / "seed_4", damaged, ignore=shutil.ignore_patterns(SNAPSHOTS_DIR))
    (damaged / "result.json").write_text((damaged / "result.json").read_text()[:40])
    argv = ["sweep", str(root), "--task", "walker-walk", "--episodes", "5", "--max-steps", "4", "--max-tau", "4"]
    assert probe_main([*argv, "--layers", "cnn0", "cnn4", "mlp1"]) == 0  # the progress on, stderr not a terminal
    captured = capsys.readouterr()
    assert "Not probed: seed 5: " in captured.out
    assert "\r" not in captured.err and "%|" not in captured.err  # no bar frames: a line per stage
    assert {"recording: 20 steps", "probing checkpoints: 12 checkpoints"} <= set(captured.err.splitlines())
    out = root / SWEEP_PROBE_DIR.format(task="walker-walk", variant="drqv2")
    summary = json.loads((out / "summary.json").read_text())
    assert all(f"Warning: {warning['message']}" in captured.err for warning in summary["warnings"])
    assert [d["seed"] for d in summary["damaged"]] == [5] and "result.json: not a readable JSON" in str(summary)
    assert [(a["seed"], a["row"], a["checkpoints"]) for a in summary["agents"]] == [
        (0, "well-performing", 3), (1, "well-performing", 3), (2, "poorly performing", 3), (3, "poorly performing", 3)
    ]  # fmt: skip
    assert summary["not_probed"] == [{"seed": 4, "final_return": 500.0}]
    assert summary["rollouts"]["recorded_from"].endswith("seed_0/final_model.zip")  # the best seed
    assert summary["columns"] == {  # the reward's inputs, then the state-vector groups
        "torso velocity": ["reward:horizontal_velocity"],
        "orientation (torso upright)": ["reward:torso_upright"],
        "torso height": ["reward:torso_height"],
        "root velocities (state)": ["velocity_0", "velocity_1", "velocity_2"],
        "leg orientations (state)": [f"orientations_{i}" for i in range(2, 14)],
    }
    image = matplotlib.image.imread(out / FIGURE2_PNG)
    assert image.shape[1] > 1000 and image[..., :3].std() > 0.05
    # Tables 1-6 from probe.csv, independently: per agent the mean test MSE over the column's targets, std across
    # the row's agents (ddof=1) at the stages 0, 400 (255 and 509 of a budget of 800 -> nearest 400), 800 frames
    with (out / "probe.csv").open() as file:
        probe = list(csv.DictReader(file))
    with (out / TABLES_1_6_CSV).open() as file:
        tables = list(csv.DictReader(file))
    assert len(tables) == 2 * 5 * 3 * 4  # rows x columns x layers x stages
    numbers = {(t["row"], t["column"]): t["table"] for t in tables}
    assert [numbers[("well-performing", c)] for c in summary["columns"]] == ["1", "3", "5", "", ""]
    assert [numbers[("poorly performing", c)] for c in summary["columns"]] == ["2", "4", "6", "", ""]
    for entry in tables:
        seeds = ["seed 0", "seed 1"] if entry["row"] == "well-performing" else ["seed 2", "seed 3"]
        names = summary["columns"][entry["column"]]
        per_agent = [
            np.mean([float(r["test_mse"]) for r in probe if r["agent"] == agent and r["layer"] == entry["layer"]
                     and int(r["frames"]) == int(entry["frame"]) and r["component"] in names])
            for agent in seeds
        ]  # fmt: skip
        assert float(entry["std"]) == pytest.approx(np.std(per_agent, ddof=1), rel=1e-6, abs=1e-12)
    assert [int(t["frame"]) for t in tables[:4]] == [0, 400, 400, 800]
    assert {t["std"] for t in tables if t["layer"] == "cnn0"} == {"0.0"}  # the pixels are the same for every agent
    assert any(float(t["std"]) > 0 for t in tables if t["layer"] == "mlp1")  # the noisy actors differ
    # the HTML report of the sweep shows Figure 2 and the tables
    capsys.readouterr()
    report = write_report(root)  # the progress on, stderr captured: one line per stage, no bar frames
    err = capsys.readouterr().err
    assert "fixed-set metrics: walker-walk / drqv2\n" in err and "\r" not in err
    page = (root / "report" / "index.html").read_text()
    assert "Figure 2" in page and "Table 1" in page
    # Figure 4 on the rollouts probe sweep recorded (all 20 observations: fewer than the 2048 drawn by default)
    assert (root / "report" / COLLAPSE_PNG.format(task="walker-walk", variant="drqv2")).exists()
    inputs = report.collapse_inputs[("walker-walk", "drqv2")]
    assert inputs.source == out / "rollouts.npz" and len(inputs.indices) == inputs.total == 20
    named = "all 20 observations of walker-walk_drqv2/rollouts.npz, 5 episodes, recorded from walker-walk/drqv2/seed_0/"
    assert f"fixed probing set ({named}final_model.zip at 800 frames)" in page
    # Two checkpoints at once, each with half the memory budget: the same results.
    assert probe_main([*argv, "--layers", "cnn0", "cnn4", "mlp1", "--no-progress", "--overwrite", "--jobs", "2"]) == 0
    with (out / "probe.csv").open() as file:
        assert list(csv.DictReader(file)) == probe
    assert json.loads((out / "summary.json").read_text())["jobs"] == 2
    capsys.readouterr()
    # a trial without snapshots: the message says how to get them
    shutil.rmtree(root / "walker-walk" / "drqv2" / "seed_3" / SNAPSHOTS_DIR)
    assert probe_main([*argv, "--overwrite", "--no-progress"]) == 2
    assert "--snapshots" in capsys.readouterr().err


def test_probe_sweep_pools_good_agents_and_splits_per_agent(run, tmp_path, capsys):
    # Rollouts "collected from well-performing agents": the two best seeds' rollouts pooled; each agent's probe on
    # its own split: cnn0 (the pixels, the same for every agent at every stage) then varies across agents.
    root = write_probe_sweep(tmp_path / "sweep", run.run_dir, {0: 950.0, 1: 920.0, 2: 20.0, 3: 10.0})
    argv = ["sweep", str(root), "--task", "walker-walk", "--episodes", "7", "--max-steps", "3", "--max-tau", "4"]
    argv += ["--layers", "cnn0", "mlp1", "--no-progress", "--pool-agents", "2", "--split-per-agent"]
    assert probe_main(argv) == 0
    out = root / SWEEP_PROBE_DIR.format(task="walker-walk", variant="drqv2")
    summary = json.loads((out / "summary.json").read_text())
    sources = summary["rollouts"]["recorded_from"].split(", ")
    assert [Path(source).parent.name for source in sources] == ["seed_0", "seed_1"]  # the two best
    assert (summary["rollouts"]["episodes"], summary["rollouts"]["samples"]) == (7, 21)  # 4 + 3 episodes
    assert summary["settings"]["split_per_agent"] is True
    with (out / TABLES_1_6_CSV).open() as file:
        tables = list(csv.DictReader(file))
    cnn0 = [t for t in tables if t["layer"] == "cnn0" and t["table"] in ("1", "2", "3", "4", "5", "6")]
    assert all(float(t["std"]) > 0 for t in cnn0)  # each agent's split: cnn0 differs across agents...
    for row in ("well-performing", "poorly performing"):
        stds = {t["std"] for t in cnn0 if t["row"] == row and t["column"] == "torso height"}
        assert len(stds) == 1  # ...and is the same at every stage (the same pixels, the same splits)
    # More agents to pool than well-performing seeds: one line naming the flag, nothing written.
    assert probe_main([*argv[:-3], "--pool-agents", "3", "--overwrite"]) == 2
    assert "--pool-agents=3 but walker-walk / drqv2 has 2 well-performing trial(s)" in capsys.readouterr().err


def test_figure4_metrics_on_the_fixed_probing_set(run, tmp_path):
    """Every snapshot of the picked agents run on the same observations: the metrics are layer_metrics of
    the snapshot's activations of those observations."""
    root = write_probe_sweep(tmp_path / "sweep", run.run_dir, {0: 950.0, 2: 400.0, 3: 10.0})
    recorder = load_checkpoint(root / "walker-walk" / "drqv2" / "seed_0" / "final_model.zip").model
    rollouts = record_rollouts(recorder, resolve_env_config(recorder.env_config), 2, max_steps=6, progress=False)
    path = rollouts.save(tmp_path / "rollouts.npz")
    settings = FixedInputSettings(pick_seed=1, rollouts=path, fixed_samples=8, sample_seed=5, device="cpu")
    report = write_report(root, progress=False, collapse_settings=settings)
    key = ("walker-walk", "drqv2")
    folder = root / "report"
    assert (folder / COLLAPSE_PNG.format(task=key[0], variant=key[1])).exists()
    assert (folder / COLLAPSE_ONLINE_PNG.format(task=key[0], variant=key[1])).exists()
    # the fixed set: 8 of the 12 observations, drawn with sample_seed
    indices = np.sort(np.random.default_rng(5).choice(12, size=8, replace=False))
    inputs = report.collapse_inputs[key]
    np.testing.assert_array_equal(inputs.indices, indices)
    np.testing.assert_array_equal(inputs.observations, rollouts.observations[indices])
    assert inputs.task == "walker-walk" and inputs.fits("walker-walk") and not inputs.fits("hopper-stand")
    picks = report.collapse_picks[key]
    assert [(p.role, p.candidates) for p in picks] == [
        ("well-performing", [0]), ("middle", [2]), ("poorly performing", [3])
    ]  # fmt: skip
    with (folder / COLLAPSE_FIXED_CSV.format(task=key[0], variant=key[1])).open() as file:
        values = {(int(r["seed"]), r["checkpoint"], r["tag"]): float(r["value"]) for r in csv.DictReader(file)}
    rows = report.collapse[key]
    for pick, row in zip(picks, rows):
        assert row.trial is pick.trial and row.widths == {"mlp1": 64, "mlp2": 64}  # hidden_dim 64
        files = sorted((pick.trial.path / SNAPSHOTS_DIR).glob("*.zip"))
        assert len(files) == 3 and list(row.metrics["collapse/mlp1/dead_units"][0]) == [0, 400, 800]
        for index, file in enumerate(files):
            activations = collect_activations(load_checkpoint(file).model, rollouts.observations[indices])
            for layer in ("mlp1", "mlp2"):
                expected = layer_metrics(activations[layer])
                for metric, value in expected.items():
                    tag = f"collapse/{layer}/{metric}"
                    assert values[(pick.trial.seed, file.name, tag)] == pytest.approx(value, rel=1e-9, nan_ok=True)
                for metric in ("numerical_rank", "input_correlation", "dead_units"):  # the default reading
                    tag = f"collapse/{layer}/{metric}"
                    assert row.metrics[tag][1][index] == pytest.approx(expected[metric], rel=1e-9, nan_ok=True)
    # the seeds' snapshots differ (noise added per seed), so do their metrics on the same inputs
    ranks = [row.metrics["collapse/mlp1/numerical_rank"][1][-1] for row in rows]
    assert ranks[0] != ranks[2]
    with (folder / COLLAPSE_AGENTS_CSV).open() as file:
        agents = list(csv.DictReader(file))
    assert [(a["row"], a["seed"], a["pick_seed"]) for a in agents] == [
        ("well-performing", str(picks[0].trial.seed), "1"), ("middle", "2", "1"), ("poorly performing", "3", "1")
    ]  # fmt: skip
    assert {a["inputs"] for a in agents} == {inputs.describe()} and "8 of the 12 observations" in inputs.describe()
    # rollouts whose images do not fit the checkpoints: the message names the rollouts, in the probe and the report
    small = dataclasses.replace(inputs, observations=inputs.observations[:, :, :24, :24])
    with pytest.raises(InputError, match="rollouts") as error:
        fixed_metrics(snapshot_files(picks[0].trial.path), small, ("mlp1",))
    assert error.value.parameter == "rollouts"
    with pytest.raises(InputError, match="rollouts") as error:
        fixed_agent_rows(picks[:1], small, settings)
    assert error.value.parameter == "rollouts"


def test_a_run_folder_report_runs_its_snapshots_on_a_fixed_set(run, tmp_path, capsys, monkeypatch):
    """`report RUN --rollouts FILE`: the run's own snapshots on that fixed set, beside its online figure; the flags
    that only a sweep uses are refused with a run folder, not ignored."""
    recorder = load_checkpoint(run.model_path).model
    rollouts = record_rollouts(recorder, resolve_env_config(recorder.env_config), 2, max_steps=6, progress=False)
    path = rollouts.save(tmp_path / "rollouts.npz")
    out = tmp_path / "report"
    argv = [str(run.run_dir), "--out", str(out), "--rollouts", str(path), "--fixed-samples", "8", "--device", "cpu"]
    assert report_main([*argv, "--no-progress"]) == 0
    assert {p.name for p in out.iterdir()} == {
        RUN_COLLAPSE_PNG,
        RUN_COLLAPSE_FIXED_PNG,
        RUN_COLLAPSE_FIXED_CSV,
        "index.html",
    }
    settings = FixedInputSettings(rollouts=path, fixed_samples=8, device="cpu")
    inputs = settings.load(path)
    expected = fixed_metrics(snapshot_files(run.run_dir), inputs, settings.layers)
    with (out / RUN_COLLAPSE_FIXED_CSV).open() as file:
        rows = list(csv.DictReader(file))
    assert {int(r["frame"]) for r in rows} == {0, 400, 800} and {r["role"] for r in rows} == {"run"}
    for layer in ("mlp1", "mlp2"):
        tag = f"collapse/{layer}/input_correlation"
        written = [float(r["value"]) for r in rows if r["tag"] == tag]
        np.testing.assert_allclose(written, expected.metrics[tag][1], rtol=1e-9)
    assert inputs.describe() in (out / "index.html").read_text()
    # only the sweep's flags: refused in one line naming them, nothing written
    with pytest.raises(SystemExit) as stop:
        report_main([*argv, "--overwrite", "--tasks", "walker-walk", "--pick-seed", "3"])
    assert stop.value.code == 2 and "--tasks, --pick-seed: for a sweep folder;" in capsys.readouterr().err
    # a run without snapshots has no fixed-set figure: one line naming --rollouts
    bare = tmp_path / "bare"
    shutil.copytree(run.run_dir, bare, ignore=shutil.ignore_patterns(SNAPSHOTS_DIR, "checkpoints"))
    assert report_main([str(bare), "--rollouts", str(path), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert f"error: --rollouts: {bare} has no snapshots to run on them (train with --snapshots)." in err
    assert not (bare / "report").exists()
    # rollouts of another task
    other = dataclasses.replace(inputs, task="hopper-stand")
    monkeypatch.setattr(FixedInputSettings, "load", lambda self, path: other)
    with pytest.raises(InputError, match="recorded on hopper-stand, not on the run's walker-walk") as error:
        write_run_report(run.run_dir, tmp_path / "other", collapse_settings=settings)
    assert error.value.parameter == "rollouts" and not (tmp_path / "other").exists()


def test_figure4_reads_one_observation_set_per_task(run, tmp_path):
    """By default every variant of a task runs on the baseline's rollouts (probe sweep's, of drqv2), named in the
    figure; --rollouts-per-variant reads each variant's own."""
    root = write_probe_sweep(tmp_path / "sweep", run.run_dir, {0: 950.0, 2: 400.0, 3: 10.0})
    shutil.copytree(root / "walker-walk" / "drqv2", root / "walker-walk" / "drqv2+reset")  # the same agents
    checkpoint = load_checkpoint(root / "walker-walk" / "drqv2" / "seed_0" / "final_model.zip")
    files = {}
    for variant, seed in (("drqv2", 0), ("drqv2+reset", 1)):  # two sets: other episode seeds
        folder = root / SWEEP_PROBE_DIR.format(task="walker-walk", variant=variant)
        folder.mkdir(parents=True)
        files[variant] = record(checkpoint, RecordOptions(episodes=2, max_steps=6, seed=seed), False).save(
            folder / "rollouts.npz"
        )
    settings = FixedInputSettings(fixed_samples=None, device="cpu")
    report = write_report(root, progress=False, collapse_settings=settings)
    base, ruled = (
        report.collapse_inputs[("walker-walk", "drqv2")],
        report.collapse_inputs[("walker-walk", "drqv2+reset")],
    )
    assert base is ruled and base.source == files["drqv2"] and base.recorded_frames == 800
    named = (
        "12 observations of walker-walk_drqv2/rollouts.npz, 2 episodes, recorded from "
        "walker-walk/drqv2/seed_0/final_model.zip at 800 frames"
    )
    assert named in base.describe()
    page = (root / "report" / "index.html").read_text()
    assert page.count(named) >= 2  # both figures' captions
    fixed = {}
    for variant in ("drqv2", "drqv2+reset"):
        with (root / "report" / COLLAPSE_FIXED_CSV.format(task="walker-walk", variant=variant)).open() as file:
            fixed[variant] = {(r["seed"], r["checkpoint"], r["tag"]): r["value"] for r in csv.DictReader(file)}
    assert fixed["drqv2"] == fixed["drqv2+reset"]  # the same agents on the same observations
    # the other reading: each variant on its own rollouts, other observations, other values
    own = dataclasses.replace(settings, rollouts_variant=None)
    other = write_report(root, out=tmp_path / "own", progress=False, collapse_settings=own)
    assert other.collapse_inputs[("walker-walk", "drqv2+reset")].source == files["drqv2+reset"]
    assert other.collapse_inputs[("walker-walk", "drqv2")].source == files["drqv2"]
    with (tmp_path / "own" / COLLAPSE_FIXED_CSV.format(task="walker-walk", variant="drqv2+reset")).open() as file:
        assert {(r["seed"], r["checkpoint"], r["tag"]): r["value"] for r in csv.DictReader(file)} != fixed["drqv2"]


def test_film_of_checkpoints(run, tmp_path, capfd):
    final = run.model_path
    first = run.run_dir / SNAPSHOTS_DIR / SNAPSHOT_FILE.format(frames=0)
    out = tmp_path / "film"
    argv = [
        "film",
        str(final),
        str(first),
        "--frames",
        "60",
        "--size",
        "64",
        "--every-frames",
        "20",
        "--seeds",
        "0",
        "1",
    ]
    assert probe_main([*argv, "--out", str(out)]) == 0  # the progress on, stderr not a terminal: one line, no bar
    assert capfd.readouterr().err == "filming: 2 checkpoints\n"
    assert sorted(p.name for p in out.iterdir()) == [
        "actions.csv",
        "filmstrip.png",
        "final_model_seed0.gif",
        "final_model_seed1.gif",
        "snapshot_0000000000_frames_seed0.gif",
        "snapshot_0000000000_frames_seed1.gif",
    ]
    with Image.open(out / "final_model_seed0.gif") as gif:
        assert gif.size == (64, 64) and gif.n_frames == 4  # frames 0, 20, 40, 60 at action repeat 20
    with (out / "actions.csv").open() as file:
        rows = list(csv.DictReader(file))
    assert len(rows) == 4 * 4 and [int(r["frame"]) for r in rows[:4]] == [0, 20, 40, 60]
    assert rows[3]["action_0"] == "" and all(-1 <= float(r["action_5"]) <= 1 for r in rows if r["action_5"])
    # the actions are the agent's deterministic ones: filming again gives the same
    model = DrQv2.load(final, buffer_size=64)
    film = film_episode(model, model.env_config, "again", frames=60, size=32, seed=1)
    again = [r for r in rows if r["film"].startswith("final_model") and r["film"].endswith("seed 1")]
    np.testing.assert_allclose(
        [[float(r[f"action_{d}"]) for d in range(6)] for r in again[:3]], film.actions[:3], rtol=1e-6
    )
    image = matplotlib.image.imread(out / "filmstrip.png")
    assert image.shape[0] > 800 and image[..., :3].std() > 0.05
    assert probe_main([*argv, "--out", str(out), "--no-progress"]) == 2  # exists: --overwrite
    with pytest.raises(SystemExit) as exit_status:  # a value out of its declared range: the parser's one line
        probe_main(["film", str(final), "--frames", "0", "--out", str(tmp_path / "x"), "--no-progress"])
    assert exit_status.value.code == 2
    assert not (tmp_path / "x").exists()


def test_probe_sweep_probes_around_an_evaluation_file_cut_mid_row(run, tmp_path, capsys):
    """A finished trial whose evaluation file ends in half a row is damaged: named with the file, the line and the
    way out on the terminal and in the summary; the readable trials are probed (exit 0)."""
    from sb3_collapse.protocol import EVAL_CSV

    root = write_probe_sweep(tmp_path / "sweep", run.run_dir, {0: 950.0, 1: 940.0, 2: 20.0, 3: 10.0})
    evaluations = root / "walker-walk" / "drqv2" / "seed_3" / EVAL_CSV
    evaluations.write_text(evaluations.read_text().rstrip("\n").rsplit(",", 1)[0] + "\n")
    argv = ["sweep", str(root), "--task", "walker-walk", "--episodes", "3", "--max-steps", "3", "--max-tau", "2"]
    assert probe_main([*argv, "--layers", "mlp1", "--no-progress"]) == 0
    out = capsys.readouterr().out
    summary = json.loads(
        (root / SWEEP_PROBE_DIR.format(task="walker-walk", variant="drqv2") / "summary.json").read_text()
    )
    assert [(a["seed"], a["row"]) for a in summary["agents"]] == [
        (0, "well-performing"), (1, "well-performing"), (2, "poorly performing")
    ]  # fmt: skip
    (damaged,) = summary["damaged"]
    assert damaged["seed"] == 3 and damaged["reason"].startswith(f"{evaluations}, line ")
    assert damaged["reason"].endswith("move the folder aside to train this seed again.")
    assert f"Not probed: seed 3: {damaged['reason']}" in out
