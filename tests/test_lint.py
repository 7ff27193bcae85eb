"""ruff (pyproject.toml's rules, line length included) passes on the package, the tests, the benchmarks and scripts;
the package holds no module that only tests or benchmarks use (those live in tests/); outside the models' own code, no
``getattr(model, "_...")`` on a model's private attributes; ``DrQv2`` in at most 450 lines; at most 12 exception
classes, no two of one name."""

from __future__ import annotations

import ast
import builtins
import re
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CHECKED = ("sb3_collapse", "tests", "benchmarks", "scripts")


def _ruff() -> list[str] | None:
    """The ruff command: the module of this interpreter's environment, else the one on the PATH; ``None``: none."""
    try:
        import ruff  # noqa: F401
    except ImportError:
        executable = shutil.which("ruff")
        return [executable] if executable else None
    return [sys.executable, "-m", "ruff"]


def test_ruff_check_passes():
    ruff = _ruff()
    if ruff is None:
        pytest.skip("ruff is not installed: pip install -e '.[dev]' (bash run.sh setup installs it)")
    result = subprocess.run(
        [*ruff, "check", "--no-cache", "--output-format", "concise", *CHECKED],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert result.returncode == 0, f"ruff check failed (fix the lines below):\n{result.stdout}{result.stderr}"


PACKAGE = ROOT / "sb3_collapse"
TEST_ONLY_NAME = re.compile(r"^(test|fake|mock|dummy|synthetic|oracle|conftest)|(_test|_fake|_mock|_oracle)$")


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(source: str, module: str) -> set[str]:
    """
    The modules that a module's source imports, at the top or inside a function (``from a.b import c`` counts
    ``a.b`` and ``a.b.c``; a relative import is resolved against ``module``, the module's dotted name).
    """
    imported = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            imported.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = module.split(".")[: -node.level] if node.level else []
            name = ".".join([*base, *([node.module] if node.module else [])])
            imported.update([name, *(f"{name}.{alias.name}" for alias in node.names)])
    return imported


def _imported_by_the_package() -> set[str]:
    """The modules that some module of the package imports."""
    return {name for path in PACKAGE.rglob("*.py") for name in _imports(path.read_text(), _module_name(path))}


def test_the_package_has_no_module_that_only_tests_use():
    """Every module of sb3_collapse/ is a package, a program (``__main__.py``, ``if __name__ == "__main__":``) or
    imported by another module of the package; none is named as a test double (test oracles and test envs live in
    tests/, e.g. tests/drqv2_reference.py and tests/random_env.py)."""
    imported = _imported_by_the_package()
    orphans, test_named = [], []
    for path in sorted(PACKAGE.rglob("*.py")):
        if TEST_ONLY_NAME.search(path.stem):
            test_named.append(str(path.relative_to(ROOT)))
        is_program = path.stem == "__main__" or 'if __name__ == "__main__":' in path.read_text()
        if path.stem != "__init__" and not is_program and _module_name(path) not in imported:
            orphans.append(str(path.relative_to(ROOT)))
    assert not test_named, f"modules named as test doubles in the package (move them to tests/): {test_named}"
    assert not orphans, f"modules that no module of the package imports (move test-only code to tests/): {orphans}"


def _draws(name: str) -> bool:
    """:return: whether an imported module is the report or matplotlib"""
    return any(name == top or name.startswith(top + ".") for top in ("sb3_collapse.report", "matplotlib"))


def _within(name: str, package: str) -> bool:
    """:return: whether the imported module ``name`` is ``package`` or inside it"""
    return name == package or name.startswith(package + ".")


def _importers(folder: Path, forbidden: Callable[[str], bool]) -> dict[str, list[str]]:
    """:return: each module under ``folder`` (its faces ``__main__.py`` left out) -> the imports that ``forbidden``
    marks, at the top or inside a function"""
    found = {}
    for path in sorted(folder.rglob("*.py")):
        names = sorted(n for n in _imports(path.read_text(), _module_name(path)) if forbidden(n))
        if path.stem != "__main__" and names:
            found[str(path.relative_to(ROOT))] = names
    return found


def test_probe_and_report_do_not_import_each_other():
    """probe/ computes and report/ draws: no module of sb3_collapse/probe imports sb3_collapse.report or matplotlib,
    no module of sb3_collapse/report imports sb3_collapse.probe, at the top or inside a function; the pipelines of
    sb3_collapse/commands call both."""
    constructed = "import numpy\ndef plot():\n    from sb3_collapse import report\n    from ..report.film import x\n"
    assert {n for n in _imports(constructed, "sb3_collapse.probe.film") if _draws(n)} == {
        "sb3_collapse.report",
        "sb3_collapse.report.film",
        "sb3_collapse.report.film.x",
    }
    assert not any(_draws(n) for n in _imports("import matplotlib_inline\nfrom sb3_collapse import reporting", "a"))
    assert _within("sb3_collapse.probe.film", "sb3_collapse.probe") and not _within(
        "sb3_collapse.prober", "sb3_collapse.probe"
    )
    drawing = _importers(PACKAGE / "probe", _draws)
    assert not drawing, f"probe modules that draw or import the report (move the drawing to report/): {drawing}"
    probing = _importers(PACKAGE / "report", lambda name: _within(name, "sb3_collapse.probe"))
    assert not probing, f"report modules that import the probe (compute in the pipeline of commands/): {probing}"


def test_nothing_below_commands_imports_it():
    """sb3_collapse/commands is the top layer: outside it, only the faces (``train.py``, ``reproduce.py``, the
    ``__main__.py`` of the packages: ``python -m sb3_collapse.<command>``) import it."""
    faces = {PACKAGE / "train.py", PACKAGE / "reproduce.py", *PACKAGE.glob("*/__main__.py")}
    constructed = "def f():\n    from sb3_collapse.commands.cli import cli_message\n"
    assert "sb3_collapse.commands.cli" in _imports(constructed, "sb3_collapse.run.runner")
    below = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        if path in faces or path.is_relative_to(PACKAGE / "commands"):
            continue
        names = sorted(n for n in _imports(path.read_text(), _module_name(path)) if _within(n, "sb3_collapse.commands"))
        if names:
            below[str(path.relative_to(ROOT))] = names
    assert not below, f"modules below commands/ that import it (move the code up, or what it needs down): {below}"
    for face in sorted(faces):
        assert len(face.read_text().splitlines()) <= 10, f"{face.relative_to(ROOT)} is a face: a few lines"


def test_importing_the_probe_loads_neither_the_report_nor_matplotlib():
    """Every library module of sb3_collapse/probe imported in a fresh interpreter, with what they import in turn."""
    modules = [_module_name(p) for p in sorted((PACKAGE / "probe").glob("*.py")) if p.stem != "__main__"]
    code = f"import sys; [__import__(m) for m in {modules!r}]; print(' '.join(sys.modules))"
    result = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=False)
    assert result.returncode == 0, result.stderr
    assert [name for name in result.stdout.split() if _draws(name)] == []


