"""The paper's numbers live in sb3_collapse.paper, the run-folder format in sb3_collapse.protocol."""

import argparse
import json
import os
import re
from pathlib import Path

import pytest

from sb3_collapse import CollapseMetrics, CollapseReset
from sb3_collapse.commands.cli import cli_message
from sb3_collapse.errors import ParameterError
from sb3_collapse.paper import PAPER
from sb3_collapse.protocol import (
    CONFIG_JSON,
    write_json_atomically,
)
from sb3_collapse.report import ReportSettings
from sb3_collapse.runfolder import read_json

PACKAGE = Path(__file__).resolve().parents[1] / "sb3_collapse"
# The paper's numbers (window, threshold, success return) live in paper.py (and DrQ-v2's presets); the run-folder
# file names in protocol.py alone.
NUMBER_OWNERS = {"paper.py", "presets.py"}
NUMBERS = re.compile(r"\b(200_000|200000|200,000|1e-3|0\.001|900(\.0)?)\b")
FILE_NAME_OWNERS = {"protocol.py"}
FILE_NAMES = re.compile(
    r"(result\.json|eval\.csv|collapse_metrics\.csv|collapse_events\.csv|config\.json|final_model|error\.txt|"
    r"sweep\.json)"
)


def _lines_matching(pattern: re.Pattern, owners: set[str]) -> list[str]:
    return [
        f"{path.relative_to(PACKAGE)}:{number}: {line.strip()}"
        for path in sorted(PACKAGE.rglob("*.py"))
        if path.name not in owners
        for number, line in enumerate(path.read_text().splitlines(), 1)
        if pattern.search(line)
    ]


def test_protocol_literals_live_in_the_protocol_module_only():
    assert _lines_matching(NUMBERS, NUMBER_OWNERS) == []
    assert _lines_matching(FILE_NAMES, FILE_NAME_OWNERS) == []


def test_the_paper_numbers_and_who_reads_them():
    assert (PAPER.check_every_frames, PAPER.window_frames, PAPER.threshold, PAPER.patience) == (
        10_000,
        200_000,
        1e-3,
        5,
    )
    assert (PAPER.layer, PAPER.success_return, PAPER.failure_return) == ("mlp1", 900.0, 30.0)
    assert PAPER.collapse_tag == "collapse/mlp1/grad_norm"
    with pytest.raises(AttributeError):
        PAPER.threshold = 0.1  # frozen
    rule = CollapseReset()
    assert (rule.window_frames, rule.check_every_frames, rule.threshold, rule.patience, rule.layer) == (
        200_000,
        10_000,
        1e-3,
        5,
        "mlp1",
    )
    assert CollapseMetrics().check_every_frames == 10_000
    report = ReportSettings()
    assert (report.collapse_threshold, report.collapse_checks, report.success_return) == (1e-3, 5, 900.0)
    assert report.collapse_tag == PAPER.collapse_tag and report.percentiles == (5.0, 95.0)


def test_atomic_writer_follows_the_umask(tmp_path):
    previous = os.umask(0o022)
    try:
        write_json_atomically(tmp_path / "result.json", {"status": "finished"})
    finally:
        os.umask(previous)
    assert (tmp_path / "result.json").stat().st_mode & 0o777 == 0o644
    assert not list(tmp_path.glob(".*.tmp"))


def test_library_errors_name_parameters_and_clis_translate():
    parser = argparse.ArgumentParser()
    parser.add_argument("--lr", dest="learning_rate")
    parser.add_argument("--eval-every-frames", dest="eval_every_frames")
    parser.add_argument("--episodes")
    parser.add_argument("--overwrite", action="store_true")
    parser.add_argument("--out")
    error = ParameterError("learning_rate", "learning_rate must be > 0 (or set eval_every_frames=0).")
    assert cli_message(error, parser) == "--lr must be > 0 (or set --eval-every-frames=0)."
    assert (
        cli_message(ParameterError("episodes", "episodes must be >= 1, got 0."), parser)
        == "--episodes must be >= 1, got 0."
    )
    assert cli_message(ValueError("3 episodes recorded: pass `overwrite=True` or another `out`."), parser) == (
        "3 episodes recorded: pass --overwrite or another --out."
    )


def test_a_settings_file_of_another_version_is_not_resumed(tmp_path):
    from sb3_collapse.run.config import TrainConfig
    from sb3_collapse.run.folder import settings_differences

    config = TrainConfig(env="walker-walk", frames=800, snapshots=True, collapse_metrics_batch=16)
    saved = json.loads(json.dumps(config.record()))
    write_json_atomically(tmp_path / CONFIG_JSON, saved)
    assert settings_differences(read_json(tmp_path / CONFIG_JSON), config) == []
    saved["probe_checkpoints"] = saved.pop("snapshots")  # a name this version does not have, one it has missing
    write_json_atomically(tmp_path / CONFIG_JSON, saved)
    assert settings_differences(read_json(tmp_path / CONFIG_JSON), config) == [
        "`probe_checkpoints=None` (the run folder has True)",
        "`snapshots=True` (the run folder has None)",
    ]
