"""Each training setting is declared once, on its TrainConfig field; the flags, --show-settings and docs/presets.md
are generated from the declarations."""

import argparse
import ast
import dataclasses
import sys
from pathlib import Path

import pytest

import sb3_collapse.commands.probe as probe_cli
import sb3_collapse.commands.report as report_cli
import sb3_collapse.commands.reproduce as reproduce_cli
from sb3_collapse.commands import probe_pipelines
from sb3_collapse.commands.cli import (
    FLAGS_END,
    MARKDOWN_BEGIN,
    MARKDOWN_END,
    CommandLine,
    flag_of,
    main,
    parsed_values,
    prog_name,
    setting_flags,
    settings_markdown,
    show_settings,
    training_arguments,
    with_markdown,
)
from sb3_collapse.commands.sweep import build_parser as sweep_parser
from sb3_collapse.commands.train import build_parser
from sb3_collapse.presets import SETTING_NAMES
from sb3_collapse.probe import ProbeSettings
from sb3_collapse.probe.pipeline import RecordOptions
from sb3_collapse.run.config import RUN, TRAINING, UNITS, TrainConfig, declared, setting

REPO_ROOT = Path(__file__).resolve().parents[2]
FIELDS = {field.name: field for field in dataclasses.fields(TrainConfig)}
CLI_ONLY_FLAGS = ("--show-settings",)  # the train CLI's flags that are no setting


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
        "docs/presets.md is out of date: run python -m sb3_collapse.commands.cli --markdown docs/presets.md"
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


# The probe's, the report's and the reproduction's flags: declared once with setting(), in their modules of commands/.

CLIS = {"sb3_collapse.probe": probe_cli, "sb3_collapse.report": report_cli, "sb3_collapse.reproduce": reproduce_cli}
POSITIONALS = {
    "run": ["a.zip"],
    "sweep": ["runs", "--task", "walker-walk"],
    "film": ["a.zip"],
    "record": ["a.zip"],
    "health": ["a.zip"],
}


def _subparsers(cli):
    """Sub-command ("" for none) -> (its parser, the arguments it needs)."""
    parser = cli.build_parser()
    if cli in (report_cli, reproduce_cli):
        return {"": (parser, ["runs"] if cli is report_cli else ["--out", "runs"])}
    (action,) = [action for action in parser._actions if isinstance(action, argparse._SubParsersAction)]
    return {command: (action.choices[command], POSITIONALS[command]) for command in cli.COMMANDS}


@pytest.mark.parametrize("package", CLIS)
def test_every_probe_report_and_reproduce_flag_is_declared_with_help_and_unit(package):
    cli = CLIS[package]
    for command, (parser, needed) in _subparsers(cli).items():
        declared = {  # the settings with a flag (the library's FixedInputSettings has a few without)
            field.name: field
            for declaration in cli.COMMANDS[command]
            for field in dataclasses.fields(declaration)
            if flag_of(field) is not None
        }
        actions = [action for action in parser._actions if action.dest != "help"]
        assert {action.dest for action in actions} == set(declared), command
        for action in actions:
            field = declared[action.dest]
            flag = flag_of(field)
            assert (action.option_strings or [action.dest]) == [flag], (command, flag)
            assert isinstance(field.metadata["help"], str) and len(field.metadata["help"]) >= 10, flag
            assert field.metadata["unit"] in UNITS, flag
        # The parser's defaults are the declarations'.
        parsed = parser.parse_args(needed)
        for name, field in declared.items():  # --rollouts-variant: None until given (--rollouts-per-variant refuses it)
            if flag_of(field).startswith("-") and not field.metadata["required"] and name != "rollouts_variant":
                assert getattr(parsed, name) == field.default, (command, name)


def test_probe_flags_keep_their_spellings_and_defaults():
    parser = probe_cli.build_parser()
    args = parser.parse_args(["run", "a.zip", "b.zip", "--split", "0.5", "0.25", "0.25", "--no-progress"])
    assert args.checkpoints == ["a.zip", "b.zip"] and args.fractions == [0.5, 0.25, 0.25] and args.progress is False
    assert ProbeSettings(**parsed_values(args, ProbeSettings)) == ProbeSettings(
        fractions=(0.5, 0.25, 0.25), progress=False
    )
    args = parser.parse_args(["record", "a.zip", "--stochastic", "--noise-std", "0.1"])
    assert RecordOptions(**parsed_values(args, RecordOptions)) == RecordOptions(deterministic=False, noise_std=0.1)
    assert parser.parse_args(["sweep", "runs", "--task", "walker-walk"]).jobs == 1
    assert parser.parse_args(["film", "a.zip", "--seeds", "0", "1"]).seeds == [0, 1]
    report = report_cli.build_parser().parse_args(["runs", "--percentiles", "10", "90", "--tasks", "walker-walk"])
    assert report.percentiles == [10.0, 90.0] and report.tasks == ["walker-walk"] and report.progress is True


