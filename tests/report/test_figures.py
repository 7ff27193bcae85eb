"""Figures 4/8/9, Figure 3(b), Table 7 and the HTML page of the report, from the fabricated sweep."""

import csv
import shutil

import matplotlib.image
import numpy as np
import pytest
from browser import check_page
from fabricated_sweep import TRANSPLANT_FRAMES, write_fake_sweep

from sb3_collapse.commands.report import main
from sb3_collapse.commands.report_pipelines import FixedInputSettings, build_report, write_report, write_run_report
from sb3_collapse.errors import InputError
from sb3_collapse.monitoring import CORRELATION_READINGS, FIGURE_CORRELATION
from sb3_collapse.paper import PAPER, evaluation_schedule
from sb3_collapse.probe.fixed_inputs import FixedInputs
from sb3_collapse.report import collapse_figure, figure2
from sb3_collapse.report.collapse_figure import (
    CORRELATION_LABELS,
    GRAD_NORM_FLOOR,
    PAPER_ROLES,
    AgentMetrics,
    agent_class,
    agent_metrics,
    figure4_metrics,
    pick_agents,
    pick_paper_agents,
    plot_collapse_metrics,
)
from sb3_collapse.report.figure2 import PanelCurve, stage_table_rows
from sb3_collapse.report.loading import Sweep, Trial
from sb3_collapse.report.pipeline import (
    COLLAPSE_AGENTS_CSV,
    COLLAPSE_ONLINE_PNG,
    COLLAPSE_PNG,
    FIGURE3B_PNG,
    RUN_COLLAPSE_PNG,
    TABLE7_CSV,
)
from sb3_collapse.report.statistics import stage_indices, transplant_curves
from sb3_collapse.runfolder import read_collapse_metrics


@pytest.fixture(scope="module")
def reported(tmp_path_factory):
    """The fabricated sweep and its report (written once for the module)."""
    root = tmp_path_factory.mktemp("figures") / "sweep"
    fake = write_fake_sweep(root)
    report = write_report(root, progress=False)
    return fake, report


def _trial(seed: int, final: float) -> Trial:
    return Trial("walker-walk", "drqv2", seed, None, "finished", {}, np.array([0, 10]), np.array([0.0, final]))


def test_pick_agents_best_median_worst():
    trials = [_trial(0, 500.0), _trial(1, 25.0), _trial(2, 950.0), _trial(3, 700.0), _trial(4, 950.0)]
    picked = [(role, t.seed) for role, t in pick_agents(trials)]
    # ranks: 950 (seed 2, tie to the smaller seed), 950 (4), 700 (3), 500 (0), 25 (1): median = third
    assert picked == [("best", 2), ("middle", 3), ("worst", 1)]
    assert [(r, t.seed) for r, t in pick_agents(trials[:2])] == [("best", 0), ("worst", 1)]
    assert [(r, t.seed) for r, t in pick_agents(trials[:1])] == [("best", 0)]
    unfinished = _trial(5, 999.0)
    unfinished.status = "running"
    assert pick_agents([unfinished]) == []


def test_agent_classes_follow_the_paper_thresholds():
    assert PAPER.success_return == 900.0 and PAPER.failure_return == 30.0
    assert [agent_class(x) for x in (950.0, 900.0, 899.99, 30.0, 29.99, -1.0)] == [
        "well-performing", "well-performing", "middle", "middle", "poorly performing", "poorly performing"
    ]  # fmt: skip


