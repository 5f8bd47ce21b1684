"""Compiled local-GP prediction (eqs. 2-3) for many query points at once, parallel over queries.

For each query ``x*`` (section 3.7): the ``k_occ`` nearest occupied endpoints (+1) and the ``k_free``
nearest free beam segments, each giving its point closest to ``x*`` (-1, eqs. 13-14); then a local GP on
these ``n <= k_occ + k_free`` training points, in coordinates centred on the query, solved by a float64
Cholesky of ``K + sigma_n^2 I`` (jitter added and the factorisation retried if it fails), and the PLS link
``p = Phi((alpha mu + beta) / sqrt(1 + alpha^2 (sigma^2 + sigma_n^2)))`` (SPEC section 5, R&W eq. 6.42).

:func:`predict_batch` runs chunks of queries in parallel (``_predict_chunk``); a chunk's neighbours are found
first (:func:`mapping.blocks.chunk_neighbours`: one range search per block of nearby queries, else
:func:`mapping.index.knn_points` / :func:`mapping.index.knn_segments` per query), then each query gets its
training set, centred on the query
(``_training_inputs``; GPPOL, section 3.6: ``_gaussian_inputs``, the means and 2x2 covariances of the inputs),
copied into one of LANES lanes, unless no input informs the query (``_informs``: every entry of ``k*`` below
:data:`NEGLIGIBLE_KERNEL` of ``k(0)``, e.g. far from precise data yet within the reach of a distant,
metres-uncertain scan): its lane stays empty and it reads the prior. Then LANES queries are solved together,
the lane index innermost so that LLVM vectorises the loops: the kernel blocks ``K``, ``k*``
(``_kernel_lanes``; GPPOL: the kernel integrated over the input distributions, eq. 19 or eq. 23,
``_noisy_kernel_lanes``; the test point stays deterministic), the Cholesky factorisation and the two forward
solves (``_solve_lanes``), then mean, variance and link (``_write_lanes``). A lane whose factorisation fails
is redone alone by the scalar path (``_kernel_blocks`` or ``_noisy_kernel_single``, then ``_solve_local``,
with jitter retries).

Arguments are named tuples (:class:`LocalGP`, :class:`InputGaussians`, and the indexes of
:mod:`mapping.index`), which numba compiles like separate arguments.

The compiled steps that allocate nothing are compiled without numba's reference counting (``_nrt=False``,
numba's option for code that needs no runtime): with it every array argument of a call costs an atomic
increment and decrement, which in the neighbour search, called for every query, took about a quarter of
its time. Such a function cannot allocate (numba refuses to compile it then), so allocation stays in the
drivers (``_predict_chunk``, :func:`mapping.blocks.chunk_neighbours`).

Compiled code is cached on disk (``cache=True``). Numba's cache does not notice edits to compiled functions
of OTHER modules that a cached function calls (e.g. :mod:`mapping.index` from :func:`predict_batch`): after
editing ``mapping/index.py``, ``mapping/blocks.py`` or ``mapping/raster.py``, delete
``mapping/__pycache__/*.nb[ic]`` (``make env`` does so after an edit of any module of ``mapping/``).

Kernel ids and packed parameters (see :meth:`mapping.kernels.Kernel.packed`):
0 neural network (eq. 7): ``(sf2, 2 sigma_0^2, 2 sigma^2)``; 1 squared exponential: ``(sf2, 1/l^2)``;
2 Matern 3/2: ``(sf2, sqrt(3)/l)``; 3 Matern 5/2: ``(sf2, sqrt(5)/l)``.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba as nb
import numpy as np
from numpy.typing import NDArray

from mapping.blocks import chunk_neighbours
from mapping.index import flat_points, flat_segments, points_of, segments_of
from mapping.vecmath import exp_nonpositive

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

KERNEL_NN = 0
KERNEL_SE = 1
KERNEL_MATERN32 = 2
KERNEL_MATERN52 = 3

SQRT2 = math.sqrt(2.0)

#: k(x*, x_i) / k(0) below which a training input does not inform the query. A query whose neighbours all
#: lie below it reads the prior without a solve (``_informs``); :mod:`mapping.reach` skips the places beyond
#: every input's reach by the same tolerance.
NEGLIGIBLE_KERNEL = 1e-5


@nb.njit(cache=True, error_model="numpy", inline="always")
def _phi(z):
    """Standard normal CDF."""
    return 0.5 * math.erfc(-z / SQRT2)


@nb.njit(cache=True, error_model="numpy", _nrt=False, fastmath=True)
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


@nb.njit(cache=True, error_model="numpy", fastmath=True, inline="always")
def _stationary(kid, c, r2):
    if kid == KERNEL_SE:
        return exp_nonpositive(-0.5 * c * r2)
    u = c * math.sqrt(r2)
    if kid == KERNEL_MATERN32:
        return (1.0 + u) * exp_nonpositive(-u)
    return (1.0 + u + u * u / 3.0) * exp_nonpositive(-u)


@nb.njit(cache=True, error_model="numpy", _nrt=False, fastmath=True)
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


@nb.njit(cache=True, error_model="numpy", _nrt=False, fastmath=True)
def _forward(L, n, b, out):
    """Solve L out = b for the lower-triangular L[:n, :n]."""
    for i in range(n):
        acc = b[i]
        for m in range(i):
            acc -= L[i, m] * out[m]
        out[i] = acc / L[i, i]


@nb.njit(cache=True, error_model="numpy", _nrt=False)
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


@nb.njit(cache=True, error_model="numpy", _nrt=False)
def _training_inputs(qx, qy, pts, ido, no, seg, idf, tf, nf, X, y):
    """Training inputs centred on the query: occupied endpoints (+1) then free points s + t d (-1)."""
    for i in range(no):
        j = ido[i]
        X[i, 0] = pts[j, 0] - qx
        X[i, 1] = pts[j, 1] - qy
        y[i] = 1.0
    for i in range(nf):
        j = idf[i]
        X[no + i, 0] = seg[j, 0] + tf[i] * seg[j, 2] - qx
        X[no + i, 1] = seg[j, 1] + tf[i] * seg[j, 3] - qy
        y[no + i] = -1.0
    return no + nf


# ---------------------------------------------------------------------------------------------------------
# The fast path: LANES queries solved together, the lane index innermost, so that the kernel blocks, the
# Cholesky factorisation and the solves run as SIMD instructions over several queries at once. The Cholesky
# and solve loops accumulate through memory (acc[lane], out[i, lane]) and pay a fixed cost per inner loop,
# which more lanes spread over more queries; beyond 32 lanes the K blocks of a chunk no longer fit in L2.

LANES = 32

# fdlibm's rational approximation of asin on [0, 0.5] (and, through asin(x) = pi/2 - 2 asin(sqrt((1-x)/2)),
# on [0.5, 1]); written without branches so that loops over lanes vectorise.
_PS0 = 1.66666666666666657415e-01
_PS1 = -3.25565818622400915405e-01
_PS2 = 2.01212532134862925881e-01
_PS3 = -4.00555345006794114027e-02
_PS4 = 7.91534994289814532176e-04
_PS5 = 3.47933107596021167570e-05
_QS1 = -2.40339491173441421878e00
_QS2 = 2.02094576023350569471e00
_QS3 = -6.88283971605453293030e-01
_QS4 = 7.70381505559019352791e-02
_PIO2 = 1.57079632679489655800e00


@nb.njit(cache=True, error_model="numpy", fastmath=True, inline="always")
def asin_fast(x):
    """asin(x) for x in [-1, 1] without branches (absolute error ~2e-16, tested against numpy).

    With z = |x| and t = min(z^2, (1 - z)/2), u = sqrt(t) is z on [0, 1/2] and sqrt((1 - z)/2) above, where
    asin(z) = pi/2 - 2 asin(u); ``big`` (0 or 1) blends the two branches."""
    z = abs(x)
    t = min(z * z, 0.5 * (1.0 - z))
    p = t * (_PS0 + t * (_PS1 + t * (_PS2 + t * (_PS3 + t * (_PS4 + t * _PS5)))))
    q = 1.0 + t * (_QS1 + t * (_QS2 + t * (_QS3 + t * _QS4)))
    u = math.sqrt(t)
    a = u + u * (p / q)
    big = 0.5 + 0.5 * math.copysign(1.0, z - 0.5)
    return math.copysign(a + big * (_PIO2 - 3.0 * a), x)


@nb.njit(cache=True, error_model="numpy", _nrt=False, fastmath=True)
def _kernel_lanes(kid, kp, XL, mask, n, K, ks, s):
    """Lower triangle of K[:n, :n, lane] (noise-free, pads zeroed) and ks[:n, lane] for LANES local problems
    with inputs XL (n, 2, LANES) centred on their queries; ``mask`` (n, LANES) is 1 for real points, 0 for
    pads. ``s`` (n, LANES) is scratch."""
    nlanes = XL.shape[2]  # a run-time trip count: LLVM vectorises the lane loops instead of unrolling them
    sf2 = kp[0]
    if kid == KERNEL_NN:
        c0 = kp[1]
        c1 = kp[2]
        sq = 1.0 / math.sqrt(1.0 + c0)
        for i in range(n):
            for lane in range(nlanes):
                x = XL[i, 0, lane]
                y = XL[i, 1, lane]
                s[i, lane] = 1.0 / math.sqrt(1.0 + c0 + c1 * (x * x + y * y))
        for i in range(n):
            for j in range(i + 1):
                for lane in range(nlanes):
                    a = (c0 + c1 * (XL[i, 0, lane] * XL[j, 0, lane] + XL[i, 1, lane] * XL[j, 1, lane])) * (
                        s[i, lane] * s[j, lane]
                    )
                    a = min(max(a, -1.0), 1.0)
                    K[i, j, lane] = sf2 * asin_fast(a) * (mask[i, lane] * mask[j, lane])
            for lane in range(nlanes):
                ks[i, lane] = sf2 * asin_fast(c0 * s[i, lane] * sq) * mask[i, lane]
        return
    for i in range(n):
        for j in range(i + 1):
            for lane in range(nlanes):
                dx = XL[i, 0, lane] - XL[j, 0, lane]
                dy = XL[i, 1, lane] - XL[j, 1, lane]
                K[i, j, lane] = (
                    sf2 * _stationary(kid, kp[1], dx * dx + dy * dy) * (mask[i, lane] * mask[j, lane])
                )
        for lane in range(nlanes):
            x = XL[i, 0, lane]
            y = XL[i, 1, lane]
            ks[i, lane] = sf2 * _stationary(kid, kp[1], x * x + y * y) * mask[i, lane]


@nb.njit(cache=True, error_model="numpy", _nrt=False, fastmath=True)
def _cholesky_lanes(K, n, invd, acc, ok):
    """In-place lower Cholesky of LANES matrices K[:n, :n, lane] (lower triangles); ``invd`` (n, LANES)
    receives 1 / L_ii; ``acc`` (2, LANES) is scratch. ``ok[lane]`` is set False where a pivot is not
    positive (that lane is garbage).

    Row by row (Cholesky-Banachiewicz), two off-diagonal entries j, j + 1 of a row at a time: they share the
    loads of row i and halve the inner loops, while each entry still subtracts its products in the order
    m = 0, 1, ..., so the factor is bit for bit that of one entry at a time."""
    nlanes = K.shape[2]
    for i in range(n):
        j = 0
        while j + 1 < i:
            for lane in range(nlanes):
                acc[0, lane] = K[i, j, lane]
                acc[1, lane] = K[i, j + 1, lane]
            for m in range(j):
                for lane in range(nlanes):
                    a = K[i, m, lane]
                    acc[0, lane] -= a * K[j, m, lane]
                    acc[1, lane] -= a * K[j + 1, m, lane]
            for lane in range(nlanes):
                lij = acc[0, lane] * invd[j, lane]
                K[i, j, lane] = lij
                K[i, j + 1, lane] = (acc[1, lane] - lij * K[j + 1, j, lane]) * invd[j + 1, lane]
            j += 2
        while j <= i:
            for lane in range(nlanes):
                acc[0, lane] = K[i, j, lane]
            for m in range(j):
                for lane in range(nlanes):
                    acc[0, lane] -= K[i, m, lane] * K[j, m, lane]
            if i == j:
                for lane in range(nlanes):
                    v = acc[0, lane]
                    bad = not (v > 0.0)
                    ok[lane] = ok[lane] and not bad
                    d = math.sqrt(v if not bad else 1.0)
                    K[i, i, lane] = d
                    invd[i, lane] = 1.0 / d
            else:
                for lane in range(nlanes):
                    K[i, j, lane] = acc[0, lane] * invd[j, lane]
            j += 1


@nb.njit(cache=True, error_model="numpy", _nrt=False, fastmath=True)
def _forward_lanes(K, n, invd, b1, out1, b2, out2):
    """Solve L out1[:, lane] = b1[:, lane] and L out2[:, lane] = b2[:, lane] for the LANES lower factors in K
    (both in one pass over L)."""
    nlanes = K.shape[2]
    for i in range(n):
        for lane in range(nlanes):
            out1[i, lane] = b1[i, lane]
            out2[i, lane] = b2[i, lane]
        for m in range(i):
            for lane in range(nlanes):
                k = K[i, m, lane]
                out1[i, lane] -= k * out1[m, lane]
                out2[i, lane] -= k * out2[m, lane]
        for lane in range(nlanes):
            out1[i, lane] *= invd[i, lane]
            out2[i, lane] *= invd[i, lane]


# ---------------------------------------------------------------------------------------------------------
# GPPOL (paper section 3.6): training inputs are Gaussians N(rho_i, Sigma_i), the query is deterministic.
# K_ij = E[k(x_i, x_j)] over independent draws (eq. 17), K_ii = E[k(x_i, x_i)] under one draw and
# k*_i = E[k(x*, x_i)] over x_i only (SPEC section 5); see mapping.noisy_kernels for the numpy reference.
# Covariances are packed (xx, xy, yy) in SL (n, 3, LANES).

INPUTS_POINTS = 0  # GPFOL: deterministic training inputs
INPUTS_GIRARD = 1  # GPPOL, SE kernel, Girard's closed form (eq. 19)
INPUTS_GH_DIFFERENCE = 2  # GPPOL, stationary kernel, Gauss-Hermite over the difference x_i - x_j (eq. 23)
INPUTS_GH_NODES = 3  # GPPOL, NN kernel, Gauss-Hermite nodes of both inputs (eq. 23)

#: Columns of GPPOL's endpoint and beam rows (:func:`_gaussian_inputs`), and of the rows of inputs whose
#: rigid groups carry each scan's offset from the group (three levels of pair covariance,
#: :func:`_pair_cov_grouped`).
OCC_COLUMNS = 9
SEG_COLUMNS = 24
OCC_COLUMNS_GROUPED = 13
SEG_COLUMNS_GROUPED = 34


@nb.njit(cache=True, error_model="numpy", _nrt=False)
def _gaussian_inputs(qx, qy, occ_mom, ido, no, seg_mom, idf, tf, nf, X, S, SLo, SGr, G, GG, y):
    """GPPOL training inputs centred on the query: means X (n, 2), packed covariances S (n, 3), packed
    covariances of the laser noise alone SLo (n, 3), rigid groups G (n,); with grouped rows, also the
    covariances within the rigid group SGr (n, 3) and the groups GG (n,), G then holding the scans.

    ``occ_mom`` (H, OCC_COLUMNS): mean, covariance, laser-noise covariance and rigid group (a scan, or the
    scans of one keyframe) of each endpoint (cell order of the point index); ``seg_mom`` (M, SEG_COLUMNS):
    per beam ``a, b, C0, C1, C2`` of :class:`mapping.unscented.BeamMoments`, the length L of its free part,
    the laser noise's ``C0, C1, C2`` and the rigid group, so that the free point at t along the segment is
    at d = t L: ``rho = a + d b``, ``Sigma = C0 + d C1 + d^2 C2`` (exact UT, Algorithm 3 steps 5-8).
    Grouped rows (OCC_COLUMNS_GROUPED, SEG_COLUMNS_GROUPED) hold the scan where the others hold the group,
    then the within-group covariance (``C0, C1, C2`` per beam) and the group."""
    for i in range(no):
        j = ido[i]
        X[i, 0] = occ_mom[j, 0] - qx
        X[i, 1] = occ_mom[j, 1] - qy
        S[i, 0] = occ_mom[j, 2]
        S[i, 1] = occ_mom[j, 3]
        S[i, 2] = occ_mom[j, 4]
        SLo[i, 0] = occ_mom[j, 5]
        SLo[i, 1] = occ_mom[j, 6]
        SLo[i, 2] = occ_mom[j, 7]
        G[i] = occ_mom[j, 8]
        y[i] = 1.0
    for i in range(nf):
        j = idf[i]
        d = tf[i] * seg_mom[j, 13]
        X[no + i, 0] = seg_mom[j, 0] + d * seg_mom[j, 2] - qx
        X[no + i, 1] = seg_mom[j, 1] + d * seg_mom[j, 3] - qy
        S[no + i, 0] = seg_mom[j, 4] + d * (seg_mom[j, 7] + d * seg_mom[j, 10])
        S[no + i, 1] = seg_mom[j, 5] + d * (seg_mom[j, 8] + d * seg_mom[j, 11])
        S[no + i, 2] = seg_mom[j, 6] + d * (seg_mom[j, 9] + d * seg_mom[j, 12])
        SLo[no + i, 0] = seg_mom[j, 14] + d * (seg_mom[j, 17] + d * seg_mom[j, 20])
        SLo[no + i, 1] = seg_mom[j, 15] + d * (seg_mom[j, 18] + d * seg_mom[j, 21])
        SLo[no + i, 2] = seg_mom[j, 16] + d * (seg_mom[j, 19] + d * seg_mom[j, 22])
        G[no + i] = seg_mom[j, 23]
        y[no + i] = -1.0
    if occ_mom.shape[1] == OCC_COLUMNS_GROUPED:
        for i in range(no):
            j = ido[i]
            SGr[i, 0] = occ_mom[j, 9]
            SGr[i, 1] = occ_mom[j, 10]
            SGr[i, 2] = occ_mom[j, 11]
            GG[i] = occ_mom[j, 12]
        for i in range(nf):
            j = idf[i]
            d = tf[i] * seg_mom[j, 13]
            SGr[no + i, 0] = seg_mom[j, 24] + d * (seg_mom[j, 27] + d * seg_mom[j, 30])
            SGr[no + i, 1] = seg_mom[j, 25] + d * (seg_mom[j, 28] + d * seg_mom[j, 31])
            SGr[no + i, 2] = seg_mom[j, 26] + d * (seg_mom[j, 29] + d * seg_mom[j, 32])
            GG[no + i] = seg_mom[j, 33]
    return no + nf


@nb.njit(cache=True, error_model="numpy", _nrt=False, fastmath=True, inline="always")
def _pair_cov(SL, SLo, GL, i, j, lane, c):
    """Entry ``c`` of the packed covariance of ``x_i - x_j``: ``Sigma_i + Sigma_j`` for inputs of different
    groups, the laser noise's alone for two of one rigid group (a scan, or the scans of one keyframe: a
    rigid motion keeps their distance, :class:`mapping.gppol.GaussianInputs`)."""
    one_scan = SLo[i, c, lane] + SLo[j, c, lane]
    two_scans = SL[i, c, lane] + SL[j, c, lane]
    return one_scan if GL[i, lane] == GL[j, lane] else two_scans  # a select, not a branch: vectorised


@nb.njit(cache=True, error_model="numpy", _nrt=False, fastmath=True, inline="always")
def _pair_cov_grouped(SL, SLo, SGr, GL, GGL, i, j, lane, c):
    """:func:`_pair_cov` of grouped inputs (GL the scans, GGL the rigid groups): the laser noise's alone for
    two inputs of one scan; the covariances within their rigid group (the laser noise and each scan's
    odometry from the group's keyframe) for two scans of one group, whose shared pose error moves both
    alike; ``Sigma_i + Sigma_j`` otherwise."""
    one_scan = SLo[i, c, lane] + SLo[j, c, lane]
    one_group = SGr[i, c, lane] + SGr[j, c, lane]
    two_groups = SL[i, c, lane] + SL[j, c, lane]
    shared = one_group if GGL[i, lane] == GGL[j, lane] else two_groups  # selects, not branches: vectorised
    return one_scan if GL[i, lane] == GL[j, lane] else shared


@nb.njit(cache=True, error_model="numpy", _nrt=False, fastmath=True, inline="always")
def _girard_se(ell2, s00, s01, s11, dx, dy):
    """Eq. (19) over sf2: ``l^2 / sqrt(det(l^2 I + S)) exp(-d^T (l^2 I + S)^-1 d / 2)`` for the packed
    covariance ``(s00, s01, s11)`` of a difference ``d = (dx, dy)``."""
    a00 = ell2 + s00
    a11 = ell2 + s11
    r = 1.0 / math.sqrt(a00 * a11 - s01 * s01)  # |L I + S|^(-1/2)
    q = (dx * dx * a11 - 2.0 * dx * dy * s01 + dy * dy * a00) * (r * r)
    return ell2 * r * exp_nonpositive(-0.5 * q)


@nb.njit(cache=True, error_model="numpy", _nrt=False, fastmath=True)
def _informs(mode, kid, kp, X, S, n):
    """Whether one of the ``n`` training inputs (means X (n, 2) centred on the query, GPPOL's packed
    covariances S (n, 3)) has ``k(x*, x_i) >= NEGLIGIBLE_KERNEL k(0)``. If none has, every entry of k* is
    negligible: the mean (eq. 2) and the variance reduction (eq. 3) vanish and the query reads the prior.
    Only the stationary kernels with a closed form are checked (exact inputs, eq. 19); the NN kernel does not
    decay and the quadrature modes are solved as they are (True)."""
    if kid == KERNEL_NN or mode == INPUTS_GH_DIFFERENCE or mode == INPUTS_GH_NODES:
        return True
    c = kp[1]
    for i in range(n):
        dx = X[i, 0]
        dy = X[i, 1]
        if mode == INPUTS_POINTS:
            v = _stationary(kid, c, dx * dx + dy * dy)
        else:  # INPUTS_GIRARD, SE: eq. (19) over k(0) = sf2
            v = _girard_se(1.0 / c, S[i, 0], S[i, 1], S[i, 2], dx, dy)
        if v >= NEGLIGIBLE_KERNEL:
            return True
    return False


@nb.njit(cache=True, error_model="numpy", _nrt=False, fastmath=True)
def _girard_lanes(kp, XL, SL, SLo, SGr, GL, GGL, grouped, mask, n, K, ks):
    """Eq. (19) for the SE kernel (``kp = (sf2, 1/l^2)``): lower triangle of K[:n, :n, lane] and ks[:n, lane]
    (the covariance of ``x_i - x_j``, :func:`_pair_cov` or, for ``grouped`` inputs, :func:`_pair_cov_grouped`,
    between training inputs; Sigma_i against the query at the origin; K_ii = sf2)."""
    nlanes = XL.shape[2]
    sf2 = kp[0]
    ell2 = 1.0 / kp[1]
    for i in range(n):
        for j in range(i):
            if grouped:
                for lane in range(nlanes):
                    v = _girard_se(
                        ell2, _pair_cov_grouped(SL, SLo, SGr, GL, GGL, i, j, lane, 0),
                        _pair_cov_grouped(SL, SLo, SGr, GL, GGL, i, j, lane, 1),
                        _pair_cov_grouped(SL, SLo, SGr, GL, GGL, i, j, lane, 2),
                        XL[i, 0, lane] - XL[j, 0, lane], XL[i, 1, lane] - XL[j, 1, lane],
                    )  # fmt: skip
                    K[i, j, lane] = sf2 * v * (mask[i, lane] * mask[j, lane])
                continue
            for lane in range(nlanes):
                v = _girard_se(
                    ell2, _pair_cov(SL, SLo, GL, i, j, lane, 0), _pair_cov(SL, SLo, GL, i, j, lane, 1),
                    _pair_cov(SL, SLo, GL, i, j, lane, 2), XL[i, 0, lane] - XL[j, 0, lane],
                    XL[i, 1, lane] - XL[j, 1, lane],
                )  # fmt: skip
                K[i, j, lane] = sf2 * v * (mask[i, lane] * mask[j, lane])
        for lane in range(nlanes):
            K[i, i, lane] = sf2 * mask[i, lane]
            s00, s01, s11 = SL[i, 0, lane], SL[i, 1, lane], SL[i, 2, lane]
            v = _girard_se(ell2, s00, s01, s11, XL[i, 0, lane], XL[i, 1, lane])
            ks[i, lane] = sf2 * v * mask[i, lane]


@nb.njit(cache=True, error_model="numpy", fastmath=True, inline="always")
def _gh_difference_value(kid, c, gz, gw, dx, dy, s00, s01, s11):
    """E[k(z)] / sf2, z ~ N((dx, dy), [[s00, s01], [s01, s11]]), by the tensor Gauss-Hermite rule (gz, gw)."""
    l00 = math.sqrt(max(s00, 0.0))
    l10 = s01 / l00 if l00 > 1e-150 else 0.0
    l11 = math.sqrt(max(s11 - l10 * l10, 0.0))
    acc = 0.0
    for a in range(gw.shape[0]):
        zx = dx + l00 * gz[a, 0]
        zy = dy + l10 * gz[a, 0] + l11 * gz[a, 1]
        acc += gw[a] * _stationary(kid, c, zx * zx + zy * zy)
    return acc


@nb.njit(cache=True, error_model="numpy", _nrt=False, fastmath=True)
def _gh_difference_lanes(kid, kp, XL, SL, SLo, SGr, GL, GGL, grouped, mask, n, K, ks, gz, gw):
    """Eq. (23) for a stationary kernel, as the 2-D integral over the difference of two inputs
    (``x_i - x_j ~ N(rho_i - rho_j, .)``, its covariance :func:`_pair_cov`, or :func:`_pair_cov_grouped`
    for ``grouped`` inputs); K_ii = sf2 (one draw)."""
    nlanes = XL.shape[2]
    sf2 = kp[0]
    c = kp[1]
    for i in range(n):
        for j in range(i):
            for lane in range(nlanes):
                if grouped:
                    s00 = _pair_cov_grouped(SL, SLo, SGr, GL, GGL, i, j, lane, 0)
                    s01 = _pair_cov_grouped(SL, SLo, SGr, GL, GGL, i, j, lane, 1)
                    s11 = _pair_cov_grouped(SL, SLo, SGr, GL, GGL, i, j, lane, 2)
                else:
                    s00 = _pair_cov(SL, SLo, GL, i, j, lane, 0)
                    s01 = _pair_cov(SL, SLo, GL, i, j, lane, 1)
                    s11 = _pair_cov(SL, SLo, GL, i, j, lane, 2)
                v = _gh_difference_value(
                    kid,
                    c,
                    gz,
                    gw,
                    XL[i, 0, lane] - XL[j, 0, lane],
                    XL[i, 1, lane] - XL[j, 1, lane],
                    s00,
                    s01,
                    s11,
                )
                K[i, j, lane] = sf2 * v * (mask[i, lane] * mask[j, lane])
        for lane in range(nlanes):
            K[i, i, lane] = sf2 * mask[i, lane]
            v = _gh_difference_value(
                kid, c, gz, gw, XL[i, 0, lane], XL[i, 1, lane], SL[i, 0, lane], SL[i, 1, lane], SL[i, 2, lane]
            )
            ks[i, lane] = sf2 * v * mask[i, lane]


@nb.njit(cache=True, error_model="numpy", _nrt=False, fastmath=True)
def _gh_nodes_lanes(kp, XL, SL, mask, n, K, ks, gz, gw, PH, SN):
    """Eq. (23) for the NN kernel (eq. 7): nodes ``phi_ia = rho_i + chol(Sigma_i) z_a`` of every input
    (PH (n, m, 2, LANES), their 1/sqrt(1 + c0 + c1 |phi|^2) in SN (n, m, LANES)); K_ij = sum_ab w_a w_b
    k(phi_ia, phi_jb), K_ii = sum_a w_a k(phi_ia, phi_ia) (one draw), ks_i = sum_a w_a k(0, phi_ia)."""
    nlanes = XL.shape[2]
    m = gw.shape[0]
    sf2 = kp[0]
    c0 = kp[1]
    c1 = kp[2]
    sq = 1.0 / math.sqrt(1.0 + c0)
    for i in range(n):
        for lane in range(nlanes):
            l00 = math.sqrt(max(SL[i, 0, lane], 0.0))
            l10 = SL[i, 1, lane] / l00 if l00 > 1e-150 else 0.0
            l11 = math.sqrt(max(SL[i, 2, lane] - l10 * l10, 0.0))
            for a in range(m):
                x = XL[i, 0, lane] + l00 * gz[a, 0]
                y = XL[i, 1, lane] + l10 * gz[a, 0] + l11 * gz[a, 1]
                PH[i, a, 0, lane] = x
                PH[i, a, 1, lane] = y
                SN[i, a, lane] = 1.0 / math.sqrt(1.0 + c0 + c1 * (x * x + y * y))
    for i in range(n):
        for j in range(i):
            for lane in range(nlanes):
                K[i, j, lane] = 0.0
            for a in range(m):
                for b in range(m):
                    wab = gw[a] * gw[b]
                    for lane in range(nlanes):
                        arg = (
                            c0
                            + c1
                            * (PH[i, a, 0, lane] * PH[j, b, 0, lane] + PH[i, a, 1, lane] * PH[j, b, 1, lane])
                        ) * (SN[i, a, lane] * SN[j, b, lane])
                        K[i, j, lane] += wab * asin_fast(min(max(arg, -1.0), 1.0))
            for lane in range(nlanes):
                K[i, j, lane] *= sf2 * (mask[i, lane] * mask[j, lane])
        for lane in range(nlanes):
            K[i, i, lane] = 0.0
            ks[i, lane] = 0.0
        for a in range(m):
            for lane in range(nlanes):
                x = PH[i, a, 0, lane]
                y = PH[i, a, 1, lane]
                s2 = SN[i, a, lane] * SN[i, a, lane]
                K[i, i, lane] += gw[a] * asin_fast(min((c0 + c1 * (x * x + y * y)) * s2, 1.0))
                ks[i, lane] += gw[a] * asin_fast(c0 * SN[i, a, lane] * sq)
        for lane in range(nlanes):
            K[i, i, lane] *= sf2 * mask[i, lane]
            ks[i, lane] *= sf2 * mask[i, lane]


@nb.njit(cache=True, error_model="numpy", _nrt=False)
def _noisy_kernel_lanes(mode, kid, kp, XL, SL, SLo, SGr, GL, GGL, grouped, mask, n, K, ks, gz, gw, PH, SN):
    """The GPPOL kernel blocks of ``mode`` (INPUTS_GIRARD, INPUTS_GH_DIFFERENCE or INPUTS_GH_NODES). The
    stationary modes treat two inputs of one rigid group (same GL) as sharing its pose error
    (:func:`_pair_cov`); ``grouped`` inputs tell the scans (GL) from the groups (GGL) and integrate two
    scans of one group over their offsets from it (:func:`_pair_cov_grouped`). The NN kernel, not
    invariant to a rigid motion, integrates every pair over both full covariances."""
    if mode == INPUTS_GIRARD:
        _girard_lanes(kp, XL, SL, SLo, SGr, GL, GGL, grouped, mask, n, K, ks)
    elif mode == INPUTS_GH_DIFFERENCE:
        _gh_difference_lanes(kid, kp, XL, SL, SLo, SGr, GL, GGL, grouped, mask, n, K, ks, gz, gw)
    else:
        _gh_nodes_lanes(kp, XL, SL, mask, n, K, ks, gz, gw, PH, SN)


# ---------------------------------------------------------------------------------------------------------
# The drivers: many queries, in parallel chunks.


class LocalGP(NamedTuple):
    """The local GP of every query: ``k_occ`` + ``k_free`` neighbours, the kernel (``kernel_id``, and its
    ``kernel_params`` as :meth:`mapping.kernels.Kernel.packed` gives them), the noise variance, the jitter of
    a failed factorisation's retries, the PLS link ``alpha``, ``beta`` and ``mean_cap`` (the bound of the
    mean the link reads, :func:`mapping.pls.fit_pls`; ``inf``: none), and ``chunk``, how many queries one
    parallel task takes (its scratch is allocated once)."""

    k_occ: int
    k_free: int
    kernel_id: int
    kernel_params: FloatArray
    noise_var: float
    jitter: float
    alpha: float
    beta: float
    mean_cap: float
    chunk: int

    @classmethod
    def of(
        cls, k_occ: int, k_free: int, kernel_id: int, kernel_params: FloatArray, noise_var: float,
        jitter: float, alpha: float, beta: float, chunk: int = 256, mean_cap: float | None = None,
    ) -> LocalGP:  # fmt: skip
        """The tuple with normalised types (one compiled specialisation for all maps); ``mean_cap`` None:
        the mean is not capped."""
        kp = np.ascontiguousarray(kernel_params, dtype=np.float64)
        cap = math.inf if mean_cap is None else float(mean_cap)
        return cls(
            int(k_occ), int(k_free), int(kernel_id), kp, float(noise_var), float(jitter), float(alpha),
            float(beta), cap, int(chunk),
        )  # fmt: skip


class InputGaussians(NamedTuple):
    """The training inputs' distributions: ``mode`` INPUTS_POINTS (GPFOL: points, the arrays unused) or a
    GPPOL mode; ``occ_moments`` (H, OCC_COLUMNS) and ``seg_moments`` (M, SEG_COLUMNS), see
    :func:`_gaussian_inputs`; the
    Gauss-Hermite rule, ``nodes`` (m, 2) standard nodes and ``weights`` (m,) summing to 1."""

    mode: int
    occ_moments: FloatArray
    seg_moments: FloatArray
    nodes: FloatArray
    weights: FloatArray

    @classmethod
    def points(cls) -> InputGaussians:
        """GPFOL: deterministic training inputs."""
        empty = (np.zeros((0, OCC_COLUMNS)), np.zeros((0, SEG_COLUMNS)))
        return cls(INPUTS_POINTS, *empty, np.zeros((1, 2)), np.ones(1))


class _LaneScratch(NamedTuple):
    """LANES local problems of one chunk (see the fast path above): inputs XL, covariances SL (SLo of the
    laser noise alone, SGr within the rigid group; scans GL, groups GGL), labels yL, ``mask`` (1 real point,
    0 pad), sizes ``counts``; K blocks KL, ksL and the solver's work arrays; GPPOL quadrature nodes PH, SN."""

    XL: FloatArray
    SL: FloatArray
    SLo: FloatArray
    SGr: FloatArray
    GL: FloatArray
    GGL: FloatArray
    yL: FloatArray
    mask: FloatArray
    counts: IntArray
    KL: FloatArray
    ksL: FloatArray
    sL: FloatArray
    invd: FloatArray
    vL: FloatArray
    wL: FloatArray
    acc: FloatArray
    ok: NDArray[np.bool_]
    PH: FloatArray
    SN: FloatArray


