"""Figures 4/8/9, Figure 3(b), Table 7 and the HTML page of the report, from the fabricated sweep."""

import csv
import shutil

import matplotlib.image
import numpy as np
import pytest
from browser import check_page
from fabricated_sweep import TRANSPLANT_FRAMES, write_fake_sweep

from sb3_collapse.protocol import PAPER
from sb3_collapse.report import write_report
from sb3_collapse.report.__main__ import main
from sb3_collapse.report.collapse_figure import pick_agents
from sb3_collapse.report.loading import Trial, read_collapse_metrics
from sb3_collapse.report.pipeline import COLLAPSE_PNG, FIGURE3B_PNG, RUN_COLLAPSE_PNG, TABLE7_CSV, write_run_report
from sb3_collapse.report.statistics import stage_indices


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


def test_collapse_figures_pick_the_fabricated_agents(reported):
    fake, report = reported
    files = {path.name for path in report.files}
    for task, variant in (
        ("walker-walk", "drqv2"),
        ("walker-walk", "drqv2+reset"),
        ("hopper-stand", "drqv2"),
        ("hopper-stand", "drqv2+reset"),
    ):
        name = COLLAPSE_PNG.format(task=task, variant=variant)
        assert name in files
        image = matplotlib.image.imread(report.files[[p.name for p in report.files].index(name)])
        assert image.shape[0] > 500 and image.shape[1] > 1000 and image[..., :3].std() > 0.05
        finals = sorted((-t.returns[-1], t.seed) for t in fake.select(task, variant))
        agents = report.collapse[(task, variant)]
        assert [a.role for a in agents] == ["best", "middle", "worst"]
        assert [a.trial.seed for a in agents] == [finals[0][1], finals[(len(finals) - 1) // 2][1], finals[-1][1]]
    assert not any(name.startswith("collapse_metrics_walker-walk_cnn-") for name in files)
    # walker-walk / drqv2: the worst seed collapsed for good (fabricated: seeds 1 and 3), the best succeeded
    walker = report.collapse[("walker-walk", "drqv2")]
    assert walker[0].final_return >= PAPER.success_return and walker[-1].final_return < PAPER.failure_return
    frames, ranks = walker[-1].metrics["collapse/mlp1/numerical_rank"]
    assert len(frames) == 20 and ranks.max() < 3.0  # collapsed all along: rank ~1-3
    # seed 2 of walker-walk / drqv2+reset: resets at 60k and 120k, escape at 170k, from collapse_events.csv
    reset_agents = {a.trial.seed: a for a in report.collapse[("walker-walk", "drqv2+reset")]}
    seed2 = next(t for t in fake.select("walker-walk", "drqv2+reset") if t.seed == 2)
    assert reset_agents[2].role == "worst"  # escaped last (170k frames): the lowest final return
    assert reset_agents[2].resets == seed2.reset_frames and reset_agents[2].escapes == [seed2.escape_frame]
    # a nan grad-norm row is dropped, not drawn: seed 4 of walker-walk / drqv2 has two
    seed4 = read_collapse_metrics(fake.path / "walker-walk" / "drqv2" / "seed_4" / "collapse_metrics.csv")
    assert len(seed4["collapse/mlp1/grad_norm"][0]) == 18 and len(seed4["collapse/mlp2/grad_norm"][0]) == 18


def test_table7_matches_the_fabricated_returns(reported):
    fake, report = reported
    assert FIGURE3B_PNG in {p.name for p in report.files}
    frames = np.arange(0, TRANSPLANT_FRAMES + 1, 10_000)
    stages = stage_indices(frames)
    assert [int(frames[i]) for i in stages] == [0, 20_000, 30_000, 50_000]  # 0.32 x 50k -> 20k, 0.64 x 50k -> 30k
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


def test_html_page_loads_every_image_and_table_in_chromium(reported, tmp_path):
    _, report = reported
    page = report.files[0].parent / "index.html"
    text = page.read_text()
    assert "http://" not in text and "https://" not in text and "<script" not in text  # nothing from the network
    result = check_page(page, tmp_path)
    pngs = [p for p in report.files if p.suffix == ".png"]
    assert len(result["images"]) == len(pngs) == 7  # figure 5, 4 collapse figures, the grid, figure 3(b)
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
    assert trial.status == "running" and len(trial.frames) == 21 and len(files) == 2
    (run / "eval.csv").unlink()
    assert main([str(run), "--no-progress", "--overwrite"]) == 2  # no longer a run folder, nor a sweep
