"""The package as pip sees it: one version string, the declared Pythons, the lowest-versions constraints, the wheel."""

import re
import shutil
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.version import Version

import sb3_collapse

ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())
PROJECT = PYPROJECT["project"]
DECLARED = [c.rsplit(" ", 1)[1] for c in PROJECT["classifiers"] if re.fullmatch(r".*Python :: 3\.\d+", c)]
README = (ROOT / "README.md").read_text()
CITATION = (ROOT / "CITATION.cff").read_text()

# Run by each declared Python: every module compiles, and every standard-library name it imports exists there.
# Importing the package needs its dependencies installed for that Python, so this is the check CI can afford.
COMPILE_CHECK = """
import ast, importlib, pathlib, sys
bad = []
for path in sorted(pathlib.Path(sys.argv[1]).rglob("*.py")):
    tree = compile(path.read_text(), str(path), "exec", ast.PyCF_ONLY_AST)
    compile(tree, str(path), "exec")
    for node in ast.walk(tree):
        names = [(a.name, None) for a in node.names] if isinstance(node, ast.Import) else []
        if isinstance(node, ast.ImportFrom) and node.level == 0:
            names = [(node.module, a.name) for a in node.names]
        for module, name in names:
            if module.split(".")[0] not in sys.stdlib_module_names:
                continue
            try:
                found = importlib.import_module(module)
                if name and not hasattr(found, name):
                    importlib.import_module(f"{module}.{name}")
            except ImportError:
                bad.append(f"{path}:{node.lineno}: {module}{'.' + name if name else ''}")
print("\\n".join(bad))
sys.exit(bool(bad))
"""


def test_one_version_string():
    assert PROJECT["dynamic"] == ["version"]
    assert PYPROJECT["tool"]["setuptools"]["dynamic"]["version"] == {"attr": "sb3_collapse.__version__"}
    version = sb3_collapse.__version__
    assert re.search(r"^version: (\S+)$", CITATION, re.MULTILINE).group(1) == version
    assert not re.search(r"\bversion = \{", README)  # the README cites through CITATION.cff, which holds the version
    assert f"\n## [{version}]" in (ROOT / "CHANGELOG.md").read_text()


def test_requires_python_is_the_lowest_declared_version():
    assert PROJECT["requires-python"] == f">={min(DECLARED, key=Version)}"


def test_lowest_constraints_are_the_lower_bounds():
    requirements = [
        *PROJECT["dependencies"],
        *(r for extra in PROJECT["optional-dependencies"].values() for r in extra),
    ]
    bounds = {}
    for text in requirements:
        requirement = Requirement(text)
        (lowest,) = [s.version for s in requirement.specifier if s.operator == ">="]
        bounds[requirement.name.lower().replace("_", "-")] = Version(lowest)
    lines = (ROOT / "constraints" / "lowest.txt").read_text().splitlines()
    pins = [line.split("==") for line in lines if line and not line.startswith("#")]
    assert {name.lower().replace("_", "-"): Version(version) for name, version in pins} == bounds
    assert len(pins) == len(bounds)


def _runnable(version: str) -> str:
    """:return: the path of ``python<version>``, the test skipped when it is absent or does not run here"""
    python = shutil.which(f"python{version}")
    if python is None or subprocess.run([python, "-c", ""], check=False, capture_output=True).returncode != 0:
        pytest.skip(f"python{version} is absent or does not run here (pyenv: set PYENV_VERSION)")
    return python


