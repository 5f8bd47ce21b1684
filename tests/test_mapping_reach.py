"""The kernel's reach (:mod:`mapping.reach`): a map answers the places no input reaches with the prior,
unsolved, and the map is the same as when every place is solved."""

from __future__ import annotations

import math

import numpy as np
import pytest

from datasets.registry import open_dataset
from mapping.config import MappingConfig
from mapping.gpmap import GPOccupancyMap
from mapping.gppol import GaussianInputs, SensorNoise, input_moments
from mapping.kernels import make_kernel
from mapping.noisy_kernels import GAUSS_HERMITE, GIRARD, InputExpectation
from mapping.reach import (
    REACH_MIN_PEAK,
    REACH_TOLERANCE,
    kernel_reach_m,
    largest_eigenvalue,
    quadratic_range,
    reach_mask,
    reach_tolerance,
    se_girard_peak,
    se_girard_reach_m,
    segment_pieces,
    spread_factor,
)
from mapping.train import GPParams
from pipeline import evaluate_map as em
from tests.conftest import data_file


def test_kernel_reach_of_the_se_kernel_is_its_closed_form_and_matern_falls_to_the_tolerance() -> None:
    se = make_kernel("se", {"sigma_f": 0.9, "length_scale": 0.3})
    assert kernel_reach_m(se) == pytest.approx(0.3 * math.sqrt(2 * math.log(1 / REACH_TOLERANCE)), rel=1e-9)
    for name in ("matern32", "matern52"):
        k = make_kernel(name, {"sigma_f": 0.9, "length_scale": 0.5})
        r0 = kernel_reach_m(k)
        k0 = k.of_difference(np.zeros((1, 2)))[0]
        assert k.of_difference(np.array([[r0, 0.0]]))[0] == pytest.approx(REACH_TOLERANCE * k0, rel=1e-6)
        assert k.of_difference(np.array([[0.9 * r0, 0.0]]))[0] > REACH_TOLERANCE * k0
    # the neural-network kernel (eq. 7) does not decay: no reach
    assert kernel_reach_m(make_kernel("nn", (0.9, 3.0, 4.0))) is None
    assert spread_factor(3.5) == 3.5


def test_se_girard_reach_bounds_the_expected_kernel() -> None:
    """Beyond the reach the closed-form expected SE kernel (eq. 19) between an exact query and a Gaussian
    input is below the tolerance for every covariance of that largest eigenvalue; just inside it is not,
    for a covariance flat across the offset. An input spread far wider than the length scale reaches
    nowhere."""
    from mapping.noisy_kernels import girard_se

    ell = 0.3
    se = make_kernel("se", {"sigma_f": 1.0, "length_scale": ell})
    assert se_girard_reach_m(ell, 0.0) == pytest.approx(kernel_reach_m(se), rel=1e-9)
    for lam in (0.0, 0.01, 0.3, 4.0):
        r = float(se_girard_reach_m(ell, lam))
        for ratio in (1.0, 0.3, 0.0):  # the other eigenvalue
            cov = np.diag([lam, ratio * lam])
            for angle in np.linspace(0, np.pi, 7):
                d = np.array([np.cos(angle), np.sin(angle)])
                beyond = girard_se(se, d * r * 1.0001, cov)
                assert beyond <= REACH_TOLERANCE * (1 + 1e-9)
        # tight: a covariance flat across the offset attains the bound
        assert girard_se(se, np.array([0.98 * r, 0.0]), np.diag([lam, 0.0])) > REACH_TOLERANCE
    assert se_girard_reach_m(ell, (ell / REACH_TOLERANCE) ** 2) == 0.0


def test_se_girard_peak_bounds_the_expected_kernel_everywhere() -> None:
    """The peak bound holds at every offset for covariances whose largest eigenvalue is at least the one
    given, and it is attained at the mean by an input spread along one axis only."""
    from mapping.noisy_kernels import girard_se

    ell = 0.3
    se = make_kernel("se", {"sigma_f": 1.0, "length_scale": ell})
    rng = np.random.default_rng(4)
    for lam in (0.0, 0.05, 2.0, 400.0):
        bound = float(se_girard_peak(ell, lam))
        for _ in range(20):
            rot = np.linalg.qr(rng.normal(size=(2, 2)))[0]
            cov = rot @ np.diag([lam, rng.uniform(0, 1) * lam]) @ rot.T
            d = rng.normal(0, 1 + math.sqrt(lam), 2) * rng.choice([0.0, 1.0])
            assert girard_se(se, d, cov) <= bound * (1 + 1e-12)
        assert girard_se(se, np.zeros(2), np.diag([lam, 0.0])) == pytest.approx(bound, rel=1e-12)
    assert float(se_girard_peak(ell, ell**2 * (REACH_MIN_PEAK**-2 - 1))) == pytest.approx(REACH_MIN_PEAK)


