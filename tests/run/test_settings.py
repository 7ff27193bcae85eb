"""Each training setting is declared once, on its TrainConfig field; the flags, --show-settings and docs/presets.md
are generated from the declarations."""

import ast
import dataclasses
from pathlib import Path

import pytest

from sb3_collapse.presets import SETTING_NAMES
from sb3_collapse.run.config import RUN, TRAINING, UNITS, TrainConfig, setting
from sb3_collapse.run.settings import (
    MARKDOWN_BEGIN,
    MARKDOWN_END,
    main,
    setting_flags,
    settings_markdown,
    show_settings,
    training_arguments,
    with_markdown,
)
from sb3_collapse.sweep.__main__ import build_parser as sweep_parser
from sb3_collapse.train import CLI_ONLY_FLAGS, build_parser

REPO_ROOT = Path(__file__).resolve().parents[2]
FIELDS = {field.name: field for field in dataclasses.fields(TrainConfig)}


def test_every_field_declares_help_unit_and_preset():
    for name, field in FIELDS.items():
        metadata = field.metadata
        assert {"help", "unit", "preset", "cli"} <= set(metadata), f"{name} is not declared with setting()"
        assert isinstance(metadata["help"], str) and len(metadata["help"]) > 10, f"{name} has no help"
        assert metadata["unit"] in UNITS, name
        assert metadata["preset"] == (name in SETTING_NAMES), f"{name}: preset={metadata['preset']}"
        assert metadata["cli"] in (TRAINING, RUN, None), name
        if metadata["preset"]:  # the task's preset fills it, for the train CLI and the sweep alike
            assert field.default is None and metadata["cli"] == TRAINING, name
    with pytest.raises(ValueError, match="unit must be one of"):
        setting(1, help="a count", unit="seconds")


def _setting_actions(parser):
    return [action for action in parser._actions if action.option_strings and action.dest != "help"]


def test_every_flag_is_a_field_with_its_declared_spelling():
    flags = setting_flags()
    train_actions = _setting_actions(build_parser())
    for action in train_actions:
        if action.option_strings[0] in CLI_ONLY_FLAGS:
            continue
        assert action.dest in FIELDS, f"{action.option_strings} has no TrainConfig field"
        assert action.option_strings == [flags[action.dest]]
    # Every field with a flag is on the train CLI; the spellings users type are kept.
    assert {action.dest for action in train_actions} >= set(flags)
    assert {flags[name] for name in ("learning_rate", "tf32", "progress_bar")} == {
        "--lr",
        "--no-tf32",
        "--no-progress-bar",
    }
    assert build_parser().parse_args(["--no-tf32", "--no-progress-bar"]).tf32 is False
    with pytest.raises(SystemExit):
        build_parser().parse_args(["--replay-sampling", "reference"])
    # The sweep's training flags: the same, one per field declared cli=TRAINING.
    shared = {action.dest for action in _setting_actions(training_arguments())}
    assert shared == {name for name, field in FIELDS.items() if field.metadata["cli"] == TRAINING}
    sweep_dests = {action.dest for action in _setting_actions(sweep_parser())}
    assert shared <= sweep_dests


def test_defaults_of_the_flags_are_the_fields():
    parsed = vars(build_parser().parse_args([]))
    parsed.pop("show_settings")
    assert TrainConfig(**parsed) == TrainConfig()


def test_show_settings_lists_every_field(capsys):
    config = TrainConfig(env="cheetah-run", batch_size=64).resolve()
    lines = show_settings(config)
    flags = setting_flags()
    for name in FIELDS.keys() - {"sources"}:
        label = name if name not in flags or flags[name].startswith("--no-") else flags[name]
        assert any(line.split()[0] == label for line in lines), name
    assert any(line.startswith("--batch-size") and "64  (user)" in line for line in lines)
    assert any(line.startswith("--frames") and "(preset)  [frames]" in line for line in lines)


def test_presets_doc_holds_the_generated_tables(tmp_path, capsys):
    doc = (REPO_ROOT / "docs" / "presets.md").read_text()
    assert doc == with_markdown(doc), (
        "docs/presets.md is out of date: run python -m sb3_collapse.run.settings --markdown docs/presets.md"
    )
    region = doc[doc.index(MARKDOWN_BEGIN) : doc.index(MARKDOWN_END)]
    assert all(f"| `{name}` |" in region for name in FIELDS)
    copy = tmp_path / "presets.md"
    copy.write_text(doc.replace(region, MARKDOWN_BEGIN))
    assert main(["--markdown", str(copy)]) == 0 and copy.read_text() == doc
    assert main(["--markdown"]) == 0 and capsys.readouterr().out == settings_markdown() + "\n"


def test_no_package_module_imports_the_train_command():
    package = REPO_ROOT / "sb3_collapse"
    for path in package.rglob("*.py"):
        if path == package / "train.py":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom):
                names = [node.module or ""] + [f"{node.module}.{alias.name}" for alias in node.names]
            elif isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            else:
                continue
            assert "sb3_collapse.train" not in names, f"{path.relative_to(REPO_ROOT)} imports the train command"
