"""The SLAM stage's one entry point: :func:`run_slam` (scans + wheel odometry -> :class:`SlamResult`).

Steps and their modules: scan-to-submap odometry (:mod:`slam.odometry`), keyframes by travel and rotation
(:mod:`slam.keyframes`), odometry factors whose covariance comes from the registrations, the incremental
pose graph with loop-closure search after every keyframe (:class:`ClosureSearch`, :mod:`slam.graph`,
:mod:`slam.loop_closure`), a robust batch optimisation in which graduated non-convexity decides which
closures stay (:func:`robust_batch`), marginals of every keyframe, and the pose and covariance of every scan.

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
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from datasets.progress import ProgressLike, StageTimer, stage
from datasets.types import Recording, ScanSequence, Trajectory
from slam import geometry as se2
from slam.config import GraphConfig, SlamConfig
from slam.consistency import keyframe_consistency_body
from slam.faults import INJECTED, FalseClosures, false_closures
from slam.graph import Edge, EdgeTable, PoseGraph, gnc_loop_inliers
from slam.keyframes import keyframe_offsets, relative_cov_body, select_keyframes
from slam.loop_closure import LoopCloser, LoopClosure
from slam.odometry import OdometryResult, run_odometry, scans_points_base
from slam.result import SlamResult

FloatArray = NDArray[np.float64]


def wheel_poses_at_scans(odometry: Trajectory, stamps_ns: NDArray[np.int64]) -> FloatArray:
    """(N, 3) wheel poses at the scan stamps: the odometry itself when it has one pose per scan at the same
    stamps (e.g. CARMEN's per-scan odometry), else interpolated (odometry sorted by stamp first). A scan
    outside the odometry's time span (:meth:`~datasets.types.Trajectory.within_span`) gets a NaN row, not
    the end pose: the steps into and out of it are registered without wheels."""
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    if len(odometry) == len(stamps) and np.array_equal(odometry.stamps_ns, stamps):
        return odometry.poses_xytheta.copy()
    order = np.argsort(odometry.stamps_ns, kind="stable")
    if not np.all(order == np.arange(len(order))):
        odometry = Trajectory(odometry.stamps_ns[order], odometry.poses_xytheta[order], odometry.frame_id)
    poses = odometry.interpolate(stamps)
    poses[~odometry.within_span(stamps)] = np.nan
    return poses


def run_slam_recording(
    recording: Recording,
    config: SlamConfig | None = None,
    progress: ProgressLike | None = None,
    faults: FalseClosures | None = None,
) -> SlamResult:
    """SLAM on whatever a recording holds: its 3D clouds (KISS-ICP + ``Pose3`` graph,
    :func:`slam.system3d.run_slam_clouds`) when it has them, else its planar scans and wheel odometry
    (:func:`run_slam`), with the wheel odometry of :func:`wheel_odometry` unless ``config.wheel_odometry``
    is ``"off"``. The result has the same contract either way. ``faults``: wrong closures to inject
    (:mod:`slam.faults`; planar scans only)."""
    if recording.clouds is not None and len(recording.clouds) > 0:
        from slam.system3d import run_slam_clouds

        if faults is not None:
            raise ValueError("false-closure injection is implemented for planar scans, not for 3D clouds")
        return run_slam_clouds(recording.clouds, config, progress)
    if config is not None and config.wheel_odometry == "off":
        wheel, wheel_source = None, "none: slam.wheel_odometry is off (scans only)"
    else:
        wheel, wheel_source = wheel_odometry(recording)
    result = run_slam(recording.scans, wheel, recording.laser_in_base_xytheta, config, progress, faults)
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


def wheel_poses_of(recording: Recording) -> FloatArray | None:
    """(N, 3) the wheel odometry SLAM uses (:func:`wheel_odometry`) at the recording's scan stamps, or None
    when it has none."""
    if recording.scans is None or len(recording.scans) == 0:
        return None
    wheel, _ = wheel_odometry(recording)
    if wheel is None or len(wheel) == 0:
        return None
    return wheel_poses_at_scans(wheel, np.asarray(recording.scans.stamps_ns, dtype=np.int64))


def run_slam(
    scans: ScanSequence,
    odometry: Trajectory | None,
    laser_in_base_xytheta: FloatArray,
    config: SlamConfig | None = None,
    progress: ProgressLike | None = None,
    faults: FalseClosures | None = None,
) -> SlamResult:
    """Odometry, keyframes, loop closures, pose graph and marginals for one recording.

    ``scans``: the planar scans in order; ``odometry``: wheel odometry (per scan or denser; None without
    wheels); ``laser_in_base_xytheta`` (3,): the laser's mounting on the base. Poses are of the base.
    ``faults``: wrong closures handed to the back end before its final optimisation (:mod:`slam.faults`).
    The stages, each a named step below: scan points, odometry, keyframes, loop-closure search on the
    incremental graph, dense verification, (fault injection), robust batch optimisation, marginals,
    consistency covariances, per-scan poses and covariances.
    """
    cfg = config or SlamConfig()
    clock = StageTimer()
    stamps = np.asarray(scans.stamps_ns, dtype=np.int64)
    mount = np.asarray(laser_in_base_xytheta, dtype=np.float64)

    with clock("points_s"):
        points = scans_points_base(scans, mount, cfg.odometry)
        wheel = wheel_poses_at_scans(odometry, stamps) if odometry is not None and len(odometry) else None
    with clock("odometry_s"):
        odo = run_odometry(points, wheel, cfg.odometry, progress)
    clock.seconds.update(odo.timings_s)

    chain = keyframe_chain(odo, cfg)
    search = ClosureSearch(odo, chain, cfg, mount)
    t0 = time.perf_counter()
    search.run(progress)  # the loop-closure search, and the incremental graph around it
    clock.seconds["loop_search_s"] = search.search_s
    clock.seconds["graph_incremental_s"] = time.perf_counter() - t0 - search.search_s
    with clock("dense_pass_s"):
        search.dense_pass()
    injected = search.inject(faults) if faults is not None else []
    with clock("graph_batch_s"):
        batch = robust_batch(search.graph.estimate(), list(search.graph.edges), cfg.graph)

    with clock("marginals_s"), stage(progress, "marginals", None):
        kf_cov_after_body = batch.graph.marginals_body()
    kf_cov_before_body = se2.propagate_chain_cov_body(
        chain.increments_xytheta, chain.increment_covs * batch.scale, chain.prior_cov
    )
    with clock("consistency_s"):
        kf_rel_before_body, kf_rel_after_body = keyframe_consistency_body(
            chain.poses_xytheta,
            batch.poses_xytheta,
            batch.graph.edges,
            [points[s] for s in chain.scans],
            search.closer.path_m[chain.scans],
            cfg.consistency,
        )
    accepted, dropped = settle_closures(search.accepted, batch)
    with clock("per_scan_s"):
        keyframe_covs_body = {
            "cov_before": kf_cov_before_body,
            "cov_after": kf_cov_after_body,
            "relative_before": kf_rel_before_body,
            "relative_after": kf_rel_after_body,
        }
        per_scan = per_scan_covariances(odo, chain, batch, keyframe_covs_body, cfg.graph)

    kf = chain.scans
    return SlamResult(
        stamps_ns=stamps,
        poses_before_xytheta=odo.poses_xytheta.copy(),
        poses_after_xytheta=per_scan["poses_after"],
        cov_before_xytheta=per_scan["cov_before"],
        cov_after_xytheta=per_scan["cov_after"],
        relative_cov_before_xytheta=per_scan["relative_before"],
        relative_cov_after_xytheta=per_scan["relative_after"],
        odometry_status=odo.status,
        keyframe_scans=kf,
        keyframe_stamps_ns=stamps[kf],
        keyframe_cov_before=_sym(se2.rotate_cov_to_world(chain.poses_xytheta, kf_cov_before_body)),
        keyframe_cov_after=_sym(se2.rotate_cov_to_world(batch.poses_xytheta, kf_cov_after_body)),
        loop_closures=tuple(accepted),
        rejected_loop_closures=tuple(search.rejected + dropped),
        graph_vertices_xytheta=batch.poses_xytheta,
        graph_edges=tuple(batch.graph.edges),
        variance_factor=batch.scale,
        timings_s={**clock.seconds, "total_s": sum(clock.seconds[k] for k in SLAM_STAGES)},
        loop_closures_dropped=len(dropped),
        fault_injection=_fault_report(faults, injected, accepted),
        keyframe_offset_cov_body=per_scan["offset_body"],
    )


#: The stages whose times make up ``timings_s["total_s"]`` (the odometry's breakdown is inside
#: ``odometry_s``).
SLAM_STAGES = (
    "points_s",
    "odometry_s",
    "loop_search_s",
    "graph_incremental_s",
    "dense_pass_s",
    "graph_batch_s",
    "marginals_s",
    "consistency_s",
    "per_scan_s",
)


def _fault_report(
    faults: FalseClosures | None, injected: list, accepted: list[LoopClosure]
) -> dict[str, float | int] | None:
    """What ``evaluate slam --inject-false-closures`` reports: how many wrong closures were injected and how
    many the back end kept (None without fault injection)."""
    if faults is None:
        return None
    kept = sum(c.reason == INJECTED for c in accepted)
    return {"fraction": faults.fraction, "seed": faults.seed, "injected": len(injected), "kept": kept}


@dataclass(frozen=True)
class KeyframeChain:
    """The keyframes of the odometry chain and the pose graph's odometry factors between them:
    ``scans`` (K,) scan indices, ``poses_xytheta`` (K, 3) their odometry poses, ``increments_xytheta``
    (K-1, 3) the relative poses between consecutive keyframes with covariances ``increment_covs``
    (K-1, 3, 3, child frame), ``prior_cov`` (3, 3) of the first keyframe."""

    scans: NDArray[np.int64]
    poses_xytheta: FloatArray
    increments_xytheta: FloatArray
    increment_covs: FloatArray
    prior_cov: FloatArray


def keyframe_chain(odo: OdometryResult, cfg: SlamConfig) -> KeyframeChain:
    """Keyframes by travel and rotation, and their odometry factors (the registrations' covariances
    composed between keyframes, scaled, with a floor)."""
    gc = cfg.graph
    poses = odo.poses_xytheta
    kf = select_keyframes(poses, cfg.keyframe_distance_m, cfg.keyframe_rotation_rad)
    floor = np.diag([gc.min_sigma_xy_m**2, gc.min_sigma_xy_m**2, gc.min_sigma_theta_rad**2])
    covs = relative_cov_body(
        poses[kf[:-1]],
        odo.cov_xytheta[kf[:-1]],
        poses[kf[1:]],
        odo.cov_xytheta[kf[1:]],
        gc.odometry_cov_scale,
    )
    prior = np.diag([gc.prior_sigma_xy_m**2, gc.prior_sigma_xy_m**2, gc.prior_sigma_theta_rad**2])
    return KeyframeChain(kf, poses[kf], se2.between(poses[kf[:-1]], poses[kf[1:]]), covs + floor, prior)


class ClosureSearch:
    """The incremental pose graph (iSAM2) and the loop-closure search after every keyframe.

    :meth:`run` adds the keyframes one by one and, every ``search_spacing_m`` of travel, searches the
    targets whose position the marginals (inflated by the running variance factor) make compatible, in
    windows of the relative pose's own covariance (iSAM2's joint marginal); :meth:`dense_pass` verifies
    every keyframe against the targets the (then consistent) graph puts near it; :meth:`inject` adds wrong
    closures for fault injection. Closures enter the graph with their robust loss."""

    def __init__(self, odo: OdometryResult, chain: KeyframeChain, cfg: SlamConfig, mount: FloatArray) -> None:
        gc = cfg.graph
        self.cfg = cfg
        self.chain = chain
        k_count = len(chain.scans)
        self.graph = PoseGraph()
        self.graph.add_pose(chain.poses_xytheta[0])
        self.graph.add_prior(0, chain.poses_xytheta[0], chain.prior_cov)
        self.graph.update()
        self.est = np.zeros((k_count, 3))
        self.est[0] = chain.poses_xytheta[0]
        # world-frame marginals (unscaled) when each keyframe was added
        self.cov_w = np.zeros((k_count, 3, 3))
        self.cov_w[0] = chain.prior_cov
        sigmas = [gc.loop_min_sigma_xy_m, gc.loop_min_sigma_xy_m, gc.loop_min_sigma_theta_rad]
        loop_floor = np.diag(sigmas) ** 2
        self.closer = LoopCloser(
            odo, chain.scans, cfg.loop_closure, cfg.odometry, gc.loop_cov_scale, mount, loop_floor
        )
        self.accepted: list[LoopClosure] = []
        self.rejected: list[LoopClosure] = []
        self.scale = 1.0  # running a-posteriori variance factor
        self.search_s = 0.0
        self._last_closure_path_m = -math.inf
        self._last_search_path_m = -math.inf

    def add_loop(self, c: LoopClosure) -> None:
        """An accepted closure as a robust factor, its kernel width grown with the current variance factor."""
        lc = self.cfg.loop_closure
        width = lc.robust_kernel_width * math.sqrt(max(self.scale, 1.0))
        cov = np.linalg.inv(c.information)
        self.graph.add_between(
            "loop", c.target_keyframe, c.query_keyframe, c.relative_xytheta, cov, lc.robust_kernel, width
        )

    def run(self, progress: ProgressLike | None = None) -> None:
        """Every keyframe after the first: add it with its odometry factor, then search closures from it."""
        with stage(progress, "loop closure", len(self.chain.scans)) as bar:
            for k in range(1, len(self.chain.scans)):
                self.add_keyframe(k)
                if self.cfg.loop_closure.enabled and self._spaced(k):
                    ts = time.perf_counter()
                    self.search(k)
                    self.search_s += time.perf_counter() - ts
                bar.advance()

    def add_keyframe(self, k: int) -> None:
        """Keyframe ``k`` and its odometry factor, optimised incrementally."""
        g, c = self.graph, self.chain
        g.add_pose(se2.compose(self.est[k - 1], c.increments_xytheta[k - 1]))
        g.add_between("odometry", k - 1, k, c.increments_xytheta[k - 1], c.increment_covs[k - 1])
        g.update()
        self.est[k] = g.estimate_of(k)
        self.cov_w[k] = se2.rotate_cov_to_world(self.est[k], g.marginal_body(k))

    def _spaced(self, k: int) -> bool:
        lc = self.cfg.loop_closure
        here_m = self.closer.path_m[self.chain.scans[k]]
        return (
            here_m - self._last_closure_path_m >= lc.closure_spacing_m
            and here_m - self._last_search_path_m >= lc.search_spacing_m
        )

    def search(self, k: int) -> None:
        """Closures from keyframe ``k`` to the compatible earlier ones; the accepted ones enter the graph."""
        lc, gc, closer = self.cfg.loop_closure, self.cfg.graph, self.closer
        self._last_search_path_m = closer.path_m[self.chain.scans[k]]
        found: list[LoopClosure] = []
        query = None
        gate_scale = max(self.scale, lc.search_cov_inflation)
        js = [j for j, _d2 in closer.candidates(k, self.est, self.cov_w * gate_scale)]
        # the relative poses' own uncertainty (joint marginals): far below the sum of the two marginals
        # once loops tie k and j together, so the search windows shrink with it
        rel_covs = se2.rotate_cov_to_world(self.est[k], self.graph.relative_covs_body(js, k)) * gate_scale
        for j, cov_rel_w in zip(js, rel_covs, strict=True):
            if not closer.within_reach(k, j, self.est, closer.window(cov_rel_w)[0]):
                continue
            if query is None:
                query = closer.query_points(k)
            closure = closer.match(k, j, self.est, cov_rel_w, query)
            (found if closure.accepted else self.rejected).append(closure)
            if len(found) >= lc.max_accepted_per_keyframe:
                break
        for closure in found:
            self.add_loop(closure)
        if found:
            self._last_closure_path_m = closer.path_m[self.chain.scans[k]]
            self.accepted.extend(found)
            self.graph.update(extra_iterations=1)
            self.est[: k + 1] = self.graph.estimate()
            self.cov_w[k] = se2.rotate_cov_to_world(self.est[k], self.graph.marginal_body(k))
            if gc.estimate_variance_factor:
                self.scale = variance_factor(self.est[: k + 1], self.graph.edge_table, self.scale, gc)[0]

    def dense_pass(self) -> None:
        """Every keyframe against the targets the (now consistent) graph puts near it, verified in place."""
        lc = self.cfg.loop_closure
        if not (lc.enabled and lc.dense_radius_m > 0 and self.accepted):
            return
        est = self.graph.estimate()
        linked: dict[int, set[int]] = {}
        for c in self.accepted:
            linked.setdefault(c.query_keyframe, set()).add(c.target_keyframe)
        dense: list[LoopClosure] = []
        inflation = max(self.scale, lc.search_cov_inflation)
        for k in range(len(self.chain.scans)):
            for j in self.closer.nearby(k, est, lc.dense_radius_m, linked.get(k, set()))[: lc.dense_targets]:
                c = self.closer.verify_at(k, j, est, (self.cov_w[k] + self.cov_w[j]) * inflation)
                if c.accepted:
                    dense.append(c)
        for c in dense:
            self.add_loop(c)
        self.accepted.extend(dense)
        self.graph.update(extra_iterations=1)

    def inject(self, faults: FalseClosures) -> list[LoopClosure]:
        """Fault injection (evaluation only): wrong closures added to the graph as accepted ones."""
        injected = false_closures(self.graph.estimate(), self.chain.scans, self.accepted, faults)
        for c in injected:
            self.add_loop(c)
        self.accepted.extend(injected)
        return injected


@dataclass(frozen=True)
class BatchResult:
    """The final optimisation: ``poses_xytheta`` (K, 3), the solved ``graph`` (kept factors, covariances x
    ``scale``, the a-posteriori variance factor), and per loop closure of the input edges (L,) whether it
    was ``kept`` and whether it is an ``inlier`` of the variance factor."""

    poses_xytheta: FloatArray
    graph: PoseGraph
    scale: float
    loop_kept: NDArray[np.bool_]
    loop_inlier: NDArray[np.bool_]


def robust_batch(initial_xytheta: FloatArray, edges: list[Edge], gc: GraphConfig) -> BatchResult:
    """The robust batch: graduated non-convexity decides which closures stay (on covariances scaled by the
    variance factor, :func:`slam.graph.gnc_loop_inliers`), then every kept factor is re-weighted by the
    a-posteriori variance factor and the graph solved again (Levenberg-Marquardt) until it settles."""
    est = np.asarray(initial_xytheta, dtype=np.float64)
    is_loop = np.array([e.kind == "loop" for e in edges], dtype=bool)
    kept = np.ones(len(edges), dtype=bool)
    if gc.outlier_rejection == "gnc" and is_loop.any():
        s0 = variance_factor(est, edges, 1.0, gc)[0] if gc.estimate_variance_factor else 1.0
        scaled = [e if e.kind == "prior" else e.scaled(s0) for e in edges]
        kept, est = gnc_loop_inliers(scaled, est, gc.gnc_inlier_probability, gc.max_iterations)
    edges = [e for e, k in zip(edges, kept, strict=True) if k]
    scale = 1.0
    inliers = np.ones(len(edges), dtype=bool)
    final: PoseGraph | None = None  # variance_factor_iterations >= 1: the loop below always builds it
    for _ in range(gc.variance_factor_iterations if gc.estimate_variance_factor else 1):
        new_scale, inliers = (
            variance_factor(est, edges, scale, gc) if gc.estimate_variance_factor else (1.0, inliers)
        )
        final = PoseGraph.from_edges([e if e.kind == "prior" else e.scaled(new_scale) for e in edges], est)
        if gc.final_optimizer == "levenberg_marquardt":
            est = final.optimize_batch(gc.max_iterations)
        converged = abs(new_scale - scale) <= 0.02 * scale
        scale = new_scale
        if converged:
            break
    loop_kept = kept[is_loop]
    loop_inlier = np.zeros(len(loop_kept), dtype=bool)
    loop_inlier[loop_kept] = inliers[[i for i, e in enumerate(edges) if e.kind == "loop"]]
    assert final is not None
    return BatchResult(est, final, scale, loop_kept, loop_inlier)


def settle_closures(
    accepted: list[LoopClosure], batch: BatchResult
) -> tuple[list[LoopClosure], list[LoopClosure]]:
    """``(kept, dropped)``: the closures the back end kept (information / the variance factor,
    ``consistent`` when an inlier of it) and those it dropped (no longer accepted, the reason says why)."""
    dropped = [
        replace(c, accepted=False, reason=f"{c.reason}; dropped by the back end (graduated non-convexity)")
        for c, k in zip(accepted, batch.loop_kept, strict=True)
        if not k
    ]
    kept = [
        replace(c, information=c.information / batch.scale, consistent=bool(ok))
        for c, k, ok in zip(accepted, batch.loop_kept, batch.loop_inlier, strict=True)
        if k
    ]
    return kept, dropped


def per_scan_covariances(
    odo: OdometryResult,
    chain: KeyframeChain,
    batch: BatchResult,
    keyframe_covs_body: dict[str, FloatArray],
    gc: GraphConfig,
) -> dict[str, FloatArray]:
    """Every scan: its keyframe's pose composed with the odometry offset (``poses_after`` (N, 3)), the
    offset's own covariance (``offset_body`` (N, 3, 3), the scan's frame), and each keyframe covariance of
    ``keyframe_covs_body`` (name -> (K, 3, 3) body frame; ``*_before`` at the odometry poses, the others
    after loop closure) composed with the offset's uncertainty, world frame."""
    poses = odo.poses_xytheta
    kf = chain.scans
    owner, offset = keyframe_offsets(kf, poses)
    anchor = kf[owner]
    off_cov = relative_cov_body(
        poses[anchor], odo.cov_xytheta[anchor], poses, odo.cov_xytheta, gc.odometry_cov_scale * batch.scale
    )
    off_cov[anchor == np.arange(len(poses))] = 0.0
    poses_after = se2.compose(batch.poses_xytheta[owner], offset)
    out = {"poses_after": poses_after, "offset_body": _sym(off_cov)}
    for name, cov_body in keyframe_covs_body.items():
        at = poses if name.endswith("_before") else poses_after
        out[name] = _sym(se2.rotate_cov_to_world(at, se2.compose_cov_body(cov_body[owner], offset, off_cov)))
    return out