class _SingleScratch(NamedTuple):
    """One local problem: inputs X, covariances S (SLo of the laser noise alone, SGr within the rigid group;
    scans G, groups GG), labels y (filled per query, then copied to its lane), and the scalar path's K, ks
    and work arrays."""

    X: FloatArray
    S: FloatArray
    SLo: FloatArray
    SGr: FloatArray
    G: FloatArray
    GG: FloatArray
    y: FloatArray
    K: FloatArray
    ks: FloatArray
    s: FloatArray
    diag: FloatArray
    v: FloatArray
    w: FloatArray


@nb.njit(cache=True, error_model="numpy", inline="always")
def _grouped(inputs):
    """Whether GPPOL's rows are grouped (:func:`_gaussian_inputs`): scans and rigid groups told apart."""
    return inputs.occ_moments.shape[1] == OCC_COLUMNS_GROUPED


@nb.njit(cache=True, error_model="numpy", inline="always")
def _pad_lanes(lanes, nfill):
    """Pads of the lanes with fewer than ``nfill`` points: zero inputs and labels (identity rows in K)."""
    XL = lanes.XL
    SL = lanes.SL
    SLo = lanes.SLo
    SGr = lanes.SGr
    yL = lanes.yL
    mask = lanes.mask
    counts = lanes.counts
    for lane in range(LANES):
        for i in range(counts[lane], nfill):
            XL[i, 0, lane] = 0.0
            XL[i, 1, lane] = 0.0
            for c in range(3):
                SL[i, c, lane] = 0.0
                SLo[i, c, lane] = 0.0
                SGr[i, c, lane] = 0.0
            lanes.GL[i, lane] = -1.0
            lanes.GGL[i, lane] = -1.0
            yL[i, lane] = 0.0
            mask[i, lane] = 0.0


