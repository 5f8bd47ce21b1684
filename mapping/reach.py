"""Where the training data can inform a GP map: a raster of the places within a stationary kernel's reach.

A local GP (paper section 3.5) with a kernel that decays with distance predicts the prior at a query whose
training inputs all lie far away: the mean (eq. 2) is ``k*^T (K + sigma_n^2 I)^-1 y`` and every entry of
``k*`` vanishes, the variance (eq. 3) is ``k(x*, x*)``. Most cells of a large building's bounding box are
such places (outside the walls, beyond the courtyards), yet finding their neighbours walks many empty
index cells. :class:`ReachMask` marks the places some training input can reach; the map answers the
others with the prior at once (:meth:`mapping.gpmap.GPOccupancyMap.query`), so a map's cost follows its
data, not its bounding box.

The reach of an input is where its kernel falls below a tolerance ``tol`` of the signal variance:
``r0`` for an exact input (``k(r0) = tol k(0)``) plus ``c sqrt(lambda)`` for a Gaussian input whose
covariance's largest eigenvalue is at most ``lambda`` (GPPOL, eq. 17-19). For the SE kernel's closed form
the expected kernel is at most ``l / sqrt(l^2 + lambda) exp(-d^2 / (2 (l^2 + lambda)))`` of ``k(0)``, which
is what the map uses (:func:`se_girard_reach_m`: an input spread over metres reaches little); a quadrature
rule puts its nodes at most ``|z|max sqrt(lambda)`` from the mean: ``c`` is that (:func:`spread_factor`).
A free segment is bounded piece by piece (:data:`REACH_PIECE_M`): a long beam's covariance grows along it.
Under the closed form, an input whose expected kernel nowhere exceeds :data:`REACH_MIN_PEAK` of ``k(0)``
(metres-uncertain scans, e.g. where passes disagree) marks nothing: where sharper inputs are near, they are
a place's nearest inputs and it is solved as before; where only such inputs are near, the place reads the
prior, which they would have moved only slightly (``tests/test_mapping_reach.py`` measures how little).
The neural-network kernel (eq. 7) does not decay: its maps keep every cell (no mask).

How far is "beyond reach" (:func:`reach_tolerance`)? Where every training input's kernel is at most
``t k(0)``, the variance reduction of eq. (3) for ``m`` neighbours is at most
``|k*|^2 / sigma_n^2 <= m t^2 k(0)^2 / sigma_n^2``: ``K + sigma_n^2 I`` has no eigenvalue below
``sigma_n^2`` since ``K`` is positive semi-definite (GPPOL's expected kernel too: an expectation of kernel
matrices). With ``t^2 = rho sigma_n^2 / (m k(0))`` the variance there provably stays above ``1 - rho`` of
the prior: with ``rho = 1 - unknown_variance_fraction`` the place is *unknown* (:mod:`mapping.exports`)
whether it is solved or not, and it reads the prior unsolved. :data:`REACH_TOLERANCE` is the floor (a
fraction near 1, a tiny noise), and the tolerance of a map built without a fraction.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba as nb
import numpy as np
from numpy.typing import NDArray

from mapping.kernels import Kernel
from mapping.raster import within_distance

FloatArray = NDArray[np.float64]

#: The least k(d) / k(0) beyond an input's reach (:func:`reach_tolerance`). The local GP keeps only the
#: nearest inputs, so the places beyond every reach at this tolerance read the prior to about float32's
#: resolution (tests/test_mapping_reach.py).
REACH_TOLERANCE = 1e-4
#: Reaches are grouped into classes whose largest reach is at most this factor above their smallest
#: (one distance transform each) ...
REACH_CLASS_RATIO = 1.2
#: ... and at most this many classes (the ratio grows where the reaches span more).
REACH_CLASSES = 16
#: A Gaussian input whose expected SE kernel nowhere exceeds this share of ``k(0)`` (a position spread above
#: about 50 length scales) makes no place near by itself (:func:`se_girard_peak`).
REACH_MIN_PEAK = 0.02
#: Free segments are bounded piece by piece, at most this long, so that the uncertain far end of a long beam
#: does not widen the reach of its precise near end.
REACH_PIECE_M = 8.0


def kernel_reach_m(kernel: Kernel, tolerance: float = REACH_TOLERANCE) -> float | None:
    """``r0``: the distance beyond which the stationary ``kernel`` is below ``tolerance`` of ``k(0)``
    (bisection on :meth:`~mapping.kernels.Kernel.of_difference`); None for a kernel that is not stationary
    (it need not decay)."""
    if not kernel.stationary:
        return None
    k0 = float(kernel.of_difference(np.zeros((1, 2)))[0])

    def above(r: float) -> bool:
        return float(kernel.of_difference(np.array([[r, 0.0]]))[0]) > tolerance * k0

    hi = 1.0
    while above(hi):
        hi *= 2.0
    lo = 0.0
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if above(mid) else (lo, mid)
    return hi


def reach_tolerance(
    noise_var: float, prior_var: float, neighbours: int, unknown_variance_fraction: float | None
) -> float:
    """``t``: beyond the reach of every input at this tolerance the local GP of ``neighbours`` inputs (noise
    ``noise_var``, prior variance ``k(0) = prior_var``) keeps a variance above ``unknown_variance_fraction``
    of the prior, so the place is unknown anyway (module docstring); at least :data:`REACH_TOLERANCE`, which
    is also the tolerance of ``None`` (the prior only where a solve would give it to float32)."""
    if unknown_variance_fraction is None or prior_var <= 0 or neighbours <= 0:
        return REACH_TOLERANCE
    rho = max(0.0, 1.0 - float(unknown_variance_fraction))
    return max(REACH_TOLERANCE, math.sqrt(rho * max(float(noise_var), 0.0) / (neighbours * prior_var)))


def spread_factor(max_node_norm: float) -> float:
    """``c``: under a quadrature rule whose largest standard node has norm ``max_node_norm``, an input of
    largest covariance eigenvalue ``lambda`` reaches ``c sqrt(lambda)`` further than an exact one."""
    return float(max_node_norm)


def se_girard_reach_m(
    length_scale_m: float,
    largest_var_m2: FloatArray,
    tolerance: float = REACH_TOLERANCE,
    least_var_m2: FloatArray | None = None,
) -> FloatArray:
    """(...,) reaches of Gaussian inputs under the SE kernel integrated in closed form (eq. 19): the
    expected kernel ``sigma_f^2 l^2 / sqrt(det(l^2 I + Sigma)) exp(-d^T (l^2 I + Sigma)^-1 d / 2)`` is at
    most ``A exp(-d^2 / (2 u))`` with ``u = l^2 + lambda``, ``A = l / sqrt(u)`` (``lambda`` >= the largest
    eigenvalue of ``Sigma``, ``largest_var_m2``), below ``tolerance`` beyond ``sqrt(2 u ln(A / tol))``
    (0 where ``A`` <= tol: so spread an input that it never matters). The reach grows with ``lambda`` for
    ``u`` up to ``u* = l^2 / (e tol^2)`` and shrinks beyond. Where the eigenvalue is known only to lie in
    ``[least_var_m2, largest_var_m2]`` (a free segment's piece), the reach is the largest over that range:
    at ``u*`` clipped into it."""
    ell2 = float(length_scale_m) ** 2
    u = ell2 + np.maximum(np.asarray(largest_var_m2, dtype=np.float64), 0.0)
    if least_var_m2 is not None:
        u_lo = ell2 + np.maximum(np.asarray(least_var_m2, dtype=np.float64), 0.0)
        u = np.clip(ell2 / (math.e * tolerance**2), np.minimum(u_lo, u), u)
    log_ratio = np.log(float(length_scale_m) / (np.sqrt(u) * tolerance))
    return np.sqrt(2.0 * u * np.maximum(log_ratio, 0.0))


def se_girard_peak(length_scale_m: float, var_m2: FloatArray) -> FloatArray:
    """(...,) upper bounds of the expected SE kernel (eq. 19) over ``k(0)`` of Gaussian inputs whose
    covariance's largest eigenvalue is at least ``var_m2``: ``l^2 / sqrt(det(l^2 I + Sigma)) <= l / sqrt(l^2 +
    lambda)`` at any distance."""
    ell = float(length_scale_m)
    return ell / np.sqrt(ell**2 + np.maximum(np.asarray(var_m2, dtype=np.float64), 0.0))


def segment_pieces(
    lengths_m: FloatArray, piece_m: float = REACH_PIECE_M
) -> tuple[NDArray[np.int64], FloatArray, FloatArray]:
    """The (S,) segments of ``lengths_m`` cut into pieces of at most ``piece_m`` (a segment of length 0 is one
    piece): for each piece its segment, and where it starts and ends along it (m), each (P,)."""
    lengths = np.asarray(lengths_m, dtype=np.float64)
    counts = np.maximum(1, np.ceil(lengths / piece_m)).astype(np.int64)
    which = np.repeat(np.arange(lengths.size), counts)
    k = np.arange(which.size) - np.repeat(np.cumsum(counts) - counts, counts)
    step = lengths[which] / counts[which]
    return which, k * step, (k + 1) * step


def quadratic_range(
    c0: FloatArray, c1: FloatArray, c2: FloatArray, a: FloatArray, b: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """The smallest and largest values of ``c0 + d c1 + d^2 c2`` over ``d`` in ``[a, b]`` (elementwise): at an
    end or at the vertex."""
    ends_a = c0 + a * (c1 + a * c2)
    ends_b = c0 + b * (c1 + b * c2)
    v = np.clip(np.divide(-c1, 2.0 * c2, out=np.zeros_like(c1), where=c2 != 0), a, b)
    at_v = c0 + v * (c1 + v * c2)
    return np.minimum(np.minimum(ends_a, ends_b), at_v), np.maximum(np.maximum(ends_a, ends_b), at_v)


def largest_eigenvalue(packed_cov: FloatArray) -> FloatArray:
    """(...,) largest eigenvalues of (..., 3) packed symmetric 2x2 matrices ``(xx, xy, yy)`` (>= 0)."""
    p = np.asarray(packed_cov, dtype=np.float64)
    half = 0.5 * (p[..., 0] + p[..., 2])
    rad = np.hypot(0.5 * (p[..., 0] - p[..., 2]), p[..., 1])
    return np.maximum(half + rad, 0.0)


@nb.njit(cache=True, error_model="numpy")
def _mark(starts, ends, cls, x0, y0, cell, nx, ny, out):
    """Mark in ``out[cls[i]]`` (C, ny, nx) the cells of the points sampled every half cell along each segment
    ``starts[i] -> ends[i]`` (a point where both are equal)."""
    step = 0.5 * cell
    for i in range(starts.shape[0]):
        ax, ay = starts[i, 0], starts[i, 1]
        dx, dy = ends[i, 0] - ax, ends[i, 1] - ay
        n = math.ceil(math.sqrt(dx * dx + dy * dy) / step) + 1
        for s in range(n + 1):
            t = s / n if n > 0 else 0.0
            ix = math.floor((ax + t * dx - x0) / cell)
            iy = math.floor((ay + t * dy - y0) / cell)
            if 0 <= ix < nx and 0 <= iy < ny:
                out[cls[i], iy, ix] = True


@dataclass(frozen=True)
class ReachMask:
    """``near`` (H, W) bool on a raster of ``cell_m`` whose lower-left corner is ``origin_xy_m``: True where
    some training input may reach (conservatively: every place within reach is True, a few beyond may be).
    Everything outside the raster is beyond reach."""

    near: NDArray[np.bool_]
    origin_xy_m: tuple[float, float]
    cell_m: float

    def _cells(self, v_m: FloatArray, axis: int) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
        """The raster column (``axis`` 0, from x) or row (1, from y) of each coordinate of ``v_m``, 0 where
        it lies off the raster, and whether it lies on it."""
        i = np.floor((np.asarray(v_m, dtype=np.float64) - self.origin_xy_m[axis]) / self.cell_m)
        inside = (i >= 0) & (i < self.near.shape[1 - axis])
        return np.where(inside, i, 0).astype(np.int64), inside

    def contains(self, points_xy_m: FloatArray) -> NDArray[np.bool_]:
        """(P,) bool: which of the (P, 2) points lie within some input's reach."""
        pts = np.asarray(points_xy_m, dtype=np.float64).reshape(-1, 2)
        cols, in_x = self._cells(pts[:, 0], 0)
        rows, in_y = self._cells(pts[:, 1], 1)
        if self.near.size == 0:
            return np.zeros(pts.shape[0], dtype=bool)
        return self.near[rows, cols] & in_x & in_y

    def contains_grid(self, xs_m: FloatArray, ys_m: FloatArray) -> NDArray[np.bool_]:
        """(H, W) bool: :meth:`contains` of the grid points ``(xs_m[j], ys_m[i])`` of the (W,) and (H,)
        coordinates, looked up once per row and column instead of per point."""
        cols, in_x = self._cells(xs_m, 0)
        rows, in_y = self._cells(ys_m, 1)
        if self.near.size == 0:
            return np.zeros((rows.size, cols.size), dtype=bool)
        return self.near[np.ix_(rows, cols)] & in_y[:, None] & in_x[None, :]

    @property
    def share(self) -> float:
        """The share of the raster's cells within reach."""
        return float(self.near.mean()) if self.near.size else 0.0