@pytest.mark.parametrize("page", ["probe.md", "sweeps.md", "reproduce.md"])
def test_flag_tables_of_the_docs_are_fresh(page, tmp_path):
    doc = (REPO_ROOT / "docs" / page).read_text()
    assert doc == with_markdown(doc), (
        f"docs/{page} is out of date: run python -m sb3_collapse.commands.cli --markdown docs/{page}"
    )
    package = {"probe.md": "sb3_collapse.probe", "sweeps.md": "sb3_collapse.report"}.get(page, "sb3_collapse.reproduce")
    cli = CLIS[package]
    for declarations in cli.COMMANDS.values():
        for field in (field for declaration in declarations for field in dataclasses.fields(declaration)):
            assert flag_of(field) is None or f"| `{flag_of(field)}`" in doc, field.name
    begin = doc.index("<!-- flags of")
    region = doc[doc.index("\n", begin) + 1 : doc.index(FLAGS_END)]
    copy = tmp_path / page
    copy.write_text(doc.replace(region, ""))
    assert main(["--markdown", str(copy)]) == 0 and copy.read_text() == doc


def _fail(*args, **kwargs):
    raise AssertionError("work started before the arguments were checked")


@pytest.mark.parametrize(
    "package, argv, flag, problem",
    [
        ("sb3_collapse.probe", ["a.zip", "--layers", "mlp9"], "--layers", "invalid choice: 'mlp9'"),
        ("sb3_collapse.probe", ["a.zip", "--max-tau", "0"], "--max-tau", "must be >= 1, got 0."),
        (
            "sb3_collapse.probe",
            ["a.zip", "--split", "0.5", "0.5", "1.5"],
            "--split",
            "summing to 1 (train validation test), got [0.5, 0.5, 1.5].",
        ),
        ("sb3_collapse.probe", ["a.zip", "--memory-gb", "0"], "--memory-gb", "must be > 0, got 0.0."),
        ("sb3_collapse.probe", ["a.zip", "--noise-std", "-1"], "--noise-std", "must be >= 0, got -1.0."),
        ("sb3_collapse.probe", ["sweep", "runs", "--task", "t", "--jobs", "0"], "--jobs", "must be >= 1, got 0."),
        ("sb3_collapse.probe", ["film", "a.zip", "--size", "8"], "--size", "must be >= 16, got 8."),
        ("sb3_collapse.probe", ["record", "a.zip", "--episodes", "0"], "--episodes", "must be >= 1, got 0."),
        ("sb3_collapse.report", ["runs", "--collapse-checks", "0"], "--collapse-checks", "must be >= 1, got 0."),
        ("sb3_collapse.report", ["runs", "--percentiles", "5", "101"], "--percentiles", "must be <= 100, got 101.0."),
        ("sb3_collapse.report", ["runs", "--fixed-samples", "1"], "--fixed-samples", "must be >= 2 (0: all), got 1."),
        ("sb3_collapse.reproduce", ["--out", "x", "--transplant-seeds", "0"], "--transplant-seeds", "must be >= 1"),
        ("sb3_collapse.reproduce", ["--out", "x", "--cpus-per-trial", "0"], "--cpus-per-trial", "must be > 0"),
    ],
)
def test_a_bad_value_exits_2_with_one_line_naming_the_flag_before_any_work(
    package, argv, flag, problem, monkeypatch, capsys
):
    cli = CLIS[package]
    for name in (
        "probe_to_folder",
        "probe_sweep",
        "film_to_folder",
        "record_to_file",
        "write_report",
        "is_run_folder",
        "run_stages",
        "dry_run",
    ):
        if hasattr(cli, name):
            monkeypatch.setattr(cli, name, _fail)
    monkeypatch.setattr(sys, "argv", ["/venv/bin/sb3-collapse-" + package.rsplit(".", 1)[1]])
    with pytest.raises(SystemExit) as exit_info:
        cli.main(argv)
    assert exit_info.value.code == 2
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert last.startswith("sb3-collapse-") and f": error: {flag}" in last.replace("argument ", "") and problem in last


