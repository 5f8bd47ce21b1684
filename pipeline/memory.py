"""The command line's memory policy: memory a step frees stays in the process for the next step.

A run's big steps (rendering a building's maps, writing their exports) allocate and free arrays of hundreds of
megabytes. glibc's malloc gives every block above its mmap threshold (at most 32 MiB) a mapping of its own and
unmaps it when freed, so the next big array is faulted in page by page again. On virtual machines whose freed
pages go back to the host (free page reporting, memory ballooning; the project's development and CI machines
are such) a fault costs many times a bare machine's. :func:`keep_freed_memory` asks glibc (``mallopt(3)``) to
serve big blocks from its heap, never to trim it, and to give every thread that one heap: what one step frees,
the next reuses without faults, in whichever thread. The process keeps its peak memory until it exits; the
peak itself does not grow (``bench``'s ``peak_rss_mib``).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys

#: mallopt(3) parameters (glibc's malloc.h).
M_TRIM_THRESHOLD = -1
M_MMAP_MAX = -4
M_ARENA_MAX = -8
#: The largest trim threshold mallopt takes (an int): the heap is trimmed only when 2 GiB at its top are free.
NEVER_TRIM_BYTES = 2**31 - 1
#: Environment variables through which a user sets glibc's malloc; any of them set: their choice stands.
USER_MALLOC_SETTINGS = (
    "MALLOC_MMAP_MAX_",
    "MALLOC_TRIM_THRESHOLD_",
    "MALLOC_MMAP_THRESHOLD_",
    "MALLOC_ARENA_MAX",
)


def keep_freed_memory() -> bool:
    """Big blocks from the heap (``M_MMAP_MAX`` 0), no trimming (``M_TRIM_THRESHOLD`` at its maximum) and one
    arena for every thread (``M_ARENA_MAX`` 1), for the allocations made from now on. Without the last, a
    thread's own arena (heaps of 64 MiB at most) would still map each bigger block apart and unmap it when
    freed, and the export's writer threads allocate some of the biggest blocks.
    Returns True when applied: glibc on Linux, and the user has set none of :data:`USER_MALLOC_SETTINGS`
    nor a malloc tunable in ``GLIBC_TUNABLES``; False otherwise (nothing changed)."""
    if not sys.platform.startswith("linux"):
        return False
    if any(name in os.environ for name in USER_MALLOC_SETTINGS):
        return False
    if "glibc.malloc." in os.environ.get("GLIBC_TUNABLES", ""):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
        libc.gnu_get_libc_version  # noqa: B018 -- present in glibc only (musl has a mallopt that does nothing)
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    return (
        bool(mallopt(M_MMAP_MAX, 0))
        and bool(mallopt(M_TRIM_THRESHOLD, NEVER_TRIM_BYTES))
        and bool(mallopt(M_ARENA_MAX, 1))
    )
