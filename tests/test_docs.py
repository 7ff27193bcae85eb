"""The documentation cannot drift from the code: its links resolve, its commands parse, its layout is complete.

Checked in README.md, docs/*.md and benchmarks/README.md:

- every relative link (``[text](path)``, ``[text](path#anchor)``, images) and every ``path.md#anchor`` reference
  names an existing file and, for an anchor, a heading of that file (GitHub's slugs);
- every repository path shown in backticks (``sb3_collapse/...py``, ``benchmarks/...``, ``docs/...``) exists;
- every ``python -m sb3_collapse.<cli> ...`` command (in code blocks and inline code) uses only flags that the
  command's ``--help`` lists (each CLI's ``main(["--help"])`` is run in-process, once per command);
- every module of ``sb3_collapse/`` is named in docs/layout.md, in the section of its package.

zoo_configs/README.md gets the same checks; the package's docstrings and the command lines' ``--help`` get those of
commands, paths and anchors, and hold no measured figure (benchmarks/README.md holds them; a text links the row).
"""

from __future__ import annotations

import ast
import contextlib
import importlib
import io
import re
import subprocess
import sys
from collections.abc import Iterator
from functools import cache
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "sb3_collapse"
DOCS = sorted([ROOT / "README.md", ROOT / "benchmarks" / "README.md", *(ROOT / "docs").glob("*.md")])
LAYOUT = ROOT / "docs" / "layout.md"

# Sub-commands of the CLIs that have them; the first is the default when the first argument is not a sub-command
# (None: a sub-command is required).
SUBCOMMANDS: dict[str, tuple[tuple[str, ...], str | None]] = {
    "sb3_collapse.probe": (("run", "record", "sweep", "film", "health"), "run"),
    "sb3_collapse.zoo": (("train", "enjoy"), None),
}
FENCE = re.compile(r"^\s*(```|~~~)")
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
ANCHOR_REFERENCE = re.compile(r"(?<![\w/.-])((?:[\w.-]+/)*[\w.-]+\.md)#([\w-]+)")
REPO_PATH = re.compile(
    r"^(?:sb3_collapse|docs|benchmarks|scripts|tests|zoo_configs)/[\w./-]*\.(?:py|md|sh|yml|yaml|png|csv\.gz)$"
)
INLINE_CODE = re.compile(r"(?<!`)(`+)(?!`)(.+?)(?<!`)\1(?!`)", re.DOTALL)
COMMAND = re.compile(r"python -m (sb3_collapse(?:\.\w+)*)([^`\n]*)")
FLAG = re.compile(r"(?<![\w-])(--?[A-Za-z][\w-]*)")


def _relative(path: Path) -> str:
    return str(path.relative_to(ROOT))


def _prose_and_code(path: Path) -> tuple[list[tuple[int, str]], list[tuple[int, str]]]:
    """
    :param path: a markdown file
    :return: its lines outside fenced code blocks (fenced lines blanked, so spans keep their line numbers) and its
        logical lines inside them (a line ending in a backslash joined to the next), each with its line number
    """
    prose, code = [], []
    in_fence, pending, pending_number = False, "", 0
    for number, line in enumerate(path.read_text().splitlines(), 1):
        if FENCE.match(line):
            in_fence = not in_fence
            prose.append((number, ""))
            continue
        if not in_fence:
            prose.append((number, line))
            continue
        prose.append((number, ""))
        if not pending:
            pending_number = number
        if line.rstrip().endswith("\\"):
            pending += line.rstrip()[:-1] + " "
            continue
        code.append((pending_number, pending + line))
        pending = ""
    return prose, code


def _inline_code(prose: list[tuple[int, str]]) -> Iterator[tuple[int, str]]:
    """The inline code spans of ``prose`` (within a paragraph, across its line breaks), with their line numbers."""
    text = "\n".join(line for _, line in prose)
    starts = [0]
    for _, line in prose:
        starts.append(starts[-1] + len(line) + 1)
    for paragraph in re.finditer(r"(?:[^\n]+\n?)+", text):
        for span in INLINE_CODE.finditer(paragraph.group()):
            offset = paragraph.start() + span.start()
            number = prose[max(i for i, start in enumerate(starts[:-1]) if start <= offset)][0]
            yield number, span.group(2).replace("\n", " ")


def _strip_inline_code(line: str) -> str:
    return INLINE_CODE.sub("", line)


