"""Kernels between Gaussian training inputs (paper section 3.6, eqs. 16-23; SPEC section 5).

A training input is ``x_i ~ N(rho_i, Sigma_i)`` (2-D, from the unscented transform, :mod:`mapping.unscented`);
a test point ``x*`` is deterministic. The GP of GPPOL uses

- ``K_ij = E[k(x_i, x_j)]`` for i != j over INDEPENDENT draws (eq. 17);
- ``K_ii = E[k(x_i, x_i)]`` under ONE draw (SPEC section 5; not the double integral of eq. 17, which would
  treat a point as two independent copies of itself). ``K_ii - E[k(x_i, x_i')]`` then acts as an
  input-dependent
  noise: a noisy input weighs less;
- ``k*_i = E[k(x*, x_i)]`` over the training input only.

Independence: beams of one scan share that scan's pose error, so their inputs are correlated; like the paper
(eq. 17) we treat every input as independent. Why: (1) the per-input Gaussians are all the core needs (no
pairwise cross-covariances per pair of the 15 + 15 neighbours, which mix beams of many scans); (2) for the
stationary kernels the pair integral of independent inputs is one 2-D integral over the difference
``x_i - x_j ~ N(rho_i - rho_j, Sigma_i + Sigma_j)``; (3) the error is on the safe side: two beams of one scan
are rigidly tied, so treating them as independent over-states their relative uncertainty (K loses some
correlation between them) but never the uncertainty of their position in the world, which is what the
cross-covariance with the query sees.

Methods:

- ``girard``: the squared exponential's closed form (Girard 2004, eq. 19), exact:
  ``k_n = sf^2 |I + (Sigma_i + Sigma_j) / l^2|^(-1/2) exp(-d^T (l^2 I + Sigma_i + Sigma_j)^-1 d / 2)``,
  ``d = rho_i - rho_j``; with a deterministic test point ``Sigma_j = 0``;
- ``gauss_hermite``: tensor-product Gauss-Hermite quadrature (eqs. 20-23) with ``level`` = eta nodes per input
  dimension (eta^2 per 2-D input; level 1 is the kernel at the means, i.e. GPFOL). Any kernel: the double
  sum of
  eq. (23) over the nodes ``phi = rho + sqrt(2) chol(Sigma) psi`` of both inputs (eta^4 terms per pair); a
  stationary kernel: the same integral as eta^2 nodes of the difference ``x_i - x_j`` (exact rewriting for
  independent inputs). Converges to eq. (19) for SE as the level rises (the paper's Figure 5; tested);
- ``sigma_points``: the same sums over a 5-node rule per input (the centre and +-sqrt(3) sigma on each axis,
  :func:`sigma_point_rule_2d`): 25 kernel evaluations per pair instead of the level-3 rule's 81.

Measured (``gppol_choices`` of ``bench``, and the two-platform / Intel runs of the GPPOL report): SE with
Girard's form is the fastest (about 50k queries per CPU second on the Intel map) and the default; the NN
kernel
needs quadrature (sigma points: about 15k per CPU second, Gauss-Hermite level 2: 30k, level 3: 7k) and, like
GPFOL's NN kernel, extrapolates walls into never-observed space.

:class:`InputExpectation` evaluates these on batches of local problems (numpy, with gradients w.r.t. the
kernel's log hyperparameters, for training); the compiled core (:mod:`mapping.core`) evaluates the same
formulas per query.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numba as nb
import numpy as np
from numpy.typing import NDArray

from mapping.core import _girard_se
from mapping.kernels import Kernel, SquaredExponentialKernel

FloatArray = NDArray[np.float64]

GIRARD = "girard"
GAUSS_HERMITE = "gauss_hermite"
SIGMA_POINTS = "sigma_points"
METHODS = (GIRARD, GAUSS_HERMITE, SIGMA_POINTS)


@lru_cache(maxsize=32)
def hermite_rule(level: int) -> tuple[FloatArray, FloatArray]:
    """Nodes psi_m (roots of H_eta) and weights w_m of eqs. (20)-(21):
    ``int e^(-psi^2) f ~ sum w_m f(psi_m)``."""
    if not 1 <= level <= 40:
        raise ValueError(f"Gauss-Hermite level must be in 1..40, got {level}")
    psi, w = np.polynomial.hermite.hermgauss(level)
    return psi, w


@lru_cache(maxsize=32)
def gauss_hermite_2d(level: int) -> tuple[FloatArray, FloatArray]:
    """(eta^2, 2) standard nodes ``sqrt(2) psi`` and (eta^2,) weights summing to 1 of the tensor rule for the
    expectation under N(0, I_2): ``E f(z) ~ sum_a w_a f(z_a)``; for N(rho, Sigma),
    ``rho + chol(Sigma) z_a``."""
    psi, w = hermite_rule(level)
    gx, gy = np.meshgrid(psi, psi, indexing="ij")
    nodes = np.sqrt(2.0) * np.stack([gx.ravel(), gy.ravel()], axis=1)
    weights = (w[:, None] * w[None, :]).ravel() / np.pi  # eq. (23): 1/pi normalises the 2-D rule
    return nodes, weights


@lru_cache(maxsize=4)
def sigma_point_rule_2d() -> tuple[FloatArray, FloatArray]:
    """The 5-node symmetric rule for E f(z), z ~ N(0, I_2): the centre (weight 1/3) and +-sqrt(3) on each axis
    (1/6 each) -- the sigma points of the unscented transform with ``n + kappa = 3`` (Julier's choice for a
    Gaussian), exact for polynomials of degree 3 and for the 4th moments along the axes. A sparse
    stand-in for the 9-node level-3 Gauss-Hermite rule (same nodes on the axes): 25 instead of 81 kernel
    evaluations per pair of inputs."""
    r = np.sqrt(3.0)
    nodes = np.array([[0.0, 0.0], [r, 0.0], [-r, 0.0], [0.0, r], [0.0, -r]])
    return nodes, np.array([1.0 / 3.0] + [1.0 / 6.0] * 4)


def rule_2d(method: str, level: int) -> tuple[FloatArray, FloatArray]:
    """Standard nodes (m, 2) and weights (m,) of ``method``'s 2-D rule (Girard's form needs none: level 1)."""
    if method == SIGMA_POINTS:
        return sigma_point_rule_2d()
    return gauss_hermite_2d(level if method == GAUSS_HERMITE else 1)


def chol2(cov: FloatArray) -> FloatArray:
    """Lower Cholesky factors of (..., 2, 2) positive SEMI-definite matrices (zero where a pivot vanishes)."""
    c = np.asarray(cov, dtype=np.float64)
    a, b, d = c[..., 0, 0], 0.5 * (c[..., 0, 1] + c[..., 1, 0]), c[..., 1, 1]
    l00 = np.sqrt(np.maximum(a, 0.0))
    safe = l00 > 1e-150
    l10 = np.where(safe, b / np.where(safe, l00, 1.0), 0.0)
    l11 = np.sqrt(np.maximum(d - l10 * l10, 0.0))
    z = np.zeros_like(l00)
    return np.stack([np.stack([l00, z], -1), np.stack([l10, l11], -1)], -2)


def girard_se(
    kernel: SquaredExponentialKernel, diff: FloatArray, cov: FloatArray, eval_gradient: bool = False
) -> FloatArray | tuple[FloatArray, FloatArray]:
    """Eq. (19): E[k(x_i - x_j)] for the SE kernel with ``x_i - x_j ~ N(diff, cov)``: (..., 2) means and
    (..., 2, 2) covariances (``Sigma_i + Sigma_j``, or ``Sigma_i`` against a deterministic point) -> (...,).

    With ``eval_gradient`` also the (..., 2) gradient w.r.t. (log sigma_f, log length_scale)."""
    sf, ell = kernel.values
    L = ell * ell
    d = np.asarray(diff, dtype=np.float64)
    c = np.asarray(cov, dtype=np.float64)
    a00 = L + c[..., 0, 0]
    a11 = L + c[..., 1, 1]
    a01 = 0.5 * (c[..., 0, 1] + c[..., 1, 0])
    det = a00 * a11 - a01 * a01  # |L I + S|; |I + S / L|^(-1/2) = L / sqrt(det)
    dx, dy = d[..., 0], d[..., 1]
    q = (dx * dx * a11 - 2.0 * dx * dy * a01 + dy * dy * a00) / det  # d^T (L I + S)^-1 d
    k = sf * sf * L / np.sqrt(det) * np.exp(-0.5 * q)
    if not eval_gradient:
        return k
    # d log k / d log l = 2 L (1/L - tr(A) / (2 det) + |A^-1 d|^2 / 2), A = L I + S
    vx = (a11 * dx - a01 * dy) / det
    vy = (a00 * dy - a01 * dx) / det
    dlog_l = 2.0 - L * (a00 + a11) / det + L * (vx * vx + vy * vy)
    return k, np.stack([2.0 * k, k * dlog_l], axis=-1)


def girard_se_matrix(kernel: SquaredExponentialKernel, X: FloatArray, cov: FloatArray) -> FloatArray:
    """K (Q, n, n) of :meth:`InputExpectation.matrix` for Girard's form without gradients or scans, compiled:
    eq. (19) between independent inputs N(X (Q, n, 2), cov (Q, n, 2, 2)) off the diagonal, k(0) on it. For
    the many leave-one-out problems of the PLS link (:func:`mapping.pls.loo_predictions`), where the batched
    numpy form spends its time on (Q, n, n, 2, 2) temporaries."""
    sf, ell = kernel.values
    X = np.ascontiguousarray(X, dtype=np.float64)
    cov = np.ascontiguousarray(cov, dtype=np.float64)
    out = np.empty((X.shape[0], X.shape[1], X.shape[1]))
    _girard_se_matrix(float(sf * sf), float(ell * ell), X, cov, out)
    return out


@nb.njit(cache=True, error_model="numpy")
def _girard_se_matrix(sf2: float, L: float, X: FloatArray, cov: FloatArray, out: FloatArray) -> None:
    for q in range(X.shape[0]):
        for i in range(X.shape[1]):
            out[q, i, i] = sf2
            for j in range(i + 1, X.shape[1]):
                s00 = cov[q, i, 0, 0] + cov[q, j, 0, 0]
                s11 = cov[q, i, 1, 1] + cov[q, j, 1, 1]
                s01 = 0.5 * ((cov[q, i, 0, 1] + cov[q, j, 0, 1]) + (cov[q, i, 1, 0] + cov[q, j, 1, 0]))
                dx = X[q, i, 0] - X[q, j, 0]
                dy = X[q, i, 1] - X[q, j, 1]
                k = sf2 * _girard_se(L, s00, s01, s11, dx, dy)  # the compiled core's eq. (19)
                out[q, i, j] = k
                out[q, j, i] = k


@dataclass(frozen=True)
class InputExpectation:
    """How a kernel is integrated over Gaussian training inputs: ``method`` (``girard``, SE only;
    ``gauss_hermite``, with ``level`` nodes per input dimension; ``sigma_points``, the 5-node rule of
    :func:`sigma_point_rule_2d`)."""

    method: str = GAUSS_HERMITE
    level: int = 3

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ValueError(f"unknown input expectation '{self.method}' (known: {', '.join(METHODS)})")
        hermite_rule(self.level)

    def rule(self) -> tuple[FloatArray, FloatArray]:
        """Standard 2-D nodes (m, 2) and weights (m,) summing to 1 (:func:`rule_2d`)."""
        return rule_2d(self.method, self.level)

    def check(self, kernel: Kernel) -> None:
        if self.method == GIRARD and not isinstance(kernel, SquaredExponentialKernel):
            raise ValueError(f"Girard's closed form (eq. 19) is for the SE kernel, not '{kernel.name}'")

    # -- training-training ------------------------------------------------------------------------------
    def matrix(
        self,
        kernel: Kernel,
        X: FloatArray,
        cov: FloatArray,
        eval_gradient: bool = False,
        local_cov: FloatArray | None = None,
        scans: NDArray | None = None,
    ) -> FloatArray | tuple[FloatArray, FloatArray]:
        """K (..., n, n) between inputs N(X (..., n, 2), cov (..., n, 2, 2)): independent draws off the
        diagonal (eq. 17), one draw on it (SPEC section 5); with ``eval_gradient`` also dK/dtheta
        (..., n, n, P).

        With ``scans`` (..., n) and ``local_cov`` (..., n, 2, 2), the covariances of the laser noise alone:
        two inputs of one scan share its pose error, and a rigid motion keeps their distance, so a
        stationary kernel integrates them over their laser noise only (the NN kernel, not invariant to
        rigid motions, keeps eq. 17)."""
        self.check(kernel)
        X = np.asarray(X, dtype=np.float64)
        cov = np.asarray(cov, dtype=np.float64)
        n = X.shape[-2]
        eye = np.eye(n, dtype=bool)
        if kernel.stationary:
            D = X[..., :, None, :] - X[..., None, :, :]
            S = cov[..., :, None, :, :] + cov[..., None, :, :, :]
            if scans is not None:
                lc = np.asarray(local_cov, dtype=np.float64)
                same = np.asarray(scans)[..., :, None] == np.asarray(scans)[..., None, :]
                S = np.where(same[..., None, None], lc[..., :, None, :, :] + lc[..., None, :, :, :], S)
            if self.method == GIRARD:
                out = girard_se(kernel, D, S, eval_gradient)
            else:
                out = _gh_difference(kernel, D, S, self.rule(), eval_gradient)
            # the diagonal, one draw: k(x, x) = k(0)
            k0 = kernel.of_difference(np.zeros((1, 2)), eval_gradient)
            if not eval_gradient:
                return np.where(eye, k0[0], out)
            return np.where(eye, k0[0][0], out[0]), np.where(eye[..., None], k0[1][0], out[1])
        return _gh_nodes_matrix(kernel, X, cov, self.rule(), eval_gradient)

    def diag(self, kernel: Kernel, X: FloatArray, cov: FloatArray) -> FloatArray:
        """(..., n) ``E[k(x_i, x_i)]`` under one draw."""
        X = np.asarray(X, dtype=np.float64)
        if kernel.stationary:
            return np.full(X.shape[:-1], kernel.of_difference(np.zeros(2)))
        nodes, w = self.nodes(X, cov)
        return np.einsum("a,...a->...", w, kernel.diag(nodes))

    # -- training-test ----------------------------------------------------------------------------------
    def cross(self, kernel: Kernel, X: FloatArray, cov: FloatArray, Z: FloatArray) -> FloatArray:
        """(..., n, m) ``E[k(x_i, z_j)]`` over the training inputs N(X (..., n, 2), cov) only, for
        deterministic test points Z (..., m, 2)."""
        self.check(kernel)
        X = np.asarray(X, dtype=np.float64)
        Z = np.asarray(Z, dtype=np.float64)
        cov = np.asarray(cov, dtype=np.float64)
        if kernel.stationary:
            D = X[..., :, None, :] - Z[..., None, :, :]
            S = np.broadcast_to(cov[..., :, None, :, :], (*D.shape, 2))
            if self.method == GIRARD:
                return girard_se(kernel, D, S)
            return _gh_difference(kernel, D, S, self.rule(), False)
        nodes, w = self.nodes(X, cov)  # (..., n, a, 2)
        lead = nodes.shape[:-3]
        n, a = nodes.shape[-3], nodes.shape[-2]
        Kn = kernel(nodes.reshape(*lead, n * a, 2), Z)  # (..., n a, m)
        return np.einsum("a,...am->...m", w, Kn.reshape(*lead, n, a, Z.shape[-2]))

    def nodes(self, X: FloatArray, cov: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Quadrature nodes (..., n, m, 2) of each input and the (m,) weights (eq. 23)."""
        z, w = self.rule()
        Lc = chol2(cov)
        return np.asarray(X)[..., None, :] + np.einsum("...pq,aq->...ap", Lc, z), w