def reach_mask(
    starts_xy_m: FloatArray,
    ends_xy_m: FloatArray,
    reach_m: FloatArray,
    cell_m: float | None = None,
    classes: int = REACH_CLASSES,
    class_ratio: float = REACH_CLASS_RATIO,
) -> ReachMask:
    """The :class:`ReachMask` of training inputs lying on the (S, 2) -> (S, 2) segments ``starts_xy_m`` ->
    ``ends_xy_m`` (a point input: start = end), each reaching ``reach_m`` (S,) metres.

    The segments are marked on a raster of ``cell_m`` (default a quarter of the 10th percentile of the
    reaches; inputs of reach 0 are left out), grouped by reach into geometric classes (each class's reaches
    within ``class_ratio``, at most ``classes`` of them), one Euclidean distance transform per class (on a
    coarser raster for long reaches, :func:`_class_near`). A place is near where its cell lies within its
    class's largest reach plus ``cell (sqrt 2 + 1/4)`` of a marked cell: half a diagonal for the query
    inside its cell, half for the input inside its cell, a quarter cell for the sampling along the
    segment."""
    starts = np.ascontiguousarray(starts_xy_m, dtype=np.float64).reshape(-1, 2)
    ends = np.ascontiguousarray(ends_xy_m, dtype=np.float64).reshape(-1, 2)
    reach = np.asarray(reach_m, dtype=np.float64).reshape(-1)
    if not (starts.shape == ends.shape and reach.shape[0] == starts.shape[0]):
        raise ValueError(f"segments {starts.shape} -> {ends.shape} with {reach.shape[0]} reaches")
    if not (np.all(np.isfinite(starts)) and np.all(np.isfinite(ends)) and np.all(np.isfinite(reach))):
        raise ValueError("reach_mask needs finite segments and reaches")
    reaching = reach > 0  # an input of reach 0 never matters
    starts, ends, reach = starts[reaching], ends[reaching], reach[reaching]
    if starts.shape[0] == 0:
        return ReachMask(np.zeros((0, 0), dtype=bool), (0.0, 0.0), 1.0)
    cell = float(cell_m) if cell_m is not None else float(np.clip(np.quantile(reach, 0.1) / 4.0, 0.05, 2.0))
    margin = cell * (math.sqrt(2.0) + 0.25)
    grow = float(reach.max()) + margin + cell
    lo = np.minimum(starts.min(axis=0), ends.min(axis=0)) - grow
    hi = np.maximum(starts.max(axis=0), ends.max(axis=0)) + grow
    nx, ny = (int(v) for v in np.ceil((hi - lo) / cell))
    r_lo, r_hi = float(reach.min()), float(reach.max())
    n_edges = 0
    if r_hi > r_lo * class_ratio:
        n_edges = min(max(1, classes) - 1, math.ceil(math.log(r_hi / r_lo) / math.log(class_ratio)) - 1)
    edges = r_lo * (r_hi / r_lo) ** (np.arange(1, n_edges + 1) / (n_edges + 1)) if n_edges else np.zeros(0)
    cls = np.searchsorted(edges, reach, side="left").astype(np.int64)  # reach <= edges[c] -> class c
    near = np.zeros((ny, nx), dtype=bool)
    for c in range(edges.size + 1):
        members = cls == c
        if members.any():
            near |= _class_near(starts[members], ends[members], float(reach[members].max()), lo, cell, nx, ny)
    return ReachMask(near, (float(lo[0]), float(lo[1])), cell)


