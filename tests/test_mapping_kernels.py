"""Kernel battery, run over every kernel: symmetry, PSD, diag, gradients vs finite differences, bounds."""

from __future__ import annotations

import numpy as np
import pytest

from mapping.kernels import KERNELS, NeuralNetworkKernel, make_kernel

RNG = np.random.default_rng(7)
X = RNG.normal(scale=2.0, size=(25, 2))
Y = RNG.normal(scale=2.0, size=(9, 2))
NON_DEFAULT = {
    "nn": {"sigma_f": 1.3, "sigma_0": 4.0, "sigma": 9.0},
    "se": {"sigma_f": 0.7, "length_scale": 0.8},
    "matern32": {"sigma_f": 1.7, "length_scale": 1.4},
    "matern52": {"sigma_f": 0.4, "length_scale": 0.3},
}


@pytest.fixture(params=sorted(KERNELS))
def kernel(request):
    return make_kernel(request.param, NON_DEFAULT[request.param])


def test_symmetric_and_positive_semidefinite(kernel) -> None:
    K = kernel(X)
    assert K.shape == (25, 25)
    np.testing.assert_allclose(K, K.T, rtol=0, atol=1e-12)
    assert np.linalg.eigvalsh(K).min() > -1e-9 * np.abs(K).max()


def test_cross_covariance_matches_joint_block(kernel) -> None:
    joint = kernel(np.vstack([X, Y]))
    np.testing.assert_allclose(kernel(X, Y), joint[:25, 25:], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(kernel(Y, X), kernel(X, Y).T, rtol=1e-12, atol=1e-12)


def test_diag_equals_diagonal(kernel) -> None:
    np.testing.assert_allclose(kernel.diag(X), np.diag(kernel(X)), rtol=1e-12, atol=1e-12)


def test_batched_call_equals_loop(kernel) -> None:
    batch = RNG.normal(size=(4, 6, 2))
    K = kernel(batch)
    for b in range(4):
        np.testing.assert_allclose(K[b], kernel(batch[b]), rtol=1e-12, atol=1e-14)


def test_analytic_gradient_matches_finite_differences(kernel) -> None:
    _, grad = kernel(X[:8], eval_gradient=True)
    theta = kernel.theta
    eps = 1e-6
    for p in range(theta.size):
        step = np.zeros_like(theta)
        step[p] = eps
        num = (kernel.with_theta(theta + step)(X[:8]) - kernel.with_theta(theta - step)(X[:8])) / (2 * eps)
        np.testing.assert_allclose(grad[..., p], num, rtol=1e-5, atol=1e-8)


def test_theta_round_trip_and_bounds(kernel) -> None:
    again = kernel.with_theta(kernel.theta)
    assert again.values == pytest.approx(kernel.values)
    b = kernel.bounds
    assert b.shape == (len(kernel.names), 2)
    assert np.all(b[:, 0] < b[:, 1])
    assert np.all((kernel.theta >= b[:, 0]) & (kernel.theta <= b[:, 1]))


def test_gp_variance_never_exceeds_prior(kernel) -> None:
    """Posterior variance (eq. 3) is between 0 and the prior variance k(x*, x*)."""
    noise = 1e-2
    K = kernel(X) + noise * np.eye(25)
    ks = kernel(X, Y)
    prior = kernel.diag(Y)
    post = prior - np.einsum("ij,ij->j", ks, np.linalg.solve(K, ks))
    assert np.all(post <= prior + 1e-12)
    assert np.all(post >= -1e-9)


def test_nn_kernel_is_equation_7() -> None:
    k = NeuralNetworkKernel((1.5, 2.0, 3.0))
    x, y = np.array([0.3, -1.2]), np.array([2.0, 0.5])
    S = np.diag([2.0**2, 3.0**2, 3.0**2])
    xt, yt = np.r_[1.0, x], np.r_[1.0, y]
    ref = 1.5**2 * np.arcsin(2 * xt @ S @ yt / np.sqrt((1 + 2 * xt @ S @ xt) * (1 + 2 * yt @ S @ yt)))
    assert k(x[None], y[None])[0, 0] == pytest.approx(ref, rel=1e-13)


def test_bad_hyperparameters_are_rejected() -> None:
    with pytest.raises(ValueError, match="must be finite and > 0"):
        make_kernel("se", {"length_scale": -1.0})
    with pytest.raises(ValueError, match="unknown kernel"):
        make_kernel("rbf2")
    with pytest.raises(ValueError, match="no hyperparameter"):
        make_kernel("se", {"sigma": 1.0})
