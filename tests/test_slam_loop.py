"""The SLAM stage on the simulated ``loop`` world (ground truth known): accuracy before and after loop
closure, consistency of the covariances (NEES), and the shape of the result.

Issue 6: ATE after loop closure at most 0.05 m and at least 5x lower than before (the scan-matching
odometry chain), average NEES of the 3-dof poses after loop closure in [1, 6]. The world's 100 m glazed
gallery is degenerate for the scanner (its axis is fixed by the wheels only), so the chain drifts along it
by the wheels' 2 % scale error and says so in its covariance; the loop closures in the lobby fix it.
The world and the degeneracy threshold were designed looking at seeds 0, 1 and 2 (not only seed 0).
"""

from __future__ import annotations

import numpy as np
import pytest

from datasets.simulation import make_world
from slam import geometry as se2
from slam import metrics
from slam.config import SlamConfig
from slam.system import SlamResult, run_slam, wheel_poses_at_scans
from slam.trajectory_io import read_g2o, write_g2o

#: Known gaps, asserted to stay where they are (then marked xfail); none at present (seed 2's ATE after loop
#: closure is only just under 5 cm: its along-track errors over 200 m of the loop are barely located).
ABOVE_5_CM: dict[int, float] = {}
#: Known gaps of the mean NEES after loop closure (below 1: conservative); none at present (seeds 0 and 1
#: were at 0.93 / 0.95 until dense scans were registered thinned, ``match_points``).
NEES_BELOW_1: dict[int, float] = {}


@pytest.fixture(scope="module", params=[0, 1, 2], ids=["seed0", "seed1", "seed2"])
def loop_run(request) -> tuple:
    rec = make_world("loop", request.param).recording
    result = run_slam(rec.scans, rec.odometry, rec.laser_in_base_xytheta, SlamConfig())
    return rec, result, request.param


def test_loop_closure_brings_the_ate_below_5_cm(loop_run) -> None:
    rec, result, seed = loop_run
    truth = rec.reference.poses_xytheta
    wheel = wheel_poses_at_scans(rec.odometry, rec.scans.stamps_ns)
    ate_wheel = metrics.ate_rmse(wheel, truth)
    ate_before = metrics.ate_rmse(result.poses_before_xytheta, truth)
    ate_after = metrics.ate_rmse(result.poses_after_xytheta, truth)
    # measured: before 0.290 / 0.307 / 0.253 m, after 0.027 / 0.035 / 0.040 m (seeds 0 / 1 / 2)
    assert ate_wheel > ate_before > 0.2  # the chain drifts along the gallery only
    if seed in ABOVE_5_CM:
        assert ate_before >= 4 * ate_after
        assert 0.05 < ate_after <= ABOVE_5_CM[seed]
        pytest.xfail(f"seed {seed}: ATE after {ate_after:.3f} m > 0.05 m (a known gap)")
    assert ate_before >= 5 * ate_after  # the criterion: before vs after loop closure
    assert ate_after <= 0.05


def test_covariances_are_consistent_with_the_real_errors(loop_run) -> None:
    rec, result, seed = loop_run
    truth = rec.reference.poses_xytheta
    nees_after = np.mean(metrics.nees(result.poses_after_xytheta, result.cov_after_xytheta, truth)[1:])
    nees_before = np.mean(metrics.nees(result.poses_before_xytheta, result.cov_before_xytheta, truth)[1:])
    # measured: before 1.64 / 1.87 / 1.18, after 1.14 / 1.53 / 1.16 (seeds 0 / 1 / 2)
    assert nees_before <= 6.0  # the chain alone is not overconfident either
    if seed in NEES_BELOW_1:
        assert NEES_BELOW_1[seed] <= nees_after < 1.0
        pytest.xfail(f"seed {seed}: mean NEES after {nees_after:.2f} < 1 (a known gap)")
    assert 1.0 <= nees_after <= 6.0


