"""Tiled and incremental maps: exact tile supports, tiled == untiled, incremental == full
recomputation (added scans, a loop closure), the on-disk tile store, and the Dask engine on the Intel map."""

from __future__ import annotations

import numpy as np
import pytest

from datasets.simulation import cast_rays
from datasets.simulation.geometry import World, box
from mapping.beams import beams_from_scans
from mapping.exports import MapExportError
from mapping.gpmap import GPOccupancyMap, grid_centres
from mapping.kernels import make_kernel
from mapping.neighbours import BeamIndex
from mapping.tiling import (
    ArraySink,
    IncrementalMap,
    SupportIndex,
    TileGrid,
    TileStore,
    concat_beams,
    merge_beams,
    render_batched,
    render_per_tile,
    render_serial,
)
from mapping.tiling.support import _segment_rect
from mapping.train import GPParams
from tests.layer_checks import assert_same_map

K_OCC, K_FREE = 15, 15
# NN-kernel parameters learnt on intel.gfs.log by the default training (fixed here: tests do not train)
PARAMS = GPParams(make_kernel("nn", {"sigma_f": 1.79, "sigma_0": 20.3, "sigma": 28.9}), 0.1, 66.5, -2.08)
LAYER_NAMES = ("probability", "mean", "variance")


def gp_factory(beams, cov):
    return GPOccupancyMap(beams, PARAMS, K_OCC, K_FREE)


def corridor_world() -> World:
    """A 60 m x 20 m hall with pillars and two rooms: local structure for a robot with an 8 m laser."""
    polys = [box(0, 0, 60, 20)]
    polys += [box(x, 4, x + 1, 5) for x in range(5, 56, 6)]
    polys += [box(x, 14, x + 2, 15) for x in range(8, 56, 9)]
    return World("corridor", tuple(polys), ("wall",) * len(polys), (0, 0, 60, 20))


def corridor_scans(n: int = 56, beams: int = 90, seed: int = 0):
    """Ranges, angles and poses of ``n`` scans along the hall (one per metre, a gentle wiggle)."""
    rng = np.random.default_rng(seed)
    x = np.linspace(2.0, 58.0, n)
    poses = np.c_[x, 10.0 + 2.5 * np.sin(x / 5.0), 0.3 * np.sin(x / 3.0)]
    angles = np.linspace(-np.pi, np.pi, beams, endpoint=False)
    edges = corridor_world().edges()
    ranges = []
    for p in poses:
        r = cast_rays(p[:2], p[2] + angles, edges)
        ranges.append(np.where(np.isfinite(r), r + rng.normal(0, 0.01, beams), np.inf))
    return ranges, [angles] * n, poses


def make(ranges, angles, poses, scan_indices=None):
    return beams_from_scans(
        ranges,
        angles,
        0.05,
        8.0,
        poses,
        no_return_free_length_m=2.0,
        free_margin_m=0.1,
        scan_indices=scan_indices,
    )


@pytest.fixture(scope="module")
def corridor():
    ranges, angles, poses = corridor_scans()
    beams = make(ranges, angles, poses)
    bounds = (0.0, 0.0, 60.0, 20.0)
    return ranges, angles, poses, beams, bounds


def assert_same_layers(a, b) -> None:
    assert_same_map(a, b)


# ---------------------------------------------------------------------------------------------------------
# geometry


def test_tile_grid_cells_are_the_untiled_grid() -> None:
    bounds = (-3.2, 1.1, 7.9, 5.0)
    pts, origin, (h, w) = grid_centres(bounds, 0.1)
    for tile_cells in (8, 13, 64):
        grid = TileGrid.from_bounds(bounds, 0.1, tile_cells)
        assert grid.shape_hw == (h, w) and grid.origin_xy_m == tuple(origin)
        full = pts.reshape(h, w, 2)
        covered = np.zeros((h, w), int)
        rects = grid.rects()
        for t in range(len(grid)):
            r0, r1, c0, c1 = grid.slices(t)
            c = grid.cell_centres(t)
            np.testing.assert_array_equal(c, full[r0:r1, c0:c1].reshape(-1, 2))  # bit for bit
            assert np.all(c.min(axis=0) >= rects[t, :2]) and np.all(c.max(axis=0) <= rects[t, 2:])
            covered[r0:r1, c0:c1] += 1
        assert np.all(covered == 1)
        assert TileGrid.from_dict(grid.to_dict()) == grid