def test_pick_paper_agents_by_class_at_random_with_a_recorded_seed():
    finals = {0: 950.0, 1: 25.0, 2: 930.0, 3: 400.0, 4: 910.0, 5: 10.0, 6: 29.0, 7: 960.0, 8: 700.0}
    trials = [_trial(seed, final) for seed, final in finals.items()]
    picks = pick_paper_agents(trials, pick_seed=3)
    assert [p.role for p in picks] == list(PAPER_ROLES)
    assert [p.candidates for p in picks] == [[0, 2, 4, 7], [3, 8], [1, 5, 6]]
    assert {p.seeds for p in picks} == {9} and {p.pick_seed for p in picks} == {3}
    # each class: one of its own seeds, drawn by numpy.random.default_rng([pick_seed, k]) over its seeds in order
    for k, pick in enumerate(picks):
        assert pick.trial.seed == pick.candidates[int(np.random.default_rng([3, k]).integers(len(pick.candidates)))]
    # reproducible for a seed (whatever the order of the trials), and other seeds pick other agents
    assert [p.trial.seed for p in pick_paper_agents(trials[::-1], pick_seed=3)] == [p.trial.seed for p in picks]
    chosen = {tuple(p.trial.seed for p in pick_paper_agents(trials, pick_seed=s)) for s in range(20)}
    assert len(chosen) > 1
    for choice in chosen:
        assert finals[choice[0]] >= 900 and 30 <= finals[choice[1]] < 900 and finals[choice[2]] < 30
    # no middle agent: the row says so, never an agent of another class
    no_middle = [t for t in trials if t.seed not in (3, 8)]
    picks = pick_paper_agents(no_middle, pick_seed=3)
    assert picks[1].trial is None and picks[1].candidates == []
    assert picks[1].absent == "no middle agent among 7 seeds"
    assert picks[0].trial.seed in (0, 2, 4, 7) and picks[2].trial.seed in (1, 5, 6)
    # unfinished trials are not candidates
    running = _trial(9, 500.0)
    running.status = "running"
    assert pick_paper_agents([running, _trial(10, 950.0)])[1].absent == "no middle agent among 1 seeds"
    with pytest.raises(ValueError, match="failure_return"):
        pick_paper_agents(trials, success_return=20.0)


def test_collapse_figures_pick_the_fabricated_agents(reported):
    fake, report = reported
    files = {path.name: path for path in report.files}
    for task, variant in (
        ("walker-walk", "drqv2"),
        ("walker-walk", "drqv2+reset"),
        ("hopper-stand", "drqv2"),
        ("hopper-stand", "drqv2+reset"),
    ):
        # no rollouts in the fabricated sweep: the online figure only, and a note says why
        assert COLLAPSE_PNG.format(task=task, variant=variant) not in files
        assert any(f"{task} / {variant}: Figure 4 on the probing samples not drawn" in note for note in report.notes)
        name = COLLAPSE_ONLINE_PNG.format(task=task, variant=variant)
        image = matplotlib.image.imread(files[name])
        assert image.shape[0] > 500 and image.shape[1] > 1000 and image[..., :3].std() > 0.05
        agents = report.collapse_online[(task, variant)]
        assert [a.role for a in agents] == list(PAPER_ROLES)
        for agent, pick in zip(agents, report.collapse_picks[(task, variant)]):
            assert agent.trial is pick.trial
            if agent.trial is not None:
                assert agent_class(agent.final_return) == agent.role
    # walker-walk / drqv2: seeds 0, 2, 4 escaped (~930), 1 and 3 collapsed (~25): no middle agent
    walker = report.collapse_online[("walker-walk", "drqv2")]
    assert walker[0].trial.seed in (0, 2, 4) and walker[2].trial.seed in (1, 3)
    assert walker[1].trial is None and walker[1].absent == "no middle agent among 5 seeds"
    frames, ranks = walker[2].metrics["collapse/mlp1/numerical_rank"]
    assert len(frames) == 20 and ranks.max() < 3.0  # collapsed all along: rank ~1-3
    # the zeros column is the count of dead units (fabricated: ~85-95% of 1024 while collapsed)
    frames, dead = walker[2].metrics["collapse/mlp1/dead_units"]
    assert len(frames) == 20 and dead.min() >= 0.85 * 1024 and walker[2].widths == {"mlp1": 1024, "mlp2": 1024}
    # hopper-stand / drqv2: seed 2 is the one middle agent (final ~410)
    hopper = report.collapse_online[("hopper-stand", "drqv2")]
    assert hopper[1].trial.seed == 2 and hopper[0].trial.seed in (1, 3, 4) and hopper[2].trial.seed == 0
    # collapse_agents.csv records every row: seed, final return, its class's seeds, the pick seed
    with files[COLLAPSE_AGENTS_CSV].open() as file:
        rows = {(r["task"], r["variant"], r["row"]): r for r in csv.DictReader(file)}
    middle = rows[("walker-walk", "drqv2", "middle")]
    assert middle["seed"] == "" and middle["final_return"] == "" and middle["seeds"] == "5"
    assert rows[("hopper-stand", "drqv2", "middle")]["seed"] == "2"
    assert rows[("walker-walk", "drqv2", "poorly performing")]["class_seeds"] == "1 3"
    assert {r["pick_seed"] for r in rows.values()} == {"0"} and {r["inputs"] for r in rows.values()} == {"online only"}
    assert not any(name.startswith("collapse_metrics_online_walker-walk_cnn-") for name in files)
    # seed 2 of walker-walk / drqv2+reset: resets at 60k and 120k, escape at 170k, from collapse_events.csv
    seed2 = next(t for t in fake.select("walker-walk", "drqv2+reset") if t.seed == 2)
    trial = next(t for t in report.sweep.select("walker-walk", "drqv2+reset") if t.seed == 2)
    agent = agent_metrics(trial, "middle")
    assert agent.resets == seed2.reset_frames and agent.escapes == [seed2.escape_frame]
    # a nan grad-norm row is dropped, not drawn: seed 4 of walker-walk / drqv2 has two
    seed4 = read_collapse_metrics(fake.path / "walker-walk" / "drqv2" / "seed_4" / "collapse_metrics.csv")
    assert len(seed4["collapse/mlp1/grad_norm"][0]) == 18 and len(seed4["collapse/mlp2/grad_norm"][0]) == 18
    # another pick seed is recorded and may pick another well-performing agent, never another class
    other = write_report(fake.path, out=fake.path / "report_seed7", progress=False,
                         collapse_settings=FixedInputSettings(pick_seed=7))  # fmt: skip
    picks = other.collapse_picks[("walker-walk", "drqv2")]
    assert picks[0].pick_seed == 7 and picks[0].trial.seed in (0, 2, 4) and picks[1].trial is None


