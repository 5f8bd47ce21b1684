"""What the SLAM stage returns (:class:`SlamResult`), for the 2D and the 3D paths alike.

Its own module so that :mod:`slam.system` (2D, and the entry point) and :mod:`slam.system3d` (clouds) both
build it without importing each other's insides.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from datasets.types import Trajectory
from slam.graph import Edge
from slam.loop_closure import LoopClosure

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class SlamResult:
    """Everything the SLAM stage produces (N scans, K keyframes).

    Per scan: ``stamps_ns`` (N,), ``poses_before_xytheta`` / ``poses_after_xytheta`` (N, 3) base poses of
    the odometry chain and of the optimised graph, ``cov_before_xytheta`` / ``cov_after_xytheta``
    (N, 3, 3) world-frame covariances (marginals: relative to the graph's anchor, the first pose),
    ``relative_cov_before_xytheta`` / ``relative_cov_after_xytheta`` (N, 3, 3) the covariances the mapper
    receives, world-frame, of each scan's pose relative to the earlier passes over the places it observes
    (:mod:`slam.consistency`), ``odometry_status`` (N,) int8 (see :mod:`slam.odometry`).
    Per keyframe: ``keyframe_scans`` (K,) scan indices, ``keyframe_stamps_ns`` (K,),
    ``keyframe_cov_before`` / ``keyframe_cov_after`` (K, 3, 3) world-frame marginals.
    ``loop_closures`` / ``rejected_loop_closures``: the verified and the refused attempts.
    ``graph_vertices_xytheta`` (K, 3) and ``graph_edges``: the optimised pose graph (g2o export), whose
    factor covariances include ``variance_factor``, the a-posteriori variance factor of the adjustment
    (every factor covariance, and so every marginal, is multiplied by it; 1 when not estimated).
    ``timings_s``: wall time per sub-stage.
    """

    stamps_ns: NDArray[np.int64]
    poses_before_xytheta: FloatArray
    poses_after_xytheta: FloatArray
    cov_before_xytheta: FloatArray
    cov_after_xytheta: FloatArray
    relative_cov_before_xytheta: FloatArray
    relative_cov_after_xytheta: FloatArray
    odometry_status: NDArray[np.int8]
    keyframe_scans: NDArray[np.int64]
    keyframe_stamps_ns: NDArray[np.int64]
    keyframe_cov_before: FloatArray
    keyframe_cov_after: FloatArray
    loop_closures: tuple[LoopClosure, ...]
    rejected_loop_closures: tuple[LoopClosure, ...]
    graph_vertices_xytheta: FloatArray
    graph_edges: tuple[Edge, ...]
    variance_factor: float = 1.0
    timings_s: dict[str, float] = field(default_factory=dict)
    loop_closures_dropped: int = 0  # accepted by verification, then dropped by the robust back end
    fault_injection: dict | None = None  # evaluate slam --inject-false-closures: injected / kept
    wheel_odometry: str = "as given"  # where the wheel odometry came from (:func:`wheel_odometry`)
    # (N, 3, 3) each scan's pose relative to its keyframe's (the odometry between them; zero for a
    # keyframe), in the scan's frame: how far it strays from the keyframe it moves with (None: not known)
    keyframe_offset_cov_body: FloatArray | None = None
    # 3D inputs only (:mod:`slam.system3d`): (N, 4, 4) poses, (N, 6, 6) and (K, 6, 6) world-frame
    # (x, y, z, rx, ry, rz) covariances; the 2D fields above are their SE(2) projections
    poses_before_se3: FloatArray | None = None
    poses_after_se3: FloatArray | None = None
    cov_after_se3: FloatArray | None = None
    keyframe_cov_before_se3: FloatArray | None = None
    keyframe_cov_after_se3: FloatArray | None = None

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
            "loop_closures_dropped_by_back_end": self.loop_closures_dropped,
            "odometry_fallbacks": int(np.sum(self.odometry_status >= 2)),
            "wheel_odometry": self.wheel_odometry,
            "timings_s": dict(self.timings_s),
            **({"fault_injection": dict(self.fault_injection)} if self.fault_injection is not None else {}),
        }
