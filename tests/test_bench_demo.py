"""The demo benchmark's isolation: its runs keep numba's cache out of the checkout."""

from __future__ import annotations

import subprocess
import sys

from pipeline.bench.demo import isolated_cache_env

CODE = (
    "from mapping.raster import GridGeometry, segment_walk\n"
    "print(segment_walk(GridGeometry.of(0.0, 0.0, 1.0, 4, 4), 0.5, 0.5, 3.5, 2.5, False)[3])\n"
)


def test_isolated_cache_env_puts_numba_cache_in_its_folder(tmp_path) -> None:
    """A compiled function called in a process with that environment caches into the given folder (so the
    demo benchmark's cold run really compiles, and the checkout's own cache is never touched)."""
    cache = tmp_path / "cache"
    env = isolated_cache_env(cache)
    argv = [sys.executable, "-c", CODE]
    first = subprocess.run(argv, env=env, cwd=tmp_path, capture_output=True, text=True)
    assert first.returncode == 0, first.stderr
    assert list(cache.rglob("*.nbi")), "no numba index written into the isolated cache folder"
    second = subprocess.run(
        argv,
        env={**env, "NUMBA_DEBUG_CACHE": "1"},
        cwd=tmp_path,
        capture_output=True,
        text=True,
    )
    assert second.returncode == 0, second.stderr
    assert "data loaded" in second.stdout and str(cache) in second.stdout
    assert second.stdout.strip().splitlines()[-1] == first.stdout.strip()
