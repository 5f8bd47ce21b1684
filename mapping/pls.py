"""Probabilistic least-squares classification (paper section 3.3, Rasmussen & Williams section 6.4).

The GP regression output is squashed through ``p(occ|x) = Phi((alpha mu + beta) / sqrt(1 + alpha^2 var))``
(R&W eq. 6.42; the paper's eq. (10) drops the square root, SPEC section 5). alpha and beta maximise the
leave-one-out likelihood, with the LOO mean and variance of eqs. (11)-(12).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy import optimize, special

from mapping.kernels import Kernel
from mapping.noisy_kernels import InputExpectation

FloatArray = NDArray[np.float64]


def loo_predictions(
    kernel: Kernel,
    X: FloatArray,
    y: FloatArray,
    noise_var: float,
    cov: FloatArray | None = None,
    expectation: InputExpectation | None = None,
) -> tuple[FloatArray, FloatArray]:
    """Leave-one-out mean (eq. 11) and variance (eq. 12) of every training point of a batch of local problems
    X (Q, n, 2), y (Q, n): ``mu_i = y_i - [K^-1 y]_i / [K^-1]_ii``, ``var_i = 1 / [K^-1]_ii``, with
    K including the noise variance (GPPOL: inputs N(X, cov (Q, n, 2, 2)), K integrated by ``expectation``).
    Returns two (Q, n) arrays."""
    if cov is None:
        K = kernel(X)
    else:
        K = (expectation or InputExpectation()).matrix(kernel, X, cov)
    K = K + noise_var * np.eye(X.shape[-2])
    Kinv = np.linalg.inv(K)
    d = np.einsum("...ii->...i", Kinv)
    a = np.einsum("...ij,...j->...i", Kinv, y)
    return y - a / d, 1.0 / d


def pls_probability(mean: FloatArray, var: FloatArray, alpha: float, beta: float) -> FloatArray:
    """p(occ) = Phi((alpha mu + beta) / sqrt(1 + alpha^2 var)) (R&W eq. 6.42)."""
    z = (alpha * np.asarray(mean) + beta) / np.sqrt(1.0 + alpha**2 * np.asarray(var))
    return special.ndtr(z)


def _neg_loo_log_lik(params: FloatArray, mu: FloatArray, var: FloatArray, y: FloatArray) -> float:
    alpha, beta = params
    z = y * (alpha * mu + beta) / np.sqrt(1.0 + alpha**2 * var)
    return -float(np.mean(special.log_ndtr(z)))


def fit_pls(mu: FloatArray, var: FloatArray, y: FloatArray) -> tuple[float, float]:
    """alpha > 0 and beta maximising the mean LOO log-likelihood ``log Phi(y (alpha mu + beta) /
    sqrt(1 + alpha^2 var))`` over all points (any shapes, broadcast together)."""
    mu, var, y = (np.asarray(a, dtype=np.float64).ravel() for a in np.broadcast_arrays(mu, var, y))
    best = None
    for a0 in (0.5, 2.0, 8.0):
        res = optimize.minimize(
            _neg_loo_log_lik,
            x0=np.array([a0, 0.0]),
            args=(mu, var, y),
            method="L-BFGS-B",
            bounds=[(1e-3, 1e3), (-20.0, 20.0)],
        )
        if best is None or res.fun < best.fun:
            best = res
    return float(best.x[0]), float(best.x[1])
