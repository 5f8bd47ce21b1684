"""The SLAM stage's one entry point: :func:`run_slam` (scans + wheel odometry -> :class:`SlamResult`).

Steps and their modules: scan-to-submap odometry (:mod:`slam.odometry`), keyframes by travel and rotation
(:mod:`slam.keyframes`), odometry factors whose covariance comes from the registrations, the incremental
pose graph with loop-closure search after every keyframe (:mod:`slam.graph`, :mod:`slam.loop_closure`),
a final batch optimisation, marginals of every keyframe, and the pose and covariance of every scan.

Covariances leaving this module are world-frame (x, y, theta) (SPEC section 2). "Before" is the odometry
chain alone (first-order propagation of the factor covariances, equal to the marginals of the chain graph),
"after" the optimised graph with loop closures. A scan between keyframes takes the pose of its keyframe
composed with its odometry offset, and its covariance adds the offset's uncertainty.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from datasets.types import ScanSequence, Trajectory
from slam import geometry as se2
from slam.config import SlamConfig
from slam.graph import Edge, PoseGraph
from slam.keyframes import keyframe_of_scan, relative_cov_body, select_keyframes
from slam.loop_closure import LoopCloser, LoopClosure
from slam.odometry import ProgressLike, run_odometry, scan_points_base

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class SlamResult:
    """Everything the SLAM stage produces (N scans, K keyframes).

    Per scan: ``stamps_ns`` (N,), ``poses_before_xytheta`` / ``poses_after_xytheta`` (N, 3) base poses of
    the odometry chain and of the optimised graph, ``cov_before_xytheta`` / ``cov_after_xytheta``
    (N, 3, 3) world-frame covariances, ``odometry_status`` (N,) int8 (see :mod:`slam.odometry`).
    Per keyframe: ``keyframe_scans`` (K,) scan indices, ``keyframe_stamps_ns`` (K,),
    ``keyframe_cov_before`` / ``keyframe_cov_after`` (K, 3, 3) world-frame marginals.
    ``loop_closures`` / ``rejected_loop_closures``: the verified and the refused attempts.
    ``graph_vertices_xytheta`` (K, 3) and ``graph_edges``: the optimised pose graph (g2o export).
    ``timings_s``: wall time per sub-stage.
    """

    stamps_ns: NDArray[np.int64]
    poses_before_xytheta: FloatArray
    poses_after_xytheta: FloatArray
    cov_before_xytheta: FloatArray
    cov_after_xytheta: FloatArray
    odometry_status: NDArray[np.int8]
    keyframe_scans: NDArray[np.int64]
    keyframe_stamps_ns: NDArray[np.int64]
    keyframe_cov_before: FloatArray
    keyframe_cov_after: FloatArray
    loop_closures: tuple[LoopClosure, ...]
    rejected_loop_closures: tuple[LoopClosure, ...]
    graph_vertices_xytheta: FloatArray
    graph_edges: tuple[Edge, ...]
    timings_s: dict[str, float] = field(default_factory=dict)

    def trajectory(self, which: str = "after") -> Trajectory:
        """The per-scan trajectory ``"before"`` or ``"after"`` loop closure, with its covariances."""
        if which == "before":
            return Trajectory(self.stamps_ns, self.poses_before_xytheta, "odom", self.cov_before_xytheta)
        if which == "after":
            return Trajectory(self.stamps_ns, self.poses_after_xytheta, "map", self.cov_after_xytheta)
        raise ValueError(f"which must be 'before' or 'after', not {which!r}")

    def summary(self) -> dict:
        """Counts and timings (JSON-ready)."""
        return {
            "scans": len(self.stamps_ns),
            "keyframes": len(self.keyframe_scans),
            "loop_closures_accepted": len(self.loop_closures),
            "loop_closures_rejected": len(self.rejected_loop_closures),
            "odometry_fallbacks": int(np.sum(self.odometry_status >= 2)),
            "timings_s": dict(self.timings_s),
        }


def wheel_poses_at_scans(odometry: Trajectory, stamps_ns: NDArray[np.int64]) -> FloatArray:
    """(N, 3) wheel poses at the scan stamps: the odometry itself when it has one pose per scan at the same
    stamps (e.g. CARMEN's per-scan odometry), else interpolated (odometry sorted by stamp first)."""
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    if len(odometry) == len(stamps) and np.array_equal(odometry.stamps_ns, stamps):
        return odometry.poses_xytheta.copy()
    order = np.argsort(odometry.stamps_ns, kind="stable")
    if not np.all(order == np.arange(len(order))):
        odometry = Trajectory(odometry.stamps_ns[order], odometry.poses_xytheta[order], odometry.frame_id)
    return odometry.interpolate(stamps)


def run_slam(
    scans: ScanSequence,
    odometry: Trajectory | None,
    laser_in_base_xytheta: FloatArray,
    config: SlamConfig | None = None,
    progress: ProgressLike | None = None,
) -> SlamResult:
    """Odometry, keyframes, loop closures, pose graph and marginals for one recording.

    ``scans``: the planar scans in order; ``odometry``: wheel odometry (per scan or denser; None without
    wheels); ``laser_in_base_xytheta`` (3,): the laser's mounting on the base. Poses are of the base.
    """
    cfg = config or SlamConfig()
    oc = cfg.odometry
    gc = cfg.graph
    timings: dict[str, float] = {}
    n = len(scans)
    stamps = np.asarray(scans.stamps_ns, dtype=np.int64)
    mount = np.asarray(laser_in_base_xytheta, dtype=np.float64)

    t0 = time.perf_counter()
    points = [
        scan_points_base(
            scans.ranges_m[i],
            scans.angles_rad[i],
            scans.range_min_m[i],
            scans.range_max_m[i],
            mount,
            oc.min_range_m,
            oc.max_range_m,
        )
        for i in range(n)
    ]
    wheel = wheel_poses_at_scans(odometry, stamps) if odometry is not None and len(odometry) else None
    timings["points_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    odo = run_odometry(points, wheel, oc, progress)
    timings["odometry_s"] = time.perf_counter() - t0
    timings.update(odo.timings_s)
    poses = odo.poses_xytheta

    # keyframes and their odometry factors
    kf = select_keyframes(poses, cfg.keyframe_distance_m, cfg.keyframe_rotation_rad)
    k_count = len(kf)
    floor = np.diag([gc.min_sigma_xy_m**2, gc.min_sigma_xy_m**2, gc.min_sigma_theta_rad**2])
    rel = se2.between(poses[kf[:-1]], poses[kf[1:]])
    fac_cov = (
        relative_cov_body(
            poses[kf[:-1]],
            odo.cov_xytheta[kf[:-1]],
            poses[kf[1:]],
            odo.cov_xytheta[kf[1:]],
            gc.odometry_cov_scale,
        )
        + floor
    )
    cov0 = np.diag([gc.prior_sigma_xy_m**2, gc.prior_sigma_xy_m**2, gc.prior_sigma_theta_rad**2])
    kf_cov_before_body = se2.propagate_chain_cov_body(rel, fac_cov, cov0)

    # incremental graph with loop-closure search after every keyframe
    t0 = time.perf_counter()
    t_search = 0.0
    graph = PoseGraph()
    graph.add_pose(poses[kf[0]])
    graph.add_prior(0, poses[kf[0]], cov0)
    graph.update()
    est = np.zeros((k_count, 3))
    est[0] = poses[kf[0]]
    cov_w = np.zeros((k_count, 3, 3))
    cov_w[0] = cov0
    closer = LoopCloser(odo, kf, cfg.loop_closure, oc, oc.point_sigma_m, gc.loop_cov_scale)
    lc = cfg.loop_closure
    accepted: list[LoopClosure] = []
    rejected: list[LoopClosure] = []
    with _stage(progress, "loop closure", k_count) as bar:
        for k in range(1, k_count):
            graph.add_pose(se2.compose(est[k - 1], rel[k - 1]))
            graph.add_between("odometry", k - 1, k, rel[k - 1], fac_cov[k - 1])
            graph.update()
            est[k] = graph.estimate_of(k)
            cov_w[k] = se2.rotate_cov_to_world(est[k], graph.marginal_body(k))
            if lc.enabled:
                ts = time.perf_counter()
                found = []
                query = None
                for j, _d2 in closer.candidates(k, est, cov_w):
                    if query is None:
                        query = closer.query_points(k)
                    closure = closer.match(k, j, est, cov_w[k] + cov_w[j], query)
                    (found if closure.accepted else rejected).append(closure)
                    if len(found) >= lc.max_accepted_per_keyframe:
                        break
                t_search += time.perf_counter() - ts
                for closure in found:
                    graph.add_between(
                        "loop",
                        closure.target_keyframe,
                        closure.query_keyframe,
                        closure.relative_xytheta,
                        np.linalg.inv(closure.information),
                        robust=lc.robust_kernel,
                        robust_width=lc.robust_kernel_width,
                    )
                if found:
                    accepted.extend(found)
                    graph.update(extra_iterations=1)
                    est[: k + 1] = graph.estimate()
                    cov_w[k] = se2.rotate_cov_to_world(est[k], graph.marginal_body(k))
            bar.advance()
    timings["loop_search_s"] = t_search
    timings["graph_incremental_s"] = time.perf_counter() - t0 - t_search

    t0 = time.perf_counter()
    if gc.final_optimizer == "levenberg_marquardt":
        est = graph.optimize_batch(gc.max_iterations)
    else:
        est = graph.estimate()
    timings["graph_batch_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    with _stage(progress, "marginals", None):
        kf_cov_after_body = graph.marginals_body()
    timings["marginals_s"] = time.perf_counter() - t0

    # every scan: its keyframe's pose and covariance composed with the odometry offset
    t0 = time.perf_counter()
    owner = keyframe_of_scan(kf, n)
    anchor = kf[owner]
    offset = se2.between(poses[anchor], poses)
    off_cov = relative_cov_body(
        poses[anchor], odo.cov_xytheta[anchor], poses, odo.cov_xytheta, gc.odometry_cov_scale
    )
    off_cov[anchor == np.arange(n)] = 0.0
    poses_after = se2.compose(est[owner], offset)
    cov_before = se2.rotate_cov_to_world(
        poses, se2.compose_cov_body(kf_cov_before_body[owner], offset, off_cov)
    )
    cov_after = se2.rotate_cov_to_world(
        poses_after, se2.compose_cov_body(kf_cov_after_body[owner], offset, off_cov)
    )
    timings["per_scan_s"] = time.perf_counter() - t0
    timings["total_s"] = (
        sum(
            timings[k]
            for k in (
                "points_s",
                "odometry_s",
                "loop_search_s",
                "graph_incremental_s",
                "graph_batch_s",
                "marginals_s",
            )
        )
        + timings["per_scan_s"]
    )

    return SlamResult(
        stamps_ns=stamps,
        poses_before_xytheta=poses.copy(),
        poses_after_xytheta=poses_after,
        cov_before_xytheta=_sym(cov_before),
        cov_after_xytheta=_sym(cov_after),
        odometry_status=odo.status,
        keyframe_scans=kf,
        keyframe_stamps_ns=stamps[kf],
        keyframe_cov_before=_sym(se2.rotate_cov_to_world(poses[kf], kf_cov_before_body)),
        keyframe_cov_after=_sym(se2.rotate_cov_to_world(est, kf_cov_after_body)),
        loop_closures=tuple(accepted),
        rejected_loop_closures=tuple(rejected),
        graph_vertices_xytheta=est,
        graph_edges=tuple(graph.edges),
        timings_s=timings,
    )


def _sym(c: FloatArray) -> FloatArray:
    return 0.5 * (c + np.swapaxes(c, -1, -2))


class _NullBar:
    def advance(self, amount: int = 1) -> None:
        pass


class _NullStage:
    def __enter__(self) -> _NullBar:
        return _NullBar()

    def __exit__(self, *exc) -> None:
        return None


def _stage(progress: ProgressLike | None, name: str, total: int | None):
    return progress.stage(name, total=total) if progress is not None else _NullStage()