@nb.njit(cache=True, error_model="numpy", inline="always")
def _solve_lanes(gp, inputs, lanes, nfill):
    """K + sigma_n^2 I (1 on the pads' diagonal), its Cholesky factor and the two forward solves
    ``L v = k*``, ``L w = y`` of every lane; ``lanes.ok[lane]`` is False where the factorisation failed."""
    kid = gp.kernel_id
    kp = gp.kernel_params
    if inputs.mode == INPUTS_POINTS:
        _kernel_lanes(kid, kp, lanes.XL, lanes.mask, nfill, lanes.KL, lanes.ksL, lanes.sL)
    else:
        _noisy_kernel_lanes(
            inputs.mode, kid, kp, lanes.XL, lanes.SL, lanes.SLo, lanes.SGr, lanes.GL, lanes.GGL,
            _grouped(inputs), lanes.mask, nfill, lanes.KL, lanes.ksL, inputs.nodes, inputs.weights, lanes.PH,
            lanes.SN,
        )  # fmt: skip
    KL = lanes.KL
    mask = lanes.mask
    ok = lanes.ok
    noise_var = gp.noise_var
    for i in range(nfill):
        for lane in range(LANES):
            KL[i, i, lane] += noise_var * mask[i, lane] + (1.0 - mask[i, lane])
    for lane in range(LANES):
        ok[lane] = True
    _cholesky_lanes(KL, nfill, lanes.invd, lanes.acc, ok)
    _forward_lanes(KL, nfill, lanes.invd, lanes.ksL, lanes.vL, lanes.yL, lanes.wL)