def github_slug(heading: str) -> str:
    """
    :param heading: a markdown heading's text (without the leading #s)
    :return: GitHub's anchor for it: the rendered text lower-cased, punctuation dropped (but ``-`` and ``_``),
        each space a hyphen
    """
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading)  # links: their text
    text = text.replace("`", "").strip().lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


@cache
def anchors(path: Path) -> frozenset[str]:
    """
    :param path: a markdown file
    :return: the anchors of its headings, duplicates numbered as GitHub numbers them (``-1``, ``-2``...), and
        those of its HTML anchors (``<a id="env-speed"></a>``: the rows of benchmarks/README.md)
    """
    prose, _ = _prose_and_code(path)
    seen: dict[str, int] = {}
    found = set()
    for _, line in prose:
        found.update(re.findall(r"<a\s+(?:id|name)=\"([^\"]+)\"", line))
        match = re.match(r"^#{1,6}\s+(.*?)\s*#*\s*$", line)
        if not match:
            continue
        slug = github_slug(match.group(1))
        count = seen.get(slug, 0)
        seen[slug] = count + 1
        found.add(slug if count == 0 else f"{slug}-{count}")
    return frozenset(found)


def _check_target(doc: Path, number: int, target: str, roots: tuple[Path, ...]) -> str | None:
    """
    :return: why ``target`` (``path``, ``path#anchor`` or ``#anchor``) named at ``doc:number`` does not resolve,
        else ``None``
    """
    path_part, _, anchor = target.partition("#")
    if path_part:
        candidates = [(root / path_part).resolve() for root in roots]
        existing = [candidate for candidate in candidates if candidate.exists()]
        if not existing:
            return f"{_relative(doc)}:{number}: {target!r}: no such file"
        file = existing[0]
    else:
        file = doc
    if anchor and file.suffix == ".md" and anchor not in anchors(file):
        return f"{_relative(doc)}:{number}: {target!r}: no heading of {_relative(file)} has the anchor #{anchor}"
    return None


@pytest.mark.parametrize("doc", DOCS, ids=_relative)
def test_relative_links_and_anchors_resolve(doc):
    prose, _ = _prose_and_code(doc)
    problems = []
    for number, line in prose:
        for target in LINK.findall(line):
            if re.match(r"^[a-z][a-z0-9+.-]*:", target):  # https:, mailto:
                continue
            problem = _check_target(doc, number, target, (doc.parent,))
            if problem:
                problems.append(problem)
        # `docs/checkpoints.md#devices` in prose: relative to the file or to the repository root.
        for file, anchor in ANCHOR_REFERENCE.findall(LINK.sub("", line)):
            problem = _check_target(doc, number, f"{file}#{anchor}", (doc.parent, ROOT))
            if problem:
                problems.append(problem)
    assert problems == [], "\n".join(problems)


@pytest.mark.parametrize("doc", DOCS, ids=_relative)
def test_repository_paths_in_backticks_exist(doc):
    prose, code = _prose_and_code(doc)
    problems = [
        f"{_relative(doc)}:{number}: `{span}`: no such file in the repository"
        for number, span in _inline_code(prose)
        if REPO_PATH.match(span) and not (ROOT / span).exists() and not (doc.parent / span).exists()
    ]
    assert problems == [], "\n".join(problems)


def _commands(doc: Path) -> Iterator[tuple[int, str, str]]:
    """The ``python -m sb3_collapse...`` commands of ``doc``: (line number, module, the rest of the command)."""
    prose, code = _prose_and_code(doc)
    lines = [(number, re.sub(r"(^|\s)#.*$", "", line)) for number, line in code]  # shell comments out
    lines += list(_inline_code(prose))
    for number, text in lines:
        for match in COMMAND.finditer(text):
            rest = re.split(r"\s(?:&&|\|\||;|>|2>|\|)\s", match.group(2))[0]  # the next command is not this one's
            yield number, match.group(1), rest


def _subcommand(module: str, rest: str) -> str | None:
    """The sub-command that ``rest`` runs (``None``: the CLI has none)."""
    if module not in SUBCOMMANDS:
        return None
    names, default = SUBCOMMANDS[module]
    words = [word for word in rest.split() if word != "..."]
    if words and words[0] in names:
        return words[0]
    return default