def test_the_correlation_column_draws_the_reading_named(reported, tmp_path):
    """The default reading (FIGURE_CORRELATION, high on a collapsed layer: tests/monitoring/test_metrics.py) is the
    column of every row; the other readings of CORRELATION_READINGS are drawn when named."""
    fake, report = reported
    walker = report.collapse_online[("walker-walk", "drqv2")]
    assert {agent.correlation for agent in walker} == {FIGURE_CORRELATION}
    frames, values = walker[2].metrics[f"collapse/mlp1/{FIGURE_CORRELATION}"]  # fabricated: ~0.95 while collapsed
    assert len(frames) == 20 and values.min() > 0.9
    for reading in CORRELATION_READINGS:
        assert figure4_metrics(reading)[1] == (reading, CORRELATION_LABELS[reading])
    with pytest.raises(InputError, match="correlation must be one of") as error:
        FixedInputSettings(correlation="correlation").validate()
    assert error.value.parameter == "correlation"
    # a row of another reading reads that reading's tag and is drawn under its label
    trial = walker[2].trial
    row = agent_metrics(trial, "poorly performing", correlation="unit_abs_correlation")
    assert row.correlation == "unit_abs_correlation" and f"collapse/mlp1/{FIGURE_CORRELATION}" not in row.metrics
    row.metrics["collapse/mlp1/unit_abs_correlation"] = (np.array([0, 10_000]), np.array([0.2, 0.9]))
    plot_collapse_metrics([row], tmp_path / "abs.png", "unit_abs_correlation")
    assert matplotlib.image.imread(tmp_path / "abs.png")[..., :3].std() > 0.05
    with pytest.raises(ValueError, match="one reading of the correlation"):
        plot_collapse_metrics([row, AgentMetrics(None, "middle")], tmp_path / "mixed.png", "mixed")