def _gh_difference(
    kernel: Kernel, D: FloatArray, S: FloatArray, rule: tuple[FloatArray, FloatArray], eval_gradient: bool
) -> FloatArray | tuple[FloatArray, FloatArray]:
    """E[k(z)], z ~ N(D, S), by the 2-D rule ``(nodes, weights)`` (stationary kernels)."""
    z, w = rule
    nodes = D[..., None, :] + np.einsum("...pq,aq->...ap", chol2(S), z)
    if not eval_gradient:
        return np.einsum("a,...a->...", w, kernel.of_difference(nodes))
    k, g = kernel.of_difference(nodes, eval_gradient=True)
    return np.einsum("a,...a->...", w, k), np.einsum("a,...ap->...p", w, g)


def _gh_nodes_matrix(
    kernel: Kernel, X: FloatArray, cov: FloatArray, rule: tuple[FloatArray, FloatArray], eval_gradient: bool
) -> FloatArray | tuple[FloatArray, FloatArray]:
    """Eq. (23) for any kernel: K_ij = sum_ab w_a w_b k(phi_ia, phi_jb) (i != j), K_ii = sum_a w_a
    k(phi_ia, phi_ia)."""
    z, w = rule
    nodes = X[..., None, :] + np.einsum("...pq,aq->...ap", chol2(cov), z)  # (..., n, a, 2)
    lead = nodes.shape[:-3]
    n, a = nodes.shape[-3], nodes.shape[-2]
    flat = nodes.reshape(*lead, n * a, 2)
    eye = np.eye(n, dtype=bool)
    if eval_gradient:
        Kn, G = kernel(flat, eval_gradient=True)
    else:
        Kn = kernel(flat)
    Kn = Kn.reshape(*lead, n, a, n, a)
    K = np.einsum("a,b,...iajb->...ij", w, w, Kn)
    Kd = np.einsum("a,...iaia->...i", w, Kn)
    K = np.where(eye, Kd[..., :, None], K)
    if not eval_gradient:
        return K
    G = G.reshape(*lead, n, a, n, a, G.shape[-1])
    dK = np.einsum("a,b,...iajbp->...ijp", w, w, G)
    dKd = np.einsum("a,...iaiap->...ip", w, G)
    return K, np.where(eye[..., None], dKd[..., :, None, :], dK)