def test_split_that_does_not_sum_to_1_is_refused_before_recording(monkeypatch, capsys):
    monkeypatch.setattr(probe_pipelines, "load_checkpoint", _fail)
    monkeypatch.setattr(probe_pipelines, "record", _fail)
    with pytest.raises(SystemExit) as exit_info:  # the sub-command's line, as every other --split error
        probe_cli.main(["a.zip", "--split", "0.5", "0.5", "0.5"])
    assert exit_info.value.code == 2 and capsys.readouterr().err.endswith(
        "run: error: --split must be 3 positive fractions summing to 1 (train validation test), got [0.5, 0.5, 0.5].\n"
    )


@pytest.mark.parametrize(
    "module", ["sb3_collapse.probe", "sb3_collapse.report", "sb3_collapse.train", "sb3_collapse.sweep"]
)
def test_console_scripts_name_themselves(module, monkeypatch):
    build = {
        "sb3_collapse.probe": probe_cli.build_parser,
        "sb3_collapse.report": report_cli.build_parser,
        "sb3_collapse.train": build_parser,
        "sb3_collapse.sweep": sweep_parser,
    }[module]
    script = "sb3-collapse-" + module.rsplit(".", 1)[1]
    monkeypatch.setattr(sys, "argv", [f"/venv/bin/{script}", "--help"])
    assert prog_name(module) == script and build().prog == script
    assert build().format_usage().startswith(f"usage: {script} ")
    monkeypatch.setattr(sys, "argv", [f"/src/{module.replace('.', '/')}/__main__.py"])
    assert build().prog == f"python -m {module}"


def test_probe_help_shows_each_default_once_as_typed(capsys):
    with pytest.raises(SystemExit):
        probe_cli.main(["run", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "(default: 0.6 0.2 0.2)" in text and "[0.6, 0.2, 0.2]" not in text and "(0.6, 0.2, 0.2)" not in text
    assert text.count("(default: 64)") == 1 and "(default: 64) (default" not in text
    assert "--no-progress do not show the progress bars" in text


def test_command_line_errors_are_one_line_with_a_pointer_to_help(capsys):
    parser = CommandLine(prog="tool")
    parser.add_argument("--n", type=int)
    sub = parser.add_subparsers(dest="command").add_parser("go")  # a sub-command's parser is one too
    sub.add_argument("--m", type=int, required=True)
    for argv, expected in (
        (["--n", "x"], "tool --help lists the flags.\ntool: error: argument --n: invalid int value: 'x'"),
        (["go"], "tool go --help lists the flags.\ntool go: error: the following arguments are required: --m"),
    ):
        with pytest.raises(SystemExit) as exit_info:
            parser.parse_args(argv)
        assert exit_info.value.code == 2 and capsys.readouterr().err == expected + "\n"


def test_a_settings_help_is_the_docstring_under_it_unless_given():
    @declared
    @dataclasses.dataclass
    class Flags:
        first: int = setting(1, unit="frames")
        """frames to skip,
        then more words"""
        second: int = setting(2, help="given")
        """not this one"""

    helps = {field.name: field.metadata["help"] for field in dataclasses.fields(Flags)}
    assert helps == {"first": "frames to skip, then more words", "second": "given"}
    assert FIELDS["frames"].metadata["help"].startswith("training budget, in frames")

    with pytest.raises(ValueError, match="Undocumented.third has no help"):

        @declared
        @dataclasses.dataclass
        class Undocumented:
            third: int = setting(3)


def test_a_dict_key_in_a_message_is_not_turned_into_a_flag():
    """The flag translation turned policy_kwargs['hidden_dim'] into policy_kwargs['--hidden-dim']: a key stays, the
    bare name of a setting still becomes its flag."""
    from sb3_collapse.commands.cli import cli_message
    from sb3_collapse.commands.train import build_parser
    from sb3_collapse.errors import ParameterError

    error = ParameterError(
        "policy_kwargs['hidden_dim']",
        "policy_kwargs['hidden_dim'] must be an integer >= 1, got 0 (or pass hidden_dim).",
    )
    assert cli_message(error, build_parser()) == (
        "policy_kwargs['hidden_dim'] must be an integer >= 1, got 0 (or pass --hidden-dim)."
    )
    assert cli_message(ParameterError("x", 'kwargs["feature_dim"] and feature_dim'), build_parser()) == (
        'kwargs["feature_dim"] and --feature-dim'
    )