def variance_factor(
    poses_xytheta: FloatArray, edges: Sequence[Edge] | EdgeTable, current: float, cfg: GraphConfig
) -> tuple[float, NDArray[np.bool_]]:
    """A-posteriori variance factor of the graph adjustment, and the loop closures counted as inliers.

    ``s = sum(r_i^T S_i^-1 r_i) / (m - n)`` over the odometry factors and the loop closures whose whitened
    error is below ``variance_factor_gate_chi2 * s`` (iterated), with ``S_i`` the factor covariances as
    added and ``m - n = 3 * (inlier loop closures)`` the redundancy of a chain plus loops. If every
    covariance is right up to one common factor, ``s`` estimates that factor (classical least-squares
    adjustment). Returns ``(current, all-True)`` when fewer than ``variance_factor_min_loops`` loops agree.
    """
    table = edges if isinstance(edges, EdgeTable) else EdgeTable(edges)
    e2 = table.errors2(poses_xytheta)
    loops = table.is_loop
    s = max(current, 1e-12)
    inl = np.ones(len(table), dtype=bool)
    for _ in range(10):
        inl = ~loops | (e2 <= cfg.variance_factor_gate_chi2 * s)
        n_loops = int(np.sum(inl & loops))
        if n_loops < cfg.variance_factor_min_loops:
            return current, np.ones(len(table), dtype=bool)
        s_new = float(np.sum(e2[inl])) / (3.0 * n_loops)
        if abs(s_new - s) <= 1e-3 * s:
            s = s_new
            break
        s = s_new
    return max(s, cfg.variance_factor_min), inl


def _sym(c: FloatArray) -> FloatArray:
    return 0.5 * (c + np.swapaxes(c, -1, -2))
