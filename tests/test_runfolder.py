"""One run-folder layer: every status on fabricated folders, the same status and final return for the sweep, the
report and the probe, and no module outside the layer reading the evaluation or result file."""

import ast
import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from sb3_collapse.protocol import FAILURE_HEADER, trial_path
from sb3_collapse.report.loading import load_sweep, load_trial
from sb3_collapse.run.lock import RunLock
from sb3_collapse.runfolder import NOT_A_RUN, RunStatus, final_return, read_evaluations, run_status
from sb3_collapse.sweep.donors import donor_candidates

PACKAGE = Path(__file__).resolve().parents[1] / "sb3_collapse"
LAYER = {"protocol.py", "runfolder.py"}
EVAL_HEADER = "frame,step,mean_reward,std_reward,episodes,wall_time_s\n"
EVAL_ROWS = "0,0,1.0,0.0,10,1.0\n1000,500,950.0,0.0,10,2.0\n2000,1000,20.0,0.0,10,3.0\n"


def _write(folder: Path, files: dict[str, str]) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for name, text in files.items():
        (folder / name).write_text(text)


FINISHED_FILES = {
    "config.json": "{}",
    "eval.csv": EVAL_HEADER + EVAL_ROWS,
    "result.json": json.dumps({"status": "finished", "frames": 2000, "resets": 0, "saved_model_eval": {}}),
}
# name -> (files, or None for no folder; status; final return)
CASES = {
    "no folder": (None, RunStatus.NEW, None),
    "empty": ({}, RunStatus.NEW, None),
    "a free lock file only": ({"run.lock": "pid 999999999 on host nowhere since x\n"}, RunStatus.NEW, None),
    "failed before training": (
        {"config.json": "{}", "error.txt": FAILURE_HEADER.format(step=0, frame=0) + "\nTraceback"},
        RunStatus.NEW,
        None,
    ),
    "stopped": ({"config.json": "{}", "eval.csv": EVAL_HEADER + EVAL_ROWS}, RunStatus.UNFINISHED, None),
    "failed while training": (
        {"config.json": "{}", "error.txt": FAILURE_HEADER.format(step=40, frame=80) + "\nTraceback"},
        RunStatus.FAILED,
        None,
    ),
    "failed in the sweep": ({"error.txt": "Traceback (most recent call last)"}, RunStatus.FAILED, None),
    "a result that is not finished": ({"config.json": "{}", "result.json": '{"status": '}, RunStatus.FAILED, None),
    "finished": (FINISHED_FILES, RunStatus.FINISHED, 20.0),
    "finished, a result file of another version": (
        {
            **FINISHED_FILES,
            "eval.csv": EVAL_HEADER + EVAL_ROWS + "3000,1500,999.0,0.0,10,4.0\n",
            "result.json": json.dumps({"status": "finished", "frames": 3000, "resets": 0}),  # no saved_model_eval
        },
        RunStatus.FINISHED,
        None,
    ),
    "finished without an evaluation file": ({**FINISHED_FILES, "eval.csv": ""}, RunStatus.FINISHED, None),
    "other files": ({"notes.txt": "mine"}, None, None),
}


def _fabricate(root: Path) -> dict[str, Path]:
    folders = {}
    for seed, (name, (files, _, _)) in enumerate(CASES.items()):
        folders[name] = trial_path(root, "walker-walk", "drqv2", seed)
        if files is not None:
            _write(folders[name], files)
    return folders


@pytest.mark.parametrize("name", list(CASES))
def test_every_status_on_fabricated_folders(tmp_path, name):
    folder = _fabricate(tmp_path)[name]
    _, status, final = CASES[name]
    assert run_status(folder) == status
    assert final_return(folder) == final


def test_running_while_a_process_holds_the_lock_and_a_file_is_no_run(tmp_path):
    folder = tmp_path / "run"
    _write(folder, {"config.json": "{}"})
    with RunLock(folder):
        assert run_status(folder) == RunStatus.RUNNING == "running"
        assert run_status(folder, check_lock=False) == RunStatus.UNFINISHED  # the process that holds the lock
    assert run_status(folder) == RunStatus.UNFINISHED
    _write(folder, FINISHED_FILES)
    with RunLock(folder):  # finishing: its result file is written, the lock not released yet
        assert run_status(folder) == RunStatus.FINISHED
    (tmp_path / "afile").write_text("")
    assert run_status(tmp_path / "afile") is None


