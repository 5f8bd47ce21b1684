"""Probabilistic least-squares classification (paper section 3.3, Rasmussen & Williams section 6.4).

The GP regression output is squashed through ``p(occ|x) = Phi((alpha mu + beta) / sqrt(1 + alpha^2 var))``
(R&W eq. 6.42; the paper's eq. (10) drops the square root, SPEC section 5), mu capped at +-c (:func:`fit_pls`
says why). alpha, beta and c maximise the leave-one-out likelihood, with the LOO mean and variance of
eqs. (11)-(12).
"""

from __future__ import annotations

import math
from functools import lru_cache

import numba as nb
import numpy as np
from numpy.typing import NDArray
from scipy import special

from mapping.kernels import Kernel, SquaredExponentialKernel
from mapping.noisy_kernels import GIRARD, InputExpectation, girard_se_matrix

FloatArray = NDArray[np.float64]


#: Local problems per batch of :func:`loo_predictions`.
LOO_CHUNK = 256


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
    if X.shape[0] > LOO_CHUNK:  # bounded temporaries (GPPOL: (n, n, 2, 2) per problem) run faster
        parts = [
            loo_predictions(
                kernel,
                X[i : i + LOO_CHUNK],
                y[i : i + LOO_CHUNK],
                noise_var,
                None if cov is None else cov[i : i + LOO_CHUNK],
                expectation,
            )
            for i in range(0, X.shape[0], LOO_CHUNK)
        ]
        return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])
    expectation = expectation or InputExpectation()
    if cov is None:
        K = kernel(X)
    elif expectation.method == GIRARD and isinstance(kernel, SquaredExponentialKernel):
        K = girard_se_matrix(kernel, X, cov)  # the same K, compiled
    else:
        K = expectation.matrix(kernel, X, cov)
    K = K + noise_var * np.eye(X.shape[-2])
    Kinv = np.linalg.inv(K)
    d = np.einsum("...ii->...i", Kinv)
    a = np.einsum("...ij,...j->...i", Kinv, y)
    return y - a / d, 1.0 / d


#: The caps the link's mean may take (:func:`fit_pls`, None: uncapped, the paper's link).
MEAN_CAPS = (1.0, 1.02, 1.05, 1.1, 1.2, 1.5, None)
#: Mean LOO negative log-likelihoods closer than this are a tie (:func:`fit_pls`).
CAP_TIE_NLL = 1e-6


def capped_mean(mean: FloatArray, mean_cap: float | None) -> FloatArray:
    """The GP mean the link reads: clipped to [-mean_cap, mean_cap] (None: as it is)."""
    m = np.asarray(mean, dtype=np.float64)
    return m if mean_cap is None else np.clip(m, -mean_cap, mean_cap)


def pls_probability(
    mean: FloatArray, var: FloatArray, alpha: float, beta: float, mean_cap: float | None = None
) -> FloatArray:
    """p(occ) = Phi((alpha mu + beta) / sqrt(1 + alpha^2 var)) (R&W eq. 6.42), mu capped by ``mean_cap``
    (:func:`capped_mean`)."""
    z = (alpha * capped_mean(mean, mean_cap) + beta) / np.sqrt(1.0 + alpha**2 * np.asarray(var))
    return special.ndtr(z)


_HALF_LOG_2PI = 0.5 * math.log(2.0 * math.pi)


@nb.njit(cache=True, error_model="numpy", inline="always")
def _log_ndtr(z: float) -> float:
    """log Phi(z), as ``scipy.special.log_ndtr``: log1p of the upper tail above 0, from erfc down to
    z = -37 (erfc of 26 is still a normal double, and C's erfc is accurate relative to its value), below by
    the asymptotic series of Mills' ratio (Abramowitz & Stegun 26.2.12, four terms)."""
    if z > 0.0:
        return math.log1p(-0.5 * math.erfc(z / math.sqrt(2.0)))
    if z > -37.0:
        return math.log(0.5 * math.erfc(-z / math.sqrt(2.0)))
    w = 1.0 / (z * z)
    return -0.5 * z * z - math.log(-z) - _HALF_LOG_2PI + math.log1p(w * (-1.0 + w * (3.0 - 15.0 * w)))


