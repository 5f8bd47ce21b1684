"""The SLAM stage's one entry point: :func:`run_slam` (scans + wheel odometry -> :class:`SlamResult`).

Steps and their modules: scan-to-submap odometry (:mod:`slam.odometry`), keyframes by travel and rotation
(:mod:`slam.keyframes`), odometry factors whose covariance comes from the registrations, the incremental
pose graph with loop-closure search after every keyframe (:mod:`slam.graph`, :mod:`slam.loop_closure`),
a final batch optimisation, marginals of every keyframe, and the pose and covariance of every scan.

Covariances leaving this module are world-frame (x, y, theta) (SPEC section 2). "Before" is the odometry
chain alone (first-order propagation of the factor covariances, equal to the marginals of the chain graph),
"after" the optimised graph with loop closures. Besides these marginals (relative to the first pose), each
scan gets the covariance the mapper uses: of its pose relative to the earlier passes over the places it
observes (:mod:`slam.consistency`). A scan between keyframes takes the pose of its keyframe composed with its
odometry offset, and its covariances add the offset's uncertainty.
"""

from __future__ import annotations

import math
import time
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from datasets.progress import ProgressLike, stage
from datasets.types import Recording, ScanSequence, Trajectory
from slam import geometry as se2
from slam.config import GraphConfig, SlamConfig
from slam.consistency import keyframe_consistency_body
from slam.graph import Edge, PoseGraph, edge_errors2
from slam.keyframes import keyframe_offsets, relative_cov_body, select_keyframes
from slam.loop_closure import LoopCloser, LoopClosure
from slam.odometry import run_odometry, scans_points_base
from slam.result import SlamResult

FloatArray = NDArray[np.float64]


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


def run_slam_recording(
    recording: Recording, config: SlamConfig | None = None, progress: ProgressLike | None = None
) -> SlamResult:
    """SLAM on whatever a recording holds: its 3D clouds (KISS-ICP + ``Pose3`` graph,
    :func:`slam.system3d.run_slam_clouds`) when it has them, else its planar scans and wheel odometry
    (:func:`run_slam`). The result has the same contract either way."""
    if recording.clouds is not None and len(recording.clouds) > 0:
        from slam.system3d import run_slam_clouds

        return run_slam_clouds(recording.clouds, config, progress)
    wheel, wheel_source = wheel_odometry(recording)
    result = run_slam(recording.scans, wheel, recording.laser_in_base_xytheta, config, progress)
    return replace(result, wheel_odometry=wheel_source)


