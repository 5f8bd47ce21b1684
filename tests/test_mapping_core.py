"""Neighbour search and the compiled local-GP prediction against brute-force numpy references."""

from __future__ import annotations

import numpy as np
import pytest

from mapping.beams import beams_from_scans
from mapping.core import NEGLIGIBLE_KERNEL
from mapping.gpmap import GPOccupancyMap, classify, grid_centres, tile_order, tile_order_where
from mapping.kernels import make_kernel
from mapping.neighbours import BeamIndex
from mapping.pls import pls_probability
from mapping.train import GPParams


def random_beams(seed: int = 0, n_scans: int = 12, n_beams: int = 30, no_return_every: int = 7):
    """Scans from random poses in a 10 m box, random ranges; every ``no_return_every``-th beam: no return."""
    rng = np.random.default_rng(seed)
    poses = np.c_[rng.uniform(0, 10, (n_scans, 2)), rng.uniform(-np.pi, np.pi, n_scans)]
    angles = [np.linspace(-np.pi / 2, np.pi / 2, n_beams) for _ in range(n_scans)]
    ranges = []
    for _ in range(n_scans):
        r = rng.uniform(0.3, 6.0, n_beams)
        r[::no_return_every] = np.inf
        ranges.append(r)
    return beams_from_scans(ranges, angles, 0.1, 8.0, poses, no_return_free_length_m=3.0, free_margin_m=0.1)


def brute_neighbours(beams, q, k_occ, k_free):
    hits = beams.hit_xy_m
    d_occ = np.hypot(*(hits - q).T)
    occ = np.argsort(d_occ, kind="stable")[:k_occ]
    P = beams.origins_xy_m
    D = beams.free_ends_xy_m - P
    l2 = np.einsum("ij,ij->i", D, D)
    t = np.clip(np.einsum("ij,ij->i", q - P, D) / np.where(l2 > 0, l2, 1.0), 0, 1)
    C = P + t[:, None] * D
    d_free = np.hypot(*(C - q).T)
    free = np.argsort(d_free, kind="stable")[:k_free]
    return hits[occ], d_occ[occ], C[free], d_free[free]


def reference_predict(beams, params, queries, k_occ, k_free):
    out = []
    for q in queries:
        xo, _, xf, _ = brute_neighbours(beams, q, k_occ, k_free)
        X = np.vstack([xo, xf]) - q
        y = np.r_[np.ones(len(xo)), -np.ones(len(xf))]
        k = params.kernel
        K = k(X) + params.noise_var * np.eye(len(y))
        ks = k(X, np.zeros((1, 2)))[:, 0]
        kss = k.diag(np.zeros((1, 2)))[0]
        mean = ks @ np.linalg.solve(K, y)
        var = kss - ks @ np.linalg.solve(K, ks)
        out.append((mean, var, np.abs(ks).max() / kss))
    mean, var, ks_ratio = np.array(out).T
    prob = pls_probability(mean, var + params.noise_var, params.alpha, params.beta, params.mean_cap)
    return mean, var, prob, ks_ratio


@pytest.mark.parametrize("cell_m", [0.2, 1.0, 5.0])
def test_knn_is_exact(cell_m: float) -> None:
    beams = random_beams(1)
    index = BeamIndex.build(beams, cell_m, cell_m)
    rng = np.random.default_rng(3)
    queries = np.vstack([rng.uniform(-3, 13, (60, 2)), [[50.0, -40.0], [-20.0, 5.0]]])  # some far outside
    occ, free, t = index.gather(queries, 15, 15)
    for q, o, f, tf in zip(queries, occ, free, t, strict=True):
        _, d_occ, _, d_free = brute_neighbours(beams, q, 15, 15)
        got_occ = np.hypot(index.hit_x[o] - q[0], index.hit_y[o] - q[1])
        np.testing.assert_allclose(got_occ, d_occ, rtol=0, atol=1e-12)
        cx = index.seg_x[f] + tf * index.seg_dx[f]
        cy = index.seg_y[f] + tf * index.seg_dy[f]
        np.testing.assert_allclose(np.hypot(cx - q[0], cy - q[1]), d_free, rtol=0, atol=1e-12)
        assert len(set(f.tolist())) == 15  # a segment listed in several cells is counted once