@nb.njit(cache=True, error_model="numpy")
def _neg_loo_log_lik_st(
    s: float, t: float, mu: FloatArray, var: FloatArray, y: FloatArray
) -> tuple[float, float, float, float, float, float]:
    """The mean negative LOO log-likelihood ``-log Phi(y (alpha mu + beta) / sqrt(1 + alpha^2 var))`` in the
    link's scale-free form ``Phi((mu + t) / sqrt(s^2 + var))`` (``s = 1 / alpha``, ``t = beta / alpha``),
    its gradient (d/ds, d/dt) and Hessian (ss, st, tt), in one pass over the points. In (alpha, beta) the
    likelihood of well-separated data runs along a flat ridge towards alpha -> inf with beta / alpha
    fixed; in (s, t) that limit is the ordinary point s -> 0.

    Per point, with ``z = y (mu + t) / r``, ``r^2 = s^2 + var`` and ``lam = N(z) / Phi(z)``:
    ``d(-log Phi)/dz = -lam``, ``d^2/dz^2 = lam (z + lam)``; ``z_t = y / r``, ``z_s = -z s / r^2``,
    ``z_st = -z_t s / r^2``, ``z_ss = z (3 s^2 / r^2 - 1) / r^2``."""
    n = mu.size
    f = 0.0
    g_s = 0.0
    g_t = 0.0
    h_ss = 0.0
    h_st = 0.0
    h_tt = 0.0
    for i in range(n):
        r2 = s * s + var[i]
        r = math.sqrt(r2)
        z = y[i] * (mu[i] + t) / r
        log_phi = _log_ndtr(z)
        lam = math.exp(-0.5 * z * z - _HALF_LOG_2PI - log_phi)  # N(z) / Phi(z)
        curv = lam * (z + lam)
        z_s = -z * s / r2
        z_t = y[i] / r
        f -= log_phi
        g_s -= lam * z_s
        g_t -= lam * z_t
        h_ss += curv * z_s * z_s - lam * z * (3.0 * s * s / r2 - 1.0) / r2
        h_st += curv * z_s * z_t + lam * z_t * s / r2
        h_tt += curv * z_t * z_t
    return f / n, g_s / n, g_t / n, h_ss / n, h_st / n, h_tt / n


#: Bounds of the link's (s, t) = (1 / alpha, beta / alpha) (:func:`_neg_loo_log_lik_st`).
LINK_BOUNDS = ((1e-3, 1e3), (-5.0, 5.0))
#: :func:`_newton_link` stops when the projected gradient's largest entry is below this, when a step
#: lowers the objective by less than :data:`LINK_FTOL` relative, or after :data:`LINK_MAX_STEPS` steps.
LINK_GTOL = 1e-10
LINK_FTOL = 1e-14
LINK_MAX_STEPS = 100


@nb.njit(cache=True, error_model="numpy")
def _newton_link(
    s: float, t: float, mu: FloatArray, var: FloatArray, y: FloatArray, bounds: FloatArray
) -> tuple[float, float, float]:
    """(objective, s, t) at the minimum of :func:`_neg_loo_log_lik_st` in the box ``bounds`` ((lo_s, hi_s,
    lo_t, hi_t)) reached from (s, t) by projected Newton steps: a variable at a bound its gradient pushes
    against stays there, the Hessian is shifted to positive definite where it is not (Levenberg), and each
    step is halved until it lowers the objective enough (Armijo). Two parameters and an analytic Hessian:
    a few passes over the points, where a quasi-Newton method needs tens."""
    lo_s, hi_s, lo_t, hi_t = bounds[0], bounds[1], bounds[2], bounds[3]
    s = min(max(s, lo_s), hi_s)
    t = min(max(t, lo_t), hi_t)
    f, g_s, g_t, h_ss, h_st, h_tt = _neg_loo_log_lik_st(s, t, mu, var, y)
    for _ in range(LINK_MAX_STEPS):
        fixed_s = (s <= lo_s and g_s > 0.0) or (s >= hi_s and g_s < 0.0)
        fixed_t = (t <= lo_t and g_t > 0.0) or (t >= hi_t and g_t < 0.0)
        p_s = 0.0 if fixed_s else g_s
        p_t = 0.0 if fixed_t else g_t
        if max(abs(p_s), abs(p_t)) <= LINK_GTOL:
            break
        # Newton direction on the free variables; a negative eigenvalue of the Hessian is shifted to its
        # absolute value, so that the step is as long as the curvature says, not thrown to a bound
        trace = (0.0 if fixed_s else h_ss) + (0.0 if fixed_t else h_tt)
        if fixed_s or fixed_t:
            lowest = trace
        else:
            half = 0.5 * trace
            lowest = half - math.sqrt(max(half * half - (h_ss * h_tt - h_st * h_st), 0.0))
        shift = 2.0 * max(0.0, -lowest) + 1e-9 * abs(trace) + 1e-300
        a = h_ss + shift
        c = h_tt + shift
        if fixed_s:
            d_s, d_t = 0.0, -p_t / c
        elif fixed_t:
            d_s, d_t = -p_s / a, 0.0
        else:
            det = a * c - h_st * h_st
            d_s = -(c * p_s - h_st * p_t) / det
            d_t = -(a * p_t - h_st * p_s) / det
        step = 1.0
        accepted = False
        for _ in range(60):
            s1 = min(max(s + step * d_s, lo_s), hi_s)
            t1 = min(max(t + step * d_t, lo_t), hi_t)
            f1, g_s1, g_t1, h_ss1, h_st1, h_tt1 = _neg_loo_log_lik_st(s1, t1, mu, var, y)
            if f1 <= f + 1e-4 * (g_s * (s1 - s) + g_t * (t1 - t)):
                accepted = True
                break
            step *= 0.5
        if not accepted:
            break
        small = f - f1 <= LINK_FTOL * max(1.0, abs(f))
        s, t, f, g_s, g_t, h_ss, h_st, h_tt = s1, t1, f1, g_s1, g_t1, h_ss1, h_st1, h_tt1
        if small:
            break
    return f, s, t


