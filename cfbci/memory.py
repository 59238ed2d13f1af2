"""Keep freed memory in the process, so the learner's large temporaries do not fault.

Every learner step allocates and frees temporaries of several megabytes (per-task,
per-fold covariance batches). glibc's ``malloc`` serves blocks above its mmap threshold
with fresh ``mmap`` calls and returns them with ``munmap``: every step then pays the page
faults of zeroed memory again, about a third of a step's time on this project's 2-core
machines. Raising the mmap, trim and top-pad thresholds (``mallopt``) keeps that memory
in the heap for reuse. Numbers are unchanged: only where the bytes live.
"""

from __future__ import annotations

import ctypes
import ctypes.util

_M_TRIM_THRESHOLD, _M_TOP_PAD, _M_MMAP_THRESHOLD = -1, -2, -3
_MMAP_THRESHOLD = 1 << 30  # glibc caps it at HEAP_MAX (32 MiB on 64-bit), which is enough
_TRIM_THRESHOLD = 1 << 30
_TOP_PAD = 64 << 20


def keep_freed_memory() -> bool:
    """Tune glibc's allocator as described above; False where there is no glibc."""
    name = ctypes.util.find_library("c")
    if name is None:
        return False
    try:
        libc = ctypes.CDLL(name)
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    return all(
        mallopt(option, value) == 1
        for option, value in (
            (_M_MMAP_THRESHOLD, _MMAP_THRESHOLD),
            (_M_TRIM_THRESHOLD, _TRIM_THRESHOLD),
            (_M_TOP_PAD, _TOP_PAD),
        )
    )