def test_scheduled_evaluations_tolerate_a_row_being_written(tmp_path):
    _write(tmp_path, {"config.json": "{}", "eval.csv": EVAL_HEADER + EVAL_ROWS + "3000,1500,5"})
    frames, returns = read_evaluations(tmp_path, partial=True)
    assert frames.tolist() == [0, 1000, 2000] and returns.tolist() == [1.0, 950.0, 20.0]
    with pytest.raises(ValueError, match=r"eval.csv, line 5: the number of fields differs"):
        read_evaluations(tmp_path)
    _write(tmp_path, {"eval.csv": EVAL_HEADER + "1000,500,1.0,0.0,10,1.0\n0,0,1.0,0.0,10,1.0\n"})
    with pytest.raises(ValueError, match="frames must increase row by row, but frame 0 follows 1000"):
        read_evaluations(tmp_path, partial=True)


def test_sweep_report_and_probe_read_the_same_status_and_final_return(tmp_path):
    folders = _fabricate(tmp_path)
    del folders["no folder"]
    # The report refuses a sweep with a file it cannot read; the status stays the same.
    for name, file in (
        ("a result that is not finished", "result.json"),
        ("finished without an evaluation file", "eval.csv"),
    ):
        with pytest.raises(ValueError, match=rf"{file}: (not a readable JSON file|missing column)"):
            load_trial("walker-walk", "drqv2", 0, folders[name])
        shutil.rmtree(folders.pop(name))
    with pytest.raises(ValueError, match=r"result\.json has no 'saved_model_eval': it was written by another version"):
        load_trial("walker-walk", "drqv2", 0, folders["finished, a result file of another version"])
    shutil.rmtree(folders.pop("finished, a result file of another version"))
    by_seed = {int(folder.name.removeprefix("seed_")): name for name, folder in folders.items()}
    # The report's trials (and the probe's: python -m sb3_collapse.probe sweep reads the sweep with load_sweep).
    sweep = load_sweep(tmp_path, include_unfinished=True, progress=False)
    assert {by_seed[t.seed]: t.status for t in sweep.trials} == {
        name: str(run_status(folder) or NOT_A_RUN) for name, folder in folders.items()
    }
    for name in ("finished",):
        trial = load_trial("walker-walk", "drqv2", 0, folders[name])
        assert trial.final_return == final_return(folders[name]) == CASES[name][2]
        assert trial.frames.tolist() == [0, 1000, 2000]
    assert math.isnan(next(t for t in sweep.trials if by_seed[t.seed] == "stopped").final_return)
    # The sweep's donors: the finished seeds with a final model, by the same final return.
    for name in ("finished",):
        (folders[name] / "final_model.zip").write_bytes(b"")
    (folders["stopped"] / "final_model.zip").write_bytes(b"")
    classes = donor_candidates(tmp_path, "walker-walk", success_return=15.0, failure_return=30.0)
    assert [(by_seed[d.seed], d.final_return) for d in classes["good"]] == [
        ("finished", 20.0),
    ]
    assert np.isclose(sorted(t.final_return for t in sweep.finished if len(t.returns)), [20.0]).all()


READ_CALLS = {"open", "read_text", "read_bytes", "loads", "load", "DictReader", "reader", "read_json", "read_csv"}
RUN_FILES = {"EVAL_CSV", "RESULT_JSON", "eval.csv", "result.json"}