def test_segment_to_rectangle_distance_against_dense_sampling() -> None:
    rng = np.random.default_rng(1)
    rect = (0.0, 0.0, 2.0, 1.0)
    u = np.linspace(0, 1, 201)
    # outside the rectangle, the nearest point of it lies on its boundary
    rect_pts = np.r_[np.c_[2 * u, 0 * u], np.c_[2 * u, 0 * u + 1], np.c_[0 * u, u], np.c_[0 * u + 2, u]]
    for _ in range(200):
        seg = rng.uniform(-3, 5, (1, 4))
        got = _segment_rect(seg, 0, *rect)
        t = np.linspace(0, 1, 400)[:, None]
        seg_pts = seg[0, :2] + t * (seg[0, 2:] - seg[0, :2])
        inside = (
            (seg_pts[:, 0] >= 0) & (seg_pts[:, 0] <= 2) & (seg_pts[:, 1] >= 0) & (seg_pts[:, 1] <= 1)
        ).any()
        brute = 0.0 if inside else np.min(np.hypot(*(seg_pts[:, None, :] - rect_pts[None]).T))
        assert got <= brute + 1e-9  # never larger than the true distance (sampling over-estimates it)
        assert got >= brute - 0.02  # and close to it (sampling step ~0.01 m)


def test_kth_distance_against_brute_force(corridor) -> None:
    *_, beams, _ = corridor
    idx = SupportIndex.build(beams, 3.0)
    rng = np.random.default_rng(2)
    hits = beams.hit_xy_m
    P, E = beams.origins_xy_m, beams.free_ends_xy_m
    D = E - P
    l2 = np.einsum("ij,ij->i", D, D)
    for q in np.c_[rng.uniform(-5, 65, 40), rng.uniform(-5, 25, 40)]:
        d_occ = np.sort(np.hypot(*(hits - q).T))
        t = np.clip(np.einsum("ij,ij->i", q - P, D) / np.where(l2 > 0, l2, 1), 0, 1)
        d_free = np.sort(np.hypot(*(P + t[:, None] * D - q).T))
        for k in (1, 15, 40):
            assert idx.kth_distance(q, k, "occ") == pytest.approx(d_occ[k - 1], abs=1e-12)
            assert idx.kth_distance(q, k, "free") == pytest.approx(d_free[k - 1], abs=1e-12)
    assert idx.kth_distance((0.0, 0.0), len(hits) + 1, "occ") == np.inf


def test_tile_support_gives_every_query_its_neighbours(corridor) -> None:
    """The exactness argument itself: the map of a tile's support finds, for every query of the tile, the
    same neighbour distances as the map of all beams."""
    *_, beams, bounds = corridor
    grid = TileGrid.from_bounds(bounds, 0.2, 16)
    idx = SupportIndex.build(beams, 1.6)
    full = BeamIndex.build(beams)
    rects = grid.rects()
    sizes = []
    for t in range(0, len(grid), 7):
        r_occ, r_free = idx.tile_radii(rects[t], K_OCC, K_FREE)
        ids = idx.support(rects[t], r_occ, r_free)
        assert np.all(np.diff(ids) > 0)  # original order
        sizes.append(ids.size)
        sub = BeamIndex.build(beams.subset(ids))
        q = grid.cell_centres(t)
        for index in (full, sub):
            occ, free, tt = index.gather(q, K_OCC, K_FREE)
            d_occ = np.hypot(*(index.hit_xy[occ] - q[:, None, :]).transpose(2, 0, 1))
            seg = index.seg[free]
            fp = seg[..., :2] + tt[..., None] * seg[..., 2:4]
            d_free = np.hypot(*(fp - q[:, None, :]).transpose(2, 0, 1))
            if index is full:
                ref = (d_occ, d_free)
            else:
                np.testing.assert_array_equal(d_occ, ref[0])
                np.testing.assert_array_equal(d_free, ref[1])
    assert np.mean(sizes) < 0.5 * len(beams)  # a support is local, not the whole map