def _class_near(
    starts: FloatArray, ends: FloatArray, reach_m: float, lo: FloatArray, cell: float, nx: int, ny: int
) -> NDArray[np.bool_]:
    """(ny, nx) near cells of the raster (corner ``lo``, ``cell``) for inputs on ``starts`` -> ``ends`` all
    reaching at most ``reach_m``. A class of long reach is transformed on a raster of up to ``reach_m / 16``
    (cheap), then read at the fine cells' centres: a query of a fine cell may lie in the next coarse cell,
    half a fine diagonal more margin."""
    coarse = max(cell, reach_m / 16.0)
    cx, cy = (nx, ny) if coarse == cell else (max(1, math.ceil(n * cell / coarse)) for n in (nx, ny))
    marked = np.zeros((1, cy, cx), dtype=np.bool_)
    _mark(
        starts, ends, np.zeros(starts.shape[0], np.int64), float(lo[0]), float(lo[1]), coarse, cx, cy, marked
    )
    margin = coarse * (math.sqrt(2.0) + 0.25) + (cell * math.sqrt(0.5) if coarse > cell else 0.0)
    near = within_distance(marked[0], (reach_m + margin) / coarse)
    if coarse == cell:
        return near
    cols = np.minimum(((np.arange(nx) + 0.5) * cell / coarse).astype(np.int64), cx - 1)
    rows = np.minimum(((np.arange(ny) + 0.5) * cell / coarse).astype(np.int64), cy - 1)
    return near[np.ix_(rows, cols)]