@nb.njit(cache=True, error_model="numpy", inline="always")
def _link(gp, mu, var):
    """p(occ) by the PLS link, the mean capped at +-``gp.mean_cap``."""
    m = min(max(mu, -gp.mean_cap), gp.mean_cap)
    return _phi((gp.alpha * m + gp.beta) / math.sqrt(1.0 + gp.alpha * gp.alpha * (var + gp.noise_var)))


@nb.njit(cache=True, error_model="numpy", inline="always")
def _write_lanes(base, nl, nfill, gp, inputs, kss, lanes, one, out_mean, out_var, out_prob):
    """Mean, variance and p(occ) of the ``nl`` queries from ``base`` on; a lane whose factorisation failed
    is redone alone, with jitter retries (``_solve_local``)."""
    ok = lanes.ok
    vL = lanes.vL
    wL = lanes.wL
    for lane in range(nl):
        q = base + lane
        if ok[lane]:
            mu = 0.0
            qq = 0.0
            for i in range(nfill):
                mu += vL[i, lane] * wL[i, lane]
                qq += vL[i, lane] * vL[i, lane]
            var = min(max(kss - qq, 0.0), kss)
        else:  # rare
            mu, var = _solve_alone(lane, gp, inputs, lanes, one)
        out_mean[q] = mu
        out_var[q] = var
        out_prob[q] = _link(gp, mu, var)