def test_result_shapes_marginals_and_closures(loop_run) -> None:
    rec, result, _ = loop_run
    n, k = len(rec.scans), len(result.keyframe_scans)
    assert isinstance(result, SlamResult)
    assert result.poses_after_xytheta.shape == (n, 3) and result.cov_after_xytheta.shape == (n, 3, 3)
    assert result.keyframe_cov_before.shape == (k, 3, 3) and result.keyframe_stamps_ns.shape == (k,)
    np.testing.assert_array_equal(result.keyframe_stamps_ns, rec.scans.stamps_ns[result.keyframe_scans])
    for covs in (result.keyframe_cov_before[1:], result.keyframe_cov_after[1:], result.cov_after_xytheta[1:]):
        np.testing.assert_allclose(covs, np.swapaxes(covs, 1, 2), atol=1e-15)
        assert np.all(np.linalg.eigvalsh(covs) > 0)
    # closing the loop shrinks the uncertainty of the far end of the loop a lot
    far = int(np.argmax(np.trace(result.keyframe_cov_before, axis1=1, axis2=2)))
    assert np.trace(result.keyframe_cov_after[far]) < 0.2 * np.trace(result.keyframe_cov_before[far])
    # keyframe poses of the graph are the per-scan poses of the keyframes
    np.testing.assert_allclose(
        result.poses_after_xytheta[result.keyframe_scans], result.graph_vertices_xytheta
    )
    # every accepted closure agrees with the ground truth
    truth = rec.reference.poses_xytheta
    assert len(result.loop_closures) >= 5
    for c in result.loop_closures:
        rel_true = se2.between(truth[c.target_scan], truth[c.query_scan])
        err = se2.between(rel_true, c.relative_xytheta)
        assert np.hypot(err[0], err[1]) < 0.1 and abs(err[2]) < 0.02
    assert sum(e.kind == "loop" for e in result.graph_edges) == len(result.loop_closures)


def test_pose_graph_exports_to_g2o(loop_run, tmp_path) -> None:
    _, result, _ = loop_run
    path = tmp_path / "pose_graph.g2o"
    write_g2o(path, result.graph_vertices_xytheta, result.graph_edges)
    g = read_g2o(path)
    np.testing.assert_array_equal(g.vertices_xytheta, result.graph_vertices_xytheta)
    assert len(g.edges) == sum(e.kind != "prior" for e in result.graph_edges)


def test_search_windows_follow_the_relative_uncertainty(loop_run) -> None:
    """The first closure after the 200 m loop is searched in a wide window (the drift; beyond the former
    6 m cap); the later ones, tied to it through the graph, in the smallest window: their relative pose's
    joint-marginal covariance is small, where the sum of the two marginals stays metres wide."""
    _rec, result, _seed = loop_run
    closures = sorted(result.loop_closures, key=lambda c: c.query_keyframe)
    first, rest = closures[0], closures[1:]
    # measured: 13.1 m, then 0.3 m for every later closure (seeds 0 / 1 / 2)
    assert first.window_xy_m > 6.0
    assert rest and max(c.window_xy_m for c in rest) <= 1.0


def test_a_wide_search_needs_the_wide_min_score() -> None:
    """A wide window tries many more poses, so it must score ``wide_min_score``: set to 1 (unreachable), the
    loop world's wide first closure is no longer accepted, and no wide closure is (a 20 m window once put a
    hospital's corridor end onto another, at score 0.32)."""
    rec = make_world("loop", 0).recording
    cfg = SlamConfig()
    lc = cfg.loop_closure.model_copy(update={"wide_min_score": 1.0})
    strict = cfg.model_copy(update={"loop_closure": lc})
    result = run_slam(rec.scans, rec.odometry, rec.laser_in_base_xytheta, strict)
    wide = cfg.loop_closure.wide_window_m
    assert not [c for c in result.loop_closures if c.window_xy_m > wide]
    rejected = result.rejected_loop_closures
    assert any(c.window_xy_m > wide and c.reason.startswith("low score") for c in rejected)