def test_segment_pieces_cover_each_segment_and_quadratic_range_brackets_it() -> None:
    """Pieces tile each segment end to end, none longer than asked; the range of a quadratic over a piece
    equals its extremes found by dense sampling (convex, concave and linear)."""
    lengths = np.array([0.0, 3.0, 8.0, 8.01, 61.9])
    which, a, b = segment_pieces(lengths, 8.0)
    assert np.array_equal(np.bincount(which, minlength=5), [1, 1, 1, 2, 8])
    for s in range(5):
        mine = which == s
        assert a[mine][0] == 0.0 and b[mine][-1] == pytest.approx(lengths[s])
        assert np.allclose(a[mine][1:], b[mine][:-1]) and np.all(b[mine] - a[mine] <= 8.0 + 1e-12)
    rng = np.random.default_rng(5)
    c0, c1, c2 = rng.normal(size=(3, 200))
    c2[:50] = 0.0
    lo_end = rng.uniform(-3, 3, 200)
    hi_end = lo_end + rng.uniform(0, 4, 200)
    lo, hi = quadratic_range(c0, c1, c2, lo_end, hi_end)
    d = lo_end[:, None] + np.linspace(0, 1, 4001)[None] * (hi_end - lo_end)[:, None]
    vals = c0[:, None] + d * (c1[:, None] + d * c2[:, None])
    assert np.all(lo <= vals.min(axis=1) + 1e-12) and np.all(hi >= vals.max(axis=1) - 1e-12)
    np.testing.assert_allclose(lo, vals.min(axis=1), atol=1e-5)
    np.testing.assert_allclose(hi, vals.max(axis=1), atol=1e-5)


def test_largest_eigenvalue_of_packed_covariances() -> None:
    rng = np.random.default_rng(0)
    a = rng.normal(size=(200, 2, 2))
    cov = a @ np.swapaxes(a, 1, 2)
    packed = np.stack([cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]], axis=1)
    np.testing.assert_allclose(largest_eigenvalue(packed), np.linalg.eigvalsh(cov)[:, -1], rtol=1e-12)


def _segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(P, S) distances of (P, 2) points to the (S, 2) -> (S, 2) segments."""
    d = b - a
    l2 = np.maximum(np.einsum("ij,ij->i", d, d), 1e-300)
    t = np.clip(np.einsum("pij,ij->pi", p[:, None, :] - a[None], d) / l2, 0.0, 1.0)
    nearest = a[None] + t[..., None] * d[None]
    return np.linalg.norm(p[:, None, :] - nearest, axis=2)


def test_reach_mask_keeps_every_place_within_reach_and_drops_the_far_ones() -> None:
    """Random segments and points of mixed reaches: every query within some input's reach is near (never
    wrongly unsolved); queries beyond every reach by more than the raster's margin are far."""
    rng = np.random.default_rng(1)
    starts = rng.uniform(0, 40, (300, 2))
    ends = starts + rng.normal(0, 4, (300, 2))
    ends[:100] = starts[:100]  # point inputs (endpoints)
    reach = rng.choice([0.8, 1.5, 3.0], 300) * rng.uniform(0.9, 1.1, 300)
    mask = reach_mask(starts, ends, reach)
    q = rng.uniform(-10, 55, (20000, 2))
    near = mask.contains(q)
    excess = _segment_distance(q, starts, ends) - reach[None]  # < 0: within that input's reach
    within = (excess <= 0).any(axis=1)
    assert within.sum() > 1000
    assert near[within].all()
    # three reach levels, a class each: beyond every reach by the raster's margin (and a cell) is far
    reach = rng.choice([0.8, 1.5, 3.0], 300)
    mask = reach_mask(starts, ends, reach)
    near = mask.contains(q)
    excess = _segment_distance(q, starts, ends) - reach[None]
    assert near[(excess <= 0).any(axis=1)].all()
    # the raster of a reach r has cells of max(cell, r / 16): its margin, twice, and a fine cell of slack
    coarse = np.maximum(mask.cell_m, reach / 16)
    slack = 2 * (coarse * (math.sqrt(2) + 0.25) + mask.cell_m) + mask.cell_m
    beyond = (excess > slack[None]).all(axis=1)
    assert beyond.sum() > 1000 and not near[beyond].any()
    assert not mask.contains(np.array([[1e4, 1e4]]))[0]  # off the raster: beyond reach
    with pytest.raises(ValueError, match="finite"):
        reach_mask(starts, ends, np.full(300, np.nan))


