"""SLAM metrics (SPEC section 6): ATE after SE(2) alignment, the relations error of Kuemmerle et al. (2009),
and the consistency of pose covariances (NEES).

- ATE: the estimate is aligned to the reference by the rigid SE(2) transform minimising the squared position
  error (Umeyama 1991 without scale), on matched poses; the RMSE of the remaining position errors.
- Relations: for each relation ``(t1, t2, dx, dy, dyaw)``, the estimated relative pose between the poses at
  ``t1`` and ``t2`` is compared with it: translational error ``|t_est - t_rel|`` (m) and absolute rotational
  error ``|wrap(yaw_est - yaw_rel)|`` (deg); their mean and standard deviation.
- NEES: with the estimate anchored at its first pose (its covariances are relative to it), the reference is
  moved onto the estimate's first pose and ``e^T S^-1 e`` is computed for every pose, ``e`` the world-frame
  (x, y, theta) error. Its mean is 3 for consistent 3-dof covariances.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from slam import geometry as se2

FloatArray = NDArray[np.float64]


def align_se2(estimate_xytheta: FloatArray, reference_xytheta: FloatArray) -> FloatArray:
    """The SE(2) transform (3,) ``T`` minimising ``sum |T * p_est - p_ref|^2`` over positions (Umeyama)."""
    est = np.asarray(estimate_xytheta, dtype=np.float64)[:, :2]
    ref = np.asarray(reference_xytheta, dtype=np.float64)[:, :2]
    if est.shape[0] == 0:
        return np.zeros(3)
    mu_e = est.mean(axis=0)
    mu_r = ref.mean(axis=0)
    h = (est - mu_e).T @ (ref - mu_r)
    u, _, vt = np.linalg.svd(h)
    d = np.eye(2)
    d[1, 1] = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    rot = vt.T @ d @ u.T
    t = mu_r - rot @ mu_e
    return np.array([t[0], t[1], np.arctan2(rot[1, 0], rot[0, 0])])


def ate_rmse(estimate_xytheta: FloatArray, reference_xytheta: FloatArray) -> float:
    """Absolute trajectory error (m): RMSE of positions after SE(2) alignment of matched (M, 3) poses."""
    est = np.asarray(estimate_xytheta, dtype=np.float64)
    ref = np.asarray(reference_xytheta, dtype=np.float64)
    if est.shape != ref.shape or est.shape[0] == 0:
        raise ValueError(f"ATE needs matched non-empty pose arrays, got {est.shape} and {ref.shape}")
    aligned = se2.compose(align_se2(est, ref), est)
    return float(np.sqrt(np.mean(np.sum((aligned[:, :2] - ref[:, :2]) ** 2, axis=1))))


#: A benchmark relation whose two scans lie at most this far apart along the odometry path (m) is local: it
#: measures the front end (scan matching on the wheels); the others join two passes and measure the loop
#: closures. The benchmark's relations are of both kinds, metres of travel apart or hundreds.
LOCAL_TRAVEL_M = 10.0


@dataclass(frozen=True)
class RelationErrors:
    """Per-relation errors and their statistics (SPEC section 3 keys via :meth:`as_dict`)."""

    trans_m: FloatArray
    rot_deg: FloatArray

    def as_dict(self) -> dict[str, float | int]:
        n = int(self.trans_m.shape[0])
        if n == 0:
            return {
                "count": 0,
                "trans_mean_m": None,
                "trans_std_m": None,
                "rot_mean_deg": None,
                "rot_std_deg": None,
            }
        return {
            "count": n,
            "trans_mean_m": float(np.mean(self.trans_m)),
            "trans_std_m": float(np.std(self.trans_m)),
            "rot_mean_deg": float(np.mean(self.rot_deg)),
            "rot_std_deg": float(np.std(self.rot_deg)),
        }


def relation_errors(
    poses1_xytheta: FloatArray, poses2_xytheta: FloatArray, relations_xytheta: FloatArray
) -> RelationErrors:
    """Errors of the estimated relative poses ``between(p1, p2)`` against (R, 3) relations (x, y, yaw)."""
    est = se2.between(np.asarray(poses1_xytheta), np.asarray(poses2_xytheta))
    rel = np.asarray(relations_xytheta, dtype=np.float64)
    trans = np.hypot(est[:, 0] - rel[:, 0], est[:, 1] - rel[:, 1])
    rot = np.degrees(np.abs(se2.wrap(est[:, 2] - rel[:, 2])))
    return RelationErrors(trans, rot)


def relations_from_trajectory(poses_xytheta: FloatArray, pairs: NDArray[np.int64]) -> FloatArray:
    """(R, 3) relative poses ``between(p[i], p[j])`` for (R, 2) index pairs (to derive a relations file)."""
    p = np.asarray(poses_xytheta, dtype=np.float64)
    pairs = np.asarray(pairs, dtype=np.int64)
    return se2.between(p[pairs[:, 0]], p[pairs[:, 1]])


def index_at_stamps(
    stamps_ns: NDArray[np.int64], query_ns: NDArray[np.int64], tolerance_ns: int
) -> NDArray[np.int64]:
    """(Q,) index of the stamp nearest to each query, -1 where the nearest is farther than ``tolerance_ns``.

    ``stamps_ns`` must be increasing.
    """
    s = np.asarray(stamps_ns, dtype=np.int64)
    q = np.asarray(query_ns, dtype=np.int64)
    if s.shape[0] == 0:
        return np.full(q.shape[0], -1, dtype=np.int64)
    i = np.clip(np.searchsorted(s, q), 1, max(s.shape[0] - 1, 1))
    lo = np.clip(i - 1, 0, s.shape[0] - 1)
    hi = np.clip(i, 0, s.shape[0] - 1)
    nearest = np.where(np.abs(s[lo] - q) <= np.abs(s[hi] - q), lo, hi)
    nearest = np.where(np.abs(s[nearest] - q) <= tolerance_ns, nearest, -1)
    return nearest.astype(np.int64)


def nees(
    estimate_xytheta: FloatArray, cov_world: FloatArray, reference_xytheta: FloatArray, anchor: int = 0
) -> FloatArray:
    """(M,) normalised estimation error squared of (M, 3) poses with (M, 3, 3) world-frame covariances.

    The reference is moved rigidly so that its pose ``anchor`` coincides with the estimate's (the frame in
    which the covariances are expressed); the anchor itself (zero covariance up to the prior) is included.
    """
    est = np.asarray(estimate_xytheta, dtype=np.float64)
    ref = np.asarray(reference_xytheta, dtype=np.float64)
    t = se2.compose(est[anchor], se2.inverse(ref[anchor]))
    ref_a = se2.compose(t, ref)
    e = est - ref_a
    e[:, 2] = se2.wrap(e[:, 2])
    return np.einsum("ni,nij,nj->n", e, np.linalg.inv(cov_world), e)


#: How far a loop closure's relative pose may be from the truth and still count as correct.
CLOSURE_TOLERANCE_M = 0.2
CLOSURE_TOLERANCE_DEG = 2.0


def loop_closure_scores(
    keyframe_reference_xytheta: FloatArray,
    keyframe_path_m: FloatArray,
    query_keyframes: NDArray[np.int64],
    target_keyframes: NDArray[np.int64],
    relative_xytheta: FloatArray,
    min_separation_m: float,
    revisit_radius_m: float = 2.0,
    coverage_m: float = 2.0,
    tolerance_m: float = CLOSURE_TOLERANCE_M,
    tolerance_deg: float = CLOSURE_TOLERANCE_DEG,
) -> dict[str, float | int | None]:
    """Precision and recall of accepted loop closures against reference keyframe poses.

    A closure ``(query, target, relative)`` is correct when ``relative`` (the query's pose in the target's
    frame) is within ``tolerance_m`` and ``tolerance_deg`` of the reference relative pose. A keyframe is a
    *revisit* when the reference puts an earlier keyframe, at least ``min_separation_m`` of travel back,
    within ``revisit_radius_m`` of it; it is *covered* when a correct closure's query keyframe lies within
    ``coverage_m`` of travel of it. Precision = correct / accepted, recall = covered revisits / revisits
    (None when there are none). Inputs: (K, 3) reference poses and (K,) travelled distance of every
    keyframe, (C,) query and target keyframe indices and (C, 3) relative poses of the accepted closures.
    """
    ref = np.asarray(keyframe_reference_xytheta, dtype=np.float64)
    path = np.asarray(keyframe_path_m, dtype=np.float64)
    q = np.asarray(query_keyframes, dtype=np.int64)
    t = np.asarray(target_keyframes, dtype=np.int64)
    rel = np.asarray(relative_xytheta, dtype=np.float64).reshape(-1, 3)
    correct = np.zeros(len(q), dtype=bool)
    if len(q):
        err = se2.between(se2.between(ref[t], ref[q]), rel)
        correct = (np.hypot(err[:, 0], err[:, 1]) <= tolerance_m) & (
            np.degrees(np.abs(err[:, 2])) <= tolerance_deg
        )
    revisit = np.zeros(len(ref), dtype=bool)
    for k in range(len(ref)):
        earlier = np.nonzero(path[:k] <= path[k] - min_separation_m)[0]
        if earlier.size:
            d = np.hypot(ref[earlier, 0] - ref[k, 0], ref[earlier, 1] - ref[k, 1])
            revisit[k] = bool(np.any(d <= revisit_radius_m))
    good_paths = path[q[correct]]
    covered = np.zeros(len(ref), dtype=bool)
    if good_paths.size:
        covered = np.min(np.abs(path[:, None] - good_paths[None, :]), axis=1) <= coverage_m
    n_rev = int(revisit.sum())
    return {
        "accepted": len(q),
        "correct": int(correct.sum()),
        "precision": float(correct.mean()) if len(q) else None,
        "revisit_keyframes": n_rev,
        "covered_revisits": int((revisit & covered).sum()),
        "recall": float((revisit & covered).sum() / n_rev) if n_rev else None,
    }


#: Scans of our odometry, each side, that may bridge a loop closure's keyframes to a relation's scans
#: (:func:`closures_against_relations`): a second or two of motion, over which the odometry errs little.
RELATION_BRIDGE_SCANS = 10


def closures_against_relations(
    keyframe_scans: NDArray[np.int64],
    odometry_xytheta: FloatArray,
    query_keyframes: NDArray[np.int64],
    target_keyframes: NDArray[np.int64],
    relative_xytheta: FloatArray,
    relation_scans: tuple[NDArray[np.int64], NDArray[np.int64]],
    relation_xytheta: FloatArray,
    bridge_scans: int = RELATION_BRIDGE_SCANS,
    tolerance_m: float = CLOSURE_TOLERANCE_M,
    tolerance_deg: float = CLOSURE_TOLERANCE_DEG,
    scan_points: Callable[[int], FloatArray] | None = None,
) -> dict[str, object]:
    """Loop closures judged by the benchmark's relations, where a relation joins the closure's two places.

    A closure ``(query, target, relative)`` (``relative``: the query keyframe's pose in the target's frame)
    is *judged* when a relation's two scans lie within ``bridge_scans`` scans of the target's and the
    query's keyframe scans (in either order); the nearest such relation, carried to the keyframes by our
    odometry over those few scans (``odometry_xytheta`` (N, 3), before loop closure, which the closure does
    not move), gives the true relative pose. The closure is correct within ``tolerance_m`` and
    ``tolerance_deg`` of it, as :func:`loop_closure_scores` judges against a reference trajectory. Inputs:
    (K,) keyframe scans, (C,) query and target keyframes, (C, 3) relative poses, the relations' (R,) scans
    ``(scan1, scan2)`` and (R, 3) relative poses (scan2's pose in scan1's frame). Returns ``judged``,
    ``correct``, ``precision`` (None when none is judged), ``bridge_scans`` and ``wrong``: per wrong
    closure its keyframes and its translation (m) and rotation (deg) errors.

    The relations are hand-checked scan alignments and can err too. With ``scan_points`` (scan index ->
    its (P, 2) base-frame points), each wrong closure also gets the overlap of the relation's two scans
    (:func:`scan_overlap`) at the relation's relative pose and at the closure's (carried to those scans by
    the odometry), and is ``disputed`` when they overlap more at the closure's (by
    :data:`DISPUTE_MARGIN`); ``disputed`` counts those (None without ``scan_points``). A disputed closure
    still counts as wrong: the scans are evidence, not truth (weak evidence where scans are sparse)."""
    kf = np.asarray(keyframe_scans, dtype=np.int64)
    odo = np.asarray(odometry_xytheta, dtype=np.float64)
    s1, s2 = (np.asarray(x, dtype=np.int64) for x in relation_scans)
    rel = np.asarray(relation_xytheta, dtype=np.float64).reshape(-1, 3)
    closures = np.asarray(relative_xytheta, dtype=np.float64).reshape(-1, 3)
    judged = correct = 0
    wrong: list[dict[str, float | int]] = []
    for q, t, measured in zip(query_keyframes, target_keyframes, closures, strict=True):
        sq, st = kf[q], kf[t]
        best = None
        for near_t, near_q, flip in ((s1, s2, False), (s2, s1, True)):
            gap = np.abs(near_t - st) + np.abs(near_q - sq)
            ok = (np.abs(near_t - st) <= bridge_scans) & (np.abs(near_q - sq) <= bridge_scans)
            if ok.any():
                i = int(np.flatnonzero(ok)[np.argmin(gap[ok])])
                if best is None or gap[i] < best[0]:
                    best = (int(gap[i]), i, flip)
        if best is None:
            continue
        _, i, flip = best
        a, b = (s2[i], s1[i]) if flip else (s1[i], s2[i])  # a near the target, b near the query
        r = se2.inverse(rel[i]) if flip else rel[i]
        truth = se2.compose(se2.compose(se2.between(odo[st], odo[a]), r), se2.between(odo[b], odo[sq]))
        err = se2.between(truth, measured)
        err_m, err_deg = float(np.hypot(err[0], err[1])), float(np.degrees(abs(se2.wrap(err[2]))))
        judged += 1
        if err_m <= tolerance_m and err_deg <= tolerance_deg:
            correct += 1
        else:
            item: dict[str, float | int | bool] = {
                "query_keyframe": int(q),
                "target_keyframe": int(t),
                "error_m": err_m,
                "error_deg": err_deg,
            }
            if scan_points is not None:  # the relation's own two scans, at its pose and at the closure's
                at_closure = se2.compose(
                    se2.compose(se2.between(odo[a], odo[st]), measured), se2.between(odo[sq], odo[b])
                )
                tgt, qry = scan_points(int(a)), scan_points(int(b))
                item["overlap_at_closure"] = scan_overlap(tgt, qry, at_closure)
                item["overlap_at_relation"] = scan_overlap(tgt, qry, r)
                item["disputed"] = item["overlap_at_closure"] >= item["overlap_at_relation"] + DISPUTE_MARGIN
            wrong.append(item)
    return {
        "judged": judged,
        "correct": correct,
        "precision": correct / judged if judged else None,
        "bridge_scans": int(bridge_scans),
        "wrong": wrong,
        "disputed": None if scan_points is None else sum(bool(w["disputed"]) for w in wrong),
    }


#: A query point overlaps the target scan when within this distance of one of its points
#: (:func:`scan_overlap`): a quarter of the closures' tolerance, so that 2 deg moves a point at 1.5 m out.
OVERLAP_M = 0.05
#: A wrong closure is disputed when its scans' overlap at the closure's pose exceeds that at the relation's
#: by at least this share of the query's points (:func:`closures_against_relations`).
DISPUTE_MARGIN = 0.02


def scan_overlap(
    target_points_xy: FloatArray,
    query_points_xy: FloatArray,
    relative_xytheta: FloatArray,
    radius_m: float = OVERLAP_M,
) -> float:
    """Share of the query scan's points (M, 2, its frame) within ``radius_m`` of a target scan point (P, 2,
    its frame) when the query is placed at ``relative_xytheta`` (3,: its pose in the target's frame); 0 for
    an empty scan."""
    qry = np.asarray(query_points_xy, dtype=np.float64).reshape(-1, 2)
    tgt = np.asarray(target_points_xy, dtype=np.float64).reshape(-1, 2)
    if qry.shape[0] == 0 or tgt.shape[0] == 0:
        return 0.0
    d, _ = cKDTree(tgt).query(se2.transform_points(np.asarray(relative_xytheta, dtype=np.float64), qry))
    return float(np.mean(d <= radius_m))


def reference_noise_sigma(reference_xytheta: FloatArray, odometry_xytheta: FloatArray) -> tuple[float, float]:
    """Per-pose noise ``(sigma_xy_m, sigma_theta_rad)`` of a reference trajectory, from its consecutive
    relative poses against the same steps of a locally accurate odometry (M, 3) each.

    A SLAM-corrected reference (GMapping's) jitters from pose to pose by more than a scan-to-map odometry
    errs over one step; the robust spread of the step differences (1.4826 MAD per axis), divided by
    sqrt(2) for the two poses of a step, estimates that jitter (an upper bound: the odometry's own step
    error is included). NEES against such a reference counts this noise as our error.
    """
    ref = np.asarray(reference_xytheta, dtype=np.float64)
    odo = np.asarray(odometry_xytheta, dtype=np.float64)
    if ref.shape[0] < 3:
        return 0.0, 0.0
    d = se2.between(se2.between(ref[:-1], ref[1:]), se2.between(odo[:-1], odo[1:]))
    d[:, 2] = se2.wrap(d[:, 2])

    def robust(x: FloatArray) -> float:
        return float(1.4826 * np.median(np.abs(x - np.median(x))))

    sigma_xy = np.sqrt(0.5 * (robust(d[:, 0]) ** 2 + robust(d[:, 1]) ** 2)) / np.sqrt(2.0)
    return float(sigma_xy), robust(d[:, 2]) / float(np.sqrt(2.0))
