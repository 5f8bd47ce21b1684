"""The SLAM stage for 3D inputs (``Recording.clouds``): KISS-ICP odometry on the clouds as they are, a GTSAM
``Pose3`` graph with loop closures, world-frame 6x6 marginals, and the SE(2) projection of poses and
covariances that the 2D mapper uses with the height-band scans (``Recording.scans``).

- Odometry: KISS-ICP's stock pipeline (:class:`kiss_icp.kiss_icp.KissICP`: voxel map, adaptive threshold,
  robust point-to-point ICP, optional deskew), configured by :class:`slam.config.CloudOdometryConfig`.
  Each registration's covariance is ``sigma^2 (J^T J)^-1`` of the point-to-point residuals against the local
  map as it was before the frame was inserted (``J_i = [-R [p_i]x, R]`` in GTSAM's ``(omega, v)`` order),
  ``sigma`` the residual RMS (floored): the noise of the odometry factor of that increment.
- Keyframes by travel and rotation; between keyframes the increments and their covariances are composed
  (``C_ab = Ad(T_b^-1) C_a Ad(T_b^-1)^T + C_b``).
- Loop closures (the 2D design): candidates are keyframes at least ``loop_closure.min_separation_m`` of
  travel back whose predicted distance exceeds ``loop_closure.search_radius_m`` by no more than 3.4 sigma
  of the chain's relative position uncertainty (its largest eigenvalue; chi2 3 dof 99%); verification
  registers the query keyframe's cloud against the target's with KISS-ICP's registration, then gates
  the inlier fraction, the RMS and the consistency of the result with the prediction (6-dof chi2);
  accepted closures enter with a robust (Cauchy) loss.
- The batch optimisation (Levenberg-Marquardt) and the marginals of every keyframe.

The result is a :class:`slam.result.SlamResult` like the 2D one (SE(2) projections in its 2D fields), with
``poses_before_se3`` / ``poses_after_se3`` (N, 4, 4) and ``cov_after_se3`` (N, 6, 6) world-frame
``(x, y, z, rx, ry, rz)``.
"""

from __future__ import annotations

import math
import time

import gtsam
import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from datasets.progress import ProgressLike, stage
from datasets.types import CloudSequence
from slam import geometry as se2
from slam.config import CloudOdometryConfig, SlamConfig
from slam.consistency import keyframe_consistency_body
from slam.graph import Edge
from slam.graph3d import (
    PoseGraph3,
    body_to_world_cov,
    pose3,
    project_cov_se2,
    project_pose_se2,
    relative_se3,
    world_to_body_cov,
)
from slam.keyframes import keyframe_of_scan
from slam.loop_closure import LoopClosure
from slam.result import SlamResult

FloatArray = NDArray[np.float64]
PRIOR_SIGMAS = np.array([1e-4, 1e-4, 1e-4, 1e-3, 1e-3, 1e-3])  # (omega, v)


def kiss_config(cfg: CloudOdometryConfig):
    """KISS-ICP's own configuration from ours."""
    from kiss_icp.config import KISSConfig

    kc = KISSConfig()
    kc.data.max_range = cfg.max_range_m
    kc.data.min_range = cfg.min_range_m
    kc.data.deskew = cfg.deskew
    kc.mapping.voxel_size = cfg.voxel_size_m if cfg.voxel_size_m is not None else cfg.max_range_m / 100.0
    kc.registration.max_num_threads = 1
    return kc


def azimuth_times(points_xyz: FloatArray) -> FloatArray:
    """(P,) per-point times in [0, 1] of a spinning lidar's sweep, from the azimuth (for deskew)."""
    yaw = -np.arctan2(points_xyz[:, 1], points_xyz[:, 0])
    return 0.5 * (yaw / np.pi + 1.0)