def _grid_around(gp: GPOccupancyMap, margin_m: float, step_m: float) -> np.ndarray:
    """(Q, 2) points every ``step_m`` over the map's data bounds grown by ``margin_m``."""
    x0, y0, x1, y1 = gp.bounds_xy_m(margin_m=margin_m)
    gx, gy = np.meshgrid(np.arange(x0, x1, step_m), np.arange(y0, y1, step_m))
    return np.column_stack([gx.ravel(), gy.ravel()])


@pytest.fixture(scope="module")
def intel_beams():
    path = data_file("intel/intel.gfs.log")
    rec = open_dataset(path)
    base = em.reference_base_poses(rec, path)
    beams = em.make_beams(rec, base, np.arange(0, 400, 4), MappingConfig())
    cov = np.tile(np.diag([0.08**2, 0.05**2, 0.02**2]), (len(rec.scans), 1, 1))
    cov[::7] *= 9.0  # some scans far less certain: their inputs reach further
    return beams, cov


@pytest.mark.parametrize(
    ("kernel", "values", "method", "level", "gaussian"),
    [
        ("se", (0.9, 0.3), GIRARD, 1, True),
        ("matern32", (0.9, 0.4), GAUSS_HERMITE, 3, True),
        ("se", (0.9, 0.3), GIRARD, 1, False),
    ],
)
def test_map_with_reach_equals_the_map_solved_everywhere(
    intel_beams, kernel, values, method, level, gaussian
):
    """The Intel lab's beams (GPPOL with pose covariances, and exact inputs): a grid around the data,
    queried with the reach test and with every point solved, agrees to 1e-5 (terms below 1e-4 of k(0) are
    what the test drops, and the nearest inputs carry the prediction), while a large
    share of the grid is answered with the prior unsolved."""
    beams, cov = intel_beams
    params = GPParams(make_kernel(kernel, values), 0.05, 6.0, -0.4)
    inputs = None
    if gaussian:
        moments = input_moments(beams, cov, [SensorNoise(0.01, 1e-4)])
        laser = input_moments(beams, None, [SensorNoise(0.01, 1e-4)])
        inputs = GaussianInputs(moments, InputExpectation(method, level), local_moments=laser)
    with_reach = GPOccupancyMap(beams, params, 15, 15, inputs=inputs)
    solved = GPOccupancyMap(beams, params, 15, 15, inputs=inputs)
    solved._reach, solved._reach_done = None, True  # every query solved
    q = _grid_around(with_reach, 25.0, 0.21)
    far = ~with_reach.reach().contains(q)
    assert 0.2 < far.mean() < 0.95
    a, b = with_reach.query(q), solved.query(q)
    for name in ("mean", "variance", "probability"):
        np.testing.assert_allclose(getattr(a, name), getattr(b, name), rtol=0, atol=1e-5)
    assert np.all(a.mean[far] == 0.0) and np.all(a.variance[far] == params.prior_variance)
    assert np.all(a.probability[far] == params.unseen_probability)