def test_the_gradient_norm_column_draws_a_collapsed_actors_zeros_on_its_floor(reported, tmp_path, monkeypatch):
    """An exact 0 (a collapsed actor's mlp1: Section 5.1, "always around zero") is drawn on the log axis' floor, not
    left out; the rule's threshold is a line of its own."""
    _, report = reported
    row = agent_metrics(report.collapse_online[("walker-walk", "drqv2")][2].trial, "poorly performing", ["mlp1"])
    row.metrics["collapse/mlp1/grad_norm"] = (
        np.array([0, 10_000, 20_000, 30_000]),
        np.array([2e-2, 0.0, 3e-11, np.nan]),
    )
    drawn = []
    monkeypatch.setattr(collapse_figure.plt, "close", drawn.append)  # keep the figure to read it
    plot_collapse_metrics([row], tmp_path / "grad.png", "title", ["mlp1"])
    (fig,) = drawn
    (ax,) = [ax for ax in fig.axes if ax.get_ylabel().startswith("gradient norm")]
    line, threshold = ax.get_lines()
    np.testing.assert_array_equal(line.get_ydata(), [2e-2, GRAD_NORM_FLOOR, 3e-11, np.nan])
    assert list(threshold.get_ydata()) == [PAPER.threshold] * 2 and ax.get_yscale() == "log"
    assert f"drawn at {GRAD_NORM_FLOOR:g}" in ax.get_ylabel() and ax.get_ylim()[0] <= GRAD_NORM_FLOOR
    assert f"the rule's threshold ({PAPER.threshold:g})" in [text.get_text() for text in fig.legends[0].get_texts()]


def test_every_variant_reads_the_baselines_rollouts_by_default(reported, capsys, tmp_path):
    fake, report = reported
    baseline = fake.path / "probe" / "walker-walk_drqv2" / "rollouts.npz"
    for variant in ("drqv2", "drqv2+reset"):  # no rollouts in the fabricated sweep: the notes name the baseline's
        (note,) = [n for n in report.notes if n.startswith(f"walker-walk / {variant}: Figure 4 on the probing")]
        command = f"python -m sb3_collapse.probe sweep {fake.path} --task walker-walk --variant drqv2,"
        assert f"no {baseline} (run {command}" in note
    own = build_report(fake.path, progress=False, collapse_settings=FixedInputSettings(rollouts_variant=None))
    (note,) = [n for n in own.notes if n.startswith("walker-walk / drqv2+reset: Figure 4 on the probing")]
    assert f"no {fake.path / 'probe' / 'walker-walk_drqv2+reset' / 'rollouts.npz'} " in note
    argv = [str(fake.path), "--out", str(tmp_path / "out"), "--no-progress", "--rollouts-variant", "drqv2"]
    with pytest.raises(SystemExit) as exit_status:  # one reading or the other
        main([*argv, "--rollouts-per-variant"])
    assert exit_status.value.code == 2 and "not allowed with" in capsys.readouterr().err


def test_fixed_set_names_its_trial_checkpoint_and_frame(tmp_path):
    snapshot = tmp_path / "sweep" / "walker-walk" / "drqv2" / "seed_3" / "snapshots" / "snapshot_0000400000_frames.zip"
    inputs = FixedInputs(np.zeros((4, 9, 8, 8), np.uint8), np.array([0, 2, 5, 7]),
                         tmp_path / "sweep" / "probe" / "walker-walk_drqv2" / "rollouts.npz", 10, 2,
                         str(snapshot), "walker-walk", 400_000)  # fmt: skip
    assert inputs.describe() == (
        "the fixed probing set (4 of the 10 observations of walker-walk_drqv2/rollouts.npz, 2 episodes, recorded from "
        "walker-walk/drqv2/seed_3/snapshots/snapshot_0000400000_frames.zip at 400,000 frames)"
    )
    inputs.recorded_from = str(snapshot.parent.parent / "final_model.zip")
    assert "recorded from walker-walk/drqv2/seed_3/final_model.zip at 400,000 frames)" in inputs.describe()


