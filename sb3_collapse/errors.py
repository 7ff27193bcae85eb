"""The package's exceptions, one class per kind of error, and the one-line message of an output that could not be
written (:func:`unwritable_message`); the command lines say them in their words (:mod:`sb3_collapse.commands.cli`)."""

from __future__ import annotations

import errno
import os
from pathlib import Path


class InputError(ValueError):
    """Bad input (a setting, a file, a folder, a command line): a command line prints ``error: ...``, exit status 2;
    ``parameter``: the Python name of the parameter at fault, when there is one."""

    def __init__(self, message: str, parameter: str | None = None) -> None:
        super().__init__(message)
        self.parameter = parameter


class ParameterError(InputError):
    """A bad value of the parameter ``parameter`` (its Python name); the message starts with that name."""

    def __init__(self, parameter: str, message: str) -> None:
        super().__init__(message, parameter)


class AssertedParameterError(ParameterError, AssertionError):
    """A bad value where Stable-Baselines3 raises an ``AssertionError``: also one, so that SB3 code catches it."""


class SpaceError(AssertedParameterError, TypeError):
    """An observation or action space the algorithm or policy cannot take (an ``AssertionError`` as in SB3)."""


class LayerMappingError(ValueError):
    """The policy's modules cannot be mapped to the named layers (:func:`~sb3_collapse.monitoring.layer_taps`)."""


class CheckpointError(InputError):
    """A checkpoint (a run's or its replay store's) that cannot be used; ``damaged``: its files are damaged (missing,
    truncated, bad checksum), so a run falls back to the one before."""

    def __init__(self, message: str, damaged: bool = False) -> None:
        super().__init__(message)
        self.damaged = damaged


class OutputError(RuntimeError):
    """A run's output (a checkpoint, a log, the final model) could not be written (a full or read-only disk)."""


class DivergenceError(FloatingPointError):
    """Training produced a loss or a weight that is not finite; the message names the update and the frame."""


class NonFiniteDataError(ValueError):
    """A reward or an observation that is not finite, from an environment (refused before it is stored) or read back
    from a replay checkpoint, or a simulator that could not step (MuJoCo's ``PhysicsError``): bad data, not a
    divergence of the training; the message names where it came from."""


class TrainingInterrupted(Exception):
    """``learn()`` stopped at the signal ``signal_name`` (``"SIGTERM"``) after writing the ``checkpoint`` folder."""

    def __init__(self, checkpoint: Path, signal_name: str) -> None:
        super().__init__(f"stopped by {signal_name} after writing the checkpoint {checkpoint}")
        self.checkpoint = checkpoint
        self.signal_name = signal_name


class MissingDependencyError(ImportError):
    """An optional package (rl_zoo3, Ray) or a system library (OpenGL) is not installed."""


class ClusterUnreachable(RuntimeError):
    """No Ray cluster answered at the sweep's ``address`` in time: retry once it is up. Nothing was written."""

    parameter = "address"


READ_ONLY_ERRNOS = (errno.EROFS, errno.EACCES, errno.EPERM)
FULL_DISK_ERRNOS = (errno.ENOSPC, errno.EDQUOT)


def unwritable_message(error: BaseException) -> str | None:
    """:return: one line for an output that could not be written (read-only, full disk), ``None`` for another error"""
    if not isinstance(error, OSError) or error.errno not in (*READ_ONLY_ERRNOS, *FULL_DISK_ERRNOS):
        return None
    where = error.filename if error.filename is not None else "an output file"
    reason = os.strerror(error.errno)
    if error.errno in FULL_DISK_ERRNOS:
        return f"could not write {where} ({reason}): free space, then run the same command again."
    return f"cannot write {where} ({reason}): choose a folder you can write to, or make this one writable."
