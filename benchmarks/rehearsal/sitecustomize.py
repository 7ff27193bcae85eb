"""
Import guard of ``bash benchmarks/gpu.sh --rehearse``: this interpreter may import only what the GPU machine has.

Python imports this module at start-up when its folder is on ``PYTHONPATH`` (the rehearsal puts it there, and its
subprocesses inherit it). From then on, a top-level module is imported only if it comes from

- the standard library (or is built in),
- the folder the carried wheels were installed into (``SB3_COLLAPSE_REHEARSAL_SITE``),
- this repository (``sb3_collapse``, the benchmarks' own modules), or
- a distribution of ``gpu_machine_packages.txt`` (the GPU machine's image).

Anything else raises ``ModuleNotFoundError`` naming the module and its distribution, as the GPU machine would (code
that treats the module as optional carries on without it). A module imported before this one (by a ``.pth`` file)
is not checked.
"""

from __future__ import annotations

import importlib.abc
import importlib.machinery
import importlib.metadata
import os
import re
import sys
import sysconfig

_HERE = os.path.dirname(os.path.abspath(__file__))
_REPOSITORY = os.path.dirname(os.path.dirname(_HERE))


def _normalize(name: str) -> str:
    """A distribution's name as PEP 503 compares them."""
    return re.sub(r"[-_.]+", "-", name).lower()


def _allowed_distributions() -> frozenset[str]:
    """The normalized names of ``gpu_machine_packages.txt``."""
    with open(os.path.join(_HERE, "gpu_machine_packages.txt")) as file:
        return frozenset(_normalize(line.strip()) for line in file if line.strip() and not line.startswith("#"))


class RehearsalImportGuard(importlib.abc.MetaPathFinder):
    """Refuses the top-level modules the GPU machine does not have (first on ``sys.meta_path``)."""

    def __init__(self) -> None:
        self.allowed = _allowed_distributions()
        paths = sysconfig.get_paths()
        roots = (paths["stdlib"], paths["platstdlib"], _REPOSITORY)
        self.roots = tuple(os.path.realpath(root) + os.sep for root in roots)
        carried = os.environ.get("SB3_COLLAPSE_REHEARSAL_SITE")
        self.carried = os.path.realpath(carried) + os.sep if carried else None
        self.checked: set[str] = set()
        self._distributions: dict[str, list[str]] | None = None

    def distributions(self, module: str) -> list[str]:
        """The installed distributions that provide the top-level ``module``."""
        if self._distributions is None:
            self._distributions = importlib.metadata.packages_distributions()
        return self._distributions.get(module, [])

    def ours(self, location: str) -> bool:
        """Whether ``location`` is in the carried wheels' folder, or in the standard library or this repository
        outside any site-packages (a virtual environment inside the repository is not the repository)."""
        if self.carried and location.startswith(self.carried):
            return True
        return location.startswith(self.roots) and f"-packages{os.sep}" not in location

    def find_spec(self, fullname: str, path=None, target=None):
        if "." in fullname or fullname in self.checked or fullname in sys.builtin_module_names:
            return
        spec = importlib.machinery.PathFinder.find_spec(fullname)
        if spec is None:
            return  # not found at all: the ordinary ModuleNotFoundError
        locations = [spec.origin] if spec.origin not in (None, "built-in", "frozen") else []
        locations += list(spec.submodule_search_locations or [])
        where = [os.path.realpath(location) for location in locations]
        if not where or all(self.ours(location) for location in where):
            self.checked.add(fullname)
            return
        # A module vendored inside an allowed distribution (setuptools/_vendor on sys.path) is that distribution's.
        tops = {fullname} | {re.split(r"[./]", location.split(f"-packages{os.sep}", 1)[-1])[0] for location in where}
        distributions = sorted({name for top in tops for name in self.distributions(top)})
        if any(_normalize(name) in self.allowed for name in distributions):
            self.checked.add(fullname)
            return
        raise ModuleNotFoundError(
            f"No module named {fullname!r} on the GPU machine (rehearsal of benchmarks/gpu.sh: {where[0]}, "
            f"distribution {', '.join(distributions) or 'unknown'}, is neither in "
            "benchmarks/rehearsal/gpu_machine_packages.txt nor among the carried wheels)",
            name=fullname,
        )


sys.meta_path.insert(0, RehearsalImportGuard())