# ---------------------------------------------------------------------------------------------------------
# tiled rendering


# SE-kernel parameters: a kernel that decays, so that the reach test and the negligible-k* skip take part
SE_PARAMS = GPParams(make_kernel("se", {"sigma_f": 0.9, "length_scale": 0.3}), 0.1, 5.0, 0.05)


def se_factory(beams, cov):
    return GPOccupancyMap(beams, SE_PARAMS, K_OCC, K_FREE)


@pytest.mark.parametrize("engine", [render_per_tile, render_batched, render_serial])
@pytest.mark.parametrize("tile_cells", [8, 33])
@pytest.mark.parametrize("kernel", ["nn", "se"])
def test_tiled_map_equals_untiled_render(corridor, tile_cells, engine, kernel) -> None:
    *_, beams, bounds = corridor
    params, factory = (PARAMS, gp_factory) if kernel == "nn" else (SE_PARAMS, se_factory)
    untiled = GPOccupancyMap(beams, params, K_OCC, K_FREE).render(bounds, 0.25)
    grid = TileGrid.from_bounds(bounds, 0.25, tile_cells)
    m = IncrementalMap(beams, grid, factory, K_OCC, K_FREE, renderer=engine)
    report = m.render_all()
    assert report.tiles_recomputed == len(grid) and report.fraction_recomputed == 1.0
    tiled = m.layers()
    assert tiled.origin_xy_m == untiled.origin_xy_m and tiled.shape == untiled.shape
    assert_same_layers(tiled, untiled)
    per_tile = engine is render_per_tile or len(grid) == 1
    assert np.all(m.support_beams < len(beams)) and np.all(m.support_beams > 0) == per_tile
    if kernel == "se":  # the SE map has places beyond every input's reach: the test covers them
        assert (untiled.mean == 0).mean() > 0.01


def test_batched_engine_leaves_the_radii_to_the_first_update(corridor) -> None:
    *_, beams, bounds = corridor
    grid = TileGrid.from_bounds(bounds, 0.25, 16)
    one = IncrementalMap(beams, grid, gp_factory, K_OCC, K_FREE, renderer=render_per_tile)
    one.render_all()
    batched = IncrementalMap(beams, grid, gp_factory, K_OCC, K_FREE, renderer=render_batched)
    batched.render_all()
    assert np.isnan(batched.rho_occ).all() and not batched.support_beams.any()  # no tile had its own support
    batched.ensure_radii()
    np.testing.assert_array_equal(batched.rho_occ, one.rho_occ)
    np.testing.assert_array_equal(batched.rho_free, one.rho_free)
    # an update on the batched map re-renders the same tiles as on the per-tile one, and gives the same map
    ranges, angles, poses, *_ = corridor
    moved = make(ranges, angles, loop_closure(poses, 20, 30, 0.03))
    a, b = one.update_poses(moved), batched.update_poses(moved)
    assert a.tiles_recomputed == b.tiles_recomputed > 0
    assert_same_layers(batched.layers(), one.layers())