def test_collapse_figure_flags(reported, tmp_path, capsys):
    fake, _ = reported
    (tmp_path / "text.npz").write_text("not a rollouts file")
    for flags, named in (
        (["--rollouts", str(tmp_path / "missing.npz")], "--rollouts"),
        (["--rollouts", str(tmp_path / "text.npz")], "text.npz is not a rollouts file"),  # the probe's error
        (["--failure-return", "950"], "--failure-return"),
    ):
        assert main([str(fake.path), "--out", str(tmp_path / "out"), "--no-progress", *flags]) == 2
        assert named in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_status:  # out of its declared range (0: all): refused before any work
        main([str(fake.path), "--out", str(tmp_path / "out"), "--no-progress", "--fixed-samples", "1"])
    assert exit_status.value.code == 2 and "--fixed-samples must be >= 2 (0: all), got 1." in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
    with pytest.raises(SystemExit) as exit_status:  # the readings by name only
        main([str(fake.path), "--out", str(tmp_path / "out"), "--correlation", "correlation"])
    assert exit_status.value.code == 2 and "--correlation: invalid choice" in capsys.readouterr().err
    flags = ["--correlation", "unit_abs_correlation", "--train-episodes", "--tasks", "hopper-stand"]
    assert main([str(fake.path), "--out", str(tmp_path / "abs"), "--no-progress", *flags]) == 0


def test_table7_matches_the_fabricated_returns(reported):
    fake, report = reported
    assert FIGURE3B_PNG in {p.name for p in report.files}
    frames = np.arange(0, TRANSPLANT_FRAMES + 1, 10_000)
    stages = stage_indices(frames, TRANSPLANT_FRAMES)  # the paper's stages at a budget of 50k: 0, 15,909, 31,818, 50k
    assert [int(frames[i]) for i in stages] == [0, 20_000, 30_000, 50_000]
    with (report.files[0].parent / TABLE7_CSV).open() as file:
        rows = list(csv.DictReader(file))
    good = [r for r in rows if (r["cnn"], r["mlp"]) == ("good", "good")]
    successful = [t for t in fake.select("walker-walk", "cnn-good_mlp-good") if t.returns[-1] >= 900.0]
    assert len(successful) == 2 and {r["successes"] for r in good} == {"2"}  # 899.99 is not a success
    expected = np.std(np.stack([t.returns for t in successful])[:, stages], axis=0, ddof=1)
    np.testing.assert_allclose([float(r["std"]) for r in good], expected, rtol=1e-9)
    cells = {(r["cnn"], r["mlp"]) for r in rows}
    assert not any(mlp == "bad" for _, mlp in cells)  # a bad MLP never succeeds: no curve, no row
    assert {r["std"] for r in rows if (r["cnn"], r["mlp"]) == ("blank", "blank")} == {""}  # one success: no std


def test_tables_1_to_7_read_the_papers_stage_frames(tmp_path):
    # The paper's budget: evaluations at 0, 1e4, ..., 1.09e6 (x in [0, 109]); snapshots add one at 1.1e6.
    budget = PAPER.train_frames
    evaluations = np.array(evaluation_schedule(budget, PAPER.check_every_frames))
    snapshots = np.append(evaluations, budget)
    assert PAPER.stages() == PAPER.stages(budget) == (0, 350_000, 700_000, 1_100_000)
    assert [int(evaluations[i]) for i in stage_indices(evaluations, budget)] == [0, 350_000, 700_000, 1_090_000]
    assert [int(snapshots[i]) for i in stage_indices(snapshots, budget)] == [0, 350_000, 700_000, 1_100_000]
    assert PAPER.stages(50_000) == (0, 15_909, 31_818, 50_000)
    # Table 7: a transplant cell of 3 successful seeds at the paper's budget, returns seed * frame / 1e4
    trials = [
        Trial("walker-walk", "cnn-good_mlp-good", seed, tmp_path, "finished", {"frames": budget}, evaluations,
              np.where(evaluations == evaluations[-1], 950.0, seed * evaluations / 1e4))
        for seed in (1, 2, 3)
    ]  # fmt: skip
    (cell,) = transplant_curves(Sweep(tmp_path, trials))["walker-walk"]
    assert cell.stage_frames == [0, 350_000, 700_000, 1_090_000]
    assert cell.stage_std == pytest.approx([0.0, 35.0, 70.0, 0.0])  # std of (1, 2, 3) x 35 and x 70, ddof=1
    # Tables 1-6: a panel on the snapshots of the same budget, values seed * frame / 1e4
    curve = PanelCurve("well-performing", "torso height", "mlp1", snapshots, np.outer([1, 2, 3], snapshots / 1e4),
                       ["seed 1", "seed 2", "seed 3"])  # fmt: skip
    rows = stage_table_rows([curve], budget)
    assert [r["frame"] for r in rows] == [0, 350_000, 700_000, 1_100_000]
    assert [r["std"] for r in rows] == pytest.approx([0.0, 35.0, 70.0, 110.0])