def wheel_odometry(recording: Recording) -> tuple[Trajectory | None, str]:
    """The wheel odometry SLAM should use, and a phrase saying where it comes from.

    A SLAM-corrected log (``meta["corrected"]``: ``*.gfs.log``, ``*-corrected.log*``) logs its corrected
    poses in the odometry fields of its scans, never handed to SLAM; its ODOM records, re-anchored at every
    scan, still hold the raw wheel motion between scans, which is used when they have it
    (:func:`datasets.carmen.corrected_log_odometry`; else SLAM runs on the scans alone). Otherwise the pose
    logged with each scan (CARMEN's raw odometry), else the odometry topic, else none.
    """
    if recording.meta.get("corrected"):
        from datasets.carmen import corrected_log_odometry

        return corrected_log_odometry(recording)
    if recording.scan_poses is not None and len(recording.scan_poses):
        return recording.scan_poses, "the odometry logged with each scan"
    if recording.odometry is not None and len(recording.odometry):
        return recording.odometry, "the odometry topic"
    return None, "none (scans only)"


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
    points = scans_points_base(scans, mount, oc)
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

    # incremental graph with loop-closure search after every keyframe
    t0 = time.perf_counter()
    t_search = 0.0
    graph = PoseGraph()
    graph.add_pose(poses[kf[0]])
    graph.add_prior(0, poses[kf[0]], cov0)
    graph.update()
    est = np.zeros((k_count, 3))
    est[0] = poses[kf[0]]
    cov_w = np.zeros((k_count, 3, 3))  # world-frame marginals (unscaled) when each keyframe was added
    cov_w[0] = cov0
    loop_floor = np.diag([gc.loop_min_sigma_xy_m, gc.loop_min_sigma_xy_m, gc.loop_min_sigma_theta_rad]) ** 2
    closer = LoopCloser(odo, kf, cfg.loop_closure, oc, gc.loop_cov_scale, mount, loop_floor)
    lc = cfg.loop_closure
    accepted: list[LoopClosure] = []
    rejected: list[LoopClosure] = []
    scale = 1.0  # running a-posteriori variance factor

    def add_loop(c: LoopClosure) -> None:
        """An accepted closure as a robust factor, its kernel width grown with the current variance factor."""
        width = lc.robust_kernel_width * math.sqrt(max(scale, 1.0))
        cov = np.linalg.inv(c.information)
        graph.add_between(
            "loop",
            c.target_keyframe,
            c.query_keyframe,
            c.relative_xytheta,
            cov,
            robust=lc.robust_kernel,
            robust_width=width,
        )

    last_closure_path_m = -math.inf
    last_search_path_m = -math.inf
    with stage(progress, "loop closure", k_count) as bar:
        for k in range(1, k_count):
            graph.add_pose(se2.compose(est[k - 1], rel[k - 1]))
            graph.add_between("odometry", k - 1, k, rel[k - 1], fac_cov[k - 1])
            graph.update()
            est[k] = graph.estimate_of(k)
            cov_w[k] = se2.rotate_cov_to_world(est[k], graph.marginal_body(k))
            here_m = closer.path_m[kf[k]]
            spaced = (
                here_m - last_closure_path_m >= lc.closure_spacing_m
                and here_m - last_search_path_m >= lc.search_spacing_m
            )
            if lc.enabled and spaced:
                last_search_path_m = here_m
                ts = time.perf_counter()
                found = []
                query = None
                gate_scale = max(scale, lc.search_cov_inflation)
                js = [j for j, _d2 in closer.candidates(k, est, cov_w * gate_scale)]
                # the relative poses' own uncertainty (joint marginals): far below the sum of the two
                # marginals once loops tie k and j together, so the search windows shrink with it
                rel_covs = se2.rotate_cov_to_world(est[k], graph.relative_covs_body(js, k)) * gate_scale
                for j, cov_rel_w in zip(js, rel_covs, strict=True):
                    if not closer.within_reach(k, j, est, closer.window(cov_rel_w)[0]):
                        continue
                    if query is None:
                        query = closer.query_points(k)
                    closure = closer.match(k, j, est, cov_rel_w, query)
                    (found if closure.accepted else rejected).append(closure)
                    if len(found) >= lc.max_accepted_per_keyframe:
                        break
                t_search += time.perf_counter() - ts
                for closure in found:
                    add_loop(closure)
                if found:
                    last_closure_path_m = closer.path_m[kf[k]]
                    accepted.extend(found)
                    graph.update(extra_iterations=1)
                    est[: k + 1] = graph.estimate()
                    cov_w[k] = se2.rotate_cov_to_world(est[k], graph.marginal_body(k))
                    if gc.estimate_variance_factor:
                        scale = variance_factor(est[: k + 1], graph.edges, scale, gc)[0]
            bar.advance()
    timings["loop_search_s"] = t_search
    timings["graph_incremental_s"] = time.perf_counter() - t0 - t_search

    # dense pass: every keyframe against the targets the (now consistent) graph puts near it
    t0 = time.perf_counter()
    if lc.enabled and lc.dense_radius_m > 0 and accepted:
        est = graph.estimate()
        linked: dict[int, set[int]] = {}
        for c in accepted:
            linked.setdefault(c.query_keyframe, set()).add(c.target_keyframe)
        dense: list[LoopClosure] = []
        for k in range(k_count):
            for j in closer.nearby(k, est, lc.dense_radius_m, linked.get(k, set()))[: lc.dense_targets]:
                c = closer.verify_at(k, j, est, (cov_w[k] + cov_w[j]) * max(scale, lc.search_cov_inflation))
                if c.accepted:
                    dense.append(c)
        for c in dense:
            add_loop(c)
        accepted.extend(dense)
        graph.update(extra_iterations=1)
    timings["dense_pass_s"] = time.perf_counter() - t0

    # batch: re-weight every factor by the a-posteriori variance factor and solve again until it settles
    t0 = time.perf_counter()
    est = graph.estimate()
    edges = list(graph.edges)
    final = graph
    scale = 1.0
    inliers = np.ones(len(edges), dtype=bool)
    for _ in range(gc.variance_factor_iterations if gc.estimate_variance_factor else 1):
        if gc.estimate_variance_factor:
            new_scale, inliers = variance_factor(est, edges, scale, gc)
        else:
            new_scale = 1.0
        final = PoseGraph.from_edges([e if e.kind == "prior" else e.scaled(new_scale) for e in edges], est)
        if gc.final_optimizer == "levenberg_marquardt":
            est = final.optimize_batch(gc.max_iterations)
        converged = abs(new_scale - scale) <= 0.02 * scale
        scale = new_scale
        if converged:
            break
    timings["graph_batch_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    with stage(progress, "marginals", None):
        kf_cov_after_body = final.marginals_body()
    timings["marginals_s"] = time.perf_counter() - t0
    kf_cov_before_body = se2.propagate_chain_cov_body(rel, fac_cov * scale, cov0)
    t0 = time.perf_counter()
    kf_rel_before_body, kf_rel_after_body = keyframe_consistency_body(
        poses[kf], est, final.edges, [points[s] for s in kf], closer.path_m[kf], cfg.consistency
    )
    timings["consistency_s"] = time.perf_counter() - t0
    loop_edges = [e for e in edges if e.kind == "loop"]
    loop_inlier = inliers[[i for i, e in enumerate(edges) if e.kind == "loop"]] if loop_edges else []
    accepted = [
        replace(c, information=c.information / scale, consistent=bool(ok))
        for c, ok in zip(accepted, loop_inlier, strict=True)
    ]

    # every scan: its keyframe's pose and covariance composed with the odometry offset
    t0 = time.perf_counter()
    owner, offset = keyframe_offsets(kf, poses)
    anchor = kf[owner]
    off_cov = relative_cov_body(
        poses[anchor], odo.cov_xytheta[anchor], poses, odo.cov_xytheta, gc.odometry_cov_scale * scale
    )
    off_cov[anchor == np.arange(n)] = 0.0
    poses_after = se2.compose(est[owner], offset)
    cov_before = se2.rotate_cov_to_world(
        poses, se2.compose_cov_body(kf_cov_before_body[owner], offset, off_cov)
    )
    cov_after = se2.rotate_cov_to_world(
        poses_after, se2.compose_cov_body(kf_cov_after_body[owner], offset, off_cov)
    )
    rel_before = se2.rotate_cov_to_world(
        poses, se2.compose_cov_body(kf_rel_before_body[owner], offset, off_cov)
    )
    rel_after = se2.rotate_cov_to_world(
        poses_after, se2.compose_cov_body(kf_rel_after_body[owner], offset, off_cov)
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
                "dense_pass_s",
                "graph_batch_s",
                "marginals_s",
                "consistency_s",
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
        relative_cov_before_xytheta=_sym(rel_before),
        relative_cov_after_xytheta=_sym(rel_after),
        odometry_status=odo.status,
        keyframe_scans=kf,
        keyframe_stamps_ns=stamps[kf],
        keyframe_cov_before=_sym(se2.rotate_cov_to_world(poses[kf], kf_cov_before_body)),
        keyframe_cov_after=_sym(se2.rotate_cov_to_world(est, kf_cov_after_body)),
        loop_closures=tuple(accepted),
        rejected_loop_closures=tuple(rejected),
        graph_vertices_xytheta=est,
        graph_edges=tuple(final.edges),
        variance_factor=scale,
        timings_s=timings,
    )


def variance_factor(
    poses_xytheta: FloatArray, edges: list[Edge], current: float, cfg: GraphConfig
) -> tuple[float, NDArray[np.bool_]]:
    """A-posteriori variance factor of the graph adjustment, and the loop closures counted as inliers.

    ``s = sum(r_i^T S_i^-1 r_i) / (m - n)`` over the odometry factors and the loop closures whose whitened
    error is below ``variance_factor_gate_chi2 * s`` (iterated), with ``S_i`` the factor covariances as
    added and ``m - n = 3 * (inlier loop closures)`` the redundancy of a chain plus loops. If every
    covariance is right up to one common factor, ``s`` estimates that factor (classical least-squares
    adjustment). Returns ``(current, all-True)`` when fewer than ``variance_factor_min_loops`` loops agree.
    """
    e2 = edge_errors2(poses_xytheta, edges)
    loops = np.array([e.kind == "loop" for e in edges])
    s = max(current, 1e-12)
    inl = np.ones(len(edges), dtype=bool)
    for _ in range(10):
        inl = ~loops | (e2 <= cfg.variance_factor_gate_chi2 * s)
        n_loops = int(np.sum(inl & loops))
        if n_loops < cfg.variance_factor_min_loops:
            return current, np.ones(len(edges), dtype=bool)
        s_new = float(np.sum(e2[inl])) / (3.0 * n_loops)
        if abs(s_new - s) <= 1e-3 * s:
            s = s_new
            break
        s = s_new
    return max(s, cfg.variance_factor_min), inl


def _sym(c: FloatArray) -> FloatArray:
    return 0.5 * (c + np.swapaxes(c, -1, -2))