@cache
def help_text(module: str, subcommand: str | None) -> str:
    """
    :param module: ``sb3_collapse.<cli>``, as ``python -m`` runs it
    :param subcommand: its sub-command, or ``None``
    :return: what ``python -m <module> [subcommand] --help`` prints (the CLI's ``main`` run in-process)
    """
    try:
        target = importlib.import_module(f"{module}.__main__")
    except ModuleNotFoundError:
        target = importlib.import_module(module)
    output = io.StringIO()
    with contextlib.redirect_stdout(output), contextlib.redirect_stderr(output):
        try:
            target.main([*([subcommand] if subcommand else []), "--help"])
        except SystemExit:
            pass
    return output.getvalue()


def _known_flags(module: str, subcommand: str | None) -> set[str]:
    return set(FLAG.findall(help_text(module, subcommand))) | {"-h", "--help"}


def test_documented_commands_use_flags_their_cli_accepts():
    problems = []
    for doc in DOCS:
        for number, module, rest in _commands(doc):
            where = f"{_relative(doc)}:{number}: python -m {module}"
            try:
                subcommand = _subcommand(module, rest)
                known = _known_flags(module, subcommand)
            except (ImportError, AttributeError) as error:
                problems.append(f"{where}: no such command ({error})")
                continue
            shown = f"{module} {subcommand}" if subcommand else module
            problems += [
                f"{where}: --help of `python -m {shown}` does not list {flag}"
                for flag in FLAG.findall(rest)
                if flag.split("=")[0] not in known
            ]
    assert problems == [], "unknown flags in the documentation:\n" + "\n".join(problems)


def test_every_documented_cli_was_checked():
    """Guards the extraction above: the commands of the README's table are found."""
    modules = {module for doc in DOCS for _, module, _ in _commands(doc)}
    assert {"sb3_collapse.train", "sb3_collapse.sweep", "sb3_collapse.report", "sb3_collapse.probe"} <= modules
    assert "sb3_collapse.zoo" in modules


def _layout_sections() -> dict[str, str]:
    """docs/layout.md's tree: the text of each entry under ``sb3_collapse/`` (``drqv2``, ``train.py``...), and
    of the whole package under ``""``."""
    text = LAYOUT.read_text()
    tree = text[text.index("sb3_collapse/\n") :]
    package = tree.split("\n")[1:]
    package = package[: next(i for i, line in enumerate(package) if not line.startswith(" "))]
    sections: dict[str, str] = {"": "\n".join(package)}
    name = None
    for line in package:
        match = re.match(r"^ {2}(\w+)/\s", line)
        if match:
            name = match.group(1)
        elif re.match(r"^ {2}\S", line):
            name = None
        if name:
            sections[name] = sections.get(name, "") + line + "\n"
    return sections


def test_layout_names_every_module():
    sections = _layout_sections()
    missing = []
    for path in sorted(PACKAGE.rglob("*.py")):
        relative = path.relative_to(PACKAGE)
        if path.name in ("__init__.py", "__main__.py"):
            continue
        if len(relative.parts) == 1:
            section, where = sections[""], "sb3_collapse/"
        else:
            section, where = sections.get(relative.parts[0], ""), f"the {relative.parts[0]}/ entry"
        if not re.search(rf"(?<![\w/]){re.escape(path.name)}\b", section):
            missing.append(f"sb3_collapse/{relative} is not named in {where} of docs/layout.md")
    for package in sorted(p.parent for p in PACKAGE.glob("*/__init__.py")):
        if package.name not in sections:
            missing.append(f"sb3_collapse/{package.name}/ has no entry in docs/layout.md")
    assert missing == [], "\n".join(missing)


# Docstrings, the command lines' --help and zoo_configs/README.md: the checks above, on those texts too.
ZOO_README = ROOT / "zoo_configs" / "README.md"
HELPS = [("sb3_collapse.train", None), ("sb3_collapse.sweep", None), ("sb3_collapse.report", None)]
HELPS += [("sb3_collapse.probe", name) for name in SUBCOMMANDS["sb3_collapse.probe"][0]]
# A measured figure (a duration, a speed, a ratio, a size) belongs in benchmarks/README.md, which a text links.
MEASURED = re.compile(
    r"(?<![\w.,])(?:\d{1,3}(?:,\d{3})+|\d+)(?:\.\d+)?"
    r"(?:\s?(?:ms|MB|GB|KB|MiB|GiB|frames/s|steps/s|updates/s|fps)\b|\s(?:s|min|minutes|hours)\b|x(?![\w]))"
)
# Sizes that are constants of the code, not measurements: (file, figure).
NOT_MEASURED = {("sb3_collapse/run/cpu_allocator.py", "32 MB"), ("sb3_collapse/run/replay_checkpoint.py", "1 MiB")}
TEXT_PATH = re.compile(r"(?<![\w/.-])(?:sb3_collapse|docs|benchmarks|scripts|tests|zoo_configs)/[\w./-]*\w")


