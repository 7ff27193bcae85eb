"""Progress bars on a terminal only; on another stream (a log file, a pipe) one line per stage instead."""

from __future__ import annotations

import sys
from collections.abc import Iterable, Sized
from typing import Any

from tqdm.auto import tqdm


def on_terminal(progress: bool = True) -> bool:
    """:return: whether a progress bar may draw: ``progress`` asked for and stderr a terminal"""
    return progress and sys.stderr.isatty()


def progress_bar(
    items: Iterable[Any] | None,
    desc: str,
    unit: str,
    progress: bool = True,
    total: int | None = None,
    leave: bool = True,
) -> tqdm:
    """
    A tqdm bar over ``items`` (or updated by hand) that draws only :func:`on_terminal`; elsewhere, with ``progress``,
    it prints one line ``desc: N units`` to stderr and draws nothing.

    :param items: what the stage iterates over (``None``: the caller calls ``update``)
    :param desc: the stage's name
    :param unit: what one item is
    :param progress: show the progress at all
    :param total: the number of items (default: their count)
    :param leave: keep the finished bar on the terminal
    :return: the bar, iterating over ``items``
    """
    if total is None and items is not None:
        items = items if isinstance(items, Sized) else list(items)
        total = len(items)
    if progress and not on_terminal():
        print(f"{desc}: {total} {unit}s" if total is not None else desc, file=sys.stderr, flush=True)
    return tqdm(items, desc=desc, unit=unit, total=total, leave=leave, disable=not on_terminal(progress))