@nb.njit(cache=True, error_model="numpy")
def _solve_alone(lane, gp, inputs, lanes, one):
    """(mean, variance) of the local problem of lane ``lane`` by the scalar path."""
    n = lanes.counts[lane]
    X = one.X
    y = one.y
    XL = lanes.XL
    yL = lanes.yL
    for i in range(n):
        X[i, 0] = XL[i, 0, lane]
        X[i, 1] = XL[i, 1, lane]
        y[i] = yL[i, lane]
    kid = gp.kernel_id
    kp = gp.kernel_params
    if inputs.mode == INPUTS_POINTS:
        kss1 = _kernel_blocks(kid, kp, X, n, one.K, one.ks, one.s)
    else:
        kss1 = _noisy_kernel_single(
            inputs.mode, kid, kp, XL, lanes.SL, lanes.SLo, lanes.SGr, lanes.GL, lanes.GGL, _grouped(inputs),
            lane, n, one.K, one.ks, inputs.nodes, inputs.weights,
        )  # fmt: skip
    return _solve_local(one.K, one.ks, kss1, y, n, gp.noise_var, gp.jitter, one.diag, one.v, one.w)


@nb.njit(cache=True, error_model="numpy")
def _predict_chunk(queries, lo, hi, points, segments, gp, inputs, kss, out_mean, out_var, out_prob):
    """Predictions at ``queries[lo:hi]``: the chunk's neighbours first, then LANES queries at a time. The
    per-query steps stay in this loop, on the scratch arrays as locals: handing the scratch tuples to a
    helper for every query is slower; the per-block steps are helpers."""
    k_occ = gp.k_occ
    k_free = gp.k_free
    nmax = k_occ + k_free
    nodes = inputs.weights.shape[0] if inputs.mode == INPUTS_GH_NODES else 1
    n_chunk = hi - lo
    ido_c = np.empty((n_chunk, max(k_occ, 1)), np.int64)
    no_c = np.zeros(n_chunk, np.int64)
    idf_c = np.empty((n_chunk, max(k_free, 1)), np.int64)
    tf_c = np.empty((n_chunk, max(k_free, 1)))
    nf_c = np.zeros(n_chunk, np.int64)
    chunk_neighbours(queries, lo, hi, points, segments, k_occ, k_free, ido_c, no_c, idf_c, tf_c, nf_c)
    one = _SingleScratch(
        np.empty((nmax, 2)), np.zeros((nmax, 3)), np.zeros((nmax, 3)), np.zeros((nmax, 3)), np.zeros(nmax),
        np.zeros(nmax), np.empty(nmax), np.empty((nmax, nmax)), np.empty(nmax), np.empty(nmax),
        np.empty(nmax), np.empty(nmax), np.empty(nmax),
    )  # fmt: skip
    lanes = _LaneScratch(
        np.zeros((nmax, 2, LANES)), np.zeros((nmax, 3, LANES)), np.zeros((nmax, 3, LANES)),
        np.zeros((nmax, 3, LANES)), np.zeros((nmax, LANES)), np.zeros((nmax, LANES)), np.zeros((nmax, LANES)),
        np.zeros((nmax, LANES)), np.zeros(LANES, np.int64), np.empty((nmax, nmax, LANES)),
        np.empty((nmax, LANES)), np.empty((nmax, LANES)), np.empty((nmax, LANES)), np.empty((nmax, LANES)),
        np.empty((nmax, LANES)), np.empty((2, LANES)), np.empty(LANES, np.bool_),
        np.empty((nmax, nodes, 2, LANES)), np.empty((nmax, nodes, LANES)),
    )  # fmt: skip
    X, S, SLo1, SGr1, G1, GG1, y = one.X, one.S, one.SLo, one.SGr, one.G, one.GG, one.y
    XL, SL, SLo, SGr, GL, GGL = lanes.XL, lanes.SL, lanes.SLo, lanes.SGr, lanes.GL, lanes.GGL
    yL, mask, counts = lanes.yL, lanes.mask, lanes.counts
    pts, seg = points.xy, segments.seg
    mode, occ_mom, seg_mom = inputs.mode, inputs.occ_moments, inputs.seg_moments
    grouped = _grouped(inputs)
    for base in range(lo, hi, LANES):
        nl = min(LANES, hi - base)
        nfill = 0
        for lane in range(LANES):
            counts[lane] = 0
            if lane >= nl:
                continue
            qx = queries[base + lane, 0]
            qy = queries[base + lane, 1]
            j = base + lane - lo
            no = no_c[j]
            nf = nf_c[j]
            ido = ido_c[j]
            idf = idf_c[j]
            tf = tf_c[j]
            # the training set, centred on the query, into this lane
            if mode == INPUTS_POINTS:
                n = _training_inputs(qx, qy, pts, ido, no, seg, idf, tf, nf, X, y)
            else:
                n = _gaussian_inputs(
                    qx, qy, occ_mom, ido, no, seg_mom, idf, tf, nf, X, S, SLo1, SGr1, G1, GG1, y
                )
            if not _informs(mode, gp.kernel_id, gp.kernel_params, X, S, n):
                continue  # an empty lane: the prior, without a solve
            if mode != INPUTS_POINTS:
                for i in range(n):
                    for c in range(3):
                        SL[i, c, lane] = S[i, c]
                        SLo[i, c, lane] = SLo1[i, c]
                    GL[i, lane] = G1[i]
                if grouped:
                    for i in range(n):
                        for c in range(3):
                            SGr[i, c, lane] = SGr1[i, c]
                        GGL[i, lane] = GG1[i]
            counts[lane] = n
            nfill = max(nfill, n)
            for i in range(n):
                XL[i, 0, lane] = X[i, 0]
                XL[i, 1, lane] = X[i, 1]
                yL[i, lane] = y[i]
                mask[i, lane] = 1.0
        if nfill == 0:  # no data at all: the prior
            for lane in range(nl):
                out_mean[base + lane] = 0.0
                out_var[base + lane] = kss
                out_prob[base + lane] = _link(gp, 0.0, kss)
            continue
        _pad_lanes(lanes, nfill)
        _solve_lanes(gp, inputs, lanes, nfill)
        _write_lanes(base, nl, nfill, gp, inputs, kss, lanes, one, out_mean, out_var, out_prob)


