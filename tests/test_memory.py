"""The command line's memory policy (pipeline.memory): freed big arrays stay in the process for reuse."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from pipeline.memory import PRETOUCH_CHUNK_BYTES

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


_PRETOUCH_CHILD = """
import sys, time
import numpy as np
from pipeline.memory import keep_freed_memory, pretouch_heap

applied = keep_freed_memory() if sys.argv[1] == "policy" else False

def rss_kib():
    return int(next(line for line in open("/proc/self/status") if line.startswith("VmRSS")).split()[1])

target = int(sys.argv[3]) * 2**20
start = rss_kib()
t0 = time.perf_counter()
with pretouch_heap(target if sys.argv[2] != "none" else 0) as done:
    if sys.argv[2] == "wait":
        while applied and done["bytes"] < target and time.perf_counter() - t0 < 60:
            time.sleep(0.01)
left_s = time.perf_counter() - t0
touched = rss_kib()
arrays = [np.ones(100 * 2**20, np.uint8) for _ in range(4)]  # 400 MiB, as the map stages' layers would be
print(applied, done["bytes"] // 2**20, start, touched, rss_kib(), left_s)
"""


def _pretouch_child(policy: str, mode: str, mib: int) -> tuple[bool, int, int, int, int, float]:
    """(policy applied, MiB pre-touched, RSS at start, after the block, after 400 MiB of new arrays (KiB),
    seconds in the block) of a fresh interpreter pre-touching ``mib`` MiB: ``mode`` "wait" stays in the
    block until done, "leave" leaves at once, "none" asks for nothing."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_") and k != "GLIBC_TUNABLES"}
    env["PYTHONPATH"] = str(ROOT)
    out = subprocess.run(
        [sys.executable, "-c", _PRETOUCH_CHILD, policy, mode, str(mib)],
        capture_output=True,
        text=True,
        check=True,
        env=env,
    ).stdout.split()
    return out[0] == "True", int(out[1]), int(out[2]), int(out[3]), int(out[4]), float(out[5])


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="reads the RSS from /proc (Linux)")
def test_pretouched_memory_is_reused_by_the_arrays_that_follow() -> None:
    applied, touched_mib, start, touched, after, _ = _pretouch_child("policy", "wait", 512)
    assert applied and touched_mib == 512
    assert touched - start > 450 * 1024  # in the process once the block has ended
    assert after - touched < 150 * 1024  # the 400 MiB of arrays took (nearly) no new memory
    applied, touched_mib, start, touched, after, _ = _pretouch_child("policy", "none", 512)
    assert applied and touched_mib == 0
    assert after - touched > 350 * 1024  # without it they do


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="reads the RSS from /proc (Linux)")
def test_pretouch_does_nothing_without_the_policy_and_stops_with_its_block() -> None:
    applied, touched_mib, start, touched, _, _ = _pretouch_child("default", "wait", 512)
    assert not applied and touched_mib == 0  # freed memory would go back to the kernel: no point
    assert touched - start < 50 * 1024
    applied, touched_mib, _, _, _, left_s = _pretouch_child("policy", "leave", 2048)
    # left at once: the thread stops at its next check, after at most the chunk it is touching
    assert applied and touched_mib <= 2 * PRETOUCH_CHUNK_BYTES // 2**20 and left_s < 5.0


def test_pretouch_estimate_follows_the_map_the_recording_spans() -> None:
    """fr-clinic's own odometry spans a map of millions of cells, intel's a few hundred thousand; a bag
    without odometry gives no estimate."""
    from datasets.registry import open_dataset
    from pipeline.config import load_config
    from pipeline.run import PRETOUCH_BYTES_PER_CELL, pretouch_estimate_bytes
    from tests.conftest import data_file

    config = load_config()

    def estimate(relative: str) -> int:
        return pretouch_estimate_bytes(open_dataset(data_file(relative)), config)

    clinic = estimate("fr-clinic/fr-clinic_robotlaser.clf.bz2")
    intel = estimate("intel/intel.clf.bz2")
    demo = estimate("lsm-demo/demo_index_fixed.bag")
    assert 10e6 < clinic / PRETOUCH_BYTES_PER_CELL < 20e6  # its maps: 15.05 M cells
    assert 0.1e6 < intel / PRETOUCH_BYTES_PER_CELL < 2e6  # its maps: 0.17 M cells (odometry drifts)
    assert demo == 0


def test_available_memory_is_the_lower_of_the_machine_and_a_container_limit(tmp_path: Path) -> None:
    from pipeline.memory import available_bytes

    meminfo = tmp_path / "meminfo"
    meminfo.write_text("MemTotal:       24000000 kB\nMemAvailable:   20000000 kB\n")
    cgroup = tmp_path / "cgroup"
    cgroup.mkdir()
    assert available_bytes(str(meminfo), str(cgroup)) == 20000000 * 1024  # no cgroup files
    (cgroup / "memory.max").write_text("max\n")
    (cgroup / "memory.current").write_text("1000\n")
    assert available_bytes(str(meminfo), str(cgroup)) == 20000000 * 1024  # no limit
    (cgroup / "memory.max").write_text(f"{4 * 2**30}\n")
    (cgroup / "memory.current").write_text(f"{2**30}\n")
    assert available_bytes(str(meminfo), str(cgroup)) == 3 * 2**30  # the container's limit leaves less
    assert available_bytes(str(tmp_path / "none"), str(cgroup)) == 3 * 2**30
    assert available_bytes(str(tmp_path / "none"), str(tmp_path / "none")) is None


def test_pretouch_stops_quietly_when_memory_runs_out(monkeypatch) -> None:
    """An estimate the machine cannot hold ends the thread without an exception escaping it (a thread's
    uncaught exception would be printed, and the command line prints nothing of its own)."""
    import threading
    import types

    import numpy as np

    import pipeline.memory as memory

    def no_memory(*args, **kwargs):
        raise MemoryError

    escaped: list[BaseException] = []
    monkeypatch.setattr(threading, "excepthook", lambda args: escaped.append(args.exc_value))
    monkeypatch.setattr(memory, "_LIBC", object())  # as if the policy were applied
    monkeypatch.setattr(memory, "available_bytes", lambda: 2**40)
    monkeypatch.setattr(memory, "np", types.SimpleNamespace(empty=no_memory, uint8=np.uint8))
    with memory.pretouch_heap(2**30) as done:
        pass
    assert done["bytes"] == 0
    assert not escaped
