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

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

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