def registration_cov(
    source_xyz: FloatArray,
    t_se3: FloatArray,
    map_tree: cKDTree | None,
    map_xyz: FloatArray,
    max_dist_m: float,
    min_sigma_m: float,
) -> tuple[FloatArray, int, float]:
    """``(cov (6, 6) (omega, v), inliers, rms_m)`` of a point-to-point registration of ``source_xyz`` (P, 3,
    body frame) at pose ``t_se3`` against map points within ``max_dist_m``."""
    if map_tree is None or source_xyz.shape[0] == 0:
        return np.diag([1e2] * 6), 0, float("nan")
    r, t = t_se3[:3, :3], t_se3[:3, 3]
    world = source_xyz @ r.T + t
    d, idx = map_tree.query(world, distance_upper_bound=max_dist_m)
    ok = np.isfinite(d)
    n = int(ok.sum())
    if n < 6:
        return np.diag([1e2] * 6), n, float("nan")
    p = source_xyz[ok]
    res = world[ok] - map_xyz[idx[ok]]
    rms = float(np.sqrt(np.mean(np.sum(res**2, axis=1)) / 3.0))
    sigma = max(rms, min_sigma_m)
    # J_i = [-R [p]x, R]; J^T J = [[ [p]x^T [p]x, -[p]x^T ], [-[p]x, I]] summed (R cancels: R^T R = I)
    px = np.zeros((n, 3, 3))
    px[:, 0, 1], px[:, 0, 2] = -p[:, 2], p[:, 1]
    px[:, 1, 0], px[:, 1, 2] = p[:, 2], -p[:, 0]
    px[:, 2, 0], px[:, 2, 1] = -p[:, 1], p[:, 0]
    h = np.zeros((6, 6))
    h[:3, :3] = np.einsum("nji,njk->ik", px, px)
    h[:3, 3:] = -np.sum(np.swapaxes(px, 1, 2), axis=0)
    h[3:, :3] = h[:3, 3:].T
    h[3:, 3:] = n * np.eye(3)
    return np.linalg.inv(h / sigma**2), n, rms


def _adjoint_inv(t_se3: FloatArray) -> FloatArray:
    return np.asarray(pose3(t_se3).inverse().AdjointMap())


def compose_rel_cov(t_b: FloatArray, cov_a: FloatArray, cov_b: FloatArray) -> FloatArray:
    """Covariance (omega, v) of ``T_a T_b`` from those of ``T_a`` and ``T_b`` (right perturbations)."""
    ad = _adjoint_inv(t_b)
    return ad @ cov_a @ ad.T + cov_b


def run_kiss_odometry(
    clouds: CloudSequence, cfg: CloudOdometryConfig, progress: ProgressLike | None = None
) -> tuple[FloatArray, FloatArray, list[FloatArray], NDArray[np.int64]]:
    """KISS-ICP on every cloud. Returns ``(poses_se3 (N, 4, 4), increment covs (N, 6, 6) (row 0 unused),
    registration sources (N,) of (P_i, 3) body-frame points, inliers (N,))``."""
    from kiss_icp.kiss_icp import KissICP

    kc = kiss_config(cfg)
    kiss = KissICP(kc)
    n = len(clouds)
    poses = np.zeros((n, 4, 4))
    covs = np.zeros((n, 6, 6))
    sources: list[FloatArray] = []
    inliers = np.zeros(n, dtype=np.int64)
    with stage(progress, "odometry (KISS-ICP)", n) as bar:
        for i in range(n):
            pts = np.asarray(clouds[i].points_xyz_m, dtype=np.float64)
            times = azimuth_times(pts) if cfg.deskew else np.zeros(0)
            map_xyz = kiss.local_map.point_cloud() if i > 0 else np.zeros((0, 3))
            _, source = kiss.register_frame(pts, times)
            source = np.asarray(source, dtype=np.float64)
            poses[i] = kiss.last_pose
            if i > 0:
                tree = cKDTree(map_xyz) if len(map_xyz) else None
                sigma = kiss.adaptive_threshold.get_threshold()
                covs[i], inliers[i], _ = registration_cov(
                    source, poses[i], tree, map_xyz, 3.0 * sigma, cfg.min_point_sigma_m
                )
                covs[i] *= cfg.odometry_cov_scale
            sources.append(source)
            bar.advance()
    return poses, covs, sources, inliers