MODEL_OWNERS = ("sb3_collapse/drqv2/", "sb3_collapse/baselines.py")
"""Where a model's private attributes may be read: the model's own package and the wrappers that implement
``sb3_collapse.common.model.CollapseModel``."""


def _private_model_probes(source: str, label: str) -> list[str]:
    """``getattr``/``hasattr``/``setattr`` of a ``_private`` name on an expression that names a model, and
    assignments to ``<...>model.no_env_step_this_round``, in one file's source (``label:line: code``, by line)."""
    found = []
    for node in ast.walk(ast.parse(source, label)):
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and len(node.args) >= 2:
            target, name = node.args[0], node.args[1]
            if (
                node.func.id in ("getattr", "hasattr", "setattr")
                and "model" in ast.unparse(target)
                and isinstance(name, ast.Constant)
                and str(name.value).startswith("_")
            ):
                found.append((node.lineno, ast.unparse(node)))
        if isinstance(node, ast.Assign):
            for target in node.targets:
                attribute = isinstance(target, ast.Attribute) and target.attr == "no_env_step_this_round"
                if attribute and ast.unparse(target.value).endswith("model"):  # type: ignore[attr-defined]
                    found.append((node.lineno, ast.unparse(node)))
    return [f"{label}:{line}: {code}" for line, code in sorted(found)]


def test_no_probe_of_a_models_private_attributes_outside_the_model():
    """The callbacks, checkpoints and experiment code reach a model through the names of ``CollapseModel``
    (``sb3_collapse/common/model.py``), not ``getattr(model, "_...")``."""
    probes = [
        probe
        for path in sorted(PACKAGE.rglob("*.py"))
        if not str(path.relative_to(ROOT)).startswith(MODEL_OWNERS)
        for probe in _private_model_probes(path.read_text(), str(path.relative_to(ROOT)))
    ]
    assert not probes, "use the CollapseModel names:\n" + "\n".join(probes)