@pytest.mark.parametrize("version", DECLARED)
def test_every_module_compiles_under_each_declared_python(version):
    check = subprocess.run(
        [_runnable(version), "-c", COMPILE_CHECK, str(ROOT / "sb3_collapse")],
        check=False,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert check.returncode == 0, check.stdout + check.stderr


@pytest.mark.parametrize(("version", "missing"), [("3.11", ["NoSuchName"]), ("3.10", ["Self", "NoSuchName"])])
def test_compile_check_names_what_a_python_lacks(tmp_path, version, missing):
    """typing.Self exists from Python 3.11 on; third-party imports (no_such) are not checked."""
    (tmp_path / "module.py").write_text("import no_such\nfrom typing import Any\nfrom typing import Self, NoSuchName\n")
    command = [_runnable(version), "-c", COMPILE_CHECK, str(tmp_path)]
    check = subprocess.run(command, check=False, capture_output=True, text=True)
    assert check.returncode == 1
    assert check.stdout.splitlines() == [f"{tmp_path / 'module.py'}:3: typing.{name}" for name in missing]


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    """The wheel that ``pip wheel`` builds from a copy of the sources (the clone stays unwritten)."""
    source, out = tmp_path_factory.mktemp("source"), tmp_path_factory.mktemp("wheel")
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        shutil.copy(ROOT / name, source)
    shutil.copytree(ROOT / "sb3_collapse", source / "sb3_collapse", ignore=shutil.ignore_patterns("__pycache__"))
    command = [sys.executable, "-m", "pip", "wheel", str(source), "--no-deps", "--no-build-isolation", "-w", str(out)]
    subprocess.run(command, check=True, capture_output=True, timeout=300)
    (path,) = out.glob("sb3_collapse-*.whl")
    return path


def test_wheel_holds_the_typing_marker_the_licenses_and_the_metadata(wheel):
    version = sb3_collapse.__version__
    assert wheel.name.startswith(f"sb3_collapse-{version}-py3-")
    with zipfile.ZipFile(wheel) as archive:
        names = set(archive.namelist())
        metadata = archive.read(f"sb3_collapse-{version}.dist-info/METADATA").decode()
    licenses = f"sb3_collapse-{version}.dist-info/licenses"
    expected = ["sb3_collapse/py.typed", "sb3_collapse/zoo/config.py", "sb3_collapse/report/data/LICENSE"]
    assert {*expected, f"{licenses}/LICENSE", f"{licenses}/sb3_collapse/report/data/LICENSE"} <= names
    assert not [name for name in names if name.startswith(("tests/", "benchmarks/"))]
    assert f"\nVersion: {version}\n" in metadata
    assert "\nRequires-Python: >=3.11\n" in metadata
    assert "\nProject-URL: Stable-Baselines3, https://github.com/DLR-RM/stable-baselines3\n" in metadata


def test_wheel_writes_the_zoo_config_outside_a_clone(wheel, tmp_path):
    with zipfile.ZipFile(wheel) as archive:
        archive.extractall(tmp_path / "site")
    command = [sys.executable, "-m", "sb3_collapse.zoo.config", "drqv2.yml"]
    env = {"PATH": "", "PYTHONPATH": str(tmp_path / "site"), "OMP_NUM_THREADS": "1"}
    subprocess.run(command, cwd=tmp_path, env=env, check=True, capture_output=True, timeout=300)
    assert (tmp_path / "drqv2.yml").read_text() == (ROOT / "zoo_configs" / "drqv2.yml").read_text()


@pytest.mark.parametrize(
    ("module", "name"),
    [
        ("run/checkpoints.py", "CHECKPOINT_FORMAT"),
        ("run/replay_checkpoint.py", "FORMAT"),
        ("probe/rollouts.py", "FORMAT_VERSION"),
        ("runfolder.py", "check_result_version"),
        ("monitoring/callbacks.py", None),
    ],
)
def test_changelog_names_the_format_checks_that_exist(module, name):
    """The versioning policy names the module (and the constant or function) that refuses another version's files."""
    changelog = (ROOT / "CHANGELOG.md").read_text()
    source = (ROOT / "sb3_collapse" / module).read_text()
    assert f"`{module}`" in changelog or f"`{module.removesuffix('.py').replace('/', '.')}." in changelog
    if name is not None:
        assert f"`{name}`" in changelog or f".{name}`" in changelog
        assert re.search(rf"^(?:{name} = |def {name}\()", source, re.MULTILINE)