def select_keyframes_se3(poses_se3: FloatArray, distance_m: float, rotation_rad: float) -> NDArray[np.int64]:
    """Indices of keyframes: the first pose, then each pose this far (travel or rotation) from the last."""
    keep = [0]
    for i in range(1, len(poses_se3)):
        rel = relative_se3(poses_se3[keep[-1]], poses_se3[i])
        angle = math.acos(max(-1.0, min(1.0, (np.trace(rel[:3, :3]) - 1.0) / 2.0)))
        if np.linalg.norm(rel[:3, 3]) >= distance_m or angle >= rotation_rad:
            keep.append(i)
    if keep[-1] != len(poses_se3) - 1:
        keep.append(len(poses_se3) - 1)
    return np.asarray(keep, dtype=np.int64)


def _chain_cov(poses: FloatArray, inc_cov: FloatArray, a: int, b: int) -> FloatArray:
    """Covariance (omega, v) of the relative pose ``a -> b`` composed from per-frame increments."""
    c = np.zeros((6, 6))
    for i in range(a + 1, b + 1):
        c = compose_rel_cov(relative_se3(poses[i - 1], poses[i]), c, inc_cov[i])
    return c


def verify_closure(
    query_xyz: FloatArray,
    target_xyz: FloatArray,
    guess_se3: FloatArray,
    cfg: CloudOdometryConfig,
    voxel_m: float,
) -> tuple[FloatArray, FloatArray, float, float]:
    """Register the query keyframe's points (its frame) against the target's (their frame) from
    ``guess_se3``. Returns ``(relative (4, 4), cov (6, 6), inlier fraction, rms_m)``."""
    from kiss_icp.pybind import kiss_icp_pybind as kiss

    vmap = kiss._VoxelHashMap(voxel_size=voxel_m, max_distance=1e9, max_points_per_voxel=20)
    vmap._add_points(kiss._Vector3dVector(target_xyz))
    reg = kiss._Registration(max_num_iterations=500, convergence_criterion=1e-4, max_num_threads=1)
    found = np.asarray(
        reg._align_points_to_map(
            points=kiss._Vector3dVector(query_xyz),
            voxel_map=vmap,
            initial_guess=pose3(guess_se3).matrix(),
            max_correspondance_distance=3.0 * voxel_m,
            kernel=voxel_m,
        )
    )
    tree = cKDTree(target_xyz)
    cov, n_in, rms = registration_cov(query_xyz, found, tree, target_xyz, voxel_m, cfg.min_point_sigma_m)
    return found, cov, n_in / max(len(query_xyz), 1), rms


