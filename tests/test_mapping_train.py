"""Training: the batched log marginal likelihood (eq. 9), its gradient, the optimiser, PLS, stored params."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mapping.kernels import make_kernel
from mapping.pls import fit_pls, loo_predictions, pls_probability
from mapping.train import (
    GPParams,
    ParamsFileError,
    log_marginal_likelihood,
    train_gp,
    train_hyperparameters,
    training_scans,
)
from tests.test_mapping_core import random_beams


def problems(seed=0, q=6, n=10):
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(q, n, 2))
    y = np.where(X[..., 0] + 0.3 * rng.normal(size=(q, n)) > 0, 1.0, -1.0)
    return X, y


def test_lml_is_equation_9_summed_over_problems() -> None:
    X, y = problems()
    k = make_kernel("se", {"length_scale": 0.9})
    total = 0.0
    for Xi, yi in zip(X, y, strict=True):
        K = k(Xi) + 0.1 * np.eye(len(yi))
        fit = -0.5 * yi @ np.linalg.solve(K, yi)
        total += fit - 0.5 * np.linalg.slogdet(K)[1] - len(yi) / 2 * np.log(2 * np.pi)
    assert log_marginal_likelihood(k, X, y, 0.1) == pytest.approx(total, rel=1e-10)


@pytest.mark.parametrize("name", ["nn", "se", "matern32", "matern52"])
def test_lml_gradient_matches_finite_differences(name: str) -> None:
    X, y = problems(1)
    k = make_kernel(name)
    _, g = log_marginal_likelihood(k, X, y, 0.05, eval_gradient=True, noise_gradient=True)
    x = np.r_[k.theta, np.log(0.05)]
    eps = 1e-6
    for p in range(x.size):
        hi, lo = x.copy(), x.copy()
        hi[p] += eps
        lo[p] -= eps
        f = [log_marginal_likelihood(k.with_theta(z[:-1]), X, y, float(np.exp(z[-1]))) for z in (hi, lo)]
        assert g[p] == pytest.approx((f[0] - f[1]) / (2 * eps), rel=1e-4, abs=1e-6)


def test_training_increases_the_likelihood_and_respects_bounds() -> None:
    X, y = problems(2, q=10)
    k0 = make_kernel("se", {"length_scale": 20.0}, {"length_scale": (0.05, 50.0)})
    trained, nv, info = train_hyperparameters(k0, X, y, 0.1, maxfun=60, maxiter=50, seed=0)
    assert log_marginal_likelihood(trained, X, y, 0.1) > log_marginal_likelihood(k0, X, y, 0.1) + 1.0
    assert np.all((trained.theta >= k0.bounds[:, 0] - 1e-9) & (trained.theta <= k0.bounds[:, 1] + 1e-9))
    assert nv == 0.1 and info["anneal_evaluations"] >= 60


def test_loo_formulas_equal_explicit_leave_one_out() -> None:
    X, y = problems(3, q=2, n=8)
    k = make_kernel("nn")
    mu, var = loo_predictions(k, X, y, 0.05)
    for q in range(2):
        for i in range(8):
            keep = np.arange(8) != i
            K = k(X[q, keep]) + 0.05 * np.eye(7)
            ks = k(X[q, keep], X[q, i : i + 1])[:, 0]
            m = ks @ np.linalg.solve(K, y[q, keep])
            v = k.diag(X[q, i : i + 1])[0] + 0.05 - ks @ np.linalg.solve(K, ks)
            assert mu[q, i] == pytest.approx(m, rel=1e-8, abs=1e-10)
            assert var[q, i] == pytest.approx(v, rel=1e-8)


def test_loo_predictions_in_batches_equal_one_batch(monkeypatch) -> None:
    from mapping import pls
    from mapping.noisy_kernels import InputExpectation

    X, y = problems(4, q=11, n=8)
    rng = np.random.default_rng(4)
    A = rng.normal(scale=0.1, size=(11, 8, 2, 2))
    cov = A @ np.swapaxes(A, -1, -2) + 1e-3 * np.eye(2)
    k = make_kernel("se")
    whole = [loo_predictions(k, X, y, 0.05), loo_predictions(k, X, y, 0.05, cov, InputExpectation("girard"))]
    monkeypatch.setattr(pls, "LOO_CHUNK", 3)  # batches of 3, 3, 3 and 2 problems
    parts = [loo_predictions(k, X, y, 0.05), loo_predictions(k, X, y, 0.05, cov, InputExpectation("girard"))]
    for a, b in zip(whole, parts, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-14)


def test_compiled_girard_matrix_equals_the_batched_one() -> None:
    from mapping.noisy_kernels import InputExpectation, girard_se_matrix

    rng = np.random.default_rng(8)
    X = rng.normal(scale=0.5, size=(7, 12, 2))
    A = rng.normal(scale=0.1, size=(7, 12, 2, 2))
    cov = A @ np.swapaxes(A, -1, -2) + 1e-4 * np.eye(2)
    cov[..., 0, 1] += 1e-3  # an asymmetric input: both forms read its symmetric part
    k = make_kernel("se", {"sigma_f": 1.3, "length_scale": 0.4})
    ours = girard_se_matrix(k, X, cov)
    np.testing.assert_allclose(ours, InputExpectation("girard").matrix(k, X, cov), rtol=1e-12, atol=1e-15)
    np.testing.assert_array_equal(ours, np.swapaxes(ours, -1, -2))


def test_pls_fit_separates_and_link_has_the_square_root() -> None:
    rng = np.random.default_rng(0)
    y = np.where(rng.random(400) < 0.5, 1.0, -1.0)
    mu = 0.8 * y + 0.3 * rng.normal(size=400)
    var = np.full(400, 0.2)
    alpha, beta, _ = fit_pls(mu, var, y, caps=(None,))
    assert alpha > 1.0 and abs(beta / alpha) < 0.2  # the boundary mu = -beta / alpha lies near 0
    p = pls_probability(mu, var, alpha, beta)
    assert np.mean((p > 0.5) == (y > 0)) > 0.95
    # SPEC section 5: Phi((a mu + b) / sqrt(1 + a^2 var)), not eq. (10)'s (1 + a^2 var)
    from scipy.stats import norm

    assert pls_probability(1.0, 3.0, 2.0, 0.5) == pytest.approx(norm.cdf(2.5 / np.sqrt(13.0)))


def test_pls_link_gradient_and_hessian_match_finite_differences() -> None:
    from scipy import optimize, special

    from mapping.pls import _neg_loo_log_lik_st

    def _neg_loo_log_lik(params, mu, var, y):  # the link in (alpha, beta), as R&W eq. 6.42 writes it
        alpha, beta = params
        return -float(np.mean(special.log_ndtr(y * (alpha * mu + beta) / np.sqrt(1.0 + alpha**2 * var))))

    rng = np.random.default_rng(3)
    y = np.where(rng.random(500) < 0.3, 1.0, -1.0)
    mu = 0.7 * y + 0.4 * rng.normal(size=500)
    var = rng.uniform(0.01, 1.5, 500)
    for s, t in ((2.0, -0.6), (0.25, 0.2), (1e-3, 0.05)):
        value, g_s, g_t, h_ss, h_st, h_tt = _neg_loo_log_lik_st(s, t, mu, var, y)
        # the same likelihood as (alpha, beta) = (1 / s, t / s)
        assert value == pytest.approx(_neg_loo_log_lik(np.array([1 / s, t / s]), mu, var, y), rel=1e-12)
        numeric = optimize.approx_fprime(
            np.array([s, t]), lambda x: _neg_loo_log_lik_st(x[0], x[1], mu, var, y)[0], 1e-7
        )
        np.testing.assert_allclose([g_s, g_t], numeric, rtol=1e-4, atol=1e-8)
        hessian = optimize.approx_fprime(
            np.array([s, t]), lambda x: np.array(_neg_loo_log_lik_st(x[0], x[1], mu, var, y)[1:3]), 1e-7
        )
        np.testing.assert_allclose([[h_ss, h_st], [h_st, h_tt]], hessian, rtol=1e-4, atol=1e-7)


def test_compiled_log_ndtr_equals_scipy_over_its_whole_range() -> None:
    from scipy import special

    from mapping.pls import _neg_loo_log_lik_st

    z = np.r_[np.linspace(-80.0, 40.0, 4001), -37.0, -36.999, 0.0, 1e-9]
    # one point per call: the likelihood of mu = z, var = 1 - s^2 (r = 1), y = 1 is -log Phi(z)
    ours = np.array([-_neg_loo_log_lik_st(0.0, 0.0, np.array([v]), np.ones(1), np.ones(1))[0] for v in z])
    np.testing.assert_allclose(ours, special.log_ndtr(z), rtol=1e-10, atol=1e-300)


def test_pls_fit_reaches_the_scale_free_limit_and_scouts_large_sets() -> None:
    from mapping import pls

    # labels decided by the mean alone: the likelihood grows towards alpha -> inf at beta / alpha fixed
    rng = np.random.default_rng(5)
    y = np.where(rng.random(20_000) < 0.3, 1.0, -1.0)
    mu = 0.8 * y + 0.25 * rng.normal(size=y.size)
    var = np.full(y.size, 0.1)
    alpha, beta, _ = fit_pls(mu, var, y, caps=(None,))
    assert alpha == pytest.approx(1 / pls.LINK_BOUNDS[0][0])  # the bound of s = 1 / alpha
    assert abs(beta / alpha) < 0.1
    # the scouting on a subset finds the optimum that all four starts on all points find
    assert y.size > pls.SCOUT_POINTS
    full = min(pls._solve_link((1 / a0, 0.0), mu, var, y) for a0 in (0.5, 2.0, 8.0, 32.0))
    nll, _, _ = pls._fit_link(mu, var, y)
    assert nll == pytest.approx(full[0], abs=1e-9)


def test_pls_link_newton_fit_equals_a_quasi_newton_one() -> None:
    """The projected Newton fit reaches, from each start, the best optimum L-BFGS-B reaches from any of them
    with the same gradient: starts where the Hessian is indefinite or the slope flat (where L-BFGS-B may
    stop early), and optima inside the box or on the bound of s."""
    from scipy import optimize

    from mapping import pls

    def lbfgsb(start, mu, var, y):
        return optimize.minimize(
            lambda x: pls._neg_loo_log_lik_st(x[0], x[1], mu, var, y)[0],
            x0=np.array(start),
            jac=lambda x: np.array(pls._neg_loo_log_lik_st(x[0], x[1], mu, var, y)[1:3]),
            method="L-BFGS-B",
            bounds=pls.LINK_BOUNDS,
            options={"ftol": 1e-15, "gtol": 1e-11},
        )

    rng = np.random.default_rng(8)
    starts = ((2.0, 0.0), (0.125, 0.0), (50.0, 3.0))
    for spread, s_on_bound in ((1.2, False), (0.25, True)):  # overlapping classes; separated ones
        y = np.where(rng.random(3000) < 0.4, 1.0, -1.0)
        mu = 0.6 * y + spread * rng.normal(size=y.size)
        var = rng.uniform(0.01, 1.0, y.size)
        ref = min((lbfgsb(x0, mu, var, y) for x0 in starts), key=lambda r: r.fun)
        for x0 in starts:
            ours = pls._solve_link(x0, mu, var, y)
            assert ours[0] <= ref.fun + 1e-12
            np.testing.assert_allclose(ours[1:], ref.x, rtol=1e-4, atol=1e-6)
            assert (ours[1] == pls.LINK_BOUNDS[0][0]) == s_on_bound


def _saturated_links(rng: np.random.Generator, overshoot_is_evidence: bool) -> tuple[np.ndarray, ...]:
    """LOO means, variances and labels: a third of the points in the link's slope, the rest saturated at
    their label with an overshoot. ``overshoot_is_evidence``: the farther beyond -1 a free point's mean, the
    surer it is free; otherwise the overshoot is unrelated to the label and the points that are wrong (one in
    ten) overshoot as often as the right ones."""
    n = 3000
    y = np.where(rng.random(n) < 0.5, 1.0, -1.0)
    mu = 0.6 * y + 0.3 * rng.normal(size=n)
    sat = rng.random(n) < 2 / 3
    over = np.abs(rng.normal(scale=0.15, size=n))
    if overshoot_is_evidence:
        wrong = sat & (rng.random(n) < 0.2) & (over < 0.05)  # the errors sit at the label, never beyond it
    else:
        wrong = sat & (rng.random(n) < 0.1)
    side = np.where(wrong, -y, y)
    mu = np.where(sat, side * (1.0 + over), mu)
    return mu, np.full(n, 0.05), y


def test_pls_mean_cap_is_chosen_by_the_loo_likelihood() -> None:
    rng = np.random.default_rng(4)
    mu, var, y = _saturated_links(rng, overshoot_is_evidence=False)
    _, _, cap = fit_pls(mu, var, y)
    assert (
        cap is not None and cap <= 1.05
    )  # the overshoot is noise: read at the label, ranked by the variance
    _, _, paper = fit_pls(mu, var, y, caps=(None,))
    assert paper is None
    mu, var, y = _saturated_links(rng, overshoot_is_evidence=True)
    _, _, cap = fit_pls(mu, var, y)
    assert cap is None or cap >= 1.2  # the overshoot is evidence: kept
    # caps no leave-one-out mean reaches tie with no cap: the paper's link is kept, however the fits round
    inside = np.clip(mu, -0.99, 0.99)
    assert fit_pls(inside, var, y)[2] is None
    assert fit_pls(inside * (1 + 1e-12), var, y)[2] is None
    # the capped link reads a mean beyond the cap as the cap itself
    assert pls_probability(-1.3, 0.1, 4.0, 0.2, 1.0) == pls_probability(-1.0, 0.1, 4.0, 0.2)
    assert pls_probability(-1.3, 0.1, 4.0, 0.2) < pls_probability(-1.0, 0.1, 4.0, 0.2)


def test_train_gp_end_to_end_and_params_round_trip(tmp_path) -> None:
    beams = random_beams(8, n_scans=20)
    params = train_gp(beams, "nn", noise_var=0.1, n_scans=10, n_problems=12, maxfun=20, maxiter=10, seed=1)
    assert params.info["n_scans"] == 10 and params.alpha > 0
    path = tmp_path / "params.json"
    params.save(path)
    again = GPParams.load(path)
    assert again.kernel.name == "nn"
    np.testing.assert_allclose(again.kernel.theta, params.kernel.theta)
    assert (again.noise_var, again.alpha, again.beta, again.mean_cap) == (
        params.noise_var,
        params.alpha,
        params.beta,
        params.mean_cap,
    )


def test_bad_params_file(tmp_path) -> None:
    path = tmp_path / "p.json"
    path.write_text("{not json")
    with pytest.raises(ParamsFileError, match="cannot read"):
        GPParams.load(path)
    path.write_text(json.dumps({"format": "gpom-gp-params-1", "kernel": "nn"}))
    with pytest.raises(ParamsFileError, match="bad GP parameter file"):
        GPParams.load(path)
    good = train_gp(
        random_beams(8, n_scans=20), "se", noise_var=0.1, n_scans=10, n_problems=12, maxfun=20, maxiter=10
    )
    bad_cap = good.to_dict()
    bad_cap["pls"]["mean_cap"] = -1.0
    path.write_text(json.dumps(bad_cap))
    with pytest.raises(ParamsFileError, match="mean_cap"):
        GPParams.load(path)
    del bad_cap["pls"]["mean_cap"]  # a file written before the cap reads as uncapped
    path.write_text(json.dumps(bad_cap))
    assert GPParams.load(path).mean_cap is None
    path.write_text(json.dumps({"format": "other"}))
    with pytest.raises(ParamsFileError, match="not a GP parameter file"):
        GPParams.load(path)


def test_training_uses_train_free_margin_and_the_map_keeps_its_own() -> None:
    from mapping.build import MapBuilder
    from pipeline.config import MappingConfig

    def fit_params(beams, cfg, mapper):
        return MapBuilder.from_config(cfg, mapper).fit(beams)

    train = {"scans": 10, "problems": 12, "anneal_evaluations": 20, "lbfgs_iterations": 10}
    budget = {"pls": {"link": "loo"}}
    narrow = random_beams(8, n_scans=20)  # free segments stop 0.1 m short
    wide = narrow.with_free_margin(0.6)
    cfg = MappingConfig(free_space={"margin_m": 0.1}, train={**train, "free_margin_m": 0.6}, **budget)
    split = fit_params(narrow, cfg, mapper="gpfol")
    plain = fit_params(
        wide, MappingConfig(free_space={"margin_m": 0.6}, train=train, **budget), mapper="gpfol"
    )
    np.testing.assert_allclose(split.kernel.theta, plain.kernel.theta, rtol=1e-9)
    assert (split.alpha, split.beta) == pytest.approx((plain.alpha, plain.beta), rel=1e-9)
    same = fit_params(
        narrow, MappingConfig(free_space={"margin_m": 0.1}, train=train, **budget), mapper="gpfol"
    )
    assert not np.allclose(same.kernel.theta, split.kernel.theta, rtol=1e-3)


def test_training_scans_are_runs_of_consecutive_scans_spread_over_the_recording() -> None:
    ids = np.arange(0, 2000, 2)  # 1,000 distinct scans, not contiguous numbers
    np.testing.assert_array_equal(training_scans(ids, 50), ids[:50])  # one window: the first scans
    picked = training_scans(ids, 50, windows=10)
    assert picked.size == 50 and np.all(np.diff(picked) > 0) and np.isin(picked, ids).all()
    runs = np.split(picked, np.flatnonzero(np.diff(np.searchsorted(ids, picked)) > 1) + 1)
    assert [r.size for r in runs] == [5] * 10  # ten runs of five consecutive scans
    assert picked[0] == ids[0] and picked[-1] == ids[-1]  # from the first scan to the last
    np.testing.assert_array_equal(training_scans(ids[:30], 50, windows=10), ids[:30])  # fewer than asked: all
    assert training_scans(np.r_[ids, ids], 53, windows=7).size == 53  # duplicates and uneven runs


def test_train_gp_reads_the_scans_of_its_windows() -> None:
    beams = random_beams(4, n_scans=40)
    params = train_gp(beams, "se", n_scans=12, n_problems=16, maxfun=5, maxiter=5, windows=3)
    assert params.info["n_scans"] == 12 and params.info["windows"] == 3
    assert params.info["scans"] == [0, 39]


def test_the_link_is_fitted_on_more_problems_than_the_hyperparameters() -> None:
    from mapping.build import MapBuilder
    from pipeline.config import MappingConfig

    beams = random_beams(6, n_scans=30)
    kw = dict(n_scans=12, n_problems=16, maxfun=10, maxiter=10, seed=2)
    plain = train_gp(beams, "se", **kw)
    assert plain.info["link_problems"] == plain.info["problems"] == 16
    same = train_gp(beams, "se", link_problems=16, **kw)
    assert (same.alpha, same.beta, same.mean_cap) == (plain.alpha, plain.beta, plain.mean_cap)
    more = train_gp(beams, "se", link_problems=400, **kw)
    assert more.info["link_problems"] == 400 and more.info["problems"] == 16
    np.testing.assert_array_equal(more.kernel.theta, plain.kernel.theta)  # the link only
    assert (more.alpha, more.beta) != (plain.alpha, plain.beta)
    # GPPOL's extra problems carry their inputs' covariances through the configuration's key
    train = {"scans": 12, "problems": 16, "anneal_evaluations": 10, "lbfgs_iterations": 10}
    for n in (16, 120):
        cfg = MappingConfig(train=train, pls={"link": "loo", "loo_problems": n})
        params = MapBuilder.from_config(cfg, "gppol").fit(beams)
        assert params.info["link_problems"] == n and params.info["problems"] == 16
    # a link fitted on held-out scans keeps the leave-one-out link it replaces, fitted the same way
    cfg = MappingConfig(train=train, pls={"link": "loo", "loo_problems": 120})
    loo = MapBuilder.from_config(cfg, "gpfol").fit(beams)
    cfg = MappingConfig(train=train, pls={"link": "holdout", "loo_problems": 120})
    held = MapBuilder.from_config(cfg, "gpfol").fit(beams)
    assert held.info["pls"]["fit"] == "holdout" and held.info["link_problems"] == 120
    assert held.info["pls"]["loo"] == {"alpha": loo.alpha, "beta": loo.beta, "mean_cap": loo.mean_cap}