def test_incremental_added_scans_equal_full_recomputation(corridor) -> None:
    ranges, angles, poses, beams, bounds = corridor
    grid = TileGrid.from_bounds(bounds, 0.25, 16)
    full = IncrementalMap(beams, grid, gp_factory, K_OCC, K_FREE)
    full.render_all()
    first, rest = np.arange(40), np.arange(40, len(poses))
    inc = IncrementalMap(beams.select_scans(first), grid, gp_factory, K_OCC, K_FREE)
    inc.render_all()
    before = inc.layers()
    new = make([ranges[i] for i in rest], [angles[i] for i in rest], poses[rest], scan_indices=rest)
    report = inc.add_scans(new)
    assert_same_layers(inc.layers(), full.layers())
    # the new scans (x > 41 m, 8 m laser) reach only the east of the hall
    assert 0 < report.fraction_recomputed < 0.6
    assert report.changed_beams == len(new)
    untouched = np.setdiff1d(np.arange(len(grid)), np.flatnonzero(inc.support_beams != full.support_beams))
    assert untouched.size > 0
    east = grid.rects()[:, 0] > 45.0
    after = inc.layers()
    changed = np.array(
        [not np.array_equal(_tile(before, grid, t), _tile(after, grid, t)) for t in range(len(grid))]
    )
    assert changed[east].all() and not changed[grid.rects()[:, 2] < 25.0].any()


def _tile(layers, grid, t):
    r0, r1, c0, c1 = grid.slices(t)
    return layers.probability[r0:r1, c0:c1]


def loop_closure(poses: np.ndarray, first: int, last: int, angle_rad: float) -> np.ndarray:
    """The poses with scans ``first..last`` turned by ``angle_rad`` about scan ``first`` (a correction that a
    loop closure spreads over part of a trajectory)."""
    out = poses.copy()
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    p0 = poses[first, :2]
    d = poses[first : last + 1, :2] - p0
    out[first : last + 1, :2] = p0 + d @ np.array([[c, -s], [s, c]]).T
    out[first : last + 1, 2] += angle_rad
    return out


def test_incremental_loop_closure_equals_full_recomputation(corridor) -> None:
    ranges, angles, poses, beams, bounds = corridor
    grid = TileGrid.from_bounds(bounds, 0.25, 16)
    m = IncrementalMap(beams, grid, gp_factory, K_OCC, K_FREE)
    m.render_all()
    assert m.update_poses(beams).tiles_recomputed == 0  # nothing moved
    moved = make(ranges, angles, loop_closure(poses, 20, 30, 0.03))
    report = m.update_poses(moved)
    ref = IncrementalMap(moved, grid, gp_factory, K_OCC, K_FREE)
    ref.render_all()
    assert_same_layers(m.layers(), ref.layers())
    assert report.changed_beams == 11 * 90  # scans 20..30 moved (scan 20 turned about itself)
    assert 0 < report.fraction_recomputed < 0.7
    m.ensure_radii()
    ref.ensure_radii()
    np.testing.assert_array_equal(m.rho_occ, ref.rho_occ)

    # below the tolerance nothing is re-rendered and the map keeps the beams it shows
    tiny = make(ranges, angles, loop_closure(moved_poses := loop_closure(poses, 20, 30, 0.03), 40, 45, 1e-5))
    report = m.update_poses(tiny, tolerance_m=1e-3)
    assert report.tiles_recomputed == 0 and report.changed_beams == 0
    np.testing.assert_array_equal(m.beams.ends_xy_m, moved.ends_xy_m)
    # ... and above it the moved beams are taken, the others kept: still an exact rendering of m.beams
    bigger = make(ranges, angles, loop_closure(loop_closure(moved_poses, 40, 45, 1e-5), 10, 12, 0.05))
    report = m.update_poses(bigger, tolerance_m=1e-3)
    assert 0 < report.tiles_recomputed < len(grid)
    ref = IncrementalMap(m.beams, grid, gp_factory, K_OCC, K_FREE)
    ref.render_all()
    assert_same_layers(m.layers(), ref.layers())


