"""The GTSAM ``Pose2`` pose graph: incremental (iSAM2) while loop closures are searched, batch
Levenberg-Marquardt at the end, marginal covariances of every keyframe.

Keys are keyframe indices 0..K-1. Factor noise is given as (3, 3) covariances in the child frame of the
measured relative pose (GTSAM's ``BetweenFactor`` convention, order x, y, theta); loop closures can carry a
robust loss (Cauchy, Huber or dynamic covariance scaling) so that a false closure cannot wreck the graph.
Marginals leave this module in GTSAM's body frame; :mod:`slam.geometry` rotates them to the world.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import gtsam
import numpy as np
from numpy.typing import NDArray

from datasets.errors import GpomError
from slam import geometry as se2

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Edge:
    """One factor of the graph, for export (g2o) and inspection.

    ``cov`` (3, 3) is the covariance in the child frame of the measurement (GTSAM ``BetweenFactor`` and
    g2o ``EDGE_SE2`` convention); for a prior, of the pose itself. ``robust`` names the loss (``"none"``,
    ``"cauchy"``, ``"huber"``, ``"dcs"``) and ``robust_width`` its width in whitened units.
    """

    kind: str  # "prior", "odometry" or "loop"
    key_from: int
    key_to: int
    measurement_xytheta: FloatArray
    cov: FloatArray
    robust: str = "none"
    robust_width: float = 1.0

    @property
    def information(self) -> FloatArray:
        """(3, 3) inverse of ``cov``."""
        return np.linalg.inv(self.cov)

    def scaled(self, factor: float) -> Edge:
        """The same edge with its covariance multiplied by ``factor``."""
        return Edge(
            self.kind,
            self.key_from,
            self.key_to,
            self.measurement_xytheta,
            self.cov * factor,
            self.robust,
            self.robust_width,
        )


def _robust(kind: str, width: float, base: gtsam.noiseModel.Base) -> gtsam.noiseModel.Base:
    est = gtsam.noiseModel.mEstimator
    if kind == "none":
        return base
    m = {"cauchy": est.Cauchy, "huber": est.Huber, "dcs": est.DCS}[kind].Create(width)
    return gtsam.noiseModel.Robust.Create(m, base)


def _pose(p: FloatArray) -> gtsam.Pose2:
    return gtsam.Pose2(float(p[0]), float(p[1]), float(p[2]))


class PoseGraphError(GpomError):
    """The pose graph cannot be solved even with the QR factorisation (a variable no factor constrains)."""


def _isam2(factorization: str) -> gtsam.ISAM2:
    params = gtsam.ISAM2Params()
    params.setRelinearizeThreshold(0.01)
    params.relinearizeSkip = 1
    params.setFactorization(factorization)
    return gtsam.ISAM2(params)


class PoseGraph:
    """A growing ``Pose2`` graph optimised incrementally with iSAM2.

    iSAM2 factorises with Cholesky, which GTSAM refuses (``IndeterminateSystemException``) when the
    information of the factors spans more than about seven orders of magnitude along a chain (a keyframe
    joined only by a wheel fallback's loose factor between millimetre-tight registrations); the graph then
    switches to the QR factorisation for good (slower, and exact on such systems). Batch solving and
    marginals fall back the same way. Only a graph that QR cannot solve either raises
    :class:`PoseGraphError`.
    """

    def __init__(self) -> None:
        self.factorization = "CHOLESKY"
        self._isam = _isam2(self.factorization)
        self.graph = gtsam.NonlinearFactorGraph()
        self._new_factors = gtsam.NonlinearFactorGraph()
        self._new_values = gtsam.Values()
        self.edges: list[Edge] = []
        self._edge_table = EdgeTable()
        self._loop_factor_index: dict[int, int] = {}
        self._n = 0
        # the estimate after the last update, computed when first read (``_stale`` until then): a keyframe
        # added incrementally needs only its own pose, and the whole estimate grows with the graph
        self._estimate_values: gtsam.Values | None = None
        self._stale = False

    def __len__(self) -> int:
        return self._n

    @property
    def edge_table(self) -> EdgeTable:
        """:attr:`edges` as an :class:`EdgeTable`, brought up to date here with the edges added since the last
        read (the graph only ever appends edges)."""
        self._edge_table.extend(self.edges[len(self._edge_table) :])
        return self._edge_table

    def add_pose(self, initial_xytheta: FloatArray) -> int:
        """A new keyframe variable with its initial guess; returns its key."""
        key = self._n
        self._new_values.insert(key, _pose(initial_xytheta))
        self._n += 1
        return key

    def add_prior(self, key: int, pose_xytheta: FloatArray, cov: FloatArray) -> None:
        cov = np.asarray(cov, dtype=np.float64)
        f = gtsam.PriorFactorPose2(key, _pose(pose_xytheta), gtsam.noiseModel.Gaussian.Covariance(cov))
        self._add(f, Edge("prior", key, key, np.asarray(pose_xytheta, float), cov))

    def add_between(
        self,
        kind: str,
        key_from: int,
        key_to: int,
        relative_xytheta: FloatArray,
        cov: FloatArray,
        robust: str = "none",
        robust_width: float = 1.0,
    ) -> None:
        """A relative-pose factor ``between(x_from, x_to) = relative`` with child-frame covariance ``cov``."""
        cov = np.asarray(cov, dtype=np.float64)
        noise = _robust(robust, robust_width, gtsam.noiseModel.Gaussian.Covariance(cov))
        key_from, key_to = int(key_from), int(key_to)
        f = gtsam.BetweenFactorPose2(key_from, key_to, _pose(relative_xytheta), noise)
        edge = Edge(kind, key_from, key_to, np.asarray(relative_xytheta, float), cov, robust, robust_width)
        self._add(f, edge)

    @classmethod
    def from_edges(cls, edges: list[Edge], initial_xytheta: FloatArray) -> PoseGraph:
        """A graph holding ``edges`` with ``initial_xytheta`` (K, 3) as its estimate (for batch solving)."""
        g = cls()
        for p in np.asarray(initial_xytheta, dtype=np.float64):
            g.add_pose(p)
        for e in edges:
            if e.kind == "prior":
                g.add_prior(e.key_from, e.measurement_xytheta, e.cov)
            else:
                g.add_between(
                    e.kind, e.key_from, e.key_to, e.measurement_xytheta, e.cov, e.robust, e.robust_width
                )
        g._estimate = g._new_values
        return g

    @property
    def _estimate(self) -> gtsam.Values | None:
        """The current estimate of every keyframe (None before the first update)."""
        if self._stale:
            self._estimate_values = self._isam.calculateEstimate()
            self._stale = False
        return self._estimate_values

    @_estimate.setter
    def _estimate(self, values: gtsam.Values | None) -> None:
        self._estimate_values = values
        self._stale = False

    def _add(self, factor: gtsam.NonlinearFactor, edge: Edge) -> None:
        self._new_factors.add(factor)
        self.graph.add(factor)
        self.edges.append(edge)

    def update(self, extra_iterations: int = 0) -> None:
        """Hand new factors and variables to iSAM2 (plus ``extra_iterations`` relinearisation passes)."""
        try:
            self._isam.update(self._new_factors, self._new_values)
            for _ in range(extra_iterations):
                self._isam.update()
        except RuntimeError as exc:
            if self.factorization == "QR":
                raise PoseGraphError(f"pose graph: {_first_line(exc)} (keyframes 0-{self._n - 1})") from None
            self._restart_with_qr()
        self._new_factors = gtsam.NonlinearFactorGraph()
        self._new_values = gtsam.Values()
        self._stale = True

    def _restart_with_qr(self) -> None:
        """A new iSAM2 on the QR factorisation holding every factor, from the last estimate."""
        values = gtsam.Values()
        known = self._estimate_values
        if self._stale:  # the last estimate was never read: the failed iSAM2 still gives one (its
            # linearisation point moved by its last solved delta)
            try:
                known = self._isam.calculateEstimate()
            except RuntimeError:
                pass
            self._stale = False
        for key in range(self._n):
            if known is not None and known.exists(key):
                values.insert(key, known.atPose2(key))
            else:
                values.insert(key, self._new_values.atPose2(key))
        self.factorization = "QR"
        self._isam = _isam2("QR")
        try:
            self._isam.update(self.graph, values)
        except RuntimeError as exc:
            raise PoseGraphError(f"pose graph: {_first_line(exc)} (keyframes 0-{self._n - 1})") from None

    def estimate(self) -> FloatArray:
        """(K, 3) current estimate of every keyframe pose."""
        if self._estimate is None:
            self.update()
        return _values_to_array(self._estimate, self._n)

    def estimate_of(self, key: int) -> FloatArray:
        """(3,) current estimate of keyframe ``key`` (from iSAM2 alone when the whole estimate is not
        needed: the same value)."""
        if self._estimate_values is None and not self._stale:
            self.update()
        if self._stale:
            p = self._isam.calculateEstimatePose2(key)
        else:
            p = self._estimate_values.atPose2(key)
        return np.array([p.x(), p.y(), p.theta()])

    def _with_qr_retry(self, query):
        """``query()`` on the current iSAM2; if Cholesky refuses, once more after switching to QR (QR's own
        failure propagates)."""
        try:
            return query()
        except RuntimeError:
            if self.factorization == "QR":
                raise
            self._restart_with_qr()
            return query()

    def marginal_body(self, key: int) -> FloatArray:
        """(3, 3) iSAM2 marginal covariance of one keyframe, body frame."""
        return np.asarray(self._with_qr_retry(lambda: self._isam.marginalCovariance(key)))

    def relative_covs_body(self, keys_from: list[int], key_to: int) -> FloatArray:
        """(len(keys_from), 3, 3) covariances of ``between(x_from, x_to)`` in ``x_to``'s body frame, from
        iSAM2's joint marginal of the keyframes (one call for all): the correlation that the shared
        odometry chain and the loop closures between them put there makes it far smaller than the sum of
        their marginals once loops close.

        With ``x = X Exp(a)`` (GTSAM's right perturbation) the relative pose ``D = X_from^-1 X_to`` moves by
        ``b - Ad(D^-1) a``: ``S = M S_ff M^T + M S_ft + S_tf M^T + S_tt`` with ``M = -Ad(D^-1)``.
        """
        keys = [int(k) for k in keys_from]
        if not keys:
            return np.zeros((0, 3, 3))

        try:
            jm = self._with_qr_retry(lambda: self._isam.jointMarginalCovariance(sorted({*keys, int(key_to)})))
        except RuntimeError as exc:
            raise PoseGraphError(f"pose graph joint marginals: {_first_line(exc)}") from None
        x_to = self.estimate_of(key_to)
        s_tt = np.asarray(jm.at(key_to, key_to))
        out = np.empty((len(keys), 3, 3))
        for i, key in enumerate(keys):
            s_ff = np.asarray(jm.at(key, key))
            s_ft = np.asarray(jm.at(key, key_to))
            m = -se2.adjoint(se2.inverse(se2.between(self.estimate_of(key), x_to)))
            cov = m @ s_ff @ m.T + m @ s_ft + s_ft.T @ m.T + s_tt
            out[i] = 0.5 * (cov + cov.T)
        return out

    def set_estimate(self, poses_xytheta: FloatArray) -> None:
        """Replace the current estimate (K, 3) (the batch optimiser starts from it)."""
        values = gtsam.Values()
        for k, p in enumerate(np.asarray(poses_xytheta, dtype=np.float64)):
            values.insert(k, _pose(p))
        self._estimate = values

    def optimize_batch(self, max_iterations: int = 100) -> FloatArray:
        """Levenberg-Marquardt on the whole graph from the current estimate; returns (K, 3) poses."""
        if self._estimate is None:
            self.update()
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(max_iterations)
        if self.factorization == "QR":
            params.setLinearSolverType("MULTIFRONTAL_QR")
        try:
            result = gtsam.LevenbergMarquardtOptimizer(self.graph, self._estimate, params).optimize()
        except RuntimeError as exc:
            if self.factorization == "QR":
                raise PoseGraphError(f"pose graph: {_first_line(exc)}") from None
            self.factorization = "QR"
            return self.optimize_batch(max_iterations)
        self._estimate = result
        return _values_to_array(result, self._n)

    def marginals_body(self) -> FloatArray:
        """(K, 3, 3) marginal covariances of every keyframe at the current estimate, body frame (from an
        iSAM2 on QR when Cholesky fails: ``gtsam.Marginals`` has no QR path)."""
        if self._estimate is None:
            self.update()
        if self.factorization == "CHOLESKY":
            try:
                marginals = gtsam.Marginals(self.graph, self._estimate)
                return np.stack([np.asarray(marginals.marginalCovariance(k)) for k in range(self._n)])
            except RuntimeError:
                pass
        isam = _isam2("QR")
        try:
            isam.update(self.graph, self._estimate)
            return np.stack([np.asarray(isam.marginalCovariance(k)) for k in range(self._n)])
        except RuntimeError as exc:
            raise PoseGraphError(f"pose graph marginals: {_first_line(exc)}") from None

    def error(self) -> float:
        """Total graph error at the current estimate."""
        return float(self.graph.error(self._estimate))


def gnc_loop_inliers(
    edges: list[Edge], initial_xytheta: FloatArray, inlier_probability: float, max_iterations: int = 100
) -> tuple[NDArray[np.bool_], FloatArray]:
    """Which loop closures a graduated non-convexity solve keeps, and its estimate (K, 3).

    GTSAM's ``GncOptimizer`` (Yang, Antonante, Tzoumas & Carlone, RA-L 2020) with the truncated least
    squares loss over the loop closures, the prior and the odometry chain known inliers: it starts from the
    convex (least-squares) problem and makes the loss non-convex step by step, so that closures which
    disagree with the chain and with each other lose their weight together instead of one by one. A factor
    is an inlier while its whitened error stays below the chi-square quantile ``inlier_probability`` (3
    degrees of freedom); loops are given without their robust loss (GNC is the robust loss). Returns
    ``(keep (E,) bool: True for every non-loop edge and the loops GNC weighs >= 0.5, estimate)``."""
    plain = [e if e.robust == "none" else replace(e, robust="none") for e in edges]
    graph = PoseGraph.from_edges(plain, initial_xytheta)
    known = [i for i, e in enumerate(edges) if e.kind != "loop"]
    lm = gtsam.LevenbergMarquardtParams()
    lm.setMaxIterations(max_iterations)
    params = gtsam.GncLMParams(lm)
    params.setLossType(gtsam.GncLossType.TLS)
    params.setKnownInliers(known)
    try:
        gnc = gtsam.GncLMOptimizer(graph.graph, graph._estimate, params)
        gnc.setInlierCostThresholdsAtProbability(inlier_probability)
        result = gnc.optimize()
    except RuntimeError as exc:
        raise PoseGraphError(f"pose graph (graduated non-convexity): {_first_line(exc)}") from None
    weights = np.asarray(gnc.getWeights(), dtype=np.float64)
    keep = np.array([e.kind != "loop" for e in edges]) | (weights >= 0.5)
    return keep, _values_to_array(result, len(initial_xytheta))


def _first_line(exc: BaseException) -> str:
    lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
    return " ".join(lines[:2]) if lines else type(exc).__name__


def _values_to_array(values: gtsam.Values, n: int) -> FloatArray:
    out = np.asarray(gtsam.utilities.extractPose2(values), dtype=np.float64).reshape(-1, 3)
    if out.shape[0] != n:
        raise ValueError(f"pose graph: {out.shape[0]} poses in the estimate, expected {n}")
    return out


class EdgeTable:
    """Edges as arrays, appended to as a graph grows (E edges): keys ``key_from`` / ``key_to`` (E,),
    measurements (E, 3), informations (E, 3, 3) and which are priors and loop closures.

    Every edge's error is then one vectorised evaluation (:meth:`errors2`); the loop-closure search
    re-estimates the variance factor after each closure it accepts, over all edges so far, and walking
    the edge objects and inverting every covariance again each time cost more than the evaluation."""

    def __init__(self, edges: Sequence[Edge] = ()) -> None:
        self._n = 0
        self._key_from = np.zeros(0, dtype=np.int64)
        self._key_to = np.zeros(0, dtype=np.int64)
        self._z = np.zeros((0, 3))
        self._info = np.zeros((0, 3, 3))
        self._prior = np.zeros(0, dtype=bool)
        self._loop = np.zeros(0, dtype=bool)
        self.extend(edges)

    def __len__(self) -> int:
        return self._n

    def extend(self, edges: Sequence[Edge]) -> None:
        """Append ``edges`` (their covariances inverted once, here)."""
        edges = list(edges)
        if not edges:
            return
        n, m = self._n, len(edges)
        if n + m > self._key_from.shape[0]:
            cap = max(n + m, 2 * self._key_from.shape[0], 64)
            for name in ("_key_from", "_key_to", "_z", "_info", "_prior", "_loop"):
                old = getattr(self, name)
                grown = np.zeros((cap, *old.shape[1:]), dtype=old.dtype)
                grown[:n] = old[:n]
                setattr(self, name, grown)
        self._key_from[n : n + m] = [e.key_from for e in edges]
        self._key_to[n : n + m] = [e.key_to for e in edges]
        self._z[n : n + m] = np.stack([e.measurement_xytheta for e in edges])
        self._info[n : n + m] = np.linalg.inv(np.stack([e.cov for e in edges]))
        self._prior[n : n + m] = [e.kind == "prior" for e in edges]
        self._loop[n : n + m] = [e.kind == "loop" for e in edges]
        self._n = n + m

    @property
    def is_loop(self) -> NDArray[np.bool_]:
        """(E,) which edges are loop closures (a copy)."""
        return self._loop[: self._n].copy()

    def errors2(self, poses_xytheta: FloatArray) -> FloatArray:
        """(E,) squared whitened errors ``r^T cov^-1 r`` of every edge at ``poses_xytheta`` (K, 3), without
        the robust loss; ``r`` is GTSAM's error (``Logmap(z^-1 * between(x_from, x_to))``, or of the
        prior)."""
        n = self._n
        if n == 0:
            return np.zeros(0)
        p = np.asarray(poses_xytheta, dtype=np.float64)
        i, j = self._key_from[:n], self._key_to[:n]
        h = np.where(self._prior[:n, None], p[i], se2.between(p[i], p[j]))
        r = se2.logmap(se2.between(self._z[:n], h))
        return np.einsum("ni,nij,nj->n", r, self._info[:n], r)


def edge_errors2(poses_xytheta: FloatArray, edges: Sequence[Edge]) -> FloatArray:
    """(E,) squared whitened errors of ``edges`` at ``poses_xytheta`` (K, 3) (:meth:`EdgeTable.errors2`)."""
    return EdgeTable(edges).errors2(poses_xytheta)


def chain_graph_marginals(
    increments_xytheta: FloatArray, cov_increments: FloatArray, start_xytheta: FloatArray, cov0: FloatArray
) -> FloatArray:
    """(N+1, 3, 3) GTSAM body-frame marginals of a pure odometry chain (a reference for the tests)."""
    g = PoseGraph()
    pose = np.asarray(start_xytheta, dtype=np.float64)
    g.add_pose(pose)
    g.add_prior(0, pose, cov0)
    for i, (inc, cov) in enumerate(zip(increments_xytheta, cov_increments, strict=True)):
        c, s = np.cos(pose[2]), np.sin(pose[2])
        pose = np.array(
            [pose[0] + c * inc[0] - s * inc[1], pose[1] + s * inc[0] + c * inc[1], pose[2] + inc[2]]
        )
        g.add_pose(pose)
        g.add_between("odometry", i, i + 1, inc, cov)
    g.update()
    return g.marginals_body()
