"""The transplant donors of Study 2: two different agents per source, picked at random with a recorded seed."""

import json
import sys
from pathlib import Path

import pytest

from sb3_collapse.commands.sweep import build_parser, main, transplant_checkpoints
from sb3_collapse.errors import InputError
from sb3_collapse.sweep import Trial, donor_candidates, pick_donors, trial_config
from sb3_collapse.sweep.donors import donors_record, final_return
from sb3_collapse.sweep.runner import sweep_settings

sys.path.insert(0, str(Path(__file__).parent.parent / "report"))
from fabricated_sweep import write_fake_sweep, write_final_models


@pytest.fixture(scope="module")
def finished_sweep(tmp_path_factory):
    """The fabricated sweep, its walker-walk/drqv2 seeds with a final model: seeds 0, 2, 4 escape (~930), seeds 1
    and 3 stay collapsed (~25), seed 5 is running and seed 6 failed."""
    fake = write_fake_sweep(tmp_path_factory.mktemp("donor_sweep") / "sweep")
    write_final_models(fake)
    return fake


def test_candidates_are_the_papers_classes(finished_sweep):
    finals = {t.seed: float(t.returns[-1]) for t in finished_sweep.select("walker-walk", "drqv2")}
    classes = donor_candidates(finished_sweep.path, "walker_walk")
    assert [d.seed for d in classes["good"]] == [s for s, v in sorted(finals.items()) if v >= 900] == [0, 2, 4]
    assert [d.seed for d in classes["bad"]] == [s for s, v in sorted(finals.items()) if v < 30] == [1, 3]
    for donor in classes["good"] + classes["bad"]:
        assert donor.final_return == pytest.approx(finals[donor.seed]) and Path(donor.path).is_file()
    # The final return is the last scheduled evaluation; a result file of another version gives none.
    folder = finished_sweep.path / "walker-walk" / "drqv2" / "seed_0"
    assert final_return(folder) == pytest.approx(finals[0])
    result = json.loads((folder / "result.json").read_text())
    (folder / "result.json").write_text(json.dumps({k: v for k, v in result.items() if k != "saved_model_eval"}))
    try:
        assert final_return(folder) is None
    finally:
        (folder / "result.json").write_text(json.dumps(result))
    assert final_return(finished_sweep.path / "walker-walk" / "drqv2" / "seed_5") is None  # running


def test_good_cnn_and_good_mlp_come_from_two_agents_reproducibly(finished_sweep):
    draws = [pick_donors(finished_sweep.path, "walker-walk", seed=seed) for seed in range(12)]
    for donors in draws:
        assert donors["good_cnn"].seed != donors["good_mlp"].seed
        assert {donors["good_cnn"].seed, donors["good_mlp"].seed} <= {0, 2, 4}
        assert {donors["bad_cnn"].seed, donors["bad_mlp"].seed} == {1, 3}
    assert pick_donors(finished_sweep.path, "walker-walk", seed=7) == draws[7]  # the seed gives the same donors
    assert len({(d["good_cnn"].seed, d["good_mlp"].seed) for d in draws}) > 1  # and the seed matters
    with pytest.raises(InputError, match="has 0 finished seed.*pass --good-cnn PATH --good-mlp PATH"):
        pick_donors(finished_sweep.path, "walker-walk", variant="drqv2+reset", sources=["good"], success_return=2000)


def test_donors_from_a_sweep_are_recorded_and_start_the_cells(finished_sweep, tmp_path, capsys):
    out = tmp_path / "grid"
    argv = ["--tasks", "walker-walk", "--seeds", "1", "--transplant-grid", "--donors-from", str(finished_sweep.path),
            "--donor-seed", "5", "--out", str(out)]  # fmt: skip
    args = build_parser().parse_args(argv)
    trials = [Trial("walker-walk", variant, 0) for variant in ("cnn-good_mlp-good", "cnn-bad_mlp-bad")]
    checkpoints, record = transplant_checkpoints(args, trials)
    picked = pick_donors(finished_sweep.path, "walker-walk", seed=5)
    assert record == donors_record(finished_sweep.path, 5, "drqv2", {"walker-walk": picked})
    assert record["tasks"]["walker-walk"]["good_cnn"]["seed"] == picked["good_cnn"].seed
    settings = sweep_settings(trials, {"frames": 800}, checkpoints, {}, record)
    assert json.loads(json.dumps(settings))["donors"]["seed"] == 5  # what sweep.json records
    good = trial_config(trials[0], out, {"frames": 800}, checkpoints)
    assert good.init_cnn == picked["good_cnn"].path and good.init_mlp == picked["good_mlp"].path
    assert good.init_cnn != good.init_mlp  # good x good is a new agent, not one reloaded
    bad = trial_config(trials[1], out, {"frames": 800}, checkpoints)
    assert {bad.init_cnn, bad.init_mlp} == {picked["bad_cnn"].path, picked["bad_mlp"].path}
    # The dry run lists the donors.
    assert main([*argv, "--dry-run"]) == 0
    printed = capsys.readouterr().out
    assert f"donor walker-walk good_cnn: seed {picked['good_cnn'].seed}" in printed and not out.exists()


def test_one_agent_for_both_parts_is_refused(finished_sweep, tmp_path, capsys):
    model = finished_sweep.path / "walker-walk" / "drqv2" / "seed_0" / "final_model.zip"
    common = ["--tasks", "walker-walk", "--seeds", "1", "--variants", "cnn-good_mlp-good", "--out", str(tmp_path)]
    cases = [
        (["--good-cnn", str(model), "--good-mlp", str(model)], "--good-cnn and --good-mlp give the same checkpoint"),
        (["--donors-from", str(finished_sweep.path), "--good-cnn", str(model)], "leave out --good-cnn"),
    ]
    for extra, message in cases:
        with pytest.raises(SystemExit) as exit_info:
            main([*common, *extra])
        err = capsys.readouterr().err
        assert exit_info.value.code == 2 and message in err and len(err.strip().splitlines()[-1]) > 0, extra