def fit_pls(
    mu: FloatArray, var: FloatArray, y: FloatArray, caps: tuple[float | None, ...] = MEAN_CAPS
) -> tuple[float, float, float | None]:
    """alpha > 0, beta and the mean's cap (one of ``caps``) maximising the mean LOO log-likelihood
    ``log Phi(y (alpha mu_c + beta) / sqrt(1 + alpha^2 var))``, mu_c = :func:`capped_mean` (any shapes,
    broadcast together).

    Why a cap: the GP regresses labels of -1 and +1, and its mean overshoots them (beyond -1 beside dense
    free space, beyond +1 inside walls). Read as it is, the link ranks an overshoot as surer than the label
    itself, an artefact of least-squares classification (it penalises predictions "too correct", Bishop
    2006, section 4.1.3); capped, the variance ranks those points instead. Whether the overshoot carries
    evidence differs by recording; the leave-one-out likelihood decides, as it decides alpha and beta
    (eq. 10), and None (the paper's link) is always a candidate. Caps the likelihood cannot tell apart
    (within :data:`CAP_TIE_NLL`, e.g. when no leave-one-out mean reaches them) go to the largest of them,
    so the choice neither rests on the optimiser's last digits nor caps where the data do not ask for it."""
    mu, var, y = (np.asarray(a, dtype=np.float64).ravel() for a in np.broadcast_arrays(mu, var, y))
    fits = [(*_fit_link(capped_mean(mu, cap), var, y), cap) for cap in caps]
    least = min(f[0] for f in fits)
    tied = [f for f in fits if f[0] <= least + CAP_TIE_NLL]
    _, alpha, beta, cap = max(tied, key=lambda f: math.inf if f[3] is None else f[3])
    return alpha, beta, cap


#: Above this many points, :func:`_fit_link` compares its starts on a random subset of this many.
SCOUT_POINTS = 8192


def _fit_link(mu: FloatArray, var: FloatArray, y: FloatArray) -> tuple[float, float, float]:
    """(mean negative LOO log-likelihood, alpha, beta) of the best of four starts in (s, t), each run to
    convergence by :func:`_newton_link`: :func:`fit_pls` compares these likelihoods across caps, and a
    fit stopped early would decide the choice. With more than :data:`SCOUT_POINTS` points the starts run
    on a random subset of that many and only the best goes on to all."""
    starts = [(1.0 / a0, 0.0) for a0 in (0.5, 2.0, 8.0, 32.0)]
    if mu.size > SCOUT_POINTS:
        few = _scout_indices(mu.size)
        scouts = [_solve_link(x0, mu[few], var[few], y[few]) for x0 in starts]
        starts = [min(scouts)[1:]]
    nll, s, t = min(_solve_link(x0, mu, var, y) for x0 in starts)
    return nll, 1.0 / s, t / s


@lru_cache(maxsize=4)
def _scout_indices(n: int) -> NDArray[np.int64]:
    """The sorted indices (SCOUT_POINTS,) of :func:`_fit_link`'s scouting subset of ``n`` points, drawn
    once per size (every cap of :func:`fit_pls` scouts on the same points): a fixed random subset, where a
    stride would keep the same neighbours of every local problem. Read-only."""
    few = np.sort(np.random.default_rng(0).choice(n, SCOUT_POINTS, replace=False))
    few.flags.writeable = False
    return few


#: :data:`LINK_BOUNDS` as :func:`_newton_link` reads them: (lo_s, hi_s, lo_t, hi_t).
_LINK_BOUNDS_FLAT = np.array(LINK_BOUNDS, dtype=np.float64).ravel()


def _solve_link(
    start_st: tuple[float, float], mu: FloatArray, var: FloatArray, y: FloatArray
) -> tuple[float, float, float]:
    """(objective, s, t) of one fit of the link from ``start_st`` within :data:`LINK_BOUNDS`."""
    f, s, t = _newton_link(float(start_st[0]), float(start_st[1]), mu, var, y, _LINK_BOUNDS_FLAT)
    return float(f), float(s), float(t)