@nb.njit(cache=True, error_model="numpy", parallel=True)
def predict_batch(queries, points, segments, gp, inputs, out_mean, out_var, out_prob):
    """GPFOL / GPPOL prediction at (Q, 2) ``queries``: writes the mean (eq. 2), latent variance (eq. 3) and
    p(occ) of each into ``out_mean``, ``out_var``, ``out_prob`` (Q,).

    ``points`` (:class:`mapping.index.PointSet`): the occupied endpoints; ``segments``
    (:class:`mapping.index.SegmentSet`): the free segments; ``gp``: a :class:`LocalGP`; ``inputs``: an
    :class:`InputGaussians` (GPFOL: :meth:`InputGaussians.points`; GPPOL: the input Gaussians, the kernel
    integrated over them by the rule it holds). Chunks of ``gp.chunk`` queries run in parallel; inside a
    chunk LANES queries are solved together, and a lane whose Cholesky fails is redone alone with jitter.
    """
    nq = queries.shape[0]
    chunk = gp.chunk
    nchunks = (nq + chunk - 1) // chunk
    kss = _prior_var(gp.kernel_id, gp.kernel_params)
    flat_p = flat_points(points)  # a parallel loop takes flat tuples only (mapping.index)
    flat_s = flat_segments(segments)
    for c in nb.prange(nchunks):
        lo = c * chunk
        hi = min(lo + chunk, nq)
        _predict_chunk(
            queries,
            lo,
            hi,
            points_of(flat_p),
            segments_of(flat_s),
            gp,
            inputs,
            kss,
            out_mean,
            out_var,
            out_prob,
        )


