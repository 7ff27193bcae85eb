"""The top of the report (the paper's headline beside the sweep's, Proposition 1) and what Figure 5 compares."""

import json
import math
from statistics import NormalDist

import numpy as np
import pytest
from fabricated_sweep import FRAMES, write_fake_sweep

from sb3_collapse.commands import report_pipelines
from sb3_collapse.commands.report_pipelines import build_report, write_report
from sb3_collapse.errors import InputError
from sb3_collapse.paper import PAPER, PAPER_RESULTS, PROPOSITION_1
from sb3_collapse.report.headline import (
    escape_interval,
    escape_probability,
    headline_rows,
    proposition1_rows,
    wilson_interval,
)
from sb3_collapse.report.loading import Sweep, Trial, load_trial
from sb3_collapse.report.statistics import ReportSettings, VariantSummary

Z = NormalDist().inv_cdf(0.975)


@pytest.fixture(scope="module")
def fake(tmp_path_factory):
    return write_fake_sweep(tmp_path_factory.mktemp("headline") / "sweep")


def test_wilson_interval_on_known_cases():
    # No success: [0, z^2 / (n + z^2)]; all successes: [n / (n + z^2), 1]; k and n - k mirror each other.
    low, high = wilson_interval(0, 40)
    assert low == 0.0 and high == pytest.approx(Z**2 / (40 + Z**2))
    low, high = wilson_interval(40, 40)
    assert low == pytest.approx(40 / (40 + Z**2)) and high == 1.0
    low, high = wilson_interval(13, 40)
    mirror = wilson_interval(27, 40)
    assert (low, high) == pytest.approx((1 - mirror[1], 1 - mirror[0])) and low < 13 / 40 < high
    assert all(math.isnan(v) for v in wilson_interval(0, 0))


def test_proposition1_on_a_constructed_case(tmp_path):
    # Baseline: 5 of 10 seeds stuck, p = 0.5; the rule: 1.1e6 frames in windows of 2e5, n = 5 whole windows.
    trials = []
    for seed in range(8):
        folder = tmp_path / "walker-walk" / "drqv2+reset" / f"seed_{seed}"
        folder.mkdir(parents=True)
        (folder / "config.json").write_text(json.dumps({"frames": 1_100_000, "reset_window_frames": 200_000}))
        trials.append(Trial("walker-walk", "drqv2+reset", seed, folder, "finished", {"escaped": seed < 7}))
    sweep = Sweep(tmp_path, trials)
    rows = [
        VariantSummary("walker-walk", "drqv2", seeds=10, unfinished=0, stuck=5),
        VariantSummary("walker-walk", "drqv2+reset", seeds=8, unfinished=0, escaped=7, reset_rule_seeds=8),
    ]
    (row,) = proposition1_rows(sweep, rows)
    assert (row.baseline, row.rule, row.windows, row.window_frames) == ("drqv2", "drqv2+reset", 5, 200_000)
    assert row.stuck.fraction == 0.5 and row.predicted.value == pytest.approx(1 - 0.5**5)
    low, high = wilson_interval(5, 10)
    assert row.predicted.interval == pytest.approx((1 - high**5, 1 - low**5))
    assert row.predicted.interval[0] < row.predicted.value < row.predicted.interval[1]
    assert (row.escaped.count, row.escaped.total, row.escaped.interval) == (7, 8, wilson_interval(7, 8))
    # The paper's walker_walk: p = 13/40 and n = 5 give 1 - p^5.
    assert escape_probability(13 / 40, 5) == pytest.approx(1 - (13 / 40) ** 5)
    assert escape_interval((0.0, 1.0), 5) == (0.0, 1.0) and escape_interval((0.5, 0.5), 2) == (0.75, 0.75)


def test_headline_sets_the_papers_numbers_beside_the_sweeps(fake, tmp_path):
    report = write_report(fake.path, out=tmp_path / "report", progress=False)
    assert [row.task for row in report.headline] == ["walker-walk", "hopper-stand"]  # the paper's order
    walker = report.headline[0]
    paper = {result.task: result for result in PAPER_RESULTS}["walker-walk"]
    assert (paper.stuck_baseline, paper.never_escaped_rule, paper.std_baseline, paper.std_rule) == (13, 0, 418.2, 38.2)
    assert walker.paper == paper
    # The fabricated walker-walk: seeds 1 and 3 of drqv2's 5 finished seeds stay collapsed; the rule's 5 escape.
    assert (walker.stuck_baseline.count, walker.stuck_baseline.total) == (2, 5)
    assert walker.stuck_baseline.interval == wilson_interval(2, 5)
    assert (walker.stuck_rule.count, walker.stuck_rule.total) == (0, 5)
    assert (walker.never_escaped_rule.count, walker.never_escaped_rule.total) == (0, 5)
    # The std over the last ten evaluations, from the written returns.
    returns = np.array([t.returns for t in fake.select("walker-walk", "drqv2")])
    expected = np.mean(np.std(returns[:, -PAPER.last_evals :], axis=0, ddof=1))
    assert walker.std_baseline.value == pytest.approx(expected)
    low, high = walker.std_baseline.interval
    assert 0 <= low <= high and math.isfinite(high)
    markdown = (tmp_path / "report" / "summary.md").read_text()
    top = markdown.split("## Proposition 1")[0]
    assert markdown.startswith("# Sweep report\n\n## The paper's headline beside this sweep's")
    assert "| walker-walk | 13/40 | 2/5 (40%, CI " in top
    assert "| 0/40 | 0/5 (0%, CI 0%-43%) | 0/5 (0%, CI 0%-43%) |" in top  # never escaped; stuck at the end
    assert "with the rule, never escaped: paper | this sweep | with the rule, stuck at the end: this sweep |" in top
    assert "| 418.2 | " in top and "| 38.2 | " in top and "| hopper-stand | 8/40 |" in top
    assert f"> {PROPOSITION_1}" in markdown and "| walker-walk | drqv2 |" in markdown  # the summary table follows
    page = (tmp_path / "report" / "index.html").read_text()
    assert page.index("headline beside this sweep") < page.index("Summary table") and "1 - p^n" in page
    # Proposition 1 from the fabricated sweep: p = 2/5, n = 200,000 // 200,000 = 1 window; observed 5/5.
    walker_rule = next(row for row in report.proposition if row.task == "walker-walk")
    assert walker_rule.windows == FRAMES // PAPER.window_frames == 1
    assert walker_rule.predicted.value == pytest.approx(1 - 2 / 5) and walker_rule.escaped.count == 5