def test_knn_is_exact_in_dense_cells_with_warm_starts() -> None:
    """Cells of thousands of beams (a robot's fans along a corridor) searched in render order, each search
    warm-started from its neighbour's result, and at the scans' origins: the dense-cell screening bound keeps
    every search exact and finite."""
    rng = np.random.default_rng(7)
    n_scans, n_beams = 60, 181
    poses = np.c_[np.linspace(0, 6, n_scans), rng.normal(0, 0.05, n_scans), rng.normal(0, 0.1, n_scans)]
    angles = [np.linspace(-np.pi / 2, np.pi / 2, n_beams)] * n_scans
    ranges = [rng.uniform(1.0, 4.0, n_beams) for _ in range(n_scans)]
    beams = beams_from_scans(ranges, angles, 0.1, 8.0, poses, no_return_free_length_m=3.0, free_margin_m=0.1)
    index = BeamIndex.build(beams, 0.5, 0.5)
    assert np.diff(index.segment_index.cell_start).max() > 1000
    pts, _, (h, w) = grid_centres((-0.5, -1.0, 6.5, 1.0), 0.05)
    queries = pts[tile_order(int(h), int(w))][::3]
    # the scans' origins, each the start of 181 segments at distance 0 (ties of the whole fan), in order
    queries = np.vstack([queries, poses[:, :2]])
    _, free, t = index.gather(queries, 15, 15)
    for q, f, tf in zip(queries, free, t, strict=True):
        _, _, _, d_free = brute_neighbours(beams, q, 15, 15)
        cx = index.seg_x[f] + tf * index.seg_dx[f]
        cy = index.seg_y[f] + tf * index.seg_dy[f]
        np.testing.assert_allclose(np.hypot(cx - q[0], cy - q[1]), d_free, rtol=0, atol=1e-12)
        assert len(set(f.tolist())) == 15


def test_knn_with_fewer_items_than_k_pads() -> None:
    beams = random_beams(2, n_scans=1, n_beams=5, no_return_every=100)  # beam 0 has no return
    assert beams.is_hit.sum() == 4 and len(beams) == 5
    index = BeamIndex.build(beams)
    occ, free, _ = index.gather(np.array([[1.0, 1.0]]), 15, 15)
    assert (occ[0, :4] >= 0).all() and (occ[0, 4:] == -1).all()
    assert (free[0, :5] >= 0).all() and (free[0, 5:] == -1).all()


