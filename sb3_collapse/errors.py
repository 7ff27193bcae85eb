"""
The package's exceptions, one class per kind of error, and the translation of their messages into the words of a
command line.

Library code names Python parameters in its messages (``episodes must be >= 1, got 0``); a CLI passes the message
through :func:`cli_message`, which names its flags instead (``--episodes must be >= 1, got 0``).
"""

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
    """
    Bad input to a library function or a command (a setting, a file, a folder, a command line): the message says what
    is wrong and what to do. A command line prints it as ``error: ...`` with exit status 2.

    :param message: the message, in Python's words (parameter names, not flags)
    :param parameter: the Python name of the parameter at fault, when there is one
    """

    def __init__(self, message: str, parameter: str | None = None) -> None:
        super().__init__(message)
        self.parameter = parameter


class ParameterError(InputError):
    """
    A bad value of a parameter; the message starts with the parameter's name.

    :param parameter: the parameter's Python name (``"batch_size"``)
    :param message: what is wrong and what to do
    """

    def __init__(self, parameter: str, message: str) -> None:
        super().__init__(message, parameter)


class AssertedParameterError(ParameterError, AssertionError):
    """
    A bad value where Stable-Baselines3 raises an ``AssertionError``: also one, so that code written for SB3 catches
    it, with a message that says what to do.

    :param parameter: the parameter's Python name
    :param message: what is wrong and what to do
    """


class SpaceError(AssertedParameterError, TypeError):
    """
    An observation or action space the algorithm or policy cannot take; the message says what to use instead. Also an
    ``AssertionError`` (what Stable-Baselines3 raises for an unsupported space) and a ``TypeError``.

    :param parameter: the parameter that brought the space (``"env"``, ``"policy"``)
    :param message: what is wrong and what to do
    """


class LayerMappingError(ValueError):
    """The policy's modules cannot be mapped to the named layers (:func:`~sb3_collapse.monitoring.layer_taps`)."""


class CheckpointError(InputError):
    """
    A checkpoint (a run's, or its replay store's) that cannot be used: damaged, or written by another version or for
    another run; the message names it and says what to do.

    :param message: what is wrong and what to do
    :param damaged: whether its files are damaged (missing, truncated, another checksum): a run then falls back to
        the checkpoint before; otherwise it is refused
    """

    def __init__(self, message: str, damaged: bool = False) -> None:
        super().__init__(message)
        self.damaged = damaged


class OutputError(RuntimeError):
    """A run's output (a checkpoint, a log, the final model) could not be written (a full or read-only disk); the
    message names the folder, what is intact and what to do."""


class DivergenceError(FloatingPointError):
    """Training produced a loss or a weight that is not finite; the message names the update and the frame."""


class TrainingInterrupted(Exception):
    """
    ``learn()`` stopped at a signal after writing a checkpoint.

    :param checkpoint: the checkpoint's folder
    :param signal_name: the signal (``"SIGTERM"``, ``"SIGINT"``)
    """

    def __init__(self, checkpoint: Path, signal_name: str) -> None:
        super().__init__(f"stopped by {signal_name} after writing the checkpoint {checkpoint}")
        self.checkpoint = checkpoint
        self.signal_name = signal_name


class MissingDependencyError(ImportError):
    """An optional package (rl_zoo3, Ray) or a system library (OpenGL) is not installed; the message says what to
    install."""


class ClusterUnreachable(RuntimeError):
    """
    No Ray cluster answered at the sweep's address in time (nothing listens there, a firewall, a head still
    starting): a fault to retry once the cluster is up. Nothing was written.

    :param message: what happened and what to do, naming the parameter (``address``)
    """

    parameter = "address"


READ_ONLY_ERRNOS = (errno.EROFS, errno.EACCES, errno.EPERM)
"""``OSError`` numbers of a folder or file that cannot be written: read-only file system, no permission."""

FULL_DISK_ERRNOS = (errno.ENOSPC, errno.EDQUOT)
"""``OSError`` numbers of a full disk or quota."""


def unwritable_message(error: BaseException) -> str | None:
    """
    One line for an output that could not be written (a read-only or full disk, no permission), saying what to do.

    :param error: any exception
    :return: the message, ``None`` for an error of another kind
    """
    if not isinstance(error, OSError) or error.errno not in (*READ_ONLY_ERRNOS, *FULL_DISK_ERRNOS):
        return None
    where = error.filename if error.filename is not None else "an output file"
    reason = os.strerror(error.errno)
    if error.errno in FULL_DISK_ERRNOS:
        return f"could not write {where} ({reason}): free space, then run the same command again."
    return f"cannot write {where} ({reason}): choose a folder you can write to, or make this one writable."


def report_unwritable_outputs(main: Callable[P, int]) -> Callable[P, int]:
    """
    Decorate a command line's ``main``: an output it could not write (:func:`unwritable_message`) ends it with one
    line, ``error: ...``, on stderr and exit status 2 for a read-only folder or no permission (fix the input), 1 for a
    full disk (try again), instead of a traceback. Other errors pass through.

    :param main: the command's ``main(argv) -> exit status``
    :return: the decorated ``main``
    """

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
    """
    :param parser: a command line (with its sub-commands' flags)
    :return: destination (Python name) -> its long flag (``{"learning_rate": "--lr", "batch_size": "--batch-size"}``)
    """
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
    """
    The message of a library error as a command line says it: the Python names of the parser's settings become
    their flags (``learning_rate`` -> ``--lr``). Names with an underscore are replaced wherever they stand as a
    word; a one-word name when it is the error's :attr:`ParameterError.parameter` and starts the message
    (``episodes`` is also an ordinary word), or when it stands in backticks: `` `overwrite=True` `` becomes
    ``--overwrite``, `` `episodes=3` `` ``--episodes 3`` and `` `out` `` ``--out``.

    :param error: the error
    :param parser: the command line whose flags name the settings
    :return: the message
    """
    message = str(error)
    flags = parameter_flags(parser)

    def quoted(match: re.Match) -> str:
        name, value = match.group(1), match.group(2)
        if name not in flags:
            return match.group(0)
        return flags[name] if value in (None, "True") else f"{flags[name]} {value}"

    message = re.sub(r"`(\w+)(?:=([^`]*))?`", quoted, message)
    for name in sorted(flags, key=len, reverse=True):
        if "_" in name:
            message = re.sub(rf"(?<![\w\-./]){re.escape(name)}(?![\w\-/])", flags[name], message)
    parameter = getattr(error, "parameter", None)
    if parameter in flags and "_" not in parameter and message.startswith(parameter):
        message = flags[parameter] + message[len(parameter) :]
    return message
