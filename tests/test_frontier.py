"""Frontiers, expected variance reduction and next-best views (mapping.frontier): a hand-made room with a
door into unknown space, and a GP map of the start of the simulated loop world."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mapping.exports import MapLayers
from mapping.frontier import (
    ExplorationSettings,
    LaserModel,
    classify_knowledge,
    expected_variance_reduction,
    frontier_layers,
    frontier_mask,
    next_best_views,
    plan_exploration,
    variance_reduction_per_cell,
    visible_cells,
)
from mapping.kernels import make_kernel
from mapping.train import GPParams

RES = 0.1
PRIOR = 0.85
PARAMS = GPParams(make_kernel("se", {"sigma_f": math.sqrt(PRIOR), "length_scale": 1.4}), 0.1, 92.6, -1.49)
# the room: free interior rows/cols 10..49, walls two cells thick around it, a door in the right wall
DOOR_ROWS = range(28, 34)
NARROW = LaserModel(range_max_m=5.0, fov_rad=math.radians(60), n_beams=61)  # headings 45 deg apart differ


def room(known_var: float = 0.005) -> MapLayers:
    """A 10 m x 6 m raster (0.1 m cells from (0, 0)): a 4 m x 4 m room (free interior, cells 10..49) inside
    a wall two cells thick (cells 8-9 and 50-51), a six-cell door in the right wall (rows 28-33, free),
    everything else unknown (p 0.5, the prior variance)."""
    h, w = 60, 100
    p = np.full((h, w), 0.5)
    v = np.full((h, w), PRIOR)
    p[8:52, 8:52] = 0.9
    v[8:52, 8:52] = known_var
    p[10:50, 10:50] = 0.1
    p[DOOR_ROWS.start : DOOR_ROWS.stop, 50:52] = 0.1
    f32 = np.float32
    return MapLayers(p.astype(f32), np.zeros((h, w), f32), v.astype(f32), RES, (0.0, 0.0))


def cell_of(layers: MapLayers, xy) -> tuple[int, int]:
    """(row, col) of the cell holding the map-frame point ``xy``."""
    r = layers.resolution_m
    return math.floor((xy[1] - layers.origin_xy_m[1]) / r), math.floor((xy[0] - layers.origin_xy_m[0]) / r)


@pytest.mark.parametrize("connectivity", [4, 8])
def test_the_frontier_is_exactly_the_doors_free_edge(connectivity: int) -> None:
    layers = room()
    k = classify_knowledge(layers, PARAMS)
    assert k.prior_variance == pytest.approx(PRIOR)
    front = frontier_mask(k.free, k.unknown, connectivity)
    expected = np.zeros(layers.shape, bool)
    expected[DOOR_ROWS.start : DOOR_ROWS.stop, 51] = True  # the outer column of the door, not the inner one
    np.testing.assert_array_equal(front, expected)
    plan = plan_exploration(layers, PARAMS, ExplorationSettings(connectivity=connectivity, laser=NARROW))
    assert len(plan.clusters) == 1 and plan.clusters.sizes_cells[0] == len(DOOR_ROWS)
    np.testing.assert_allclose(plan.clusters.centroids_xy_m[0], [5.15, 3.1], atol=1e-9)


def test_unknown_follows_the_variance_fraction_and_nan() -> None:
    layers = room()
    layers.variance[5, 5] = np.nan
    layers.variance[0, 0] = 0.7 * PRIOR
    k = classify_knowledge(layers, PARAMS, unknown_variance_fraction=0.8)
    assert k.unknown[5, 5] and not k.unknown[0, 0] and k.unknown[0, 1]
    assert classify_knowledge(layers, PARAMS, unknown_variance_fraction=0.6).unknown[0, 0]


def test_settings_take_the_configured_thresholds_and_refuse_bad_ones() -> None:
    from mapping.config import MappingConfig

    s = ExplorationSettings.from_config(MappingConfig(free_threshold=0.3), 0.7, n_views=2)
    assert (s.free_threshold, s.occupied_threshold, s.unknown_variance_fraction, s.n_views) == (
        0.3,
        0.65,
        0.7,
        2,
    )
    with pytest.raises(ValueError):
        ExplorationSettings(unknown_variance_fraction=0.0)
    with pytest.raises(ValueError):
        ExplorationSettings(connectivity=6)


def test_a_scan_facing_a_wall_at_10_cm_removes_nothing_and_one_facing_the_door_removes_most() -> None:
    """Facing the left wall from 0.1 m every ray stops in the wall within 0.12 m; if the wall did not stop the
    rays they would reach the unknown cells beyond it."""
    exact = room(known_var=0.0)
    occupied = classify_knowledge(exact, PARAMS).occupied
    wall_pose = np.array([[1.1, 3.05, math.pi]])  # the wall's inner face is at x = 1.0
    assert expected_variance_reduction(wall_pose, exact, PARAMS, occupied, NARROW)[0] == 0.0
    layers = room()
    occupied = classify_knowledge(layers, PARAMS).occupied
    headings = np.linspace(0.0, 2 * math.pi, 8, endpoint=False)
    centre = np.array([[3.0, 3.05, th] for th in headings])
    gains = expected_variance_reduction(centre, layers, PARAMS, occupied, NARROW)
    assert int(np.argmax(gains)) == 0  # heading 0: through the door
    wall = expected_variance_reduction(wall_pose, layers, PARAMS, occupied, NARROW)[0]
    one_unknown_cell = PRIOR**2 / (PRIOR + PARAMS.noise_var)
    assert 0.0 < wall < 1e-3 * gains[0]
    assert gains[0] > 50 * one_unknown_cell


def test_the_gain_is_the_sum_of_the_single_observation_updates_over_the_cells_seen() -> None:
    layers = room()
    occupied = classify_knowledge(layers, PARAMS).occupied
    pose = np.array([4.0, 3.05, 0.3])
    seen = visible_cells(pose, layers, occupied, NARROW)
    v = layers.variance.astype(np.float64)
    v_after = v * PARAMS.noise_var / (v + PARAMS.noise_var)  # eqs. (2)-(3), one point at the query
    np.testing.assert_allclose(variance_reduction_per_cell(v, PARAMS.noise_var), v - v_after)
    gain = expected_variance_reduction(pose[None], layers, PARAMS, occupied, NARROW)[0]
    assert gain == pytest.approx((v - v_after)[seen].sum(), rel=1e-9)
    assert seen[cell_of(layers, pose)] and not seen[30, 5]  # behind the left wall


def test_next_best_views_stand_in_free_space_and_look_through_the_door() -> None:
    layers = room()
    settings = ExplorationSettings(laser=NARROW, n_views=3)
    plan = plan_exploration(layers, PARAMS, settings)
    views = next_best_views(layers, PARAMS, settings)
    np.testing.assert_array_equal(views, plan.views_xytheta)
    assert views.shape == (3, 3)
    for x, y, _ in views:
        assert plan.knowledge.free[cell_of(layers, (x, y))]
    x, y, th = views[0]
    assert x == pytest.approx(5.15 - settings.step_m, abs=0.15) and y == pytest.approx(3.1, abs=0.15)
    assert abs(math.atan2(math.sin(th), math.cos(th))) < 1e-9  # facing +x, the door
    # greedy on a shrinking variance: each view adds no more than the one before
    assert np.all(np.diff(plan.view_gains) <= 1e-9) and plan.view_gains[-1] > 0
    assert plan.information.dtype == np.float32  # as exported
    assert plan.information.sum(dtype=np.float64) == pytest.approx(plan.view_gains.sum(), rel=1e-6)
    out = frontier_layers(layers, PARAMS, settings)
    assert set(out) == {"frontier", "information"}
    assert out["frontier"].dtype == np.float32 and out["frontier"].sum() == len(DOOR_ROWS)


def _plain_greedy(layers: MapLayers, settings: ExplorationSettings) -> tuple[list[int], list[float]]:
    """The greedy choice recomputing every candidate's gain each round, each scan cast one after the other
    (what the lazy choice, cast in parallel, must equal)."""
    from mapping.frontier import _cast_scans, _RayCaster, candidate_poses, cluster_frontier, frontier_anchors

    s = settings
    k = classify_knowledge(
        layers, PARAMS, s.free_threshold, s.occupied_threshold, s.unknown_variance_fraction
    )
    frontier = frontier_mask(k.free, k.unknown, s.connectivity, s.outside_unknown)
    anchors = frontier_anchors(
        cluster_frontier(frontier, layers, s.min_cluster_cells), layers, s.anchor_spacing_m
    )
    candidates = candidate_poses(anchors, k, layers, s)
    current = np.where(np.isfinite(layers.variance), np.maximum(layers.variance, 0), k.prior_variance).astype(
        float
    )
    chosen: list[int] = []
    gains_out: list[float] = []
    c = _RayCaster(layers, k.occupied, s.laser, threads=1)
    for _ in range(min(s.n_views, len(candidates))):
        seen_by = np.zeros(layers.shape, np.int64)
        gains = _cast_scans(
            candidates, c.offsets, c.range_max, c.grid, c.blocking, current, PARAMS.noise_var, seen_by, 0
        )
        gains[chosen] = -np.inf
        best = int(np.argmax(gains))
        if not gains[best] > 0:
            break
        chosen.append(best)
        gains_out.append(float(gains[best]))
        seen = visible_cells(candidates[best], layers, k.occupied, s.laser)
        current[seen] = current[seen] * PARAMS.noise_var / (current[seen] + PARAMS.noise_var)
    return chosen, gains_out


@pytest.mark.parametrize("n_views", [1, 4, 12])
def test_lazy_greedy_views_equal_the_plain_greedy_choice(n_views: int) -> None:
    """Two rooms' worth of doors: the lazy choice (bounds from earlier rounds) picks the same views with
    the same gains as recomputing every candidate every round."""
    layers = room()
    layers.probability[40:46, 8:10] = 0.1  # a second door, in the left wall
    settings = ExplorationSettings(laser=NARROW, n_views=n_views)
    plan = plan_exploration(layers, PARAMS, settings)
    chosen, gains = _plain_greedy(layers, settings)
    assert len(chosen) == min(n_views, len(plan.candidates_xytheta)) and len(chosen) > 0
    np.testing.assert_array_equal(plan.views_xytheta, plan.candidates_xytheta[chosen])
    np.testing.assert_allclose(plan.view_gains, gains, rtol=0, atol=0)


def test_a_map_without_unknown_space_has_no_frontier_and_no_views() -> None:
    layers = room()
    layers.variance[:] = 0.005
    settings = ExplorationSettings(outside_unknown=False)
    plan = plan_exploration(layers, PARAMS, settings)
    assert not plan.frontier.any() and plan.views_xytheta.shape == (0, 3)
    assert not plan.information.any()


def test_on_a_gp_map_of_the_loop_world_the_layers_fit_and_the_best_view_gains() -> None:
    """The start of the simulated loop (20 scans of the gallery, true poses), GPFOL at 0.2 m."""
    from datasets.simulation import make_world
    from mapping.build import MapBuilder
    from mapping.config import MappingConfig

    rec = make_world("loop", 0).recording
    poses = np.asarray(rec.reference.poses_xytheta)
    idx = np.arange(0, 40, 2)
    builder = MapBuilder.from_config(MappingConfig(), "gpfol")
    beams = builder.beams(rec.scans, poses, rec.laser_in_base_xytheta, idx)
    x, y = poses[idx, 0], poses[idx, 1]
    layers = builder.gp_map(beams, PARAMS).render((x.min() - 12, y.min() - 8, x.max() + 12, y.max() + 8), 0.2)
    plan = plan_exploration(layers, PARAMS)
    for name, layer in plan.layers().items():
        assert layer.shape == layers.shape, name
    assert plan.frontier.any() and plan.views_xytheta.shape[0] >= 1
    assert plan.view_gains[0] > 0 and plan.candidate_gains.max() == pytest.approx(plan.view_gains[0])
    for vx, vy, _ in plan.views_xytheta:
        assert plan.knowledge.free[cell_of(layers, (vx, vy))]


@pytest.mark.parametrize("res_m", [0.05, 0.1, 0.3, 0.25])
@pytest.mark.parametrize("clearance_m", [0.0, 0.1, 0.3, 0.35, 1.0, 2.5])
def test_clearance_by_squared_cells_equals_the_metre_comparison(res_m: float, clearance_m: float) -> None:
    """The candidates' clearance test on integer squared cell distances keeps exactly the cells that
    ``sqrt(d2) * res >= clearance`` keeps."""
    from mapping.frontier import _min_squared_cells

    d2 = np.arange(0, 2000, dtype=np.float64)
    expected = np.sqrt(d2) * res_m >= clearance_m
    np.testing.assert_array_equal(d2 >= _min_squared_cells(res_m, clearance_m), expected)


def test_effective_variance_reads_missing_estimates_as_the_prior() -> None:
    from mapping.frontier import _effective_variance

    layers = room()
    layers.variance[0, :4] = [np.nan, np.inf, -1e-9, 0.25]
    v = _effective_variance(layers, PRIOR)
    assert v.dtype == np.float64
    np.testing.assert_array_equal(v[0, :4], [PRIOR, PRIOR, 0.0, np.float64(np.float32(0.25))])
    np.testing.assert_array_equal(v[1:], layers.variance[1:].astype(np.float64))