@nb.njit(cache=True, error_model="numpy")
def _noisy_kernel_single(mode, kid, kp, XL, SL, SLo, SGr, GL, GGL, grouped, lane, n, K, ks, gz, gw):
    """The GPPOL blocks of one lane of XL / SL / SLo / SGr / GL / GGL into the full K[:n, :n] and ks[:n]
    (the fallback path); returns k(x*, x*)."""
    X1 = np.empty((n, 2, 1))
    S1 = np.empty((n, 3, 1))
    Lo1 = np.empty((n, 3, 1))
    Gr1 = np.empty((n, 3, 1))
    G1 = np.empty((n, 1))
    GG1 = np.empty((n, 1))
    m1 = np.ones((n, 1))
    for i in range(n):
        X1[i, 0, 0] = XL[i, 0, lane]
        X1[i, 1, 0] = XL[i, 1, lane]
        G1[i, 0] = GL[i, lane]
        GG1[i, 0] = GGL[i, lane]
        for c in range(3):
            S1[i, c, 0] = SL[i, c, lane]
            Lo1[i, c, 0] = SLo[i, c, lane]
            Gr1[i, c, 0] = SGr[i, c, lane]
    K1 = np.empty((n, n, 1))
    ks1 = np.empty((n, 1))
    nodes = gw.shape[0] if mode == INPUTS_GH_NODES else 1
    _noisy_kernel_lanes(
        mode, kid, kp, X1, S1, Lo1, Gr1, G1, GG1, grouped, m1, n, K1, ks1, gz, gw, np.empty((n, nodes, 2, 1)),
        np.empty((n, nodes, 1)),
    )  # fmt: skip
    for i in range(n):
        for j in range(i + 1):
            K[i, j] = K1[i, j, 0]
            K[j, i] = K1[i, j, 0]
        ks[i] = ks1[i, 0]
    return _prior_var(kid, kp)