def docstrings() -> Iterator[tuple[str, str]]:
    """Every string statement of the package (module, class, function and attribute docstrings), with its place."""
    for path in sorted(PACKAGE.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            value = node.value if isinstance(node, ast.Expr) else None
            if isinstance(value, ast.Constant) and isinstance(value.value, str):
                yield f"{_relative(path)}:{node.lineno}", value.value


def _text_problems(where: str, text: str) -> list[str]:
    """What the checks of the markdown files find in a plain ``text`` (a docstring, a --help) at ``where``: commands'
    flags, repository paths and ``path.md#anchor`` references, and measured figures (not allowed: link the row)."""
    problems = []
    for match in COMMAND.finditer(text):
        module, rest = match.group(1), re.split(r"\s(?:&&|\|\||;|>|2>|\|)\s", match.group(2))[0]
        subcommand = _subcommand(module, rest)
        shown = f"{module} {subcommand}" if subcommand else module
        problems += [
            f"{where}: --help of `python -m {shown}` does not list {flag}"
            for flag in FLAG.findall(rest)
            if flag.split("=")[0] not in _known_flags(module, subcommand)
        ]
    for path in TEXT_PATH.findall(text):
        if REPO_PATH.match(path) and not (ROOT / path).exists():
            problems.append(f"{where}: {path}: no such file in the repository")
    for file, anchor in ANCHOR_REFERENCE.findall(text):
        if (ROOT / file).exists() and anchor not in anchors(ROOT / file):
            problems.append(f"{where}: {file}#{anchor}: no heading of {file} has the anchor #{anchor}")
    file = where.split(":")[0]
    problems += [
        f"{where}: {figure!r} is a measured figure: link its row of benchmarks/README.md instead"
        for figure in (match.group().strip() for match in MEASURED.finditer(text))
        if (file, figure) not in NOT_MEASURED
    ]
    return problems


def test_docstrings_pass_the_documentation_checks():
    problems = [problem for where, text in docstrings() for problem in _text_problems(where, text)]
    assert problems == [], "\n".join(problems)


@pytest.mark.parametrize(("module", "subcommand"), HELPS, ids=lambda value: str(value))
def test_command_line_help_passes_the_documentation_checks(module, subcommand):
    text = help_text(module, subcommand)
    assert "usage:" in text
    assert _text_problems(f"python -m {module} {subcommand or ''} --help", text) == []


def test_zoo_configs_readme_passes_the_documentation_checks(monkeypatch):
    test_relative_links_and_anchors_resolve(ZOO_README)
    test_repository_paths_in_backticks_exist(ZOO_README)
    monkeypatch.setitem(globals(), "DOCS", [ZOO_README])
    assert {module for _, module, _ in _commands(ZOO_README)} == {"sb3_collapse.zoo", "sb3_collapse.zoo.config"}
    test_documented_commands_use_flags_their_cli_accepts()


def test_the_checks_of_plain_texts_find_what_they_look_for():
    """Each check on constructed texts: a wrong flag, path, anchor and a measured figure; a clean text passes."""
    assert ("sb3_collapse/run/folder.py:1", (PACKAGE / "run" / "folder.py").read_text()[3:].split('"""')[0]) in set(
        docstrings()
    )
    assert _text_problems("x", "Run `python -m sb3_collapse.train --frames 10`, see docs/training.md.") == []
    assert _text_problems("x", "It takes 3 minutes (1.5 s per update) and 12 GB: 2.5x the reference.") == [
        f"x: {figure!r} is a measured figure: link its row of benchmarks/README.md instead"
        for figure in ("3 minutes", "1.5 s", "12 GB", "2.5x")
    ]
    assert _text_problems("x", "9x84x84 pixels, 1,024 units, batch 256, 10,000 frames, CRC-32s, [0, min(n, d)]") == []
    assert _text_problems("x", "python -m sb3_collapse.train --no-such-flag") == [
        "x: --help of `python -m sb3_collapse.train` does not list --no-such-flag"
    ]
    assert _text_problems("x", "See docs/nothing.md and docs/training.md#no-such-heading.") == [
        "x: docs/nothing.md: no such file in the repository",
        "x: docs/training.md#no-such-heading: no heading of docs/training.md has the anchor #no-such-heading",
    ]


def test_the_demo_says_which_preset_values_it_changes():
    """run.sh's demo command and the README's quick start name each value the demo changes, and the preset's."""
    from sb3_collapse.presets import preset

    script = (ROOT / "run.sh").read_text()
    command = re.search(r"-m sb3_collapse\.train (.*?)\"\$@\"", script.replace("\\\n", " "), re.DOTALL).group(1)
    values = dict(re.findall(r"--([\w-]+) (\S+)", command))
    walker = preset(values.pop("env"))
    changed = {name.replace("-", "_"): value for name, value in values.items()}
    changed = {name: int(value) for name, value in changed.items() if hasattr(walker, name)}
    assert set(changed) == {"frames", "seed_frames", "batch_size", "eval_every_frames", "eval_episodes"}
    readme = (ROOT / "README.md").read_text()
    said = readme[readme.index("The demo runs") :].split("\n\n")[0].replace("\n", " ")
    message = script[script.index("at its DrQ-v2 preset but") :].split('"')[0]

    def shown(number: int) -> str:
        return f"{number / 1e6:g}M" if number >= 1_000_000 else f"{number:,}"

    for name, value in changed.items():
        ours, theirs = shown(value), shown(getattr(walker, name))
        assert ours != theirs, name
        assert f"{ours} " in said and f"({theirs})" in said.replace("the preset: ", ""), (name, said)
        assert f"{ours} " in message and f"({theirs})" in message.replace("preset: ", ""), (name, message)


API = ROOT / "docs" / "api"
def _public_packages() -> list[str]:
    """The packages of ``sb3_collapse`` and its top-level modules that declare their public names in ``__all__``."""
    inits = [init for init in PACKAGE.glob("*/__init__.py") if "__all__" in init.read_text()]
    modules = [path for path in PACKAGE.glob("*.py") if path.name != "__init__.py" and "__all__" in path.read_text()]
    return sorted([f"sb3_collapse.{init.parent.name}" for init in inits] + [f"sb3_collapse.{m.stem}" for m in modules])


DOCUMENTED_MODULES = ("sb3_collapse.errors", "sb3_collapse.paper", "sb3_collapse.presets")  # every name public


def test_every_name_the_docs_import_is_public():
    # A name a user is taught to import is in the API reference: in a public __all__ or a wholly public module.
    public = {f"{module}.{name}" for module in _public_packages() for name in importlib.import_module(module).__all__}
    public |= {f"sb3_collapse.{name}" for name in importlib.import_module("sb3_collapse").__all__}
    taught = []
    for doc in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        for number, line in _prose_and_code(doc)[1]:
            if (found := re.match(r"\s*from (sb3_collapse(?:\.\w+)*) import \(?([\w, ]+)", line)) is None:
                continue
            module, names = found[1], [name.strip() for name in found[2].split(",") if name.strip()]
            taught += [(f"{_relative(doc)}:{number}", module, name) for name in names]
    assert taught, "no import found in the docs: the pattern is wrong"
    internal = [
        f"{where}: {module}.{name}"
        for where, module, name in taught
        if module not in DOCUMENTED_MODULES and f"{module}.{name}" not in public
    ]
    assert internal == [], f"the docs import internal names (make them public or stop teaching them): {internal}"


def test_the_api_reference_names_every_public_package():
    documented = set(re.findall(r"^\.\. automodule:: (\S+)", (API / "index.rst").read_text(), re.MULTILINE))
    assert {"sb3_collapse", *_public_packages()} <= documented


def test_the_api_reference_builds_without_warnings_and_documents_every_exported_name(tmp_path):
    pytest.importorskip("sphinx")
    command = [sys.executable, "-m", "sphinx", "-q", "-E", "-W", "--keep-going", "-b", "html", str(API), str(tmp_path)]
    built = subprocess.run(command, check=False, capture_output=True, text=True, timeout=600)
    assert built.returncode == 0, built.stdout + built.stderr
    html = (tmp_path / "index.html").read_text()
    shown = set(re.findall(r'<span class="sig-name descname"><span class="pre">(\w+)', html))
    missing = [
        f"{package}.{name}"
        for package in _public_packages()
        for name in importlib.import_module(package).__all__
        if name not in shown
    ]
    assert missing == [], f"names of __all__ missing from the API reference (docs/api/index.rst): {missing}"
