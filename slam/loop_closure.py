"""Loop closures: candidates gated by the current uncertainty, correlative search, verification.

For a new keyframe ``k`` (the *query*), earlier keyframes ``j`` (the *targets*) are candidates when
(1) the robot travelled at least ``min_separation_m`` between them and (2) their positions are compatible
with the current marginals: ``dp^T (S_k + S_j + r^2 I)^-1 dp <= gate_chi2`` (2 dof, ``r`` the radius within
which two keyframes still see the same place; the sum of the marginals bounds the relative uncertainty from
above). The nearest candidates are matched when their search window -- set by the covariance of the relative
pose itself, from the joint marginal of the two keyframes (:meth:`slam.graph.PoseGraph.relative_covs_body`),
small where closures already tie them together and wide after a long loop -- can bring them within
``max_distance_m`` of the query:

- the query is the keyframe's scan merged with the scans since ``query_keyframes`` earlier keyframes (in
  the keyframe's frame through the odometry, locally accurate), thinned to one point per voxel;
- the target is the map of the scans within ``target_keyframes`` keyframes of ``j`` (in ``j``'s frame);
- a correlative search over a window of ``window_sigmas`` standard deviations of the predicted relative
  pose (coarse-to-fine when wide), then point-to-line Gauss-Newton (no prior);
- verification: the mean correlative score; the overlap gate: the fraction of query points within
  ``inlier_m`` of a target point after refinement (*hits*); the free-space gate: among the query points
  that fall where the target knows something, the fraction lying in space its beams saw free (*conflicts*:
  a wrong alignment puts points inside rooms and corridors, a right one with partial overlap does not);
  the residual RMS; the ratio of the smallest to the largest eigenvalue of the translational alignment
  information (rejects corridors, where the match slides along the axis); the Mahalanobis distance of the
  found relative pose from the prediction.

An accepted closure enters the graph with the alignment covariance (scaled like the odometry) and a robust
loss, so that a false closure that passed the gates is down-weighted rather than obeyed.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from slam import geometry as se2
from slam.config import LoopClosureConfig, OdometryConfig
from slam.odometry import FIRST, MATCHED, OdometryResult
from slam.scan_matching import (
    PointGrid,
    ScorePyramid,
    SearchResult,
    bnb_depth,
    branch_and_bound_search,
    mark_free_space,
    overlap,
    refine_point_to_line,
    scan_normals,
    voxel_thin,
)

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class LoopClosure:
    """One verified (or rejected) loop-closure attempt.

    ``relative_xytheta`` is the query keyframe's pose in the target keyframe's frame
    (``between(target, query)``); ``information`` (3, 3) its information in the query's frame (GTSAM/g2o
    convention), already scaled for the graph. ``score`` is the mean correlative score, ``fitness`` the
    overlap (fraction of query points matched), ``mahalanobis2`` the squared distance from the prediction.
    """

    query_keyframe: int
    target_keyframe: int
    query_scan: int
    target_scan: int
    relative_xytheta: FloatArray
    information: FloatArray
    score: float
    fitness: float
    rms_m: float
    mahalanobis2: float
    accepted: bool
    reason: str
    window_xy_m: float = 0.0
    window_theta_rad: float = 0.0
    consistent: bool = True  # counted as an inlier by the final variance-factor estimate


def _sigmas(cov: FloatArray) -> tuple[float, float]:
    """The largest translational and the rotational standard deviation of a (3, 3) covariance."""
    return (
        math.sqrt(max(np.linalg.eigvalsh(cov[:2, :2]).max(), 0.0)),
        math.sqrt(max(cov[2, 2], 0.0)),
    )


class LoopCloser:
    """Finds and verifies loop closures between keyframes of one odometry run."""

    def __init__(
        self,
        odometry: OdometryResult,
        keyframe_scans: NDArray[np.int64],
        cfg: LoopClosureConfig,
        odo_cfg: OdometryConfig,
        cov_scale: float,
        laser_in_base_xytheta: FloatArray | None = None,
        cov_floor: FloatArray | None = None,
    ) -> None:
        self.odo = odometry
        mount = np.zeros(3) if laser_in_base_xytheta is None else np.asarray(laser_in_base_xytheta, float)
        self.laser_origin_base = mount[:2].copy()
        self.kf = np.asarray(keyframe_scans, dtype=np.int64)
        self.cfg = cfg
        self.odo_cfg = odo_cfg
        self.cov_scale = cov_scale
        self.cov_floor = np.zeros((3, 3)) if cov_floor is None else np.asarray(cov_floor, dtype=np.float64)
        poses = odometry.poses_xytheta
        self.path_m = se2.path_length_m(poses[:, :2]) if len(poses) else np.zeros(1)
        self._targets: OrderedDict[int, PointGrid] = OrderedDict()
        self._pyramids: dict[int, ScorePyramid] = {}
        # per scan, its points within map_range_m of the laser and (once a target map needs them) their
        # normals: a scan serves the maps of several targets
        self._near_points: dict[int, tuple[FloatArray, FloatArray | None]] = {}
        self._usable = np.isin(odometry.status, (FIRST, MATCHED))

    # -- maps ---------------------------------------------------------------------------------------------

    def _scan_near(self, s: int, normals: bool) -> tuple[FloatArray, FloatArray | None]:
        """Scan ``s``'s points within ``map_range_m`` of its laser (:meth:`_near`), (P, 2) in its base frame,
        and with ``normals`` their (P, 2) normals (from the whole scan's neighbours), else None (cached)."""
        got = self._near_points.get(s)
        if got is None or (normals and got[1] is None):
            near = self._near(s)
            pts = self.odo.points_base[s][near] if got is None else got[0]
            nrm = None
            if normals:
                oc = self.odo_cfg
                nrm = scan_normals(
                    self.odo.points_base[s],
                    oc.normal_radius_m,
                    oc.normal_max_neighbours,
                    radius_per_m=oc.normal_radius_per_m,
                )[near]
            got = (pts, nrm)
            self._near_points[s] = got
        return got

    def _scans_between(self, k_first: int, k_last: int) -> NDArray[np.int64]:
        """Scan indices from keyframe ``k_first`` to the scan before keyframe ``k_last + 1``."""
        k_first = max(k_first, 0)
        k_last = min(k_last, len(self.kf) - 1)
        start = self.kf[k_first]
        stop = self.kf[k_last + 1] if k_last + 1 < len(self.kf) else len(self.odo.poses_xytheta)
        scans = np.arange(start, stop)
        return scans[self._usable[scans]]

    def _points_in_frame(self, anchor_scan: int, scans: NDArray[np.int64], normals: bool):
        """Points, normals (or None) and beam origins of ``scans`` in the frame of ``anchor_scan`` through
        the odometry, each (P, 2)."""
        if len(scans) == 0:
            return np.zeros((0, 2)), np.zeros((0, 2)), np.zeros((0, 2))
        rel = se2.between(self.odo.poses_xytheta[anchor_scan], self.odo.poses_xytheta[scans])
        near = [self._scan_near(int(s), normals) for s in scans]
        counts = np.array([p.shape[0] for p, _ in near])
        pts = np.concatenate([p for p, _ in near])
        per_point = np.repeat(rel, counts, axis=0)
        c, s_ = np.cos(per_point[:, 2]), np.sin(per_point[:, 2])

        def rotate(v: FloatArray) -> FloatArray:
            return np.stack([c * v[:, 0] - s_ * v[:, 1], s_ * v[:, 0] + c * v[:, 1]], axis=1)

        out = rotate(pts) + per_point[:, :2]
        origins = se2.transform_points_each(rel, self.laser_origin_base)
        origins = np.repeat(origins, counts, axis=0)
        if not normals:
            return out, None, origins
        nrm = np.concatenate([n for _, n in near])
        return out, rotate(nrm), origins

    def _near(self, s: int) -> NDArray[np.bool_]:
        """Which points of scan ``s`` lie within ``map_range_m`` of its laser (far points make big, slow maps
        and add little to a closure)."""
        d = self.odo.points_base[s] - self.laser_origin_base
        return np.hypot(d[:, 0], d[:, 1]) <= self.cfg.map_range_m

    def target_grid(self, j: int) -> PointGrid:
        """The map around keyframe ``j`` in its frame (cached)."""
        grid = self._targets.get(j)
        if grid is not None:
            self._targets.move_to_end(j)
            return grid
        m = self.cfg.target_keyframes
        scans = self._scans_between(j - m, j + m)
        pts, nrm, origins = self._points_in_frame(int(self.kf[j]), scans, normals=True)
        keep = voxel_thin(pts, self.odo_cfg.resolution_m)
        grid = PointGrid.from_points(
            pts[keep],
            nrm[keep],
            resolution_m=self.odo_cfg.resolution_m,
            radius_m=self.odo_cfg.max_correspondence_m,
            sigma_m=self.odo_cfg.resolution_m,
        )
        mark_free_space(grid, origins[keep], pts[keep], self.cfg.free_space_margin_m)
        self._targets[j] = grid
        if len(self._targets) > 64:
            old, _ = self._targets.popitem(last=False)
            self._pyramids.pop(old, None)
        return grid

    def target_pyramid(self, j: int) -> ScorePyramid:
        """The branch-and-bound pyramid of :meth:`target_grid` ``(j)`` at the search resolution (cached)."""
        pyr = self._pyramids.get(j)
        if pyr is None:
            cfg = self.cfg
            res = self.odo_cfg.resolution_m * cfg.search_pool
            pyr = ScorePyramid.of_grid(
                self.target_grid(j), bnb_depth(cfg.max_window_m, res), pool=cfg.search_pool
            )
            self._pyramids[j] = pyr
        return pyr

    def query_points(self, k: int) -> FloatArray:
        """The query cloud of keyframe ``k`` in its frame, thinned."""
        scans = self._scans_between(k - self.cfg.query_keyframes, k - 1)
        scans = np.union1d(scans, [self.kf[k]]) if self._usable[self.kf[k]] else scans
        pts, _, _ = self._points_in_frame(int(self.kf[k]), scans, normals=False)
        return pts[voxel_thin(pts, self.cfg.query_voxel_m)]

    # -- candidates ---------------------------------------------------------------------------------------

    def candidates(self, k: int, estimate: FloatArray, cov_world: FloatArray) -> list[tuple[int, float]]:
        """Earlier keyframes ``(j, d2)`` passing the separation and Mahalanobis gates, nearest first.

        ``estimate`` (>= k+1, 3) current keyframe poses, ``cov_world`` (>= k+1, 3, 3) their world-frame
        marginals (any value for keyframes older than the last closure is an upper bound).
        """
        cfg = self.cfg
        sep = self.path_m[self.kf[k]] - self.path_m[self.kf[:k]]
        js = np.nonzero((sep >= cfg.min_separation_m) & (np.arange(k) % cfg.target_stride == 0))[0]
        if js.size == 0:
            return []
        dp = estimate[js, :2] - estimate[k, :2]
        s = cov_world[js, :2, :2] + cov_world[k, :2, :2] + cfg.overlap_radius_m**2 * np.eye(2)
        d2 = np.einsum("ni,nij,nj->n", dp, np.linalg.inv(s), dp)
        ok = (d2 <= cfg.gate_chi2) & (np.hypot(dp[:, 0], dp[:, 1]) <= cfg.max_distance_m + cfg.max_window_m)
        order = np.argsort(d2[ok])[: cfg.max_candidates]
        return [(int(js[ok][i]), float(d2[ok][i])) for i in order]

    # -- matching -----------------------------------------------------------------------------------------

    def match(
        self, k: int, j: int, estimate: FloatArray, cov_rel_world: FloatArray, query: FloatArray | None = None
    ) -> LoopClosure:
        """Search and verify the pose of keyframe ``k`` in the frame of keyframe ``j``.

        ``cov_rel_world`` (3, 3) is the uncertainty of the relative pose (world frame), which sets the search
        window and the consistency gate.
        """
        cfg = self.cfg
        pred = se2.between(estimate[j], estimate[k])
        # the relative uncertainty in j's frame
        r = se2.rot3(-estimate[j, 2])
        cov_rel = r @ cov_rel_world @ r.T
        sig_xy, sig_th = _sigmas(cov_rel)
        win_xy, win_th = self.window(cov_rel_world)
        pts = self.query_points(k) if query is None else query
        grid = self.target_grid(j)

        def reject(reason: str, pose=pred, score=0.0, fit=0.0, rms=math.inf, d2=math.nan) -> LoopClosure:
            return self._rejected(k, j, reason, pose, score, fit, rms, d2, win_xy, win_th)

        if pts.shape[0] < self.odo_cfg.min_points or len(grid) < self.odo_cfg.min_points:
            return reject("too few points")
        stride = max(1, math.ceil(pts.shape[0] / cfg.search_max_points))
        # a wide window tries many more poses, so a wrong alignment scores higher there by chance
        min_score = cfg.min_score if win_xy <= cfg.wide_window_m else max(cfg.min_score, cfg.wide_min_score)
        found = branch_and_bound_search(
            self.target_pyramid(j),
            pts[::stride],
            pred,
            win_xy,
            win_th,
            cfg.search_step_rad,
            min_score=min_score,
            prior_sigma_xy_m=max(sig_xy, 1e-3),
            prior_sigma_theta_rad=max(sig_th, 1e-4),
            prior_weight=cfg.search_prior_weight,
        )
        if found.score <= 0.0:
            return reject("low score", pred, 0.0, 0.0, math.inf, math.nan)
        return self._verify(k, j, found.pose_xytheta, found.score, pred, cov_rel, pts, grid, win_xy, win_th)

    def within_reach(self, k: int, j: int, estimate: FloatArray, win_xy_m: float) -> bool:
        """Whether a search window of half-width ``win_xy_m`` can bring target ``j`` within
        ``max_distance_m`` of keyframe ``k`` (farther, their views overlap little)."""
        d = float(np.hypot(*(estimate[j, :2] - estimate[k, :2])))
        return d - win_xy_m <= self.cfg.max_distance_m

    def window(self, cov_rel_world: FloatArray) -> tuple[float, float]:
        """The search half-windows ``(m, rad)`` for a relative pose of covariance ``cov_rel_world`` (3, 3):
        ``window_sigmas`` standard deviations (the largest translational one), clipped to the configured
        bounds (a rotation of the covariance changes neither)."""
        cfg = self.cfg
        sig_xy, sig_th = _sigmas(cov_rel_world)
        win_xy = float(np.clip(cfg.window_sigmas * sig_xy, cfg.min_window_m, cfg.max_window_m))
        win_th = float(np.clip(cfg.window_sigmas * sig_th, cfg.min_window_rad, cfg.max_window_rad))
        return win_xy, win_th

    def nearby(self, k: int, estimate: FloatArray, radius_m: float, exclude: set[int]) -> list[int]:
        """Target anchors at least ``min_separation_m`` of travel before keyframe ``k`` whose estimated
        position lies within ``radius_m`` of it, nearest first (``exclude``: anchors to skip)."""
        sep = self.path_m[self.kf[k]] - self.path_m[self.kf[:k]]
        js = np.nonzero((sep >= self.cfg.min_separation_m) & (np.arange(k) % self.cfg.target_stride == 0))[0]
        if js.size == 0:
            return []
        d = np.hypot(estimate[js, 0] - estimate[k, 0], estimate[js, 1] - estimate[k, 1])
        order = np.argsort(d)
        return [int(js[i]) for i in order if d[i] <= radius_m and int(js[i]) not in exclude]

    def verify_at(self, k: int, j: int, estimate: FloatArray, cov_rel_world: FloatArray) -> LoopClosure:
        """Refine and verify keyframe ``k`` against target ``j`` from their estimated relative pose, without
        a search (the graph is already consistent: the dense pass after loop closure)."""
        pred = se2.between(estimate[j], estimate[k])
        r = se2.rot3(-estimate[j, 2])
        return self._verify(
            k,
            j,
            pred,
            1.0,
            pred,
            r @ cov_rel_world @ r.T,
            self.query_points(k),
            self.target_grid(j),
            0.0,
            0.0,
        )

    def _rejected(
        self,
        k: int,
        j: int,
        reason: str,
        pose: FloatArray,
        score: float,
        fit: float,
        rms: float,
        d2: float,
        win_xy: float,
        win_th: float,
    ) -> LoopClosure:
        """A rejected attempt of keyframe ``k`` against target ``j`` (no information: never added)."""
        kf = self.kf
        return LoopClosure(
            k,
            j,
            int(kf[k]),
            int(kf[j]),
            pose,
            np.zeros((3, 3)),
            score,
            fit,
            rms,
            d2,
            False,
            reason,
            win_xy,
            win_th,
        )

    def _verify(
        self,
        k: int,
        j: int,
        start: FloatArray,
        score: float,
        pred: FloatArray,
        cov_rel: FloatArray,
        pts: FloatArray,
        grid: PointGrid,
        win_xy: float,
        win_th: float,
    ) -> LoopClosure:
        """Point-to-line refinement from ``start`` and the verification gates (module docstring)."""
        cfg = self.cfg
        found = SearchResult(start, score)

        def reject(reason: str, pose=pred, score=0.0, fit=0.0, rms=math.inf, d2=math.nan) -> LoopClosure:
            return self._rejected(k, j, reason, pose, score, fit, rms, d2, win_xy, win_th)

        al = refine_point_to_line(
            grid,
            pts,
            found.pose_xytheta,
            max_dist_m=self.odo_cfg.max_correspondence_m,
            kernel_m=self.odo_cfg.kernel_m,
            point_sigma_m=self.odo_cfg.point_sigma_m,
        )
        pose = al.pose_xytheta
        hits, conflicts = overlap(grid, pts, pose, cfg.inlier_m)
        fit = hits / pts.shape[0]
        conflict = conflicts / max(hits + conflicts, 1)
        e = pose - pred
        e[2] = se2.wrap(e[2])
        try:
            d2 = float(e @ np.linalg.solve(cov_rel, e))
        except np.linalg.LinAlgError:
            d2 = math.inf
        oc = self.odo_cfg
        sigma = max(al.rms_m, oc.min_point_sigma_m) if oc.sigma_from_residuals else oc.point_sigma_m
        info_w = al.hessian / sigma**2
        eig = np.linalg.eigvalsh(al.hessian[:2, :2]) if al.inliers >= 3 else np.zeros(2)
        ratio = float(eig[0] / eig[1]) if eig[1] > 0 else 0.0
        if found.score < cfg.min_score:
            return reject("low score", pose, found.score, fit, al.rms_m, d2)
        if fit < cfg.min_hit_fraction:
            return reject("low overlap", pose, found.score, fit, al.rms_m, d2)
        if conflict > cfg.max_conflict_ratio:
            return reject("free-space conflict", pose, found.score, fit, al.rms_m, d2)
        if al.rms_m > cfg.max_rms_m:
            return reject("high residual", pose, found.score, fit, al.rms_m, d2)
        if ratio < cfg.min_eigen_ratio:
            return reject("degenerate", pose, found.score, fit, al.rms_m, d2)
        if d2 > cfg.consistency_chi2:
            return reject("inconsistent", pose, found.score, fit, al.rms_m, d2)
        # information of the relative pose, in the query's frame (GTSAM / g2o convention), scaled
        cov_w = np.linalg.inv(info_w) * self.cov_scale
        cov_body = se2.rotate_cov_to_body(pose, cov_w) + self.cov_floor
        info = np.linalg.inv(cov_body)
        return LoopClosure(
            k,
            j,
            int(self.kf[k]),
            int(self.kf[j]),
            pose,
            0.5 * (info + info.T),
            found.score,
            fit,
            al.rms_m,
            d2,
            True,
            "accepted",
            win_xy,
            win_th,
        )