def test_the_rules_cell_counts_the_seeds_that_never_escaped(fake, tmp_path):
    # Seed 4 of walker-walk / drqv2+reset: its result file says the rule never saw an escape, yet its mlp1 gradient
    # norms are healthy at the end: never escaped 1/5 (the paper's count), stuck at the end 0/5 (its own column).
    path = fake.path / "walker-walk" / "drqv2+reset" / "seed_4" / "result.json"
    result = json.loads(path.read_text())
    path.write_text(json.dumps(result | {"escaped": False, "escape_frame": None}))
    try:
        report = write_report(fake.path, out=tmp_path / "report", progress=False)
    finally:
        path.write_text(json.dumps(result))
    walker = report.headline[0]
    never, stuck = walker.never_escaped_rule, walker.stuck_rule
    assert (never.count, never.total, never.interval) == (1, 5, wilson_interval(1, 5))
    assert (stuck.count, stuck.total, stuck.interval) == (0, 5, wilson_interval(0, 5))
    low, high = wilson_interval(1, 5)
    cells = f"| 0/40 | 1/5 (20%, CI {100 * low:.0f}%-{100 * high:.0f}%) | 0/5 (0%, CI 0%-43%) |"
    assert cells == "| 0/40 | 1/5 (20%, CI 4%-62%) | 0/5 (0%, CI 0%-43%) |"
    assert cells in (tmp_path / "report" / "summary.md").read_text().split("## Proposition 1")[0]
    page = (tmp_path / "report" / "index.html").read_text()
    for text in ("with the rule, never escaped: paper", "with the rule, stuck at the end: this sweep",
                 "1/5 (20%, CI 4%-62%)", "never saw an escape"):  # fmt: skip
        assert text in page
    # Proposition 1's observed escape reads the same record: 4 of 5
    walker_rule = next(row for row in report.proposition if row.task == "walker-walk")
    assert (walker_rule.escaped.count, walker_rule.escaped.total) == (4, 5)


def test_figure5_has_no_transplant_series(fake, monkeypatch, tmp_path):
    drawn = {}

    def record(curves, path, references=None, partial=None, percentiles=(5.0, 95.0)):
        drawn["curves"], drawn["partial"] = curves, partial
        return plot(curves, path, references, partial, percentiles)

    plot = report_pipelines.plot_figure5
    monkeypatch.setattr(report_pipelines, "plot_figure5", record)
    report = write_report(fake.path, out=tmp_path / "report", include_unfinished=True, progress=False)
    names = {task: [curve.name for curve in curves] for task, curves in drawn["curves"].items()}
    assert names == {"hopper-stand": ["drqv2", "drqv2+reset"], "walker-walk": ["drqv2", "drqv2+reset"]}
    # The running transplant seed (cnn-blank_mlp-blank) is not drawn dotted either; drqv2's unfinished seeds are.
    assert sorted((t.variant, t.seed) for t in drawn["partial"]["walker-walk"]) == [("drqv2", 5), ("drqv2", 6)]
    assert report.grid and "figure3b.png" in {p.name for p in report.files}  # the cells stay in Figure 3
    # A sweep of transplant cells only has no Figure 5 panel.
    only_grid = build_report(fake.path, variants=["cnn-good_mlp-good", "cnn-bad_mlp-bad"], progress=False)
    assert only_grid.curves == {} and only_grid.grid


def test_a_result_file_of_another_version_is_refused(fake):
    folder = fake.path / "walker-walk" / "drqv2" / "seed_0"
    result = json.loads((folder / "result.json").read_text())
    assert load_trial("walker-walk", "drqv2", 0, folder).frames[-1] == result["frames"] == FRAMES
    old = {key: value for key, value in result.items() if key != "saved_model_eval"}
    (folder / "result.json").write_text(json.dumps(old))
    try:
        with pytest.raises(InputError, match=r"result\.json has no 'saved_model_eval': it was written by another"):
            load_trial("walker-walk", "drqv2", 0, folder)
    finally:
        (folder / "result.json").write_text(json.dumps(result))


def test_headline_of_a_task_without_the_rule(fake):
    sweep = build_report(fake.path, variants=["drqv2"], progress=False)
    rows = headline_rows(sweep.sweep, sweep.rows, ReportSettings())
    assert rows[0].stuck_rule is None and rows[0].never_escaped_rule is None and rows[0].stuck_baseline.count == 2
    assert "not in this sweep" in sweep.markdown and "No rule variant with its baseline" in sweep.markdown
