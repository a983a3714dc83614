"""The C allocator and a long take's large arrays: kept and recycled, not mapped anew each time.

numpy takes every array from malloc. glibc serves blocks above its mmap
threshold (128 KiB at first, raised on its own up to 32 MiB) straight from the
system, every page a fault on first touch, and hands back free memory at the top
of its heap beyond twice that threshold. A long take's arrays (a minute at 120 Hz
with 48 markers: 60,000 frames times 15 joints' matrices, 65 MiB) are made and
dropped many times over; mapped anew each time, they made a quarter to half of the
60,000-frame take's page faults and about 0.3 s of its system time (BENCHMARKS.md).

:func:`keep_large_blocks` sets both thresholds to :data:`LARGE` (``mallopt``),
once per process, so that such blocks come from the heap and go back to it; the
heap's free memory is kept for the next array (a long-lived process keeps up to
its largest take's working memory). Where the user set glibc's own variables
(``MALLOC_MMAP_THRESHOLD_``, ``MALLOC_TRIM_THRESHOLD_``, ``GLIBC_TUNABLES``) they
are kept. Where ``mallopt`` is not there (not glibc), freeing one 32 MiB block
raises glibc-like dynamic thresholds as far as they go (a 32 MiB block never
written, so never faulted in) and costs one allocation elsewhere.
"""
from __future__ import annotations

import ctypes
import os
import sys

__all__ = ["LARGE", "keep_large_blocks"]

#: Blocks up to this size come from the heap, and this much free memory at its top is kept (bytes).
LARGE = 1 << 30

_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
_USER_VARS = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_", "GLIBC_TUNABLES")
_DONE = False


def keep_large_blocks() -> None:
    """Large blocks from the heap and kept there (see the module's docstring); once per process."""
    global _DONE
    if _DONE:
        return
    _DONE = True
    if any(v in os.environ for v in _USER_VARS):
        return
    if sys.platform.startswith("linux"):
        try:
            mallopt = ctypes.CDLL(None).mallopt
            mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
            if mallopt(_M_MMAP_THRESHOLD, LARGE) == 1 and mallopt(_M_TRIM_THRESHOLD, LARGE) == 1:
                return
        except (OSError, AttributeError):
            pass
    import numpy as np

    np.empty(1 << 22)  # 32 MiB, freed at once, untouched