def test_covariance_changes_rerender_the_tiles_of_their_scans(corridor) -> None:
    *_, poses, beams, bounds = corridor
    grid = TileGrid.from_bounds(bounds, 0.5, 16)
    cov = np.tile(np.diag([0.01, 0.01, 0.001]), (len(poses), 1, 1))
    seen = []

    def factory(b, c):
        seen.append(c)
        return gp_factory(b, c)

    m = IncrementalMap(beams, grid, factory, K_OCC, K_FREE, cov_xytheta=cov)
    m.render_all()
    assert seen[0] is m.cov_xytheta
    new_cov = cov.copy()
    new_cov[50] *= 2.0  # one scan near the east end
    assert m.update_poses(beams, new_cov, cov_tolerance=0.5).tiles_recomputed == 0
    report = m.update_poses(beams, new_cov)
    assert report.changed_beams == int((beams.scan_index == 50).sum())
    assert 0 < report.tiles_recomputed < len(grid) // 2
    np.testing.assert_array_equal(m.cov_xytheta, new_cov)
    # a map without covariances (GPFOL) ignores them
    g = IncrementalMap(beams, grid, gp_factory, K_OCC, K_FREE)
    g.render_all()
    assert g.update_poses(beams, new_cov).tiles_recomputed == 0


def test_update_needs_the_same_beams_and_a_rendering(corridor) -> None:
    *_, beams, bounds = corridor
    grid = TileGrid.from_bounds(bounds, 0.5, 16)
    m = IncrementalMap(beams, grid, gp_factory, K_OCC, K_FREE)
    with pytest.raises(RuntimeError, match="render_all"):
        m.update_poses(beams)
    m.render_all()
    with pytest.raises(ValueError, match="not the old beams"):
        m.update_poses(beams.select_scans(np.arange(10)))


def test_beams_concat_and_merge(corridor) -> None:
    *_, beams, _ = corridor
    a, b = beams.select_scans(np.arange(10)), beams.select_scans(np.arange(10, 20))
    ab = concat_beams(a, b)
    np.testing.assert_array_equal(ab.ends_xy_m, beams.select_scans(np.arange(20)).ends_xy_m)
    np.testing.assert_array_equal(ab.scan_index, np.r_[a.scan_index, b.scan_index])
    shifted = merge_beams(a, a, np.ones(len(a), bool))
    np.testing.assert_array_equal(shifted.origins_xy_m, a.origins_xy_m)


# ---------------------------------------------------------------------------------------------------------
# the on-disk store


def test_tile_store_streams_tiles_and_reads_back_lazily(corridor, tmp_path) -> None:
    *_, beams, bounds = corridor
    grid = TileGrid.from_bounds(bounds, 0.25, 20)
    mem = IncrementalMap(beams, grid, gp_factory, K_OCC, K_FREE)
    mem.render_all()
    with TileStore.create(tmp_path / "map", grid) as store:
        m = IncrementalMap(beams, grid, gp_factory, K_OCC, K_FREE, sink=store)
        m.render_all()
        with pytest.raises(TypeError, match="in-memory"):
            m.layers()
    back = TileStore.open(tmp_path / "map")
    assert back.grid == grid and back.done().all()
    ref = mem.layers()
    for name in LAYER_NAMES:
        lazy = back.layer(name)
        assert isinstance(lazy, np.memmap) and lazy.shape == grid.shape_hw
        np.testing.assert_array_equal(np.asarray(lazy), getattr(ref, name))
        np.testing.assert_array_equal(np.load(tmp_path / "map" / f"{name}.npy"), getattr(ref, name))
        window = back.as_dask(name)[10:50, 30:90].compute()
        np.testing.assert_array_equal(window, getattr(ref, name)[10:50, 30:90])
    w = back.window(slice(10, 50), slice(30, 90))
    assert w.origin_xy_m == pytest.approx((bounds[0] + 30 * 0.25, bounds[1] + 10 * 0.25))
    np.testing.assert_array_equal(w.variance, ref.variance[10:50, 30:90])


