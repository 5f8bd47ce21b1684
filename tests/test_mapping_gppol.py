"""GPPOL end to end: the compiled core against the numpy reference, the two-platform world (the
paper's dataset II) and the Intel lab with perturbed poses."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from datasets.registry import open_dataset
from mapping.config import MappingConfig
from mapping.core import NEGLIGIBLE_KERNEL
from mapping.gpmap import GPOccupancyMap
from mapping.gppol import GaussianInputs, RigidGroups, SensorNoise, input_moments
from mapping.kernels import make_kernel
from mapping.noisy_kernels import GAUSS_HERMITE, GIRARD, SIGMA_POINTS, InputExpectation, sigma_point_rule_2d
from mapping.train import GPParams
from pipeline import evaluate_map as em
from pipeline.errors import PipelineError
from pipeline.progress import Progress
from tests.conftest import data_file

FAST = {"train": {"anneal_evaluations": 40, "lbfgs_iterations": 40, "problems": 48}}


@pytest.fixture(scope="module")
def intel():
    path = data_file("intel/intel.gfs.log")
    rec = open_dataset(path)
    return rec, em.reference_base_poses(rec, path)


def _reference_prediction(gp: GPOccupancyMap, queries: np.ndarray, k_occ: int, k_free: int):
    """Mean, variance, p(occ) of eqs. 2-3 + PLS from the numpy kernels between distributions (two inputs
    of one scan integrated over their laser noise alone, as the core does)."""
    inputs = gp.inputs
    X, cov, local, scans, y, full = gp.index.local_gaussians_by_scan(
        queries, k_occ, k_free, inputs.moments, inputs.free_moments, inputs.local(), inputs.local_free()
    )
    kern, ex = gp.params.kernel, inputs.expectation
    K = ex.matrix(kern, X, cov, local_cov=local, scans=scans) + gp.params.noise_var * np.eye(X.shape[1])
    ks = ex.cross(kern, X, cov, np.zeros((X.shape[0], 1, 2)))[..., 0]
    kss = kern(np.zeros((1, 2)))[0, 0]
    a = np.linalg.solve(K, np.concatenate([y[..., None], ks[..., None]], axis=2))
    mu = np.einsum("qi,qi->q", ks, a[..., 0])
    var = kss - np.einsum("qi,qi->q", ks, a[..., 1])
    p = gp.params
    from scipy.special import ndtr

    m = mu if p.mean_cap is None else np.clip(mu, -p.mean_cap, p.mean_cap)
    prob = ndtr((p.alpha * m + p.beta) / np.sqrt(1.0 + p.alpha**2 * (var + p.noise_var)))
    return mu, var, prob, full


@pytest.mark.parametrize(
    ("kernel", "method", "level"),
    [("se", GIRARD, 1), ("se", GAUSS_HERMITE, 3), ("matern32", GAUSS_HERMITE, 2), ("nn", SIGMA_POINTS, 1),
     ("nn", GAUSS_HERMITE, 2)],
)  # fmt: skip
def test_compiled_core_matches_the_numpy_reference(intel, kernel, method, level) -> None:
    rec, base = intel
    cfg = MappingConfig()
    beams = em.make_beams(rec, base, np.arange(40, 70), cfg)
    cov = np.tile(np.diag([0.1**2, 0.05**2, 0.02**2]), (len(rec.scans), 1, 1))
    cov[:, 0, 2] = cov[:, 2, 0] = 0.5 * 0.1 * 0.02  # correlated terms kept
    moments = input_moments(beams, cov, [SensorNoise(0.01, 1e-4)])
    laser_only = input_moments(beams, None, [SensorNoise(0.01, 1e-4)])
    values = {"nn": (0.9, 3.0, 4.0), "se": (0.9, 0.6), "matern32": (0.9, 0.8)}[kernel]
    params = GPParams(make_kernel(kernel, values), 0.1, 8.0, 0.3, {"inputs": {}})
    inputs = GaussianInputs(moments, InputExpectation(method, level), local_moments=laser_only)
    gp = GPOccupancyMap(beams, params, 15, 15, inputs=inputs)
    rng = np.random.default_rng(3)
    q = beams.hit_xy_m[rng.choice(int(beams.is_hit.sum()), 60, replace=False)] + rng.normal(0, 0.4, (60, 2))
    mu, var, prob, full = _reference_prediction(gp, q, 15, 15)
    pred = gp.query(q[full], sort=False)
    assert full.sum() > 50
    np.testing.assert_allclose(pred.mean, mu, atol=2e-7, rtol=1e-6)
    np.testing.assert_allclose(pred.variance, var, atol=2e-7, rtol=1e-6)
    np.testing.assert_allclose(pred.probability, prob, atol=1e-6)
    # the inputs matter: the same map with exact inputs (GPFOL) differs, and so does one whose beams of a
    # scan are taken as independent (eq. 17 for every pair) for the stationary kernels
    assert (
        np.abs(GPOccupancyMap(beams, params, 15, 15).query(q[full], sort=False).variance - var).max() > 1e-3
    )
    independent = GPOccupancyMap(
        beams, params, 15, 15, inputs=GaussianInputs(moments, InputExpectation(method, level))
    ).query(q[full], sort=False)
    assert (np.abs(independent.variance - var).max() > 1e-3) == params.kernel.stationary


@pytest.mark.parametrize("mode", ["girard", "gh_difference"])
def test_two_points_of_one_scan_keep_their_kernel_two_of_two_scans_integrate_over_both(mode) -> None:
    """Monte Carlo over rigid motions of two scans (independent, each with translation and heading
    errors): E[k] between two points of one scan is the kernel at their distance (a rigid motion keeps
    it); between points of two scans it is the kernel integrated over both points' covariances, which for
    translations is exact (eq. 19 / Gauss-Hermite), checked against the draws."""
    from mapping.core import INPUTS_GH_DIFFERENCE, INPUTS_GIRARD, KERNEL_SE, _noisy_kernel_lanes
    from mapping.noisy_kernels import girard_se

    rng = np.random.default_rng(0)
    ell, sf2 = 0.5, 0.8
    pose_sd = np.array([0.3, 0.2])  # translation only: every point's distribution is exactly Gaussian
    p_a = np.array([[1.0, 0.2], [1.3, 0.9]])  # scan A's points, in its frame (scan at the origin)
    p_b = np.array([[1.6, 0.4]])  # scan B's point
    draws = 200_000
    e_a = rng.normal(size=(draws, 2)) * pose_sd
    e_b = rng.normal(size=(draws, 2)) * pose_sd
    th = rng.normal(size=draws) * 0.1  # a heading error of scan A too: it keeps the distance within A
    rot = np.stack([np.cos(th), -np.sin(th), np.sin(th), np.cos(th)], -1).reshape(-1, 2, 2)
    a0, a1 = (rot @ p_a[i] + e_a for i in (0, 1))
    b0 = p_b[0] + e_b
    k = lambda d: sf2 * np.exp(-0.5 * np.sum(d * d, axis=-1) / ell**2)  # noqa: E731
    within_mc, across_mc = k(a0 - a1).mean(), k(a1 - b0).mean()
    # the core, one lane: inputs A0, A1 (scan 0), B0 (scan 1); covariances: the translation part
    X = np.zeros((3, 2, 32))
    X[:, :, 0] = [p_a[0], p_a[1], p_b[0]]
    S = np.zeros((3, 3, 32))
    S[:, 0, 0], S[:, 2, 0] = pose_sd[0] ** 2, pose_sd[1] ** 2
    G = np.zeros((3, 32))
    G[2, 0] = 1.0
    K, ks = np.zeros((3, 3, 32)), np.zeros((3, 32))
    z, w = InputExpectation(GAUSS_HERMITE, 8).rule()
    core_mode = INPUTS_GIRARD if mode == "girard" else INPUTS_GH_DIFFERENCE
    kp = np.array([sf2, 1.0 / ell**2])
    _noisy_kernel_lanes(core_mode, KERNEL_SE, kp, X, S, np.zeros_like(S), S, G, G, False, np.ones((3, 32)), 3,
                        K, ks, np.ascontiguousarray(z), np.ascontiguousarray(w), np.zeros((3, 1, 2, 32)),
                        np.zeros((3, 1, 32)))  # fmt: skip
    assert K[1, 0, 0] == pytest.approx(k(p_a[0] - p_a[1]), rel=1e-6)  # within one scan: the kernel itself
    assert K[1, 0, 0] == pytest.approx(within_mc, rel=1e-9)  # ... which every draw gives
    assert K[2, 1, 0] == pytest.approx(across_mc, rel=0.01)  # across scans: integrated over both
    se = make_kernel("se", (np.sqrt(sf2), ell))  # sigma_f, length scale
    exact = girard_se(se, (p_b[0] - p_a[1])[None], np.diag(2 * pose_sd**2)[None])[0]
    assert K[2, 1, 0] == pytest.approx(exact, rel=1e-5 if mode == "girard" else 1e-3)
    # taken as independent (eq. 17 for every pair), the within-scan entry would shrink instead
    K2 = np.zeros_like(K)
    alone = G * 0 + np.arange(3)[:, None]
    _noisy_kernel_lanes(core_mode, KERNEL_SE, kp, X, S, S, S, alone, alone, False, np.ones((3, 32)), 3, K2,
                        ks, np.ascontiguousarray(z), np.ascontiguousarray(w), np.zeros((3, 1, 2, 32)),
                        np.zeros((3, 1, 32)))  # fmt: skip
    assert K2[1, 0, 0] < 0.95 * within_mc  # 0.91 of it here


@pytest.mark.parametrize("mode", ["girard", "gh_difference"])
def test_two_scans_of_one_rigid_group_integrate_over_their_offsets_alone(mode) -> None:
    """Monte Carlo over a rigid group (a keyframe's error, translation and heading, moves scans A and B
    alike; each also strays from it by its own offset error) and a scan C of another group: E[k] between
    points of A and B is the kernel integrated over the two offsets' covariances alone (exact for
    translations); between B and C over both full covariances; within A the kernel itself."""
    from mapping.core import INPUTS_GH_DIFFERENCE, INPUTS_GIRARD, KERNEL_SE, _noisy_kernel_lanes
    from mapping.noisy_kernels import girard_se

    rng = np.random.default_rng(1)
    ell, sf2 = 0.5, 0.8
    group_sd, offset_sd = np.array([0.4, 0.3]), np.array([0.15, 0.1])
    pts = np.array([[1.0, 0.2], [1.3, 0.9], [1.6, 0.4], [1.2, -0.3]])  # A, A, B, C (group frame)
    draws = 400_000
    th = rng.normal(size=draws) * 0.1  # the group's heading error: keeps distances within the group
    rot = np.stack([np.cos(th), -np.sin(th), np.sin(th), np.cos(th)], -1).reshape(-1, 2, 2)
    e_group = rng.normal(size=(draws, 2)) * group_sd
    e_a, e_b = (rng.normal(size=(draws, 2)) * offset_sd for _ in range(2))
    a1 = rot @ pts[1] + e_group + e_a
    b0 = rot @ pts[2] + e_group + e_b
    c0 = pts[3] + rng.normal(size=(draws, 2)) * np.sqrt(group_sd**2 + offset_sd**2)
    k = lambda d: sf2 * np.exp(-0.5 * np.sum(d * d, axis=-1) / ell**2)  # noqa: E731
    X = np.zeros((4, 2, 32))
    X[:, :, 0] = pts
    S, S_group = np.zeros((4, 3, 32)), np.zeros((4, 3, 32))
    S[:, 0, 0], S[:, 2, 0] = group_sd**2 + offset_sd**2  # full: the group's and the offset's translation
    S_group[:, 0, 0], S_group[:, 2, 0] = offset_sd**2  # within the group: the offset's alone
    scan, group = np.zeros((4, 32)), np.zeros((4, 32))
    scan[:, 0], group[:, 0] = [0, 0, 1, 2], [0, 0, 0, 1]
    K, ks = np.zeros((4, 4, 32)), np.zeros((4, 32))
    z, w = InputExpectation(GAUSS_HERMITE, 8).rule()
    core_mode = INPUTS_GIRARD if mode == "girard" else INPUTS_GH_DIFFERENCE
    _noisy_kernel_lanes(core_mode, KERNEL_SE, np.array([sf2, 1.0 / ell**2]), X, S, np.zeros_like(S), S_group,
                        scan, group, True, np.ones((4, 32)), 4, K, ks, np.ascontiguousarray(z),
                        np.ascontiguousarray(w), np.zeros((4, 1, 2, 32)), np.zeros((4, 1, 32)))  # fmt: skip
    tol = 1e-5 if mode == "girard" else 3e-3  # Gauss-Hermite of level 8 over the wider spread
    se = make_kernel("se", (np.sqrt(sf2), ell))
    assert K[1, 0, 0] == pytest.approx(k(pts[0] - pts[1]), rel=1e-6)  # one scan
    assert K[2, 1, 0] == pytest.approx(k(a1 - b0).mean(), rel=0.01)  # one group, two scans
    within = girard_se(se, (pts[2] - pts[1])[None], np.diag(2 * offset_sd**2)[None])[0]
    assert K[2, 1, 0] == pytest.approx(within, rel=tol)
    assert K[3, 2, 0] == pytest.approx(k(b0 - c0).mean(), rel=0.01)  # two groups
    across = girard_se(se, (pts[3] - pts[2])[None], np.diag(2 * (group_sd**2 + offset_sd**2))[None])[0]
    assert K[3, 2, 0] == pytest.approx(across, rel=tol)
    assert k(a1 - b0).mean() > 1.2 * across  # the shared error does not separate A from B


def test_a_query_whose_neighbours_all_have_negligible_k_star_reads_the_prior_unsolved(intel) -> None:
    """One scan placed metres uncertain reaches far (its inputs' reach covers places far from the data), yet
    where a query's own neighbours all have k(x*, x_i) below NEGLIGIBLE_KERNEL of k(0) the core answers the
    prior without a solve; the full solve (numpy reference) differs from it by little there, and every
    other query is solved as before."""
    rec, base = intel
    beams = em.make_beams(rec, base, np.arange(40, 70), MappingConfig())
    cov = np.tile(np.diag([0.02**2, 0.02**2, 0.005**2]), (len(rec.scans), 1, 1))
    cov[55] = np.diag([4.0**2, 4.0**2, 0.2**2])  # one scan a pass the graph barely ties down
    moments = input_moments(beams, cov, [SensorNoise(0.01, 1e-4)])
    laser_only = input_moments(beams, None, [SensorNoise(0.01, 1e-4)])
    params = GPParams(make_kernel("se", (0.9, 0.3)), 0.1, 8.0, 0.3, {"inputs": {}})
    inputs = GaussianInputs(moments, InputExpectation(GIRARD), local_moments=laser_only)
    gp = GPOccupancyMap(beams, params, 15, 15, inputs=inputs)
    lo, hi = beams.hit_xy_m.min(axis=0) - 12.0, beams.hit_xy_m.max(axis=0) + 12.0
    q = np.random.default_rng(5).uniform(lo, hi, (4000, 2))
    q = q[gp.reach().contains(q)]  # the places some input reaches: the reach test solves them all
    mu, var, _, full = _reference_prediction(gp, q, 15, 15)
    q, mu, var = q[full], mu[full], var[full]
    X, cov_q, *_ = gp.index.local_gaussians_by_scan(
        q, 15, 15, inputs.moments, inputs.free_moments, inputs.local(), inputs.local_free()
    )
    ks = inputs.expectation.cross(params.kernel, X, cov_q, np.zeros((X.shape[0], 1, 2)))[..., 0]
    kss = params.prior_variance
    negligible = np.abs(ks).max(axis=1) < NEGLIGIBLE_KERNEL * kss
    assert 20 < negligible.sum() < negligible.size - 20  # both kinds of query are there
    pred = gp.query(q, sort=False)
    np.testing.assert_array_equal(pred.mean[negligible], 0.0)
    np.testing.assert_array_equal(pred.variance[negligible], kss)
    assert np.abs(mu[negligible]).max() < 1e-3 and np.abs(var[negligible] - kss).max() < 1e-6
    np.testing.assert_allclose(pred.mean[~negligible], mu[~negligible], atol=2e-7, rtol=1e-6)
    np.testing.assert_allclose(pred.variance[~negligible], var[~negligible], atol=2e-7, rtol=1e-6)


def test_exact_inputs_make_gppol_gpfol(intel) -> None:
    """Zero pose covariance and laser noise: every kernel expectation is the kernel itself."""
    rec, base = intel
    beams = em.make_beams(rec, base, np.arange(0, 30), MappingConfig())
    moments = input_moments(beams, None, [SensorNoise(0.0, 0.0)])
    params = GPParams(make_kernel("nn", (0.9, 3.0, 4.0)), 0.1, 8.0, 0.3)
    q = beams.hit_xy_m[::37] + 0.2
    ref = GPOccupancyMap(beams, params, 15, 15).query(q)
    pol = GPOccupancyMap(
        beams, params, 15, 15, inputs=GaussianInputs(moments, InputExpectation(SIGMA_POINTS))
    )
    got = pol.query(q)
    np.testing.assert_allclose(got.mean, ref.mean, atol=1e-9)
    np.testing.assert_allclose(got.variance, ref.variance, atol=1e-9)


def test_core_arrays_hold_each_inputs_moments(intel) -> None:
    """The rows the compiled core reads: an endpoint's mean and covariances at its range, a beam's UT
    coefficients and the length of its free part, exactly as the moments give them."""
    rec, poses = intel
    cfg = MappingConfig()
    rows = np.arange(0, 400, 4)
    beams = em.make_beams(rec, poses, rows, cfg)
    cov = np.tile(np.diag([4e-4, 2.5e-4, 1e-5]), (len(rec.scans), 1, 1))
    noise = [SensorNoise(1e-4, 3e-6)]
    inputs = GaussianInputs(input_moments(beams, cov, noise), local_moments=input_moments(beams, None, noise))
    hits = np.flatnonzero(beams.is_hit)[::-1].copy()
    occ, seg = inputs.core_arrays(beams, hits)
    mo, lo = inputs.moments, inputs.local()
    d = beams.ranges_m[hits]
    np.testing.assert_array_equal(occ[:, :2], mo.mean_at(d, hits))
    np.testing.assert_array_equal(occ[:, 2:5], mo.packed_cov_at(d, hits))
    np.testing.assert_array_equal(occ[:, 5:8], lo.packed_cov_at(d, hits))
    np.testing.assert_array_equal(occ[:, 8], beams.scan_index[hits])
    np.testing.assert_array_equal(seg[:, 0:2], mo.a)
    np.testing.assert_array_equal(seg[:, 2:4], mo.b)
    for k, f in enumerate(("c0", "c1", "c2")):
        np.testing.assert_array_equal(seg[:, 4 + 3 * k : 7 + 3 * k], getattr(mo, f))
        np.testing.assert_array_equal(seg[:, 14 + 3 * k : 17 + 3 * k], getattr(lo, f))
    np.testing.assert_array_equal(seg[:, 13], np.hypot(*(beams.free_ends_xy_m - beams.origins_xy_m).T))
    np.testing.assert_array_equal(seg[:, 23], beams.scan_index)
    assert not np.array_equal(occ[:, 2:5], occ[:, 5:8])  # the pose covariance is in the full ones only


def test_sigma_point_rule_moments() -> None:
    z, w = sigma_point_rule_2d()
    assert w.sum() == pytest.approx(1.0)
    np.testing.assert_allclose(w @ z, 0.0, atol=1e-15)
    np.testing.assert_allclose(np.einsum("a,ai,aj->ij", w, z, z), np.eye(2), atol=1e-14)
    np.testing.assert_allclose(w @ z**4, [3.0, 3.0])  # 4th moments along the axes are exact
    np.testing.assert_allclose(w @ z**3, 0.0, atol=1e-14)


def test_perturbation_is_seeded_and_parsed() -> None:
    base = np.zeros((5, 3))
    a, cov = em.perturb(base, 0.1, 0.02, seed=3)
    b, _ = em.perturb(base, 0.1, 0.02, seed=3)
    c, _ = em.perturb(base, 0.1, 0.02, seed=4)
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)
    np.testing.assert_allclose(cov[2], np.diag([0.01, 0.01, 0.0004]))
    z = np.random.default_rng(em.PERTURB_SEED_BASE + 3).standard_normal((5, 3))
    np.testing.assert_allclose(a, z * [0.1, 0.1, 0.02])
    assert em.parse_perturbation("0.1,0.02") == (0.1, 0.02)
    assert em.parse_perturbation("100,3.14159") == (100.0, 3.14159)
    for bad in ("0.1", "a,b", "-1,0.1", "0.1,0.02,3", "1e9,0.1", "100.1,0", "0.1,3.2", "0.1,nan"):
        with pytest.raises(PipelineError, match="perturb-poses"):
            em.parse_perturbation(bad)


@pytest.mark.slow
def test_two_platform_world_gppol_beats_gpfol_where_observed_and_its_variance_orders_the_regions() -> None:
    """The paper's dataset II (section 4.1.2, Figures 9-10): where some beam looked, GPPOL above GPFOL (the
    noisy platform's phantoms cost GPFOL) and both above the grid; GPPOL's variance lowest where platform I
    scanned, higher where only the noisy platform II did, highest where neither did.

    Not asserted, because it does not hold with the default GPPOL kernel (SE): GPPOL above GPFOL over EVERY
    cell of the raster (measured 0.870 vs 0.892; the paper 0.9303 vs 0.8715). 77 % of the cells are never
    observed (inside the blocks); there the NN kernel of GPFOL extrapolates the walls and the SE kernel
    returns to its prior. GPPOL with the NN kernel (sigma-point rule) scores 0.8929 vs 0.8919."""
    from pipeline.mapping_figures import REGIONS, two_platform_result

    r = two_platform_result(seed=0, every=3)
    auc, seen = r["auc"], r["auc_observed"]
    # measured (every 3rd cell): gppol 0.870, gpfol 0.892, grid 0.716
    assert auc["gppol"] > auc["grid"] + 0.1 and auc["gpfol"] > auc["grid"] + 0.1
    assert seen["gppol"] > seen["gpfol"] + 0.008 and seen["gpfol"] > seen["grid"]  # 0.996, 0.982
    only2 = REGIONS[1]
    assert r["auc_by_region"]["gppol"][only2] > r["auc_by_region"]["gpfol"][only2] + 0.02  # 0.994 vs 0.962
    v = r["median_variance"]["gppol"]
    assert 3.0 * v[REGIONS[0]] < v[REGIONS[1]] and 3.0 * v[REGIONS[1]] < v[REGIONS[2]]  # 0.010, 0.114, 0.821
    # GPFOL hardly tells the two platforms apart (measured 0.054 vs 0.070)
    f = r["median_variance"]["gpfol"]
    assert f[REGIONS[1]] / f[REGIONS[0]] < 0.2 * v[REGIONS[1]] / v[REGIONS[0]]


@pytest.mark.slow
def test_intel_perturbed_poses_gppol_beats_gpfol(intel) -> None:
    """Poses perturbed by 0.1 m / 0.02 rad (the Hilbert-maps reference's perturb_data), GPPOL given that
    covariance; scored on the unperturbed poses' test points (hold-out protocol, seed 0)."""
    rec, base = intel
    cfg = MappingConfig(**FAST)
    out = em.evaluate_holdout(rec, base, [0], cfg, Progress(), perturb_poses=(0.1, 0.02))
    row = out["per_seed"][0]
    assert row["auc_gppol"] > row["auc_gpfol"] + 0.005  # measured 0.970 vs 0.961 (default training)
    assert row["auc_gpfol"] > row["auc_grid"]


@pytest.mark.slow
def test_two_platform_world_gppol_with_the_papers_nn_kernel_beats_gpfol_on_every_cell() -> None:
    """The paper's dataset II scored as SPEC section 6 says (every cell; here every 3rd row and column), with
    the paper's GPPOL kernel (NN, eq. 7; sigma-point rule: mapping/configs/gppol_nn.yaml): GPPOL above GPFOL
    above the grid. Small margin (measured 0.8928 vs 0.8919 on every cell of seed 0; seeds 1, 2: 0.8948 vs
    0.8918, 0.8890 vs 0.8885): the 77 % never-observed cells weigh as much for both."""
    from pipeline.mapping_figures import two_platform_result
    from tests.conftest import REPO

    r = two_platform_result(seed=0, every=3, config_path=REPO / "mapping" / "configs" / "gppol_nn.yaml")
    auc = r["auc"]
    assert auc["gppol"] > auc["gpfol"] > auc["grid"] + 0.1
    assert r["auc_observed"]["gppol"] > r["auc_observed"]["gpfol"] + 0.008


def test_a_rigid_group_is_mapped_as_one_scan(intel) -> None:
    """Scans of one rigid group share one pose error: their points are placed relative to each other up to
    the laser noise alone, exactly as the points of one scan (the map equals the one whose grouped scans
    are merged into one), and differently from independent scans. With offsets from the group, two scans of
    it integrate over the offsets instead: offsets as large as the whole covariance give the independent
    scans' map, and smaller ones a third map."""
    rec, poses = intel
    rows = np.arange(40, 70)
    beams = em.make_beams(rec, poses, rows, MappingConfig())
    cov = np.tile(np.diag([0.05**2, 0.05**2, 0.01**2]), (len(rec.scans), 1, 1))
    groups = np.arange(len(rec.scans)) // 3  # three consecutive scans move together
    noise = [SensorNoise(1e-4, 3e-6)]
    params = GPParams(make_kernel("se", (0.9, 0.3)), 0.1, 8.0, 0.3, {"inputs": {}})

    def gppol(b, rigid_groups, offset_cov=None):
        inputs = GaussianInputs(
            input_moments(b, cov, noise),
            local_moments=input_moments(b, None, noise),
            rigid_groups=rigid_groups,
            group_moments=None if offset_cov is None else input_moments(b, offset_cov, noise),
        )
        return GPOccupancyMap(b, params, 15, 15, inputs=inputs)

    merged = replace(beams, scan_index=groups[beams.scan_index])
    q = beams.hit_xy_m[::23] + np.array([0.07, -0.04])
    grouped = gppol(beams, groups).query(q)
    one_scan = gppol(merged, None).query(q)
    alone = gppol(beams, None).query(q)
    np.testing.assert_array_equal(grouped.mean, one_scan.mean)
    np.testing.assert_array_equal(grouped.variance, one_scan.variance)
    assert np.abs(grouped.mean - alone.mean).max() > 1e-3
    whole_offsets = gppol(beams, groups, cov).query(q)
    np.testing.assert_array_equal(whole_offsets.mean, alone.mean)
    np.testing.assert_array_equal(whole_offsets.variance, alone.variance)
    small_offsets = gppol(beams, groups, 0.2 * cov).query(q)
    assert min(np.abs(small_offsets.mean - m).max() for m in (grouped.mean, alone.mean)) > 1e-4
    occ, seg = gppol(beams, groups).inputs.core_arrays(beams, np.flatnonzero(beams.is_hit))
    assert occ.shape[1] == 9 and seg.shape[1] == 24  # exactly rigid groups: the group in the scan's place
    np.testing.assert_array_equal(occ[:, 8], groups[beams.scan_index[beams.is_hit]])
    np.testing.assert_array_equal(seg[:, 23], groups[beams.scan_index])
    occ, seg = gppol(beams, groups, 0.2 * cov).inputs.core_arrays(beams, np.flatnonzero(beams.is_hit))
    assert occ.shape[1] == 13 and seg.shape[1] == 34  # with offsets: the scans and the groups apart
    np.testing.assert_array_equal(occ[:, 8], beams.scan_index[beams.is_hit])
    np.testing.assert_array_equal(occ[:, 12], groups[beams.scan_index[beams.is_hit]])
    np.testing.assert_array_equal(seg[:, 23], beams.scan_index)
    np.testing.assert_array_equal(seg[:, 33], groups[beams.scan_index])
    np.testing.assert_array_equal(
        gppol(beams, None, 0.2 * cov).inputs.core_arrays(beams, np.flatnonzero(beams.is_hit))[0].shape,
        (int(beams.is_hit.sum()), 9),
    )
    with pytest.raises(ValueError, match="rigid groups"):
        gppol(beams, groups[:50]).inputs.core_arrays(beams, np.flatnonzero(beams.is_hit))


def test_rigid_groups_compare_and_select_groups_with_their_offsets() -> None:
    """``RigidGroups.equal`` tells groups and offsets apart (None: each scan alone); ``take`` keeps each
    selected scan's group and offset."""
    groups = np.array([0, 0, 1])
    offsets = np.arange(1.0, 4.0)[:, None, None] * np.eye(3)
    rigid, offset = RigidGroups(groups), RigidGroups(groups, offsets)
    assert RigidGroups.equal(None, None) and not RigidGroups.equal(rigid, None)
    assert not RigidGroups.equal(None, rigid)
    assert RigidGroups.equal(rigid, RigidGroups(groups.copy())) and not RigidGroups.equal(rigid, offset)
    assert not RigidGroups.equal(rigid, RigidGroups(np.array([0, 1, 1])))
    assert RigidGroups.equal(offset, RigidGroups(groups, offsets.copy()))
    assert not RigidGroups.equal(offset, RigidGroups(groups, 2 * offsets))
    taken = offset.take(np.array([2, 0]))
    np.testing.assert_array_equal(taken.group_of_scan, [1, 0])
    np.testing.assert_array_equal(taken.offset_cov_body, offsets[[2, 0]])
    assert rigid.take(np.array([1])).offset_cov_body is None and len(taken) == 2


def test_the_builder_hands_rigid_groups_to_gppol_only_with_covariances(intel) -> None:
    """``MapBuilder`` passes the rigid groups to GPPOL's inputs (its tiles' factory too); without pose
    covariances they mean nothing and are dropped."""
    from mapping.build import MapBuilder

    rec, poses = intel
    cfg = MappingConfig(**FAST)
    beams = em.make_beams(rec, poses, np.arange(40, 60), cfg)
    cov = np.tile(np.diag([0.05**2, 0.05**2, 0.01**2]), (len(rec.scans), 1, 1))
    groups = RigidGroups(np.arange(len(rec.scans)) // 4)
    builder = MapBuilder.from_config(cfg, "gppol")
    params = GPParams(make_kernel("se", (0.9, 0.3)), 0.1, 8.0, 0.3, {"inputs": {}})
    inputs = builder.gp_map(beams, params, cov, groups).inputs
    np.testing.assert_array_equal(inputs.rigid_groups, groups.group_of_scan)
    assert inputs.group_moments is None  # exactly rigid: the laser noise alone within a group
    assert builder.gp_map(beams, params, None, groups).inputs.rigid_groups is None
    bounds = (*beams.hit_xy_m.min(axis=0), *beams.hit_xy_m.max(axis=0))
    tiled = builder.tiled_map(beams, params, bounds, 64, cov, rigid_groups=groups)
    assert tiled.factory.rigid_groups is groups
    # offsets in each scan's frame reach the inputs turned into the world at the beams' headings
    body = np.tile(np.diag([0.03**2, 0.001**2, 0.002**2]), (len(rec.scans), 1, 1))
    offsets = RigidGroups(groups.group_of_scan, body)
    inputs = builder.gp_map(beams, params, cov, offsets).inputs
    world = offsets.offset_cov_world(beams)
    heading = beams.base_poses_xytheta()[:, 2]
    c, s = np.cos(heading), np.sin(heading)
    along = world[beams.scan_index, :2, :2] @ np.stack([c, s], 1)[:, :, None]
    np.testing.assert_allclose(along[:, :, 0], 0.03**2 * np.stack([c, s], 1), atol=1e-12)
    expected = builder.gaussian_inputs(beams, world, params.kernel).moments
    np.testing.assert_array_equal(inputs.group_moments.c0, expected.c0)
    with pytest.raises(ValueError, match="offset covariances"):
        RigidGroups(groups.group_of_scan, body[:5])
