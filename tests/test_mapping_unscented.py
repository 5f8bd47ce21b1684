"""The unscented transform of beams (eqs. 24-28): exact on linear maps, close to Monte Carlo on the beam map,
and the exact linear / quadratic dependence on the distance along the beam."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mapping.unscented import (
    BeamMoments,
    UTParams,
    beam_moments,
    beam_point,
    pack_cov,
    psd_sqrt,
    sigma_points,
    unpack_cov,
    unscented_transform,
)

MOUNT = np.array([0.3, 0.05, 0.02])
# realistic noise: a laser of 2 cm / 0.1 deg, a correlated pose covariance of ~0.1 m / 0.02 rad
POSE_COV = np.array([[0.01, 0.004, 0.0005], [0.004, 0.012, -0.0008], [0.0005, -0.0008, 0.0004]])


def random_cov(rng: np.random.Generator, n: int, scale: float = 1.0) -> np.ndarray:
    a = rng.normal(size=(n, n)) * scale
    return a @ a.T + 1e-3 * np.eye(n)


def state_cov(range_var: float, bearing_var: float, pose_cov: np.ndarray) -> np.ndarray:
    c = np.zeros((5, 5))
    c[0, 0], c[1, 1] = range_var, bearing_var
    c[2:, 2:] = pose_cov
    return c


@pytest.mark.parametrize("alpha", [1e-3, 0.3, 1.0])
def test_ut_of_a_linear_map_is_exact(alpha: float) -> None:
    rng = np.random.default_rng(0)
    A = rng.normal(size=(2, 5))
    b = rng.normal(size=2)
    mean = rng.normal(size=5)
    cov = random_cov(rng, 5)
    m, c = unscented_transform(lambda x: x @ A.T + b, mean, cov, UTParams(alpha=alpha))
    tol = 1e-12 if alpha > 0.1 else 1e-7  # xi = 1e-3: weights of -1e6 cancel
    np.testing.assert_allclose(m, A @ mean + b, rtol=0, atol=tol)
    np.testing.assert_allclose(c, A @ cov @ A.T, rtol=tol, atol=tol)


def test_weights_and_sigma_points() -> None:
    ut = UTParams()
    c, wm, wc = ut.weights(5)
    assert wm.sum() == pytest.approx(1.0) and wm.shape == (11,)
    assert wc[0] == pytest.approx(wm[0] + 1 - ut.alpha**2 + ut.beta)  # eq. (25)
    cov = np.diag([1.0, 4.0, 0.0, 0.0, 9.0])  # a singular covariance has sigma points too
    pts = sigma_points(np.zeros(5), cov, ut)
    assert pts.shape == (11, 5)
    np.testing.assert_allclose(pts[2, 1], c * 2.0)  # +sqrt(n + lambda) * column 2 of the root
    np.testing.assert_allclose(pts[7, 1], -c * 2.0)
    L = psd_sqrt(cov)
    np.testing.assert_allclose(L @ L.T, cov, atol=1e-12)
    with pytest.raises(ValueError, match="n \\+ lambda"):
        UTParams(alpha=0.5, kappa=-5.0).weights(5)


@pytest.mark.parametrize(
    ("r_m", "range_var", "bearing_var", "pose_cov"),
    [
        (8.0, 4e-4, np.deg2rad(0.1) ** 2, POSE_COV),  # laser 2 cm / 0.1 deg on a correlated pose
        (15.0, 1e-4, 0.0, np.zeros((3, 3))),  # the two-platform world's accurate laser, exact pose
        (3.0, 1e-4, 3e-6, np.diag([0.04, 0.01, 0.001])),
    ],
)
def test_ut_matches_monte_carlo_within_one_percent(r_m, range_var, bearing_var, pose_cov) -> None:
    """Realistic noise: mean within 1% of the spread, covariance within 1% (relative Frobenius norm).
    4e6 draws: the Monte Carlo covariance itself is good to ~0.1%."""
    rng = np.random.default_rng(1)
    mean = np.array([r_m, 0.3, 1.0, 2.0, 0.7])
    cov = state_cov(range_var, bearing_var, pose_cov)
    samples = rng.multivariate_normal(mean, cov, size=4_000_000, method="eigh")
    pts = beam_point(samples, MOUNT)
    mc_mean, mc_cov = pts.mean(axis=0), np.cov(pts.T)
    m, c = unscented_transform(lambda s: beam_point(s, MOUNT), mean, cov)
    assert np.linalg.norm(m - mc_mean) < 0.01 * np.sqrt(np.trace(mc_cov))
    assert np.linalg.norm(c - mc_cov) < 0.01 * np.linalg.norm(mc_cov)


def test_ut_keeps_the_second_order_mean_even_with_the_papers_tiny_spread() -> None:
    """xi = 1e-3 is not a linearisation: the mean of r (cos e, sin e), e ~ N(0, s^2), is r exp(-s^2/2) along
    the beam, which a linearisation (r, 0) misses."""
    r, s = 10.0, 0.1
    mean = np.array([r, 0.0, 0.0, 0.0, 0.0])
    cov = state_cov(0.0, 0.0, np.diag([0.0, 0.0, s * s]))
    for alpha in (1e-3, 0.3):
        m, c = unscented_transform(beam_point, mean, cov, UTParams(alpha=alpha))
        assert m[0] == pytest.approx(r * np.exp(-s * s / 2), rel=3e-5)  # (a linearisation: r, 5e-3 off)
        # across the beam: var = r^2 (1 - e^(-2 s^2)) / 2 = r^2 (s^2 - s^4 + ...); the UT keeps r^2 s^2
        assert c[1, 1] == pytest.approx(r * r * (1 - np.exp(-2 * s * s)) / 2, rel=1.5 * s * s)


def test_free_point_moments_are_exact_in_the_distance_along_the_beam() -> None:
    """rho(d) = a + d b and Sigma(d) = C0 + d C1 + d^2 C2 against a UT of (d, b, x, y, theta) at every d."""
    rng = np.random.default_rng(2)
    bearings = np.array([-1.2, 0.0, 0.4, 2.9])
    poses = np.c_[rng.uniform(-50, 50, (4, 2)), rng.uniform(-3, 3, 4)]
    covs = np.stack([random_cov(rng, 3, 0.1) for _ in range(4)])
    rvar, bvar = np.array([0.8, 1e-4, 0.01, 0.0]), np.array([1.5e-4, 0.0, 1e-3, 1e-5])
    for ut in (UTParams(), UTParams(alpha=1.0)):
        mom = beam_moments(bearings, poses, covs, rvar, bvar, MOUNT, ut)
        for d in (0.0, 0.37, 2.0, 7.5, 30.0):
            for i in range(4):
                mean = np.r_[d, bearings[i], poses[i]]
                m, c = unscented_transform(
                    lambda s: beam_point(s, MOUNT), mean, state_cov(rvar[i], bvar[i], covs[i]), ut
                )
                np.testing.assert_allclose(mom.mean_at(d, np.array([i]))[0], m, rtol=0, atol=1e-11)
                np.testing.assert_allclose(mom.cov_at(d, np.array([i]))[0], c, rtol=1e-10, atol=1e-13)


def test_shared_scan_covariances_give_the_per_beam_coefficients_bit_for_bit() -> None:
    """A covariance per scan with ``cov_of_beam`` (its root taken once) equals it repeated for each beam;
    enough beams for several parallel chunks."""
    rng = np.random.default_rng(5)
    n_scans, m = 7, 9000
    scan = np.sort(rng.integers(0, n_scans, m))
    poses = np.c_[rng.uniform(-50, 50, (n_scans, 2)), rng.uniform(-3, 3, n_scans)][scan]
    covs = np.stack([random_cov(rng, 3, 0.1) for _ in range(n_scans)])
    covs[2] = 0.0  # an exact pose: a zero root
    bearings = rng.uniform(-np.pi, np.pi, m)
    shared = beam_moments(bearings, poses, covs, 1e-4, 3e-6, MOUNT, cov_of_beam=scan)
    repeated = beam_moments(bearings, poses, covs[scan], 1e-4, 3e-6, MOUNT)
    for f in ("a", "b", "c0", "c1", "c2"):
        np.testing.assert_array_equal(getattr(shared, f), getattr(repeated, f))


_TWO_THREADS = """
from concurrent.futures import ThreadPoolExecutor
import numpy as np
from mapping.unscented import beam_moments
m = 100_000
def work(seed):
    rng = np.random.default_rng(seed)
    for _ in range(5):
        beam_moments(rng.uniform(-3, 3, m), np.zeros((m, 3)), np.eye(3) * 1e-4, 1e-4, 3e-6)
