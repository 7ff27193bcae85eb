"""Output folders that never show a partial set of files as complete (used by the probe and the report)."""

from __future__ import annotations

import os
import shutil
from collections.abc import Sequence
from pathlib import Path
from types import TracebackType


class StagedOutputs:
    """
    Write files into ``<out>/.partial-<pid>/`` and move them into ``out`` on :meth:`commit` (``marker`` last, after
    removing the previous outputs this run did not write); without a commit the staging folder (and ``out`` if this
    created it and it is empty) is removed. ``outputs``: every file name a run may write (or glob pattern).

    :raises error: when ``out`` is a file, or holds a previous run's outputs and ``overwrite`` is false
    """

    def __init__(
        self,
        out: str | Path,
        outputs: Sequence[str],
        marker: str,
        overwrite: bool = True,
        error: type[Exception] = ValueError,
    ) -> None:
        if marker not in outputs:
            raise ValueError(f"The marker {marker!r} must be one of the outputs {list(outputs)}.")
        self.out = Path(out)
        if self.out.exists() and not self.out.is_dir():
            raise error(f"out {self.out} is a file; give a folder.", parameter="out")
        self.outputs = tuple(outputs)
        existing = self.existing()
        if existing and not overwrite:
            raise error(
                f"{self.out} already holds outputs ({', '.join(existing)}): pass `overwrite=True` or another `out`.",
                parameter="out",
            )
        self.marker = marker
        self.staging = self.out / f".partial-{os.getpid()}"
        self.created = not self.out.exists()
        self.committed = False

    def existing(self) -> list[str]:
        """:return: the names in ``out`` of outputs (or matches of output patterns) of a previous run"""
        return sorted({path.name for pattern in self.outputs for path in self.out.glob(pattern) if path.is_file()})

    def __enter__(self) -> StagedOutputs:  # noqa: PYI034  not subclassed
        self.staging.mkdir(parents=True, exist_ok=False)
        return self

    def path(self, name: str) -> Path:
        """Where to write ``name`` before the commit."""
        return self.staging / name

    def commit(self) -> list[Path]:
        """:return: the final paths of the staged files, moved into ``out`` in this order (the marker last)"""
        staged = sorted((path.name for path in self.staging.iterdir()), key=lambda name: name == self.marker)
        (self.out / self.marker).unlink(missing_ok=True)
        for name in self.existing():
            if name not in staged:
                (self.out / name).unlink(missing_ok=True)
        for name in staged:
            os.replace(self.staging / name, self.out / name)
        self.staging.rmdir()
        self.committed = True
        return [self.out / name for name in staged]

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if not self.committed:
            shutil.rmtree(self.staging, ignore_errors=True)
            if self.created and self.out.exists() and not any(self.out.iterdir()):
                self.out.rmdir()
