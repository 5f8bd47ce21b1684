"""The command line's memory policy (pipeline.memory): freed big arrays stay in the process for reuse."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

_CHILD = """
import sys
import numpy as np
from pipeline.memory import keep_freed_memory

applied = keep_freed_memory() if sys.argv[1] == "policy" else False

def rss_kib():
    return int(next(line for line in open("/proc/self/status") if line.startswith("VmRSS")).split()[1])

def allocate_and_free():
    global held
    block = np.ones(200 * 2**20, np.uint8)
    held = rss_kib()
    del block

if sys.argv[2] == "thread":  # as the export's writer threads do
    import threading
    worker = threading.Thread(target=allocate_and_free)
    worker.start()
    worker.join()
else:
    allocate_and_free()
print(applied, held, rss_kib())
"""


def _child(mode: str, env: dict[str, str] | None = None, where: str = "main") -> tuple[bool, int, int]:
    """(policy applied, RSS holding a 200 MiB array, RSS after freeing it) of a fresh interpreter, KiB; the
    array made and freed in the main thread or (``where`` "thread") in a thread of its own."""
    full_env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_") and k != "GLIBC_TUNABLES"}
    full_env.update(env or {}, PYTHONPATH=str(ROOT))
    out = subprocess.run(
        [sys.executable, "-c", _CHILD, mode, where], capture_output=True, text=True, check=True, env=full_env
    ).stdout.split()
    return out[0] == "True", int(out[1]), int(out[2])


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="reads the RSS from /proc (Linux)")
def test_freed_memory_stays_in_the_process_only_with_the_policy() -> None:
    applied, held, after = _child("policy")
    assert applied
    assert after > held - 20 * 1024  # the 200 MiB stay, ready for the next array
    applied, held, after = _child("default")
    assert not applied
    assert after < held - 150 * 1024  # glibc's default: the block's own mapping goes back to the kernel


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="reads the RSS from /proc (Linux)")
def test_memory_freed_in_a_thread_stays_in_the_process_too() -> None:
    applied, held, after = _child("policy", where="thread")
    assert applied
    assert after > held - 20 * 1024
    applied, held, after = _child("default", where="thread")
    assert not applied
    assert after < held - 150 * 1024


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc")
def test_a_users_malloc_settings_stand() -> None:
    users = (
        {"MALLOC_TRIM_THRESHOLD_": "131072"},
        {"MALLOC_ARENA_MAX": "4"},
        {"GLIBC_TUNABLES": "glibc.malloc.mmap_max=8"},
    )
    for env in users:
        applied, held, after = _child("policy", env)
        assert not applied
        assert after < held - 150 * 1024