def test_the_probe_finder_finds_what_it_looks_for():
    source = (
        "def f(self, model, name):\n"
        "    a = getattr(self.model, '_n_updates', 0)\n"
        "    b = hasattr(model, '_pending_step')\n"
        "    self.model.no_env_step_this_round = True\n"
        "    c = getattr(model, 'num_frames')\n"  # public: allowed
        "    d = getattr(self, '_state', None)\n"  # not a model: allowed
        "    return a, b, c, d\n"
    )
    assert [probe.split(": ", 1)[0] for probe in _private_model_probes(source, "example.py")] == [
        "example.py:2",
        "example.py:3",
        "example.py:4",
    ]


DRQV2_MAX_LINES = 450
"""``DrQv2`` stays the algorithm, in SB3's override set (as SB3's ``td3/td3.py``): checks, save/load plumbing and
replay memory live beside it in ``sb3_collapse/drqv2/``."""


def test_the_drqv2_algorithm_module_is_at_most_450_lines():
    lines = len((PACKAGE / "drqv2" / "drqv2.py").read_text().splitlines())
    assert lines <= DRQV2_MAX_LINES, f"sb3_collapse/drqv2/drqv2.py has {lines} lines (at most {DRQV2_MAX_LINES})"


MAX_EXCEPTION_CLASSES = 12
"""Exception classes the package may define: one per kind of error (``sb3_collapse/errors.py``)."""


def _exception_classes(sources: dict[str, str]) -> list[tuple[str, str]]:
    """
    :param sources: label (a file) -> Python source
    :return: (name, ``label:line``) of every class deriving, directly or through another class, from a built-in
        exception
    """
    exceptions = {
        name for name, value in vars(builtins).items() if isinstance(value, type) and issubclass(value, BaseException)
    }
    classes = [
        (node.name, {ast.unparse(base).rsplit(".", 1)[-1] for base in node.bases}, f"{label}:{node.lineno}")
        for label, source in sources.items()
        for node in ast.walk(ast.parse(source))
        if isinstance(node, ast.ClassDef)
    ]
    found: list[tuple[str, str]] = []
    while True:
        new = [(name, where) for name, bases, where in classes if bases & exceptions and (name, where) not in found]
        if not new:
            return sorted(found, key=lambda item: item[1])
        found += new
        exceptions |= {name for name, _ in new}


def test_the_package_has_one_exception_class_per_kind_of_error():
    sources = {str(path.relative_to(ROOT)): path.read_text() for path in sorted(PACKAGE.rglob("*.py"))}
    classes = _exception_classes(sources)
    listed = "\n".join(f"{where}: {name}" for name, where in classes)
    assert len(classes) <= MAX_EXCEPTION_CLASSES, f"{len(classes)} exception classes, reuse one:\n{listed}"
    names = [name for name, _ in classes]
    assert len(set(names)) == len(names), f"two exception classes share a name:\n{listed}"


def test_the_exception_finder_finds_what_it_looks_for():
    sources = {
        "a.py": "class A(ValueError):\n    pass\nclass Plain:\n    pass\n",
        "b.py": "class B(errors.A, KeyError):\n    pass\nclass C(B):\n    pass\nclass D(Plain):\n    pass\n",
    }
    assert _exception_classes(sources) == [("A", "a.py:1"), ("B", "b.py:1"), ("C", "b.py:3")]


def _package_imports() -> dict[str, set[str]]:
    """Top-level part of the package (``drqv2``, ``run``, ``paper``...) -> the other parts it imports, at the top or
    inside a function; the command lines (``__main__.py``, ``train.py``), the top layer, are left out."""
    graph: dict[str, set[str]] = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = path.relative_to(PACKAGE).parts
        if path.name == "__main__.py" or parts == ("train.py",) or parts == ("__init__.py",):
            continue
        part = parts[0].removesuffix(".py")
        names = _imports(path.read_text(), _module_name(path))
        graph.setdefault(part, set()).update(
            name.split(".")[1] for name in names if name.startswith("sb3_collapse.") and name.split(".")[1] != part
        )
    return graph


def test_no_part_of_the_package_imports_one_that_imports_it_back():
    graph = _package_imports()
    assert graph["probe"] and "report" not in graph["probe"]  # the walk sees the imports

    def reachable(start: str) -> set[str]:
        seen, todo = set(), [start]
        while todo:
            for name in graph.get(todo.pop(), ()):
                if name not in seen:
                    seen.add(name)
                    todo.append(name)
        return seen

    cycles = sorted(f"{a} -> {b}" for a in graph for b in graph[a] if a in reachable(b))
    assert not cycles, "parts of the package that import each other (docs/layout.md shows the layers): " + ", ".join(
        cycles
    )
