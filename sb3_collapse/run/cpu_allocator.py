"""Keep large freed CPU buffers in the process, so that DrQ-v2 updates on the CPU do not page-fault.

Every DrQ-v2 update allocates and frees activations and gradients of tens of MB (``256 x 32 x 41 x 41`` floats).
glibc's ``malloc`` serves blocks over 32 MB with a fresh ``mmap`` and returns them with ``munmap`` when freed, so
each update touches hundreds of MB of new pages, which the kernel zero-fills on first write (what this costs:
benchmarks/README.md#notes-on-what-each-measures).

:func:`tune_cpu_allocator` raises glibc's mmap threshold to 1 GiB and stops heap trimming, so freed blocks
are reused. The cost: the process keeps its peak heap instead of returning it to the system. Blocks over
1 GiB (replay buffers, say) are still mapped lazily. It only affects CPU tensors; CUDA memory has its own
caching allocator. Set ``SB3_COLLAPSE_TUNE_MALLOC=0`` to leave the allocator alone.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os

MMAP_THRESHOLD_BYTES = 1 << 30
"""Blocks below this size come from the heap and are reused after being freed."""

_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
_tuned = False


def tune_cpu_allocator() -> bool:
    """
    Raise glibc's mmap threshold and trim threshold (see the module docstring), once per process.

    :return: whether the allocator is tuned: ``False`` where the C library is not glibc, or when the
        environment variable ``SB3_COLLAPSE_TUNE_MALLOC`` is ``0``
    """
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
    _tuned = bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)) and bool(
        mallopt(_M_TRIM_THRESHOLD, MMAP_THRESHOLD_BYTES)
    )
    return _tuned