def test_html_page_loads_every_image_and_table_in_chromium(reported, tmp_path):
    _, report = reported
    page = report.files[0].parent / "index.html"
    text = page.read_text()
    assert "http://" not in text and "https://" not in text and "<script" not in text  # nothing from the network
    result = check_page(page, tmp_path)
    pngs = [p for p in report.files if p.suffix == ".png"]
    assert len(result["images"]) == len(pngs) == 7  # figure 5, 4 online collapse figures, the grid, figure 3(b)
    for image in result["images"]:
        assert image["complete"] and image["width"] > 0 and image["height"] > 0, image
    assert len(result["tables"]) >= 6
    for table in result["tables"]:
        assert table["body_rows"] > 0 and table["columns"] > 0, table
    for expected in ("walker-walk / drqv2", "seed 5", "DrQ-v2 published", "Table 7", "running"):
        assert expected in text


def test_single_run_folder(reported, tmp_path, capsys):
    fake, _ = reported
    run = tmp_path / "walker-walk_s2"
    shutil.copytree(fake.path / "walker-walk" / "drqv2+reset" / "seed_2", run)
    assert main([str(run), "--no-progress"]) == 0
    assert "walker-walk / drqv2+reset / seed 2 (finished)" in capsys.readouterr().out
    image = matplotlib.image.imread(run / "report" / RUN_COLLAPSE_PNG)
    assert image.shape[1] > 1000 and (run / "report" / "index.html").exists()
    assert main([str(run), "--no-progress"]) == 2
    assert "--overwrite" in capsys.readouterr().err
    # an unfinished run is drawn as far as it goes
    (run / "result.json").unlink()
    trial, files = write_run_report(run, out=tmp_path / "partial")
    assert trial.status == "unfinished" and len(trial.frames) == 21 and len(files) == 2  # no process holds it
    (run / "eval.csv").unlink()
    assert main([str(run), "--no-progress", "--overwrite"]) == 2  # no longer a run folder, nor a sweep


def test_figure2_marks_the_columns_and_layers_the_probe_warns_of(tmp_path, monkeypatch):
    frames = np.array([0, 1000])
    curves = [
        PanelCurve("well-performing", column, layer, frames, np.ones((1, 2)), ["seed 1"])
        for column in ("torso height", "torso velocity")
        for layer in ("cnn4", "mlp1")
    ]
    drawn = []
    monkeypatch.setattr(figure2.plt, "close", drawn.append)  # keep the figure to read it
    figure2.plot_figure2(curves, tmp_path / "f.png", "t", flat_columns=["torso velocity"], few_layers=["cnn4"])
    (fig,) = drawn
    titles = {ax.get_title(): ax.title.get_color() for ax in fig.axes}
    flat = "well-performing (1): torso velocity (barely varies)"
    assert titles == {"well-performing (1): torso height": "black", flat: "red"}
    legend = {text.get_text(): text.get_color() for text in fig.legends[0].get_texts()}
    assert legend == {"cnn4*": "red", "mlp1": "black"}
    assert "warnings of summary.json" in fig._suptitle.get_text()
