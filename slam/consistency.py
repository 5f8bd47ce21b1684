"""How consistently each scan is placed relative to the other passes over the places it sees.

The covariance a map needs is not a pose's world-frame marginal. A marginal is the uncertainty relative to
the graph's anchor (the first pose): it grows with the distance travelled from it even where every scan
agrees with its neighbours, and it changes when the graph is anchored elsewhere. Fed to GPPOL it blurs whole
regions that are locally consistent. What makes a map inconsistent is two passes over one place that the
trajectory places inconsistently (a doubled wall); what the mapper needs is the uncertainty of a scan
relative to the other scans that observe the same place. This module computes that, as a covariance per
keyframe:

- **Revisits** (:func:`revisit_partners`): the keyframes' scan endpoints fall into coarse cells; a cell's
  *visits* are the runs of keyframes that observe it without the robot travelling ``revisit_gap_m`` out of
  its sight. Keyframe ``j`` is a *partner* of a later keyframe ``k`` when at least ``min_shared`` of ``k``'s
  cells are ones ``j`` saw in an earlier visit: an earlier pass over the place ``k`` observes.
- **Relative covariances** (:class:`RelativeCovariance`): the covariance of ``between(x_j, x_k)`` in the
  linearised pose graph -- the conditional covariance of ``x_k`` given ``x_j``, which does not depend on
  where (or how tightly) the graph is anchored. The graph's information matrix is factorised once (sparse
  LU of a symmetric positive definite matrix, so ``P H P^T = L D L^T``); each pair is one sparse forward
  substitution, ``S = Y^T D^-1 Y`` with ``Y = L^-1 P A`` and ``A`` the (3K, 3) Jacobian of the relative
  pose.
- **The scan's covariance for the map** (:func:`consistency_covariances_body`): the smallest relative
  covariance (by its effect on the map, position plus rotation times a lever arm) of ``k`` to any partner;
  where no earlier pass sees ``k``'s place, the local odometry uncertainty (its covariance relative to the
  previous keyframe). The first pass over a place is the local anchor, as for a mapper that builds its map
  incrementally: it stays sharp. After loop closure a later pass is as uncertain as the optimised graph
  says it is relative to it: small where closures tie them together, large where the closure search found
  nothing. Before loop closure the odometry places a later pass as inconsistently as the correction loop
  closure applies to it (:func:`closure_corrections`): sharp where the odometry's passes agree, uncertain
  where the closure will move them (:func:`keyframe_consistency_body`).

Literature: relative (rather than absolute) uncertainty as what matters locally in a pose graph, e.g.
Olson, Leonard & Teller (ICRA 2006) and the relative-error metric of Kuemmerle et al. (2009); the joint
marginals of iSAM (Kaess & Dellaert, 2009). Computing them from one sparse factorisation is ours.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numba as nb
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spl
from numpy.typing import NDArray

from slam import geometry as se2
from slam.config import ConsistencyConfig
from slam.graph import Edge, PoseGraphError, edge_errors2

FloatArray = NDArray[np.float64]


# ------------------------------------------------------------------------------------ information matrix


def _robust_weights(poses_xytheta: FloatArray, edges: Sequence[Edge]) -> FloatArray:
    """(E,) the weight the robust loss of each edge gives its residual at ``poses_xytheta`` (1 without one):
    iteratively re-weighted least squares, as GTSAM linearises a robust noise model."""
    e = np.sqrt(np.maximum(edge_errors2(poses_xytheta, list(edges)), 0.0))
    kind = np.array([edge.robust for edge in edges])
    c = np.array([edge.robust_width for edge in edges], dtype=np.float64)
    w = np.ones(len(edges))
    huber = (kind == "huber") & (e > c)
    w[huber] = c[huber] / e[huber]
    cauchy = kind == "cauchy"
    w[cauchy] = 1.0 / (1.0 + (e[cauchy] / c[cauchy]) ** 2)
    dcs = kind == "dcs"
    w[dcs] = np.minimum(1.0, 2.0 * c[dcs] / (c[dcs] + e[dcs] ** 2)) ** 2
    return w


def information_matrix(poses_xytheta: FloatArray, edges: Sequence[Edge]) -> sp.csc_matrix:
    """(3K, 3K) information matrix ``J^T W J`` of a ``Pose2`` graph linearised at ``poses_xytheta`` (K, 3).

    Tangent coordinates are GTSAM's right perturbations (body frame, order x, y, theta). A between factor
    ``z ~ between(x_i, x_j)`` has Jacobians ``-Ad(between(x_i, x_j)^-1)`` (on ``x_i``) and ``I`` (on
    ``x_j``), exact where its residual vanishes (GTSAM's also carry the derivative of the residual's
    Logmap, a second-order difference at a consistent estimate); robust losses weight their factor as at
    the current residual."""
    poses = np.asarray(poses_xytheta, dtype=np.float64)
    k = len(poses)
    edges = list(edges)
    if not edges:
        return sp.csc_matrix((3 * k, 3 * k))
    w = np.linalg.inv(np.stack([e.cov for e in edges])) * _robust_weights(poses, edges)[:, None, None]
    i = np.array([e.key_from for e in edges], dtype=np.int64)
    j = np.array([e.key_to for e in edges], dtype=np.int64)
    prior = np.array([e.kind == "prior" for e in edges])
    ji = -se2.adjoint(se2.inverse(se2.between(poses[i], poses[j])))
    jit = np.swapaxes(ji, 1, 2)
    blocks = [
        (i[prior], i[prior], w[prior]),
        (i[~prior], i[~prior], (jit @ w @ ji)[~prior]),
        (i[~prior], j[~prior], (jit @ w)[~prior]),
        (j[~prior], i[~prior], (w @ ji)[~prior]),
        (j[~prior], j[~prior], w[~prior]),
    ]
    r3, c3 = np.meshgrid(np.arange(3), np.arange(3), indexing="ij")
    rows = np.concatenate([(3 * a[:, None, None] + r3).ravel() for a, _, _ in blocks])
    cols = np.concatenate([(3 * b[:, None, None] + c3).ravel() for _, b, _ in blocks])
    vals = np.concatenate([m.ravel() for _, _, m in blocks])
    return sp.csc_matrix((vals, (rows, cols)), shape=(3 * k, 3 * k))


@nb.njit(cache=True)
def _pair_covariances(
    l_indptr: NDArray[np.int32],
    l_indices: NDArray[np.int32],
    l_data: FloatArray,
    inv_d: FloatArray,
    perm: NDArray[np.int64],
    keys_from: NDArray[np.int64],
    keys_to: NDArray[np.int64],
    m_from: FloatArray,
) -> FloatArray:
    """(P, 3, 3) ``A^T H^-1 A`` for each pair, ``A`` = ``m_from[p]^T`` at ``keys_from[p]``'s rows and ``I`` at
    ``keys_to[p]``'s; ``P H P^T = L D L^T`` (``L`` unit lower triangular, CSC; ``perm[i]``: the row of
    variable ``i`` in the factor)."""
    n = inv_d.shape[0]
    out = np.zeros((keys_from.shape[0], 3, 3))
    y = np.zeros((n, 3))
    for p in range(keys_from.shape[0]):
        lo = n
        for r in range(3):
            for c in range(3):
                row = perm[3 * keys_from[p] + r]
                y[row, c] += m_from[p, c, r]
                lo = min(lo, row)
            row = perm[3 * keys_to[p] + r]
            y[row, r] += 1.0
            lo = min(lo, row)
        acc = np.zeros((3, 3))
        for col in range(lo, n):
            y0 = y[col, 0]
            y1 = y[col, 1]
            y2 = y[col, 2]
            if y0 == 0.0 and y1 == 0.0 and y2 == 0.0:
                continue
            for idx in range(l_indptr[col], l_indptr[col + 1]):
                row = l_indices[idx]
                if row > col:
                    v = l_data[idx]
                    y[row, 0] -= v * y0
                    y[row, 1] -= v * y1
                    y[row, 2] -= v * y2
            w = inv_d[col]
            acc[0, 0] += w * y0 * y0
            acc[0, 1] += w * y0 * y1
            acc[0, 2] += w * y0 * y2
            acc[1, 1] += w * y1 * y1
            acc[1, 2] += w * y1 * y2
            acc[2, 2] += w * y2 * y2
            y[col, 0] = 0.0
            y[col, 1] = 0.0
            y[col, 2] = 0.0
        acc[1, 0] = acc[0, 1]
        acc[2, 0] = acc[0, 2]
        acc[2, 1] = acc[1, 2]
        out[p] = acc
    return out


class RelativeCovariance:
    """Covariances of relative poses ``between(x_j, x_k)`` of a pose graph, from one sparse factorisation.

    ``poses_xytheta`` (K, 3): the linearisation point (the graph's estimate); ``edges``: its factors
    (:class:`slam.graph.Edge`, a prior among them or not: relative covariances do not depend on the gauge,
    but the factorisation needs one, so a graph without a prior gets a unit one on keyframe 0, which
    changes no relative covariance)."""

    def __init__(self, poses_xytheta: FloatArray, edges: Sequence[Edge]) -> None:
        self.poses_xytheta = np.asarray(poses_xytheta, dtype=np.float64)
        k = len(self.poses_xytheta)
        edges = list(edges)
        if k and not any(e.kind == "prior" for e in edges):
            edges.append(Edge("prior", 0, 0, self.poses_xytheta[0], np.eye(3)))
        h = information_matrix(self.poses_xytheta, edges)
        try:
            lu = spl.splu(
                h,
                permc_spec="MMD_AT_PLUS_A",
                diag_pivot_thresh=0.0,
                options={"SymmetricMode": True},
            )
        except RuntimeError as exc:  # a singular system: a keyframe no factor constrains
            raise PoseGraphError(f"pose graph: cannot factorise its information matrix ({exc})") from None
        if not np.array_equal(lu.perm_r, lu.perm_c):
            raise PoseGraphError("pose graph: its information matrix needed pivoting (not positive definite)")
        d = lu.U.diagonal()
        if np.any(~np.isfinite(d)) or np.any(d <= 0):
            raise PoseGraphError("pose graph: its information matrix is not positive definite")
        lower = lu.L.tocsc()
        self._l_indptr = lower.indptr.astype(np.int32)
        self._l_indices = lower.indices.astype(np.int32)
        self._l_data = lower.data.astype(np.float64)
        self._inv_d = 1.0 / d
        self._perm = np.asarray(lu.perm_r, dtype=np.int64)

    def between_body(self, keys_from: NDArray, keys_to: NDArray) -> FloatArray:
        """(P, 3, 3) covariance of ``between(x_from, x_to)`` in ``x_to``'s body frame for each pair: with
        right perturbations ``a``, ``b`` the relative pose ``D = x_from^-1 x_to`` moves by
        ``b - Ad(D^-1) a``."""
        kf = np.asarray(keys_from, dtype=np.int64).reshape(-1)
        kt = np.asarray(keys_to, dtype=np.int64).reshape(-1)
        if kf.size == 0:
            return np.zeros((0, 3, 3))
        k = len(self.poses_xytheta)
        if kf.shape != kt.shape or min(kf.min(), kt.min()) < 0 or max(kf.max(), kt.max()) >= k:
            raise ValueError(f"keyframe pairs must be two equal-length lists of keys in 0..{k - 1}")
        d = se2.between(self.poses_xytheta[kf], self.poses_xytheta[kt])
        m_from = -se2.adjoint(se2.inverse(d))
        out = _pair_covariances(
            self._l_indptr,
            self._l_indices,
            self._l_data,
            self._inv_d,
            self._perm,
            kf,
            kt,
            np.ascontiguousarray(m_from),
        )
        return 0.5 * (out + np.swapaxes(out, -1, -2))


# --------------------------------------------------------------------------------------------- revisits


def keyframe_cells(
    poses_xytheta: FloatArray, points_base: Sequence[FloatArray], cell_m: float
) -> sp.csr_matrix:
    """(K, C) 0/1 matrix: the coarse cells (``cell_m`` a side, world frame) that each keyframe's scan
    endpoints (``points_base[k]`` (P_k, 2) in its base frame) fall into, at the keyframe poses (K, 3)."""
    rows: list[NDArray] = []
    keys: list[NDArray] = []
    poses = np.asarray(poses_xytheta, dtype=np.float64)
    for k, (pose, pts) in enumerate(zip(poses, points_base, strict=True)):
        pts = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
        if len(pts) == 0:
            continue
        ij = np.floor(se2.transform_points(pose, pts) / cell_m).astype(np.int64)
        cell = np.unique(ij[:, 0] * 2_000_003 + ij[:, 1])
        rows.append(np.full(len(cell), k, dtype=np.int64))
        keys.append(cell)
    k_count = len(points_base)
    if not rows:
        return sp.csr_matrix((k_count, 0))
    _, col = np.unique(np.concatenate(keys), return_inverse=True)
    row = np.concatenate(rows)
    return sp.csr_matrix(
        (np.ones(len(row), dtype=np.float64), (row, col)), shape=(k_count, int(col.max()) + 1)
    )


def revisit_partners(
    cells: sp.csr_matrix,
    path_m: FloatArray,
    gap_m: float,
    min_shared: float,
    max_partners: int,
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Pairs ``(j, k)``: keyframe ``j`` belongs to another pass over the place keyframe ``k`` observes.

    ``cells`` (K, C) from :func:`keyframe_cells`; ``path_m`` (K,) the distance travelled to each keyframe.
    A *visit* of a cell is a run of keyframes observing it in which no two consecutive observers lie more
    than ``gap_m`` of travel apart: the robot left the place and came back in between. ``j`` qualifies
    when the cells it shares with ``k`` in different visits are at least ``min_shared`` of ``k``'s cells
    (a long corridor seen along its length over one pass is one visit of each of its cells, so the scans of
    that pass are not each other's partners). Of those, up to ``max_partners`` sharing the most cells, each
    at least ``gap_m`` of travel from the ones taken before it (one per pass); only ``j < k``. Returns
    ``(keys_from, keys_to)``: the partners ``j``, their keyframes ``k``."""
    path = np.asarray(path_m, dtype=np.float64)
    k_count = cells.shape[0]
    coo = cells.tocoo()
    by_cell = np.lexsort((coo.row, coo.col))
    kf, cell = coo.row[by_cell].astype(np.int64), coo.col[by_cell].astype(np.int64)
    new_visit = np.ones(len(kf), dtype=bool)
    if len(kf) > 1:
        same_cell = cell[1:] == cell[:-1]
        new_visit[1:] = ~same_cell | (path[kf[1:]] - path[kf[:-1]] > gap_m)
    visit = np.cumsum(new_visit) - 1
    visits = sp.csr_matrix(
        (np.ones(len(kf)), (kf, visit)), shape=(k_count, int(visit[-1]) + 1 if len(visit) else 0)
    )
    n_cells = np.asarray(cells.sum(axis=1)).ravel()
    cells_t, visits_t = cells.T.tocsc(), visits.T.tocsc()
    out_from: list[int] = []
    out_to: list[int] = []
    chunk = 512
    for start in range(0, k_count, chunk):
        # cells shared in different visits = all shared cells - those shared within one visit
        shared = (cells[start : start + chunk] @ cells_t - visits[start : start + chunk] @ visits_t).tocsr()
        shared.eliminate_zeros()
        for r in range(shared.shape[0]):
            k = start + r
            lo, hi = shared.indptr[r], shared.indptr[r + 1]
            js = shared.indices[lo:hi]
            counts = shared.data[lo:hi]
            ok = (counts >= min_shared * max(n_cells[k], 1.0)) & (js < k)
            if not np.any(ok):
                continue
            js, counts = js[ok], counts[ok]
            taken: list[int] = []
            for idx in np.argsort(-counts, kind="stable"):
                j = int(js[idx])
                if all(abs(path[j] - path[t]) >= gap_m for t in taken):
                    taken.append(j)
                    if len(taken) >= max_partners:
                        break
            out_from.extend(taken)
            out_to.extend([k] * len(taken))
    return np.asarray(out_from, dtype=np.int64), np.asarray(out_to, dtype=np.int64)


def map_effect(cov_body: FloatArray, lever_m: FloatArray) -> FloatArray:
    """(...,) how far a pose error of covariance ``cov_body`` (..., 3, 3) moves what the scan sees:
    position variance plus heading variance times the squared lever arm ``lever_m`` (...,) (m^2)."""
    c = np.asarray(cov_body, dtype=np.float64)
    return c[..., 0, 0] + c[..., 1, 1] + np.asarray(lever_m) ** 2 * c[..., 2, 2]


def consistency_covariances_body(
    local: RelativeCovariance,
    partners: tuple[NDArray[np.int64], NDArray[np.int64]],
    pair_covs_body: FloatArray,
    lever_m: FloatArray,
) -> FloatArray:
    """(K, 3, 3) body-frame covariance of each keyframe relative to its revisit partners.

    ``partners`` ``(j, k)`` (P pairs, :func:`revisit_partners`) with ``pair_covs_body`` (P, 3, 3), the
    covariance of ``k`` relative to ``j`` in ``k``'s frame: each keyframe takes the one with the smallest
    :func:`map_effect` (``lever_m`` (K,)). A keyframe without a partner takes its covariance relative to
    the previous keyframe in the graph ``local`` (the first one: to the next): the local odometry
    uncertainty."""
    k_count = len(local.poses_xytheta)
    out = np.zeros((k_count, 3, 3))
    if k_count < 2:
        return out
    keys = np.arange(k_count)
    out[:] = local.between_body(np.where(keys == 0, 1, keys - 1), keys)
    j, k = partners
    if len(j):
        effect = map_effect(pair_covs_body, np.asarray(lever_m)[k])
        order = np.lexsort((effect, k))  # by keyframe, then by effect: the first of each keyframe is best
        first = order[np.unique(k[order], return_index=True)[1]]
        out[k[first]] = pair_covs_body[first]
    return out


def closure_corrections(
    poses_before_xytheta: FloatArray,
    poses_after_xytheta: FloatArray,
    keys_from: NDArray[np.int64],
    keys_to: NDArray[np.int64],
) -> FloatArray:
    """(P, 3) how loop closure changes the relative pose of each pair: ``Log(D_after^-1 D_before)`` with
    ``D = between(x_from, x_to)``, in ``x_to``'s frame (the odometry's error of ``x_to`` relative to
    ``x_from``, as the optimised graph sees it)."""
    b = np.asarray(poses_before_xytheta, dtype=np.float64)
    a = np.asarray(poses_after_xytheta, dtype=np.float64)
    d_before = se2.between(b[keys_from], b[keys_to])
    d_after = se2.between(a[keys_from], a[keys_to])
    return se2.logmap(se2.between(d_after, d_before))


def keyframe_consistency_body(
    poses_before_xytheta: FloatArray,
    poses_after_xytheta: FloatArray,
    edges_after: Sequence[Edge],
    points_base: Sequence[FloatArray],
    path_m: FloatArray,
    cfg: ConsistencyConfig,
) -> tuple[FloatArray, FloatArray]:
    """(K, 3, 3) body-frame consistency covariances of the K keyframes before and after loop closure.

    ``poses_before_xytheta`` / ``poses_after_xytheta`` (K, 3): the odometry chain and the optimised graph;
    ``edges_after``: the optimised graph's factors (a prior, the odometry chain, the loop closures);
    ``points_base``: each keyframe's scan points (P_k, 2) in its base frame; ``path_m`` (K,): travel to
    each keyframe. Which passes see the same place is decided on the optimised poses (the best knowledge
    of it), for both maps.

    After loop closure a keyframe is as uncertain relative to an earlier pass as the optimised graph says.
    Before it, the odometry places the passes as they are: inconsistent by the correction that loop closure
    applies to their relative pose (:func:`closure_corrections`), whose own uncertainty is the optimised
    graph's, so the covariance is ``e e^T + S_after``: sharp where the passes of the odometry agree,
    uncertain where the closure moves them apart. Without a partner: the local odometry uncertainty of the
    graph (the chain before, the optimised graph after)."""
    cells = keyframe_cells(poses_after_xytheta, points_base, cfg.cell_m)
    j, k = revisit_partners(cells, path_m, cfg.revisit_gap_m, cfg.min_shared, cfg.max_partners)
    lever = np.array(
        [math.sqrt(float(np.mean(np.sum(np.square(p), axis=1)))) if len(p) else 1.0 for p in points_base]
    )
    optimised = RelativeCovariance(poses_after_xytheta, edges_after)
    pair_after = optimised.between_body(j, k)
    after = consistency_covariances_body(optimised, (j, k), pair_after, lever)
    chain = RelativeCovariance(poses_before_xytheta, [e for e in edges_after if e.kind != "loop"])
    e = closure_corrections(poses_before_xytheta, poses_after_xytheta, j, k)
    pair_before = pair_after + e[:, :, None] * e[:, None, :]
    before = consistency_covariances_body(chain, (j, k), pair_before, lever)
    return before, after