def run_slam_clouds(
    clouds: CloudSequence, config: SlamConfig | None = None, progress: ProgressLike | None = None
):
    """KISS-ICP odometry, ``Pose3`` graph with loop closures, marginals and SE(2) projections for the
    clouds of one recording. Returns a :class:`slam.result.SlamResult` (see the module docstring)."""

    cfg = (config or SlamConfig()).cloud
    timings: dict[str, float] = {}
    n = len(clouds)
    stamps = np.asarray(clouds.stamps_ns, dtype=np.int64)
    t0 = time.perf_counter()
    poses, inc_cov, sources, _ = run_kiss_odometry(clouds, cfg, progress)
    timings["odometry_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    kf = select_keyframes_se3(poses, cfg.keyframe_distance_m, cfg.keyframe_rotation_rad)
    k_count = len(kf)
    rel = [relative_se3(poses[kf[k - 1]], poses[kf[k]]) for k in range(1, k_count)]
    rel_cov = [_chain_cov(poses, inc_cov, int(kf[k - 1]), int(kf[k])) for k in range(1, k_count)]
    graph = PoseGraph3()
    prior_cov = np.diag(PRIOR_SIGMAS**2)
    graph.add_pose(poses[kf[0]])
    graph.add_prior(0, poses[kf[0]], prior_cov)
    edges = [Edge("prior", 0, 0, project_pose_se2(poses[kf[0]]), _cov_se2_of_body(prior_cov))]
    for k in range(1, k_count):
        graph.add_pose(poses[kf[k]])
        graph.add_between("odometry", k - 1, k, rel[k - 1], rel_cov[k - 1])
        edges.append(
            Edge("odometry", k - 1, k, project_pose_se2(rel[k - 1]), _cov_se2_of_body(rel_cov[k - 1]))
        )

    # loop closures against the odometry chain
    voxel = kiss_config(cfg).mapping.voxel_size
    path = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(poses[kf, :3, 3], axis=0), axis=1))])
    accepted: list[LoopClosure] = []
    rejected: list[LoopClosure] = []
    chi2_3 = 11.34  # 3 dof, 99%
    with stage(progress, "loop closure (3D)", k_count) as bar:
        for k in range(k_count):
            for j in range(k):
                if path[k] - path[j] < cfg.loop_closure.min_separation_m:
                    break
                guess = relative_se3(poses[kf[j]], poses[kf[k]])
                dist = float(np.linalg.norm(guess[:3, 3]))
                if dist > cfg.loop_closure.search_radius_m + 50.0:
                    continue
                c_rel = _chain_cov(poses, inc_cov, int(kf[j]), int(kf[k]))
                pos_cov = c_rel[3:, 3:]
                slack = max(dist - cfg.loop_closure.search_radius_m, 0.0)
                if slack > 0 and slack**2 > chi2_3 * float(np.max(np.linalg.eigvalsh(pos_cov))):
                    continue
                found, cov, frac, rms = verify_closure(sources[kf[k]], sources[kf[j]], guess, cfg, voxel)
                dev = np.asarray(gtsam.Pose3.Logmap(pose3(guess).between(pose3(found))))
                d2 = float(dev @ np.linalg.solve(c_rel + cov, dev))
                ok = frac >= cfg.loop_closure.min_inlier_fraction and rms <= cfg.loop_closure.max_rms_m
                ok = ok and d2 <= cfg.loop_closure.consistency_chi2
                closure = LoopClosure(
                    query_keyframe=k,
                    target_keyframe=j,
                    query_scan=int(kf[k]),
                    target_scan=int(kf[j]),
                    relative_xytheta=project_pose_se2(found),
                    information=np.linalg.inv(_cov_se2_of_body(cov)),
                    score=float(frac),
                    fitness=float(frac),
                    rms_m=float(rms),
                    mahalanobis2=d2,
                    accepted=bool(ok),
                    reason="" if ok else "3D verification failed",
                )
                (accepted if ok else rejected).append(closure)
                if ok:
                    graph.add_between(
                        "loop",
                        j,
                        k,
                        found,
                        cov,
                        robust=cfg.loop_closure.robust_kernel,
                        robust_width=cfg.loop_closure.robust_kernel_width,
                    )
                    edges.append(
                        Edge(
                            "loop",
                            j,
                            k,
                            project_pose_se2(found),
                            _cov_se2_of_body(cov),
                            cfg.loop_closure.robust_kernel,
                            cfg.loop_closure.robust_kernel_width,
                        )
                    )
                    break
            bar.advance()
    timings["loop_search_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    est = graph.optimize() if k_count > 1 else graph.estimate()
    kf_cov_after = graph.marginals_world()
    timings["graph_batch_s"] = time.perf_counter() - t0
    # the chain alone: first-order propagation of the increments from the prior
    kf_cov_before = np.zeros((k_count, 6, 6))
    body = prior_cov
    kf_cov_before[0] = body_to_world_cov(poses[kf[0]], body)
    for k in range(1, k_count):
        body = compose_rel_cov(rel[k - 1], body, rel_cov[k - 1])
        kf_cov_before[k] = body_to_world_cov(poses[kf[k]], body)

    # every frame: its keyframe's pose composed with the odometry offset
    owner = keyframe_of_scan(kf, n)
    after = np.zeros((n, 4, 4))
    cov_after_se3 = np.zeros((n, 6, 6))
    cov_before_se3 = np.zeros((n, 6, 6))
    off_cov_se2 = np.zeros((n, 3, 3))
    for i in range(n):
        k = int(owner[i])
        off = relative_se3(poses[kf[k]], poses[i])
        off_cov = _chain_cov(poses, inc_cov, int(kf[k]), i)
        off_cov_se2[i] = _cov_se2_of_body(off_cov)
        after[i] = est[k] @ off
        b_after = compose_rel_cov(off, world_to_body_cov(est[k], kf_cov_after[k]), off_cov)
        b_before = compose_rel_cov(off, world_to_body_cov(poses[kf[k]], kf_cov_before[k]), off_cov)
        cov_after_se3[i] = body_to_world_cov(after[i], b_after)
        cov_before_se3[i] = body_to_world_cov(poses[i], b_before)
    cov_after = np.stack([project_cov_se2(after[i], cov_after_se3[i]) for i in range(n)])
    cov_before = np.stack([project_cov_se2(poses[i], cov_before_se3[i]) for i in range(n)])
    # the mapper's covariances: relative to the earlier passes over each place, on the SE(2) projection
    t0 = time.perf_counter()
    before_se2, after_se2, kf_se2 = project_pose_se2(poses), project_pose_se2(after), project_pose_se2(est)
    path_kf = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(poses[kf, :2, 3], axis=0), axis=1))])
    rel_before_body, rel_after_body = keyframe_consistency_body(
        before_se2[kf],
        kf_se2,
        edges,
        [sources[i][:, :2] for i in kf],
        path_kf,
        (config or SlamConfig()).consistency,
    )
    offset = se2.between(before_se2[kf[owner]], before_se2)
    rel_before = se2.rotate_cov_to_world(
        before_se2, se2.compose_cov_body(rel_before_body[owner], offset, off_cov_se2)
    )
    rel_after = se2.rotate_cov_to_world(
        after_se2, se2.compose_cov_body(rel_after_body[owner], offset, off_cov_se2)
    )
    timings["consistency_s"] = time.perf_counter() - t0
    timings["total_s"] = sum(timings.values())
    return SlamResult(
        stamps_ns=stamps,
        poses_before_xytheta=project_pose_se2(poses),
        poses_after_xytheta=project_pose_se2(after),
        cov_before_xytheta=cov_before,
        cov_after_xytheta=cov_after,
        relative_cov_before_xytheta=0.5 * (rel_before + np.swapaxes(rel_before, 1, 2)),
        relative_cov_after_xytheta=0.5 * (rel_after + np.swapaxes(rel_after, 1, 2)),
        odometry_status=np.where(np.arange(n) == 0, 0, 1).astype(np.int8),
        keyframe_scans=kf,
        keyframe_stamps_ns=stamps[kf],
        keyframe_cov_before=np.stack(
            [project_cov_se2(poses[kf[k]], kf_cov_before[k]) for k in range(k_count)]
        ),
        keyframe_cov_after=np.stack([project_cov_se2(est[k], kf_cov_after[k]) for k in range(k_count)]),
        loop_closures=tuple(accepted),
        rejected_loop_closures=tuple(rejected),
        graph_vertices_xytheta=project_pose_se2(est),
        graph_edges=tuple(edges),
        variance_factor=1.0,
        timings_s=timings,
        poses_before_se3=poses,
        poses_after_se3=after,
        cov_after_se3=cov_after_se3,
        keyframe_cov_after_se3=kf_cov_after,
        keyframe_cov_before_se3=kf_cov_before,
    )


def _cov_se2_of_body(cov_body: FloatArray) -> FloatArray:
    """(3, 3) (x, y, yaw) block of a body-frame (omega, v) covariance of a near-level relative pose."""
    idx = [3, 4, 2]
    return np.asarray(cov_body)[np.ix_(idx, idx)]
