"""numba's on-disk cache across interpreters, and the warm-up ``make env`` runs to fill it
(:mod:`pipeline.warmup`)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np

from datasets.types import Recording, ScanSequence, Trajectory
from pipeline.warmup import WARMUP_SCANS, there_and_back
from tests.conftest import REPO
from tests.test_pipeline import check_run_folder

# A GPFOL and a GPPOL map over three scans of a round room, each queried at two points.
MAP_QUERY = """
import numpy as np

from datasets.types import ScanSequence
from mapping.build import MapBuilder
from mapping.config import MappingConfig
from mapping.kernels import make_kernel
from mapping.train import GPParams

angles = np.linspace(-np.pi, np.pi, 90, endpoint=False)
scans = ScanSequence([np.full(90, 4.0)] * 3, [angles] * 3, [0, 10**9, 2 * 10**9], 0.1, 30.0)
poses = np.array([[0.0, 0.0, 0.0], [0.3, 0.0, 0.1], [0.6, 0.0, 0.2]])
cov = np.tile(np.diag([0.01, 0.01, 0.001]), (3, 1, 1))
params = GPParams(make_kernel("nn", (0.9, 3.0, 4.0)), 0.1, 8.0, 0.3)
for mapper in ("gpfol", "gppol"):
    builder = MapBuilder.from_config(MappingConfig(), mapper)
    gp = builder.gp_map(builder.beams(scans, poses, np.zeros(3)), params, cov)
    print(mapper, *gp.query(np.array([[0.0, 0.0], [3.9, 0.2]])).probability)
"""


# What a real recording reaches and the short simulated run does not (pipeline.warmup.warm_other_paths): a
# wheel-seeded search window of a few cells, a reset of a submap of far-spread points, and a big map's
# figure (pasted at one pixel per cell).
REAL_PATHS = """
import sys
from pathlib import Path

import numpy as np

from mapping.exports import MapLayers
from mapping.figures import layer_figure, save_figure
from slam.odometry import search_window
from slam.scan_matching import PointGrid