@pytest.mark.parametrize(
    ("kernel_name", "mean_cap"),
    [("nn", None), ("se", None), ("matern32", None), ("matern52", None), ("se", 1.0)],
)
def test_compiled_prediction_matches_numpy_reference(kernel_name: str, mean_cap: float | None) -> None:
    beams = random_beams(4)
    values = {"nn": {"sigma_0": 3.0, "sigma": 5.0}, "se": {"length_scale": 0.7}}.get(kernel_name, {})
    params = GPParams(
        make_kernel(kernel_name, values), noise_var=0.05, alpha=2.5, beta=-0.2, mean_cap=mean_cap
    )
    gp = GPOccupancyMap(beams, params, k_occ=15, k_free=15, index_cell_m=0.5)
    queries = np.random.default_rng(5).uniform(-2, 12, (80, 2))
    pred = gp.query(queries)
    mean, var, prob, ks_ratio = reference_predict(beams, params, queries, 15, 15)
    prior = params.kernel.diag(np.zeros((1, 2)))[0]
    # a query whose neighbours all have k* below NEGLIGIBLE_KERNEL of k(0) reads the prior, unsolved (beyond
    # every input's reach, or within the reach raster's margin); the solve differs from it by little
    far = ks_ratio < NEGLIGIBLE_KERNEL if params.kernel.stationary else np.zeros(len(queries), bool)
    assert far.sum() < len(queries) // 2
    np.testing.assert_array_equal(pred.mean[far], 0.0)
    np.testing.assert_array_equal(pred.variance[far], prior)
    assert np.abs(mean[far]).max(initial=0) < 1e-3 and np.abs(var[far] - prior).max(initial=0) < 1e-6
    near = ~far
    np.testing.assert_allclose(pred.mean[near], mean[near], rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(pred.variance[near], var[near], rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(pred.probability[near], prob[near], rtol=1e-7, atol=1e-9)
    assert np.all((pred.variance >= 0) & (pred.variance <= prior))
    if mean_cap is not None:  # the cap acts: some means overshoot the labels, and the link reads them capped
        over = np.abs(pred.mean) > mean_cap
        assert over.any()
        uncapped = pls_probability(pred.mean, pred.variance + params.noise_var, params.alpha, params.beta)
        assert not np.allclose(pred.probability[over], uncapped[over], rtol=1e-3)


def test_render_equals_query_at_cell_centres_and_any_resolution() -> None:
    beams = random_beams(6)
    params = GPParams(make_kernel("nn", {"sigma_0": 3.0, "sigma": 5.0}), 0.05, 2.0, 0.0)
    gp = GPOccupancyMap(beams, params)
    layers = gp.render((0.0, 0.0, 4.0, 3.0), 0.5)
    assert layers.probability.shape == (6, 8)
    assert layers.origin_xy_m == (0.0, 0.0)
    # cell (row 1, column 2) is centred at x = 1.25, y = 0.75
    p = gp.query(np.array([[1.25, 0.75]])).probability[0]
    assert layers.probability[1, 2] == pytest.approx(p, rel=1e-6)
    fine = gp.render((0.0, 0.0, 4.0, 3.0), 0.1)
    assert fine.probability.shape == (30, 40)
    coarse = list(gp.render_anytime((0.0, 0.0, 4.0, 3.0), (0.1, 1.0)))
    assert [c.resolution_m for c in coarse] == [1.0, 0.1]


def test_tile_order_lists_every_cell_tile_by_tile() -> None:
    # a 4 x 5 grid (cell id = row * 5 + column) in 2 x 2 tiles, odd rows of a tile right to left
    expected = [0, 1, 6, 5, 2, 3, 8, 7, 4, 9, 10, 11, 16, 15, 12, 13, 18, 17, 14, 19]
    assert tile_order(4, 5, 2).tolist() == expected
    order = tile_order(37, 53)
    assert np.array_equal(np.sort(order), np.arange(37 * 53))


@pytest.mark.parametrize("shape", [(4, 5), (37, 53), (16, 16), (1, 40), (33, 1)])
@pytest.mark.parametrize("share", [0.0, 0.3, 1.0])
def test_tile_order_where_keeps_tile_orders_order_of_the_selected_cells(shape, share) -> None:
    rng = np.random.default_rng(shape[0] * 100 + shape[1])
    selected = rng.random(shape) < share
    for tile in (2, 16):
        order = tile_order(*shape, tile)
        assert np.array_equal(tile_order_where(selected, tile), order[selected.ravel()[order]])
    order = tile_order(*shape)  # the default tile of both
    assert np.array_equal(tile_order_where(selected), order[selected.ravel()[order]])


def test_segment_entry_copies_hold_each_segment_relative_to_its_entrys_cell() -> None:
    """Every entry of the segment index carries its segment, the start relative to the centre of the entry's
    cell, computed in float64 and rounded to float32 once (the compiled walk equals the definition)."""
    from mapping.index import build_segment_index, segment_entry_copies

    seg = BeamIndex.build(random_beams(3)).seg
    index = build_segment_index(seg[:, :2], seg[:, :2] + seg[:, 2:4], 0.7)
    copies = segment_entry_copies(index, seg)
    nx, ny = index.shape
    cell_of = np.repeat(np.arange(nx * ny), np.diff(index.cell_start))
    centre = index.origin_xy_m + (np.c_[cell_of // ny, cell_of % ny] + 0.5) * index.cell_m
    rows = seg[index.items]
    assert (
        copies.dtype == np.float32
        and copies.shape == (5, index.items.size)
        and index.items.size > seg.shape[0]
    )
    assert np.array_equal(copies[:2], (rows[:, :2] - centre).T.astype(np.float32))
    assert np.array_equal(copies[2:], rows[:, 2:].T.astype(np.float32))


def test_index_entries_by_cell_keep_a_stable_sorts_order() -> None:
    """The counting sort of the indexes gives numpy's stable argsort and each cell's start."""
    from mapping.index import _by_cell

    rng = np.random.default_rng(3)
    for n_cells, n in ((1, 5), (50, 0), (50, 3000), (10_000, 200_000)):
        cells = rng.integers(0, n_cells, n)
        start, order = _by_cell(cells, n_cells)
        np.testing.assert_array_equal(order, np.argsort(cells, kind="stable"))
        np.testing.assert_array_equal(np.diff(start), np.bincount(cells, minlength=n_cells))
        assert start[0] == 0 and start[-1] == n


def test_render_equals_query_of_all_cell_centres() -> None:
    """Rendering (queries in tile order) gives each cell what a query of its centre alone gives."""
    beams = random_beams(6)
    params = GPParams(make_kernel("nn", {"sigma_0": 3.0, "sigma": 5.0}), 0.05, 2.0, 0.0)
    gp = GPOccupancyMap(beams, params)
    bounds = (-1.0, -1.0, 11.0, 10.0)
    layers = gp.render(bounds, 0.25)
    pts, _, (h, w) = grid_centres(bounds, 0.25)
    pred = gp.query(pts, sort=False)
    for name in ("probability", "mean", "variance"):
        ref = getattr(pred, name).reshape(h, w).astype(np.float32)
        np.testing.assert_array_max_ulp(getattr(layers, name), ref, maxulp=2)


def test_duplicate_training_points_do_not_break_the_solve() -> None:
    """Queries behind the laser clamp every free point of a scan to its origin: K is singular but for noise
    and jitter; predictions stay finite."""
    ranges = [np.full(40, 2.0)]
    angles = [np.linspace(-0.3, 0.3, 40)]
    beams = beams_from_scans(ranges, angles, 0.1, 10.0, np.array([[0.0, 0.0, 0.0]]), free_margin_m=0.1)
    params = GPParams(make_kernel("se", {"length_scale": 0.5}), noise_var=1e-9, alpha=1.0, beta=0.0)
    pred = GPOccupancyMap(beams, params, jitter=1e-8).query(np.array([[-1.0, 0.0], [-5.0, 0.3]]))
    assert np.all(np.isfinite(pred.mean)) and np.all(np.isfinite(pred.probability))


def test_classify_thresholds() -> None:
    p = np.array([0.1, 0.35, 0.5, 0.65, 0.9])
    np.testing.assert_array_equal(classify(p, 0.65, 0.35), [0, 0, -1, 1, 1])
    with pytest.raises(ValueError):
        classify(p, 0.3, 0.6)


def test_failed_cholesky_falls_back_to_jitter() -> None:
    """Zero noise and coincident free points make K singular: the lane is redone alone with jitter."""
    ranges = [np.full(20, 2.0)] * 3
    angles = [np.linspace(-0.2, 0.2, 20)] * 3
    poses = np.zeros((3, 3))  # three identical scans: every training point has exact duplicates
    beams = beams_from_scans(ranges, angles, 0.1, 10.0, poses, free_margin_m=0.1)
    params = GPParams(make_kernel("se", {"length_scale": 0.5}), noise_var=0.0, alpha=1.0, beta=0.0)
    pred = GPOccupancyMap(beams, params, jitter=1e-6).query(np.array([[-1.0, 0.0], [1.0, 0.0], [2.5, 0.1]]))
    assert np.all(np.isfinite(pred.mean)) and np.all(np.isfinite(pred.variance))
    assert np.all((pred.variance >= 0) & (pred.variance <= 1.0))


def test_asin_fast_matches_numpy() -> None:
    import numba as nb

    from mapping.core import asin_fast

    @nb.njit
    def many(x):
        out = np.empty_like(x)
        for i in range(x.size):
            out[i] = asin_fast(x[i])
        return out

    x = np.r_[np.linspace(-1, 1, 200_001), -1.0, -0.5, 0.0, 0.5, 1.0, 1e-300, -1e-17]
    np.testing.assert_allclose(many(x), np.arcsin(x), rtol=0, atol=1e-15)


def test_the_searches_do_no_reference_counting() -> None:
    """The neighbour searches are built without numba's reference counting (mapping.core docstring):
    compiled afresh with their own options (numba shows no code of a function loaded from its cache), their
    code calls neither NRT_incref nor NRT_decref, while the same function compiled with the default options
    does."""
    import numba as nb

    from mapping import blocks, index

    bi = BeamIndex.build(random_beams())
    segments, points, k = bi.segments, bi.points, 5

    def buffers(most: int, dtype: type) -> tuple:
        return (np.empty(k), np.empty(k, np.int64), np.empty(k), np.empty(k, np.int64), 0,
                np.empty(max(most, 1), dtype))  # fmt: skip

    candidates = np.empty((3, max(segments.index.most, 1)))
    calls: tuple = (
        (
            index.knn_segments,
            (0.0, 0.0, segments, k, *buffers(segments.index.most, np.float32), candidates),
        ),
        (index.knn_points, (0.0, 0.0, points, k, *buffers(points.index.most, np.float64))),
    )
    # the block search's per-block and per-query steps (mapping.blocks), on a block centred at (5, 5)
    cen = np.arange(k, dtype=np.int64)
    cand, ids = np.ascontiguousarray(bi.seg[:40].T), np.arange(40, dtype=np.int64)
    raw = (np.empty(4096), np.empty(4096, np.int64))
    out = (np.empty(k), np.empty(k, np.int64), np.empty(k))
    calls += (
        (blocks._points_within, (5.0, 5.0, 3.0, points, *raw)),
        (blocks._segments_within, (5.0, 5.0, 3.0, segments, np.empty(segments.index.most, np.float32), *raw)),
        (
            blocks._query_points,
            (
                5.0,
                5.0,
                points.xy,
                k,
                cen,
                np.ascontiguousarray(points.xy[:40].T),
                ids,
                40,
                np.empty(40),
                *out,
            ),
        ),
        (blocks._query_segments, (5.0, 5.0, bi.seg, k, cen, cand, ids, 40, np.empty(40), np.empty(40), *out)),
    )
    for fn, args in calls:
        assert fn.targetoptions.get("_nrt") is False, fn.__name__
        expected = fn(*args)
        assert expected > 0, fn.__name__
        for options, counts in ((fn.targetoptions, False), ({"error_model": "numpy"}, True)):
            fresh = nb.njit(**options)(fn.py_func)
            assert fresh(*args) == expected
            ir = fresh.inspect_llvm(fresh.signatures[0])
            assert ("NRT_incref" in ir or "NRT_decref" in ir) is counts, (fn.__name__, options)