def test_tile_store_errors(tmp_path) -> None:
    grid = TileGrid.from_bounds((0, 0, 10, 10), 0.5, 8)
    TileStore.create(tmp_path / "s", grid).close()
    assert not TileStore.open(tmp_path / "s").done().any()  # nothing written yet
    with pytest.raises(MapExportError, match="already exists"):
        TileStore.create(tmp_path / "s", grid)
    with pytest.raises(MapExportError, match="not a readable tile store"):
        TileStore.open(tmp_path)
    with open(tmp_path / "s" / "mean.npy", "r+b") as f:
        f.truncate(100)
    with pytest.raises(MapExportError, match=r"mean\.npy has the wrong size"):
        TileStore.open(tmp_path / "s")


def test_array_sink_adopts_a_rendering(corridor) -> None:
    *_, beams, bounds = corridor
    grid = TileGrid.from_bounds(bounds, 0.5, 16)
    m = IncrementalMap(beams, grid, gp_factory, K_OCC, K_FREE)
    m.render_all()
    adopted = IncrementalMap(beams, grid, gp_factory, K_OCC, K_FREE, sink=ArraySink(grid, m.layers()))
    adopted.adopt_rendered()
    assert np.isnan(adopted.rho_occ).all()  # computed lazily, by the first update or on demand
    adopted.ensure_radii()
    m.ensure_radii()  # rendered through one map of all beams: no radii until asked
    np.testing.assert_array_equal(adopted.rho_occ, m.rho_occ)
    np.testing.assert_array_equal(adopted.rho_free, m.rho_free)
    with pytest.raises(ValueError, match="do not fit"):
        ArraySink(TileGrid.from_bounds(bounds, 0.25, 16), m.layers())


# ---------------------------------------------------------------------------------------------------------
# the benchmark's machinery, on a small city


def test_large_map_benchmark_machinery_on_a_small_city() -> None:
    from datasets.simulation.city import city_edges, city_path, city_ranges
    from pipeline.bench.scale import bench_large_map

    edges, poses = city_edges(100.0), city_path(100.0)
    assert len(edges) >= 4 * 4 and np.all((poses[:, :2] >= 0) & (poses[:, :2] <= 100))
    ranges, angles = city_ranges(poses[:5], edges)
    assert ranges.shape == (5, angles.size) and np.all(ranges > 1.0)  # the path runs along the streets
    result = bench_large_map(100.0, 0.5, 32)  # in a fresh process, as in ``bench``
    assert result["cells"] == 200 * 200 and result["tiles"] == 49 and result["all_tiles_written"]
    assert 0 < result["peak_rss_mib"] < 2048 and result["tiles_per_s"] > 0
    assert result["probability_sample_fractions"]["free (<0.35)"] > 0.05


def test_peak_memory_of_a_child_process_is_its_own() -> None:
    """``large_map_peak_rss_mib`` is measured in a child process: its peak must not start at the parent's
    resident size (getrusage's max RSS does, after fork + exec)."""
    import subprocess
    import sys

    from pipeline.bench import peak_rss_mib
    from tests.conftest import REPO

    ballast = np.ones(400 * 2**20 // 8)  # 400 MiB resident in this process
    code = "from pipeline.bench import peak_rss_mib; print(peak_rss_mib())"
    child = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, check=True)
    assert peak_rss_mib() > 400 and float(ballast[-1]) == 1.0
    assert float(child.stdout) < 300  # an interpreter with numpy, not this process's 400 MiB


def test_the_quiet_cluster_logs_cover_loggers_with_levels_of_their_own() -> None:
    """distributed's configuration sets ``tornado.application`` to ERROR; within the local cluster's quiet
    block it must be silent too (an interrupt's race in distributed's ``sync`` logged a traceback there),
    and get its level back afterwards."""
    import logging

    import distributed  # noqa: F401  (its configuration sets the loggers' levels)

    from pipeline.scale import _quiet_cluster_logs

    app = logging.getLogger("tornado.application")
    before = app.level
    assert before != logging.NOTSET
    with _quiet_cluster_logs():
        assert not app.isEnabledFor(logging.ERROR)
        assert not logging.getLogger("distributed.client").isEnabledFor(logging.ERROR)
    assert app.level == before