@nb.njit(cache=True, error_model="numpy", _nrt=False)
def _prior_var(kid, kp):
    """k(x*, x*) in query-centred coordinates."""
    if kid == KERNEL_NN:
        return kp[0] * math.asin(kp[1] / (1.0 + kp[1]))
    return kp[0]


@nb.njit(cache=True, error_model="numpy")
def _gather_chunk(queries, lo, hi, points, segments, k_occ, k_free, out_occ, out_free, out_t):
    """Neighbours of ``queries[lo:hi]`` (see :func:`gather_batch`)."""
    n = hi - lo
    no = np.zeros(n, np.int64)
    nf = np.zeros(n, np.int64)
    ido = np.empty((n, max(k_occ, 1)), np.int64)
    idf = np.empty((n, max(k_free, 1)), np.int64)
    tf = np.empty((n, max(k_free, 1)))
    chunk_neighbours(queries, lo, hi, points, segments, k_occ, k_free, ido, no, idf, tf, nf)
    for j in range(n):
        for i in range(k_occ):
            out_occ[lo + j, i] = ido[j, i] if i < no[j] else -1
        for i in range(k_free):
            out_free[lo + j, i] = idf[j, i] if i < nf[j] else -1
            out_t[lo + j, i] = tf[j, i] if i < nf[j] else 0.0


@nb.njit(cache=True, error_model="numpy", parallel=True)
def gather_batch(queries, points, segments, k_occ, k_free, out_occ, out_free, out_t):
    """Neighbour ids of (Q, 2) queries among ``points`` and ``segments`` (as in :func:`predict_batch`):
    ``out_occ`` (Q, k_occ) endpoint ids, ``out_free`` (Q, k_free) segment ids and ``out_t`` (Q, k_free)
    positions of the free points along them; -1 pads missing neighbours. The same search as
    :func:`predict_batch` (chunks of 256 in parallel, :func:`mapping.blocks.chunk_neighbours`), so that
    timing it isolates the neighbour search."""
    nq = queries.shape[0]
    chunk = 256
    nchunks = (nq + chunk - 1) // chunk
    flat_p = flat_points(points)
    flat_s = flat_segments(segments)
    for c in nb.prange(nchunks):
        lo = c * chunk
        hi = min(lo + chunk, nq)
        _gather_chunk(
            queries, lo, hi, points_of(flat_p), segments_of(flat_s), k_occ, k_free, out_occ, out_free, out_t
        )
