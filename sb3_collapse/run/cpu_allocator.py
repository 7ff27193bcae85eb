"""Keep large freed CPU buffers in the process, so that DrQ-v2 updates on the CPU do not page-fault (glibc serves
blocks over 32 MB with a fresh ``mmap``, zero-filled at every update; docs/algorithm.md)."""

from __future__ import annotations

import ctypes
import ctypes.util
import os

MMAP_THRESHOLD_BYTES = 1 << 30  # blocks below this size come from the heap and are reused after being freed

_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # mallopt's options (glibc's malloc.h)
_tuned = False


def tune_cpu_allocator() -> bool:
    """Raise glibc's mmap and trim thresholds to :data:`MMAP_THRESHOLD_BYTES`, once per process: freed blocks below it
    are reused (the process keeps its peak heap). Return whether it is tuned: ``False`` where the C library is not
    glibc, or with the environment variable ``SB3_COLLAPSE_TUNE_MALLOC=0``."""

    global _tuned
    if _tuned:
        return True
    if os.environ.get("SB3_COLLAPSE_TUNE_MALLOC", "1") == "0":
        return False
    name = ctypes.util.find_library("c")
    if name is None:
        return False
    try:
        libc = ctypes.CDLL(name)
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # not glibc (musl, macOS, Windows)
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    _tuned = all(mallopt(option, MMAP_THRESHOLD_BYTES) for option in (_M_MMAP_THRESHOLD, _M_TRIM_THRESHOLD))
    return _tuned
