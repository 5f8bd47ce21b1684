"""Compiled local-GP prediction (eqs. 2-3) for many query points at once, parallel over queries.

For each query ``x*`` (section 3.7): the ``k_occ`` nearest occupied endpoints (+1) and the ``k_free`` nearest
free beam segments, each giving its point closest to ``x*`` (-1, eqs. 13-14); then a local GP on these
``n <= k_occ + k_free`` training points, in coordinates centred on the query, solved by a float64 Cholesky
of ``K + sigma_n^2 I`` (jitter added and the factorisation retried if it fails), and the PLS link
``p = Phi((alpha mu + beta) / sqrt(1 + alpha^2 (sigma^2 + sigma_n^2)))`` (SPEC section 5, R&W eq. 6.42).

Seams for GPPOL (issue 5): the per-query work is split into
neighbour search (:func:`mapping.index.knn_points`, :func:`mapping.index.knn_segments`: ids, and the
position ``t`` of each free point along its beam),
``_training_inputs`` (training point means, centred on the query; GPPOL adds their 2x2 covariances here),
``_kernel_blocks`` (``K`` between training points, ``k*`` between training points and the query, ``k**``;
GPPOL swaps these for the kernels integrated over the training input distributions) and
``_solve_local`` (Cholesky, mean, variance). A GPPOL driver reuses the neighbour search and
``_solve_local``, and replaces the two middle steps.

Kernel ids and packed parameters (see :meth:`mapping.kernels.Kernel.packed`):
0 neural network (eq. 7): ``(sf2, 2 sigma_0^2, 2 sigma^2)``; 1 squared exponential: ``(sf2, 1/l^2)``;
2 Matern 3/2: ``(sf2, sqrt(3)/l)``; 3 Matern 5/2: ``(sf2, sqrt(5)/l)``.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from mapping.index import knn_points, knn_segments

KERNEL_NN = 0
KERNEL_SE = 1
KERNEL_MATERN32 = 2
KERNEL_MATERN52 = 3

SQRT2 = math.sqrt(2.0)


@nb.njit(cache=True, fastmath=False, inline="always")
def _phi(z):
    """Standard normal CDF."""
    return 0.5 * math.erfc(-z / SQRT2)


@nb.njit(cache=True, fastmath=True)
def _kernel_blocks(kid, kp, X, n, K, ks, s):
    """Fill K[:n, :n] (upper and lower) and ks[:n] for training inputs X[:n] (centred on the query, which is
    the origin) and return k(x*, x*). ``s`` (n,) is scratch."""
    sf2 = kp[0]
    if kid == KERNEL_NN:
        c0 = kp[1]
        c1 = kp[2]
        sq = 1.0 / math.sqrt(1.0 + c0)
        for i in range(n):
            s[i] = 1.0 / math.sqrt(1.0 + c0 + c1 * (X[i, 0] * X[i, 0] + X[i, 1] * X[i, 1]))
        for i in range(n):
            xi = X[i, 0]
            yi = X[i, 1]
            si = s[i]
            for j in range(i + 1):
                a = (c0 + c1 * (xi * X[j, 0] + yi * X[j, 1])) * si * s[j]
                v = sf2 * math.asin(min(max(a, -1.0), 1.0))
                K[i, j] = v
                K[j, i] = v
            ks[i] = sf2 * math.asin(c0 * si * sq)
        return sf2 * math.asin(c0 / (1.0 + c0))
    # stationary kernels: functions of the distance only
    for i in range(n):
        xi = X[i, 0]
        yi = X[i, 1]
        for j in range(i + 1):
            dx = xi - X[j, 0]
            dy = yi - X[j, 1]
            v = sf2 * _stationary(kid, kp[1], dx * dx + dy * dy)
            K[i, j] = v
            K[j, i] = v
        ks[i] = sf2 * _stationary(kid, kp[1], xi * xi + yi * yi)
    return sf2


@nb.njit(cache=True, fastmath=True, inline="always")
def _stationary(kid, c, r2):
    if kid == KERNEL_SE:
        return math.exp(-0.5 * c * r2)
    u = c * math.sqrt(r2)
    if kid == KERNEL_MATERN32:
        return (1.0 + u) * math.exp(-u)
    return (1.0 + u + u * u / 3.0) * math.exp(-u)


@nb.njit(cache=True, fastmath=True)
def _cholesky_inplace(A, n, diag):
    """Lower Cholesky factor of the symmetric A[:n, :n] written into its lower triangle (row-major,
    Cholesky-Banachiewicz); the upper triangle keeps A, ``diag`` (n,) must hold A's diagonal so that a failed
    factorisation can be retried. Returns False if a pivot is not positive."""
    for i in range(n):
        for j in range(i + 1):
            acc = A[j, i] if j < i else diag[i]
            for m in range(j):
                acc -= A[i, m] * A[j, m]
            if i == j:
                if acc <= 0.0 or not math.isfinite(acc):
                    return False
                A[i, i] = math.sqrt(acc)
            else:
                A[i, j] = acc / A[j, j]
    return True


@nb.njit(cache=True, fastmath=True)
def _forward(L, n, b, out):
    """Solve L out = b for the lower-triangular L[:n, :n]."""
    for i in range(n):
        acc = b[i]
        for m in range(i):
            acc -= L[i, m] * out[m]
        out[i] = acc / L[i, i]


@nb.njit(cache=True)
def _solve_local(K, ks, kss, y, n, noise_var, jitter, diag, v, w):
    """Mean and variance of the local GP (eqs. 2-3) from K[:n,:n] (noise-free), ks, kss and labels y.

    Adds ``noise_var`` to the diagonal; if the Cholesky fails, retries with jitter 1x, 10x, ... 1e6x of
    ``jitter`` times the mean diagonal. Returns (mean, variance) with the variance clipped to [0, kss]
    (the clip only acts on round-off: in exact arithmetic 0 <= var <= kss)."""
    if n == 0:
        return 0.0, kss
    mean_diag = 0.0
    for i in range(n):
        mean_diag += K[i, i]
    mean_diag /= n
    extra = 0.0
    ok = False
    for attempt in range(8):
        for i in range(n):
            diag[i] = K[i, i] + noise_var + extra
        if _cholesky_inplace(K, n, diag):
            ok = True
            break
        extra = jitter * max(mean_diag, 1e-12) * 10.0**attempt
    if not ok:
        return 0.0, kss
    _forward(K, n, ks, v)
    _forward(K, n, y, w)
    mu = 0.0
    q = 0.0
    for i in range(n):
        mu += v[i] * w[i]
        q += v[i] * v[i]
    var = kss - q
    if var < 0.0:
        var = 0.0
    elif var > kss:
        var = kss
    return mu, var


@nb.njit(cache=True)
def _training_inputs(qx, qy, hx, hy, ido, no, sx, sy, sdx, sdy, idf, tf, nf, X, y):
    """Training inputs centred on the query: occupied endpoints (+1) then free points s + t d (-1)."""
    for i in range(no):
        j = ido[i]
        X[i, 0] = hx[j] - qx
        X[i, 1] = hy[j] - qy
        y[i] = 1.0
    for i in range(nf):
        j = idf[i]
        X[no + i, 0] = sx[j] + tf[i] * sdx[j] - qx
        X[no + i, 1] = sy[j] + tf[i] * sdy[j] - qy
        y[no + i] = -1.0
    return no + nf


@nb.njit(cache=True, parallel=True)
def predict_batch(
    queries,
    hx,
    hy,
    p_geom,
    p_start,
    p_items,
    sx,
    sy,
    sdx,
    sdy,
    sinv,
    s_geom,
    s_start,
    s_items,
    k_occ,
    k_free,
    kid,
    kp,
    noise_var,
    jitter,
    alpha,
    beta,
    chunk,
    out_mean,
    out_var,
    out_prob,
):
    """GPFOL prediction at (Q, 2) ``queries``: writes mean (eq. 2), latent variance (eq. 3) and p(occ).

    ``hx, hy``: occupied endpoints; ``sx, sy, sdx, sdy, sinv``: free segments (start, direction, 1/|d|^2);
    ``*_geom`` = (origin x, origin y, cell, nx, ny) and ``*_start``, ``*_items`` of their grid indexes.
    Queries are processed in chunks of ``chunk`` in parallel; scratch is allocated once per chunk.
    """
    nq = queries.shape[0]
    nchunks = (nq + chunk - 1) // chunk
    nmax = k_occ + k_free
    for c in nb.prange(nchunks):
        d2o = np.empty(max(k_occ, 1))
        ido = np.empty(max(k_occ, 1), np.int64)
        to = np.empty(max(k_occ, 1))
        d2f = np.empty(max(k_free, 1))
        idf = np.empty(max(k_free, 1), np.int64)
        tf = np.empty(max(k_free, 1))
        X = np.empty((nmax, 2))
        y = np.empty(nmax)
        K = np.empty((nmax, nmax))
        ks = np.empty(nmax)
        s = np.empty(nmax)
        diag = np.empty(nmax)
        v = np.empty(nmax)
        w = np.empty(nmax)
        lo = c * chunk
        hi = min(lo + chunk, nq)
        for q in range(lo, hi):
            qx = queries[q, 0]
            qy = queries[q, 1]
            no = knn_points(
                qx, qy, hx, hy, p_geom[0], p_geom[1], p_geom[2], int(p_geom[3]), int(p_geom[4]),
                p_start, p_items, k_occ, d2o, ido, to,
            )  # fmt: skip
            nf = knn_segments(
                qx, qy, sx, sy, sdx, sdy, sinv, s_geom[0], s_geom[1], s_geom[2], int(s_geom[3]),
                int(s_geom[4]), s_start, s_items, k_free, d2f, idf, tf,
            )  # fmt: skip
            n = _training_inputs(qx, qy, hx, hy, ido, no, sx, sy, sdx, sdy, idf, tf, nf, X, y)
            kss = _kernel_blocks(kid, kp, X, n, K, ks, s)
            mu, var = _solve_local(K, ks, kss, y, n, noise_var, jitter, diag, v, w)
            out_mean[q] = mu
            out_var[q] = var
            out_prob[q] = _phi((alpha * mu + beta) / math.sqrt(1.0 + alpha * alpha * (var + noise_var)))


@nb.njit(cache=True, parallel=True)
def gather_batch(
    queries,
    hx,
    hy,
    p_geom,
    p_start,
    p_items,
    sx,
    sy,
    sdx,
    sdy,
    sinv,
    s_geom,
    s_start,
    s_items,
    k_occ,
    k_free,
    out_occ,
    out_free,
    out_t,
):
    """Neighbour ids of (Q, 2) queries: ``out_occ`` (Q, k_occ) endpoint ids, ``out_free`` (Q, k_free) segment
    ids and ``out_t`` (Q, k_free) positions of the free points along them; -1 pads missing neighbours."""
    nq = queries.shape[0]
    for q in nb.prange(nq):
        d2o = np.empty(max(k_occ, 1))
        to = np.empty(max(k_occ, 1))
        ido = np.empty(max(k_occ, 1), np.int64)
        d2f = np.empty(max(k_free, 1))
        idf = np.empty(max(k_free, 1), np.int64)
        tf = np.empty(max(k_free, 1))
        qx = queries[q, 0]
        qy = queries[q, 1]
        no = knn_points(
            qx, qy, hx, hy, p_geom[0], p_geom[1], p_geom[2], int(p_geom[3]), int(p_geom[4]),
            p_start, p_items, k_occ, d2o, ido, to,
        )  # fmt: skip
        nf = knn_segments(
            qx, qy, sx, sy, sdx, sdy, sinv, s_geom[0], s_geom[1], s_geom[2], int(s_geom[3]),
            int(s_geom[4]), s_start, s_items, k_free, d2f, idf, tf,
        )  # fmt: skip
        for i in range(k_occ):
            out_occ[q, i] = ido[i] if i < no else -1
        for i in range(k_free):
            out_free[q, i] = idf[i] if i < nf else -1
            out_t[q, i] = tf[i] if i < nf else 0.0