def test_metres_uncertain_scans_mark_nothing_and_leave_the_map_as_solved_everywhere(
    intel_beams, monkeypatch
) -> None:
    """Every ninth scan metres-uncertain (as where passes disagree): its inputs, spread too wide to inform
    a place on their own, no longer widen the reach (a smaller share of the grid is solved). Where the map
    solves, it is the map solved everywhere; the places left to the prior are those where only the
    uncertain inputs lie near, and solving them moves nothing a planner sees (the variance stays within
    1e-4 of the prior: unknown)."""
    beams, cov = intel_beams
    cov = cov.copy()
    cov[4::9] = np.diag([20.0**2, 20.0**2, 0.2**2])
    params = GPParams(make_kernel("se", (0.9, 0.3)), 0.05, 6.0, -0.4)
    moments = input_moments(beams, cov, [SensorNoise(0.01, 1e-4)])
    laser = input_moments(beams, None, [SensorNoise(0.01, 1e-4)])

    def gp_map() -> GPOccupancyMap:
        inputs = GaussianInputs(moments, InputExpectation(GIRARD, 1), local_moments=laser)
        return GPOccupancyMap(beams, params, 15, 15, inputs=inputs)

    floored, solved = gp_map(), gp_map()
    solved._reach, solved._reach_done = None, True
    monkeypatch.setattr("mapping.gpmap.REACH_MIN_PEAK", 0.0)
    unfloored = gp_map()
    unfloored.reach()
    monkeypatch.undo()
    q = _grid_around(floored, 25.0, 0.21)
    near, near_unfloored = floored.reach().contains(q), unfloored.reach().contains(q)
    assert not (near & ~near_unfloored).any()
    assert near.mean() < 0.8 * near_unfloored.mean()
    a, b = floored.query(q), solved.query(q)
    for name in ("mean", "variance", "probability"):  # where solved, solved the same way
        np.testing.assert_array_equal(getattr(a, name)[near], getattr(b, name)[near])
    # where only the uncertain scans are near, the prior stands in for a prediction they barely moved
    assert np.all(a.probability[~near] == params.unseen_probability)
    assert np.abs(b.probability[~near] - params.unseen_probability).max() < 1e-3
    assert b.variance[~near].min() > (1 - 1e-4) * params.prior_variance


def test_reach_tolerance_bounds_the_variance_reduction_of_any_local_problem() -> None:
    """Module docstring: with every input beyond the reach at ``reach_tolerance(noise, k0, m, f)`` the
    local GP's variance stays above ``f`` of the prior, whatever the inputs' layout (random ones, clustered
    ones, a ring around the query); the floor is REACH_TOLERANCE."""
    rng = np.random.default_rng(0)
    for sf2, ell, noise, m, f in [
        (1.1, 0.3, 0.1, 30, 0.9),
        (0.8, 0.5, 0.01, 30, 0.6),
        (2.0, 0.2, 0.3, 12, 0.95),
    ]:
        se = make_kernel("se", {"sigma_f": math.sqrt(sf2), "length_scale": ell})
        t = reach_tolerance(noise, sf2, m, f)
        assert t == pytest.approx(math.sqrt((1 - f) * noise / (m * sf2)))
        r0 = kernel_reach_m(se, t)
        worst = 0.0
        for layout in range(300):
            angles = (
                rng.uniform(0, 2 * np.pi, m) if layout % 3 else np.linspace(0, 2 * np.pi, m, endpoint=False)
            )
            radius = r0 * (1.0 + (rng.exponential(0.3, m) if layout % 3 == 1 else np.zeros(m)))
            X = np.column_stack([radius * np.cos(angles), radius * np.sin(angles)])
            if layout % 3 == 2:  # clustered: near-duplicate inputs, K + noise I nearly singular
                X = X[:1] + rng.normal(0, 1e-3, (m, 2)) * ell
                X *= r0 / np.linalg.norm(X, axis=1).min()
            K = se.of_difference((X[:, None, :] - X[None, :, :]).reshape(-1, 2)).reshape(m, m)
            ks = se.of_difference(X)
            assert ks.max() <= t * sf2 * (1 + 1e-9)
            reduction = ks @ np.linalg.solve(K + noise * np.eye(m), ks)
            worst = max(worst, reduction / sf2)
        assert worst <= 1 - f
    assert reach_tolerance(1e-9, 1.0, 30, 0.9) == REACH_TOLERANCE
    assert reach_tolerance(0.1, 1.0, 30, None) == REACH_TOLERANCE
    assert reach_tolerance(0.1, 1.0, 30, 1.0) == REACH_TOLERANCE