with ThreadPoolExecutor(2) as pool:
    list(pool.map(work, range(2)))
print("done")
"""


def test_two_threads_computing_moments_at_once_work_on_numbas_workqueue_layer() -> None:
    """A run computes its maps' placement layers in two threads. Numba's fallback threading layer aborts the
    process when two threads launch a parallel loop at once; the moments take turns."""
    env = {**os.environ, "NUMBA_THREADING_LAYER": "workqueue"}
    root = str(Path(__file__).resolve().parents[1])
    env["PYTHONPATH"] = root + os.pathsep + env.get("PYTHONPATH", "")
    done = subprocess.run(
        [sys.executable, "-c", _TWO_THREADS], env=env, cwd=root, capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 0 and done.stdout.strip() == "done", done.stderr[-2000:]


def test_exact_inputs_give_points_and_zero_covariance() -> None:
    bearings = np.array([0.1, -0.5])
    poses = np.array([[1.0, 2.0, 0.3], [-4.0, 0.5, -2.0]])
    mom = beam_moments(bearings, poses, np.zeros((2, 3, 3)), 0.0, 0.0, MOUNT)
    d = np.array([3.0, 0.5])
    expect = beam_point(np.c_[d, bearings, poses], MOUNT)
    np.testing.assert_allclose(mom.mean_at(d), expect, atol=1e-12)
    np.testing.assert_allclose(mom.cov_at(d), 0.0, atol=1e-15)
    one = mom.subset(np.array([1]))
    assert isinstance(one, BeamMoments) and len(one) == 1
    np.testing.assert_array_equal(one.mean_at(d[1:]), mom.mean_at(d[1:], np.array([1])))


def test_covariances_grow_with_the_distance_and_stay_positive() -> None:
    """Bearing and heading errors spread a point across the beam in proportion to its distance."""
    mom = beam_moments(np.array([0.0]), np.zeros((1, 3)), np.diag([0.01, 0.01, 0.0004])[None], 1e-4, 3e-6)
    c = mom.cov_at(np.array([0.0, 1.0, 5.0, 20.0]), np.zeros(4, np.int64))
    across = c[:, 1, 1]
    assert np.all(np.diff(across) > 0)
    assert across[3] == pytest.approx(0.01 + 400 * (0.0004 + 3e-6), rel=0.01)
    assert np.all(np.linalg.eigvalsh(c) > 0)


def test_pack_unpack_roundtrip() -> None:
    c = np.array([[[2.0, 0.5], [0.5, 1.0]]])
    np.testing.assert_array_equal(unpack_cov(pack_cov(c)), c)
