"""The command line's memory policy: memory a step frees stays in the process for the next step.

A run's big steps (rendering a building's maps, writing their exports) allocate and free arrays of hundreds of
megabytes. glibc's malloc gives every block above its mmap threshold (at most 32 MiB) a mapping of its own and
unmaps it when freed, so the next big array is faulted in page by page again. On virtual machines whose freed
pages go back to the host (free page reporting, memory ballooning; the project's development and CI machines
are such) a fault costs many times a bare machine's. :func:`keep_freed_memory` asks glibc (``mallopt(3)``) to
serve big blocks from its heap, never to trim it, and to give every thread that one heap: what one step frees,
the next reuses without faults, in whichever thread. The process keeps its peak memory until it exits; the
peak itself does not grow (``bench``'s ``peak_rss_mib``).

On such machines the faults themselves are slow (seconds per gigabyte of system time), and a big building's
map stages and exports take gigabytes of memory the process has not had yet. SLAM runs on one core before
them. :func:`pretouch_heap` uses the other: while SLAM runs, a thread touches heap memory that the later
stages will reuse, so that their faults are taken where a core is idle (the JVM's ``AlwaysPreTouch`` does the
same for its heap). It is an estimate of what the stages will need and stops when SLAM ends; without the
policy above it does nothing, as freed memory would go back to the kernel.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

#: mallopt(3) parameters (glibc's malloc.h).
M_TRIM_THRESHOLD = -1
M_MMAP_MAX = -4
M_ARENA_MAX = -8
#: The largest trim threshold mallopt takes (an int): the heap is trimmed only when 2 GiB at its top are free.
NEVER_TRIM_BYTES = 2**31 - 1
PRETOUCH_BLOCK_BYTES = 2**30  # each pre-touched block stays below NEVER_TRIM_BYTES
PRETOUCH_CHUNK_BYTES = 32 * 2**20  # touched between checks of the stop signal
PRETOUCH_MIN_BYTES = 256 * 2**20  # below this the faults are too few to be worth a thread
PRETOUCH_MAX_SHARE = 0.25  # of the machine's available memory, at most
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
    applied = (
        bool(mallopt(M_MMAP_MAX, 0))
        and bool(mallopt(M_TRIM_THRESHOLD, NEVER_TRIM_BYTES))
        and bool(mallopt(M_ARENA_MAX, 1))
    )
    global _LIBC
    _LIBC = libc if applied else None
    if applied:  # for the pre-touch's fences (_fence_after)
        libc.malloc.argtypes = (ctypes.c_size_t,)
        libc.malloc.restype = ctypes.c_void_p
        libc.free.argtypes = (ctypes.c_void_p,)
    return applied


_LIBC: ctypes.CDLL | None = None  # glibc, once keep_freed_memory() has applied the policy


def keeping_freed_memory() -> bool:
    """Whether :func:`keep_freed_memory` has applied the policy in this process (the command line does)."""
    return _LIBC is not None


_FENCES: list[int] = []  # tiny blocks that keep pre-touched ones apart from the heap's top (never freed)
_FENCE_SIZES = (64, 4096, 65536)


def _fence_after(libc: ctypes.CDLL, end: int) -> bool:
    """Allocate a small block (never freed) right after the heap block that ends at address ``end``, if
    glibc places one there (it does when the block was split from the heap's top and no free chunk fits the
    small one); True when done. Misplaced tries are freed."""
    for size in _FENCE_SIZES:
        fence = libc.malloc(size)
        if fence and end <= fence <= end + 64:
            _FENCES.append(fence)
            return True
        libc.free(fence)
    return False


def available_bytes(meminfo: str = "/proc/meminfo", cgroup: str = "/sys/fs/cgroup") -> int | None:
    """What the process may still take (bytes): the machine's ``MemAvailable`` and, under a cgroup v2
    memory limit (a container's), what the limit leaves; None where neither is known."""
    known: list[int] = []
    try:
        with open(meminfo) as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    known.append(int(line.split()[1]) * 1024)
                    break
    except (OSError, ValueError, IndexError):
        pass
    try:
        limit = Path(cgroup, "memory.max").read_text().strip()
        if limit != "max":
            known.append(int(limit) - int(Path(cgroup, "memory.current").read_text().strip()))
    except (OSError, ValueError):
        pass
    return max(min(known), 0) if known else None


@contextmanager
def pretouch_heap(nbytes: int) -> Iterator[dict[str, int]]:
    """Within the block, a thread touches up to ``nbytes`` of new heap memory (at most
    :data:`PRETOUCH_MAX_SHARE` of the available memory) and frees it into the heap when the block ends, so
    that the steps after the block reuse it without page faults. The thread stops at the block's end,
    touched or not. Yields ``{"bytes": ...}``, the bytes touched once the block has ended (0 when nothing was
    done: the policy of :func:`keep_freed_memory` not applied, or ``nbytes`` below
    :data:`PRETOUCH_MIN_BYTES`).

    Each block of at most :data:`PRETOUCH_BLOCK_BYTES` is followed by a small block that is never freed,
    so that no freed block ends the heap, where glibc would give it back to the kernel. Touching is numpy
    assignments, which release the GIL: the block's own work is not held up."""
    report = {"bytes": 0}
    libc = _LIBC
    available = available_bytes() if libc is not None else None
    if available is not None:
        nbytes = min(nbytes, int(PRETOUCH_MAX_SHARE * available))
    if libc is None or nbytes < PRETOUCH_MIN_BYTES:
        yield report
        return
    stop = threading.Event()
    page = os.sysconf("SC_PAGE_SIZE") if hasattr(os, "sysconf") else 4096
    blocks: list[np.ndarray] = []

    def touch() -> None:
        left = nbytes
        while left > 0 and not stop.is_set():
            try:
                block = np.empty(min(left, PRETOUCH_BLOCK_BYTES), np.uint8)
            except MemoryError:  # the estimate was too much for this machine: keep what is touched
                return
            blocks.append(block)
            _fence_after(libc, block.ctypes.data + block.size)
            for start in range(0, block.size, PRETOUCH_CHUNK_BYTES):
                if stop.is_set():
                    break
                block[start : start + PRETOUCH_CHUNK_BYTES : page] = 0
                report["bytes"] += min(PRETOUCH_CHUNK_BYTES, block.size - start)
            left -= block.size

    worker = threading.Thread(target=touch, name="pretouch", daemon=True)
    worker.start()
    try:
        yield report
    finally:
        stop.set()
        worker.join()
        blocks.clear()