def run_file_reads(source: str) -> list[int]:
    """
    :param source: a module's source
    :return: the lines where it reads the evaluation or result file: a read call (``open``, ``read_text``,
        ``json.loads``...) whose arguments or receiver name the file (the protocol's constant or the literal), or a
        variable assigned from an expression that does
    """
    tree = ast.parse(source)

    def names(node: ast.AST) -> set[str]:
        found = set()
        for sub in ast.walk(node):
            if isinstance(sub, ast.Name):
                found.add(sub.id)
            elif isinstance(sub, ast.Attribute):
                found.add(sub.attr)
            elif isinstance(sub, ast.Constant) and isinstance(sub.value, str):
                found.add(sub.value)
        return found

    tainted = set(RUN_FILES)
    for node in ast.walk(tree):
        if isinstance(node, ast.Assign) and names(node.value) & RUN_FILES:
            tainted |= {target.id for target in node.targets if isinstance(target, ast.Name)}
    lines = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Call):
            function = node.func.attr if isinstance(node.func, ast.Attribute) else getattr(node.func, "id", "")
            if function in READ_CALLS and names(node) & tainted:
                lines.append(node.lineno)
    return sorted(set(lines))


def test_the_lint_finds_a_read_of_the_run_files():
    assert run_file_reads("json.loads((folder / RESULT_JSON).read_text())") == [1]
    assert run_file_reads("path = run_dir / 'eval.csv'\nwith path.open() as f:\n    pass") == [2]
    assert run_file_reads("write_json_atomically(run_dir / RESULT_JSON, summary)\nprint(RESULT_JSON)") == []


def test_only_the_run_folder_layer_reads_the_evaluation_and_result_files():
    offenders = {
        str(path.relative_to(PACKAGE)): lines
        for path in sorted(PACKAGE.rglob("*.py"))
        if path.name not in LAYER and (lines := run_file_reads(path.read_text()))
    }
    assert offenders == {}


def test_an_unreadable_result_file_stays_failed_and_names_the_file_the_reason_and_the_way_out(tmp_path, capsys):
    """run_status says failed (not repaired); unreadable_result is one line; a run named by --logdir passes it over."""
    from sb3_collapse.run.config import TrainConfig
    from sb3_collapse.run.folder import new_run_dir
    from sb3_collapse.runfolder import DAMAGED_RESULT_WAY_OUT, read_result, unreadable_result

    folder = tmp_path / "run"
    _write(folder, {"config.json": "{}", "result.json": "[1, 2"})
    assert run_status(folder) == RunStatus.FAILED and read_result(folder) is None and final_return(folder) is None
    reason = unreadable_result(folder)
    assert reason == (
        f"{folder / 'result.json'}: not a readable JSON file (Expecting ',' delimiter: line 1 column 6 (char 5)); "
        f"{DAMAGED_RESULT_WAY_OUT}."
    )
    assert "\n" not in reason and DAMAGED_RESULT_WAY_OUT == "move the folder aside to train this seed again"
    _write(folder, {"result.json": "[1, 2]"})  # readable, but not an object
    assert unreadable_result(folder).startswith(f"{folder / 'result.json'}: expected a JSON object, got list; move")
    assert unreadable_result(tmp_path / "nothing") is None

    config = TrainConfig(env="cartpole-balance").resolve()
    assert new_run_dir(tmp_path, "run", config) == tmp_path / "run_2"
    assert capsys.readouterr().out == (
        f"{folder}: {unreadable_result(folder)} Not resuming it.\n"
        f"Training into {tmp_path / 'run_2'}: run holds an unreadable result file.\n"
    )


def test_a_run_named_by_logdir_says_which_folder_it_takes_when_not_the_first(tmp_path, capsys):
    """A finished run and a folder that is not a run are passed over with one line naming the new folder and why."""
    from sb3_collapse.run.config import TrainConfig
    from sb3_collapse.run.folder import new_run_dir

    config = TrainConfig(env="cartpole-balance").resolve()
    assert new_run_dir(tmp_path, "run", config) == tmp_path / "run"
    assert capsys.readouterr().out == ""  # the first folder: nothing to say
    _write(tmp_path / "run", FINISHED_FILES)
    _write(tmp_path / "run_2", {"notes.txt": "mine"})
    assert run_status(tmp_path / "run") == RunStatus.FINISHED and run_status(tmp_path / "run_2") is None
    assert new_run_dir(tmp_path, "run", config) == tmp_path / "run_3"
    assert capsys.readouterr().out == (
        f"Training into {tmp_path / 'run_3'}: run holds a finished run (result.json); run_2 is not a run folder.\n"
    )