def test_se_girard_reach_over_a_range_of_eigenvalues_is_the_largest_of_the_range() -> None:
    """A free segment's piece knows its eigenvalue only within a range; the reach grows and then shrinks
    with the eigenvalue, so the range's reach is its largest (not the one at the upper end)."""
    ell, tol = 0.3, 0.02
    for lo, hi in [(0.0, 0.01), (0.0, 500.0), (50.0, 400.0), (300.0, 2000.0)]:
        ranged = float(se_girard_reach_m(ell, hi, tol, lo))
        inside = se_girard_reach_m(ell, np.linspace(lo, hi, 2001), tol)
        assert ranged >= inside.max() * (1 - 1e-12)
        assert ranged <= inside.max() * (1 + 1e-3)
    assert float(se_girard_reach_m(ell, 500.0, tol, 0.0)) > float(se_girard_reach_m(ell, 500.0, tol))


@pytest.mark.parametrize(("gaussian", "fraction"), [(True, 0.9), (False, 0.9), (True, 0.6)])
def test_a_reach_of_the_unknown_fraction_changes_no_places_class(intel_beams, gaussian, fraction) -> None:
    """Given the classification's fraction, the reach shrinks to where the variance bound proves a place
    unknown: fewer places are solved; each place it leaves to the prior has, solved, a variance above that
    fraction of the prior (unknown either way), and where it solves, the map is the map solved everywhere."""
    beams, cov = intel_beams
    params = GPParams(make_kernel("se", (0.9, 0.3)), 0.05, 6.0, -0.4)

    def gp_map(unknown_variance_fraction: float | None) -> GPOccupancyMap:
        inputs = None
        if gaussian:
            moments = input_moments(beams, cov, [SensorNoise(0.01, 1e-4)])
            laser = input_moments(beams, None, [SensorNoise(0.01, 1e-4)])
            inputs = GaussianInputs(moments, InputExpectation(GIRARD, 1), local_moments=laser)
        return GPOccupancyMap(
            beams, params, 15, 15, inputs=inputs, unknown_variance_fraction=unknown_variance_fraction
        )

    tight, floor, solved = gp_map(fraction), gp_map(None), gp_map(None)
    solved._reach, solved._reach_done = None, True
    q = _grid_around(tight, 5.0, 0.07)
    near, near_floor = tight.reach().contains(q), floor.reach().contains(q)
    assert not (near & ~near_floor).any()
    assert near.sum() < 0.9 * near_floor.sum()
    a, b = tight.query(q), solved.query(q)
    for name in ("mean", "variance", "probability"):  # (a few in a million differ by how queries share SIMD
        x, y = getattr(a, name)[near], getattr(b, name)[near]  # lanes: a near-singular lane is redone alone)
        assert np.mean(x == y) > 0.9999
        np.testing.assert_allclose(x, y, rtol=0, atol=2e-3)
    prior = params.prior_variance
    assert np.all(a.variance[~near] == prior) and np.all(a.probability[~near] == params.unseen_probability)
    assert b.variance[~near].min() > fraction * prior


def test_the_nn_kernel_solves_every_query(intel_beams) -> None:
    beams, _ = intel_beams
    gp = GPOccupancyMap(beams, GPParams(make_kernel("nn", (0.9, 3.0, 4.0)), 0.05, 6.0, -0.4), 15, 15)
    assert gp.reach() is None


def test_contains_grid_equals_contains_at_every_grid_point() -> None:
    """The per-row-and-column lookup of a render equals the per-point test, inside, across and beyond the
    raster's edges (and for an empty raster)."""
    rng = np.random.default_rng(3)
    starts = rng.uniform(0, 20, (40, 2))
    mask = reach_mask(starts, starts + rng.normal(0, 2, (40, 2)), rng.uniform(0.2, 2.0, 40))
    xs = np.arange(-30.0, 50.0, 0.37) + 0.05
    ys = np.arange(-25.0, 45.0, 0.41) + 0.02
    gx, gy = np.meshgrid(xs, ys)
    per_point = mask.contains(np.column_stack([gx.ravel(), gy.ravel()])).reshape(gx.shape)
    np.testing.assert_array_equal(mask.contains_grid(xs, ys), per_point)
    assert 0.02 < per_point.mean() < 0.9
    empty = reach_mask(starts, starts, np.zeros(40))
    assert not empty.contains_grid(xs, ys).any() and empty.contains_grid(xs, ys).shape == gx.shape
