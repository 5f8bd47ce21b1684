"""Kernels between Gaussian inputs: Girard's closed form (eq. 19), Gauss-Hermite quadrature (eqs. 20-23), the
one-draw diagonal and the deterministic test point of SPEC section 5."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from mapping.kernels import make_kernel
from mapping.noisy_kernels import (
    GAUSS_HERMITE,
    GIRARD,
    InputExpectation,
    _gh_nodes_matrix,
    gauss_hermite_2d,
    girard_se,
    hermite_rule,
)

SE = make_kernel("se", {"sigma_f": 1.3, "length_scale": 0.5})
NN = make_kernel("nn", {"sigma_f": 1.0, "sigma_0": 2.0, "sigma": 3.0})
M32 = make_kernel("matern32", {"sigma_f": 0.9, "length_scale": 0.7})


def random_inputs(seed: int = 0, n: int = 6, scale: float = 0.3):
    rng = np.random.default_rng(seed)
    X = rng.uniform(-1, 1, (n, 2))
    A = rng.normal(size=(n, 2, 2)) * scale
    return X, A @ A.transpose(0, 2, 1)


def mc_pair(kernel, rho_i, cov_i, rho_j, cov_j, n=400_000, seed=3):
    rng = np.random.default_rng(seed)
    xi = rho_i + rng.normal(size=(n, 2)) @ np.linalg.cholesky(cov_i).T
    xj = rho_j + rng.normal(size=(n, 2)) @ np.linalg.cholesky(cov_j).T
    k = kernel(xi[:, None, :], xj[:, None, :])[:, 0, 0]
    return k.mean(), k.std() / np.sqrt(n)


def test_hermite_rule_integrates_polynomials() -> None:
    psi, w = hermite_rule(5)  # exact for degree <= 9: int e^(-x^2) x^4 = 3 sqrt(pi) / 4
    assert np.sum(w * psi**4) == pytest.approx(3 * np.sqrt(np.pi) / 4, rel=1e-12)
    z, wz = gauss_hermite_2d(4)
    assert wz.sum() == pytest.approx(1.0) and z.shape == (16, 2)
    np.testing.assert_allclose(np.einsum("a,ai,aj->ij", wz, z, z), np.eye(2), atol=1e-12)  # N(0, I) moments
    with pytest.raises(ValueError):
        hermite_rule(0)


def test_girard_matches_monte_carlo() -> None:
    X, cov = random_inputs()
    K = InputExpectation(GIRARD).matrix(SE, X, cov)
    mc, err = mc_pair(SE, X[0], cov[0], X[1], cov[1])
    assert K[0, 1] == pytest.approx(mc, abs=4 * err)
    ks = InputExpectation(GIRARD).cross(SE, X, cov, np.zeros((1, 2)))
    mc, err = mc_pair(SE, X[2], cov[2], np.zeros(2), 1e-30 * np.eye(2))
    assert ks[2, 0] == pytest.approx(mc, abs=4 * err)


def test_gauss_hermite_converges_to_girard_as_the_level_rises() -> None:
    """The paper's Figure 5: SE between a point and a Gaussian of variance 0, 0.2, ..., 1 along a line of
    offsets; the quadrature error falls as the level rises and vanishes at high levels."""
    offsets = np.linspace(-3, 3, 61)
    kernel = make_kernel("se", {"sigma_f": 1.0, "length_scale": 1.0})
    errors = {}
    for level in (1, 2, 3, 5, 8, 13, 20):
        worst = 0.0
        for var in (0.0, 0.2, 0.4, 0.6, 0.8, 1.0):
            D = np.c_[offsets, np.zeros_like(offsets)]
            S = np.broadcast_to(var * np.eye(2), (offsets.size, 2, 2))
            exact = girard_se(kernel, D, S)
            gh = InputExpectation(GAUSS_HERMITE, level).cross(
                kernel, D[:, None, :], S[:, None], np.zeros((offsets.size, 1, 2))
            )[:, 0, 0]
            worst = max(worst, float(np.abs(gh - exact).max()))
            if var == 0.0:
                np.testing.assert_allclose(gh, exact, atol=1e-14)  # a point: every level is exact
        errors[level] = worst
    levels = sorted(errors)
    assert all(errors[a] > errors[b] for a, b in itertools.pairwise(levels))
    assert errors[1] > 0.1 and errors[20] < 1e-4
    # eq. (23) literally, with the nodes of both inputs (eta^4 terms), converges to the same value
    X, cov = random_inputs(1)
    exact = InputExpectation(GIRARD).matrix(kernel, X, cov)
    lit = [
        np.abs(_gh_nodes_matrix(kernel, X, cov, gauss_hermite_2d(lv), False) - exact).max()
        for lv in (2, 4, 8, 12)
    ]
    assert all(a > b for a, b in itertools.pairwise(lit)) and lit[-1] < 1e-4


def test_gauss_hermite_nn_kernel_matches_monte_carlo() -> None:
    """The NN kernel has a cusp where two inputs coincide (asin at 1), so the quadrature converges more
    slowly than for SE where two input distributions overlap (pair 0-3 here) -- but it converges."""
    X, cov = random_inputs(2)
    K = {lv: InputExpectation(GAUSS_HERMITE, lv).matrix(NN, X, cov) for lv in (2, 4, 12, 32)}
    err = [np.abs(K[lv] - K[32]).max() for lv in (2, 4, 12)]
    assert err[0] > err[1] > err[2] and err[2] < 2e-3
    for i, j in ((0, 1), (0, 3)):
        mc, se = mc_pair(NN, X[i], cov[i], X[j], cov[j])
        assert K[32][i, j] == pytest.approx(mc, abs=4 * se + 1e-4)
    ks = InputExpectation(GAUSS_HERMITE, 12).cross(NN, X, cov, np.array([[0.2, -0.1]]))
    mc, err = mc_pair(NN, X[3], cov[3], np.array([0.2, -0.1]), 1e-30 * np.eye(2))
    assert ks[3, 0] == pytest.approx(mc, abs=4 * err + 1e-4)


def test_the_diagonal_is_one_draw_not_two() -> None:
    """K_ii = E[k(x, x)] (SPEC section 5): SE gives sf^2; NN its one-draw expectation, which is larger than
    the double integral of eq. (17) (two independent copies of the input)."""
    X, cov = random_inputs(3)
    K = InputExpectation(GIRARD).matrix(SE, X, cov)
    np.testing.assert_allclose(np.diag(K), SE.values[0] ** 2)
    two_draws = girard_se(SE, np.zeros((6, 2)), 2 * cov)
    assert np.all(two_draws < np.diag(K) - 1e-3)
    ex = InputExpectation(GAUSS_HERMITE, 12)
    Kn = ex.matrix(NN, X, cov)
    rng = np.random.default_rng(4)
    x = X[0] + rng.normal(size=(400_000, 2)) @ np.linalg.cholesky(cov[0]).T
    one = NN.diag(x)
    assert Kn[0, 0] == pytest.approx(one.mean(), abs=4 * one.std() / 633 + 1e-4)
    np.testing.assert_allclose(np.diag(Kn), ex.diag(NN, X, cov), rtol=1e-12)
    two, err = mc_pair(NN, X[0], cov[0], X[0], cov[0])
    assert Kn[0, 0] > two + 10 * err


@pytest.mark.parametrize(
    ("kernel", "method"), [(SE, GIRARD), (SE, GAUSS_HERMITE), (M32, GAUSS_HERMITE), (NN, GAUSS_HERMITE)]
)
def test_exact_inputs_reduce_to_the_point_kernel_and_k_is_psd(kernel, method) -> None:
    X, cov = random_inputs(5, n=8)
    ex = InputExpectation(method, 3)
    np.testing.assert_allclose(ex.matrix(kernel, X, np.zeros_like(cov)), kernel(X), atol=1e-12)
    Z = np.array([[0.0, 0.0], [0.5, 0.1]])
    np.testing.assert_allclose(ex.cross(kernel, X, np.zeros_like(cov), Z), kernel(X, Z), atol=1e-12)
    K = ex.matrix(kernel, X, cov)
    np.testing.assert_allclose(K, K.T, atol=1e-14)
    assert np.linalg.eigvalsh(K).min() > -1e-10
    # uncertain inputs weigh less: K shrinks off the diagonal
    off = ~np.eye(8, dtype=bool)
    assert np.abs(K[off]).sum() < np.abs(kernel(X)[off]).sum()


@pytest.mark.parametrize(
    ("kernel", "method"), [(SE, GIRARD), (SE, GAUSS_HERMITE), (M32, GAUSS_HERMITE), (NN, GAUSS_HERMITE)]
)
def test_gradients_match_finite_differences(kernel, method) -> None:
    X, cov = random_inputs(6)
    X = np.stack([X, X[::-1] * 0.7])  # a batch of two local problems
    cov = np.stack([cov, cov[::-1]])
    ex = InputExpectation(method, 3)
    _, G = ex.matrix(kernel, X, cov, eval_gradient=True)
    th = kernel.theta
    for p in range(th.size):
        h = np.zeros_like(th)
        h[p] = 1e-6
        num = (
            ex.matrix(kernel.with_theta(th + h), X, cov) - ex.matrix(kernel.with_theta(th - h), X, cov)
        ) / 2e-6
        np.testing.assert_allclose(G[..., p], num, rtol=1e-5, atol=1e-8)


def test_girard_is_for_the_squared_exponential_only() -> None:
    X, cov = random_inputs()
    with pytest.raises(ValueError, match="SE kernel"):
        InputExpectation(GIRARD).matrix(NN, X, cov)
    with pytest.raises(ValueError, match="unknown input expectation"):
        InputExpectation("simpson")