grid = PointGrid.around(np.zeros(2), 60.0)
points = np.array([[-50.0, 0.0], [50.0, 1.0], [0.0, 50.0]])
grid.insert(points, np.tile([0.0, 1.0], (3, 1)))
search_window(grid, points, np.array([0.1, 0.0, 0.01]), 0.1, 0.05, 0.004)
grid.reset(np.full(2, -60.0))
p = np.random.default_rng(0).uniform(0, 1, (1500, 2500)).astype(np.float32)
save_figure(layer_figure(MapLayers(p, p, p, 0.1, (0.0, 0.0)), "probability"), Path(sys.argv[1]))
"""


def _python(*args: str, timeout: float) -> subprocess.CompletedProcess:
    env = {**os.environ, "NUMBA_DEBUG_CACHE": "1"}
    env.pop("NUMBA_CACHE_DIR", None)  # numba's default: __pycache__ beside each module, as `make env` fills
    env.pop("NUMBA_DISABLE_JIT", None)
    return subprocess.run(
        [sys.executable, *args], cwd=REPO, env=env, capture_output=True, text=True, timeout=timeout
    )


def _cache_lines(output: str, what: str) -> list[str]:
    """The compiled functions whose cache entry numba reports ``data loaded`` / ``data saved``."""
    return re.findall(rf"\[cache\] {what} (?:from|to) '.*?([\w.]+)-\d+\.py\d+\.\d+\.nbc'", output)


def test_a_second_interpreter_loads_the_compiled_map_query() -> None:
    first = _python("-c", MAP_QUERY, timeout=300)  # loads the cache, or compiles and saves it
    assert first.returncode == 0, first.stderr
    second = _python("-c", MAP_QUERY, timeout=60)
    assert second.returncode == 0, second.stderr
    out = second.stdout
    assert _cache_lines(out, "data saved") == [], "the second interpreter compiled again"
    assert "core.predict_batch" in _cache_lines(out, "data loaded")
    # the same maps both times (to rounding: freshly compiled and loaded code may differ in the last bits),
    # and real answers: p(occ) is higher at the room's wall than at its centre
    got, expected = _probabilities(out), _probabilities(first.stdout)
    assert set(got) == {"gpfol", "gppol"}
    for mapper, (centre, wall) in got.items():
        np.testing.assert_allclose([centre, wall], expected[mapper], rtol=1e-9)
        assert 0 < centre < wall < 1, mapper


def test_the_warmup_compiles_what_real_recordings_reach_beyond_the_simulated_run(tmp_path) -> None:
    """After :func:`pipeline.warmup.warm_other_paths` in one interpreter, the real code paths it stands for
    load every compiled function from the cache in the next one (none is compiled again)."""
    warm = _python("-c", "from pipeline.warmup import warm_other_paths; warm_other_paths()", timeout=300)
    assert warm.returncode == 0, warm.stderr
    real = _python("-c", REAL_PATHS, str(tmp_path / "map.png"), timeout=300)
    assert real.returncode == 0, real.stderr
    loaded, saved = _cache_lines(real.stdout, "data loaded"), _cache_lines(real.stdout, "data saved")
    for name in ("scan_matching._csm", "scan_matching._clear_around", "figures._over"):
        assert name in loaded and name not in saved, (name, saved)


def _probabilities(output: str) -> dict[str, tuple[float, float]]:
    """``MAP_QUERY``'s answers: p(occ) at the room's centre and at its wall, per mapper."""
    rows = [line.split() for line in output.splitlines() if line.startswith(("gpfol ", "gppol "))]
    return {row[0]: (float(row[1]), float(row[2])) for row in rows}


def _recording(n: int) -> Recording:
    """``n`` scans at 2 Hz (scan ``k``'s ranges all ``k + 1``) with odometry at 20 Hz: x = t."""
    angles = np.linspace(-1.0, 1.0, 5)
    stamps = 10**9 + 13_000_000 + np.arange(n) * 500_000_000
    odom_stamps = 10**9 + np.arange(n * 10 + 1) * 50_000_000
    t = (odom_stamps - odom_stamps[0]) / 1e9
    odom = np.stack([t, np.zeros_like(t), np.zeros_like(t)], axis=1)
    truth = np.stack([(stamps - 10**9) / 1e9, np.ones(n), np.zeros(n)], axis=1)
    return Recording(
        source=Path("test"),
        format="simulation",
        scans=ScanSequence([np.full(5, k + 1.0) for k in range(n)], [angles] * n, stamps, 0.1, 30.0),
        odometry=Trajectory(odom_stamps, odom, "odom"),
        reference=Trajectory(stamps, truth, "map"),
    )


def test_there_and_back_mirrors_every_stream_in_time() -> None:
    rec = _recording(10)
    out = there_and_back(rec, 6)
    assert out.scans is not None and out.odometry is not None and out.reference is not None
    stamps = out.scans.stamps_ns
    assert len(stamps) == 11 and np.all(np.diff(stamps) == 500_000_000)
    assert [float(r[0]) for r in out.scans.ranges_m] == [1, 2, 3, 4, 5, 6, 5, 4, 3, 2, 1]
    assert np.all(np.diff(out.odometry.stamps_ns) > 0)
    # the odometry of the way back at each scan is the way out's at the same scan: the robot backs up
    at = out.odometry.interpolate(stamps)
    np.testing.assert_allclose(at[6:], at[4::-1], atol=1e-12)
    np.testing.assert_allclose(at[:6], rec.odometry.interpolate(rec.scans.stamps_ns[:6]), atol=1e-12)
    np.testing.assert_array_equal(out.reference.stamps_ns, stamps)
    np.testing.assert_array_equal(out.reference.poses_xytheta[-1], rec.reference.poses_xytheta[0])


def test_warmup_runs_the_pipeline_with_loop_closure(tmp_path) -> None:
    res = _python("-m", "pipeline.warmup", "--out", str(tmp_path), timeout=600)
    assert res.returncode == 0, res.stderr
    assert "numba cache warm" in res.stderr
    summary = check_run_folder(tmp_path / "run")
    assert summary["counts"]["scans"] == 2 * WARMUP_SCANS - 1 and summary["mapper"] == "gppol"
    # the way back closes loops (the loop-closure search is among the code the warm-up compiles)
    assert summary["counts"]["loop_closures"] >= 1
    assert summary["metrics"]["auc"] is not None  # scored against the ground truth, like the demo
    assert (tmp_path / "run" / "report.html").is_file()
