"""The package's exceptions, one class per kind of error, and :func:`cli_message`, which says a library message
(``episodes must be >= 1``) in a command line's words (``--episodes must be >= 1``)."""

from __future__ import annotations

import argparse
import errno
import functools
import os
import re
import sys
from collections.abc import Callable
from pathlib import Path
from typing import ParamSpec

P = ParamSpec("P")


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


def report_unwritable_outputs(main: Callable[P, int]) -> Callable[P, int]:
    """:return: a command line's ``main``, ended by an unwritable output with ``error: ...`` and exit status 2
    (read-only) or 1 (full disk), not a traceback"""

    @functools.wraps(main)
    def wrapped(*args: P.args, **kwargs: P.kwargs) -> int:
        try:
            return main(*args, **kwargs)
        except OSError as error:
            message = unwritable_message(error)
            if message is None:
                raise
            print(f"error: {message}", file=sys.stderr)
            return 1 if error.errno in FULL_DISK_ERRNOS else 2

    return wrapped


def parameter_flags(parser: argparse.ArgumentParser) -> dict[str, str]:
    """:return: each destination (Python name) of ``parser`` and its sub-commands -> its long flag (``"--lr"``)"""
    flags = {}
    for action in parser._actions:
        long_flags = [flag for flag in action.option_strings if flag.startswith("--")]
        if long_flags and action.dest != "help":
            flags.setdefault(action.dest, long_flags[0])
        if isinstance(action, argparse._SubParsersAction):  # the flags of every sub-command
            for subparser in action.choices.values():
                for dest, flag in parameter_flags(subparser).items():
                    flags.setdefault(dest, flag)
    return flags


def cli_message(error: BaseException, parser: argparse.ArgumentParser) -> str:
    """:return: ``error``'s message with ``parser``'s flags for Python names (``learning_rate`` -> ``--lr``): names
    with an underscore anywhere; a one-word name when it is the error's ``parameter`` and starts the message, or in
    backticks (`` `episodes=3` `` -> ``--episodes 3``)"""
    message = str(error)
    flags = parameter_flags(parser)

    def quoted(match: re.Match) -> str:
        name, value = match.group(1), match.group(2)
        if name not in flags:
            return match.group(0)
        return flags[name] if value in (None, "True") else f"{flags[name]} {value}"

    message = re.sub(r"`(\w+)(?:=([^`]*))?`", quoted, message)
    for name in sorted(flags, key=len, reverse=True):
        if "_" in name:  # a dict's key stays as it is: policy_kwargs['hidden_dim']
            message = re.sub(rf"(?<![\w\-./])(?<!\[['\"]){re.escape(name)}(?![\w\-/])", flags[name], message)
    parameter = getattr(error, "parameter", None)
    if parameter in flags and "_" not in parameter and message.startswith(parameter):
        message = flags[parameter] + message[len(parameter) :]
    return message
