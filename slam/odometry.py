"""Scan-to-submap odometry for planar scans, seeded by the wheel odometry and gated.

Every scan is registered against a local map of the recent scans (Cartographer-style submaps: each inserted
scan goes into the two active submaps; a scan is matched to the older one, which holds between
``submap_scans`` and twice as many scans). The prediction is the previous pose composed with the wheel
increment (or, without wheels, the previous increment). With wheels, a dense scan registers with about
``match_points`` of its points, spread evenly along it (:func:`match_subset`); the submaps get every point.
Two registrations are available:

- ``point_to_line`` (default): a correlative search (Olson 2009) in a small window around the prediction,
  then robust point-to-line Gauss-Newton with the wheel prediction as a Gaussian prior;
- ``kiss_icp``: KISS-ICP's own voxel map and robust point-to-point ICP (its pybind core, scans lifted to
  z = 0, no deskew), seeded by the same prediction; the submap grid is kept alongside for the gates and
  the information matrix.

With ``normal_check`` the refinement skips map points whose normal faces away from the scan point's
(both face their sensors): the far face of a thin wall seen earlier from the other side. Translation
directions the scan barely constrains (a featureless corridor's axis, ``degenerate_ratio``) keep the
prediction and its uncertainty (:func:`remap_degenerate`). A point-to-line registration that matches few
of its points or that the gates reject is searched again over every heading within ``retry_window_rad``
(wheels can turn 10-20 deg wrong between the keyframes of a sparse log) and the better-explaining match
kept. Either result is rejected -- and the wheel prediction used instead, with the wheel uncertainty --
when too few points match or the motion deviates implausibly from the wheels. Without wheels the prediction
is a constant-velocity guess, searched widely (branch and bound); dense scans are searched in a compact
window that adapts to the guess's recent errors. A gap in the wheel records (a NaN wheel pose) makes the
steps around it steps without wheels. Each scan gets the covariance of its registration,
``(H / sigma^2 + Lambda_wheel)^-1`` (world frame), which the graph scales into factor noise.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numba as nb
import numpy as np
from numpy.typing import NDArray

from datasets.progress import ProgressLike, stage
from datasets.types import ScanSequence
from slam import geometry as se2
from slam.config import OdometryConfig
from slam.scan_matching import (
    Alignment,
    PointGrid,
    SearchResult,
    branch_and_bound_search,
    correlative_search,
    refine_point_to_line,
    scan_normals,
    voxel_thin,
)

FloatArray = NDArray[np.float64]

# status of each scan's registration
FIRST = 0
MATCHED = 1
FALLBACK = 2  # registration rejected by the gates: wheel prediction used
TOO_FEW_POINTS = 3  # not enough usable beams: wheel prediction used
STATUS_NAMES = {FIRST: "first", MATCHED: "matched", FALLBACK: "fallback", TOO_FEW_POINTS: "too_few_points"}


@dataclass(frozen=True)
class OdometryResult:
    """Per-scan output of :func:`run_odometry` (N scans).

    - ``poses_xytheta`` (N, 3): base poses in the odometry frame (the wheel frame's first pose, or the
      origin without wheels);
    - ``cov_xytheta`` (N, 3, 3): world-frame covariance of each scan's registration against its submap
      (unscaled ``(H / sigma^2 + Lambda)^-1``; for rejected scans, the accumulated wheel uncertainty since the
      last registered scan);
    - ``status`` (N,) int8: :data:`FIRST`, :data:`MATCHED`, :data:`FALLBACK`, :data:`TOO_FEW_POINTS`;
    - ``inlier_fraction`` (N,): fraction of the scan's points matched to the submap;
    - ``rms_m`` (N,): robust RMS of the point-to-line residuals at the solution (NaN if not registered);
    - ``points_base`` (N,) list of (P_i, 2) base-frame points used (for loop closure);
    - ``timings_s``: wall time per sub-stage.
    """

    poses_xytheta: FloatArray
    cov_xytheta: FloatArray
    status: NDArray[np.int8]
    inlier_fraction: FloatArray
    rms_m: FloatArray
    points_base: list[FloatArray]
    timings_s: dict[str, float] = field(default_factory=dict)
    submap_restarts: int = 0  # submaps started afresh after a run of rejected registrations
    retries: int = 0  # registrations searched again over wider headings (``retry_below_inliers``)

    def status_counts(self) -> dict[str, int]:
        """Number of scans per status name."""
        return {name: int(np.sum(self.status == code)) for code, name in STATUS_NAMES.items()}


def scan_points_base(
    ranges_m: NDArray,
    angles_rad: NDArray,
    range_min_m: float,
    range_max_m: float,
    laser_in_base_xytheta: FloatArray,
    min_range_m: float,
    max_range_m: float,
) -> FloatArray:
    """(P, 2) base-frame end points of the valid returns, in beam order.

    A return is valid when finite, ``>= max(range_min, min_range_m)`` and ``< min(range_max, max_range_m)``
    (no-return beams carry no end point, SPEC section 2).
    """
    r = np.asarray(ranges_m, dtype=np.float64)
    a = np.asarray(angles_rad, dtype=np.float64)
    lo = max(float(range_min_m), min_range_m)
    hi = min(float(range_max_m), max_range_m)
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(r) & (r >= lo) & (r < hi)
    r, a = r[ok], a[ok]
    pts = np.stack([r * np.cos(a), r * np.sin(a)], axis=1)
    return se2.transform_points(np.asarray(laser_in_base_xytheta, dtype=np.float64), pts)


def scans_points_base(
    scans: ScanSequence, laser_in_base_xytheta: FloatArray, cfg: OdometryConfig, count: int | None = None
) -> list[FloatArray]:
    """:func:`scan_points_base` of the first ``count`` scans of ``scans`` (default all), with the range
    limits of ``cfg``: a list of (P_i, 2) arrays."""
    n = len(scans) if count is None else count
    mount = np.asarray(laser_in_base_xytheta, dtype=np.float64)
    return [scan_points_at(scans, i, mount, cfg) for i in range(n)]


def scan_points_at(
    scans: ScanSequence, i: int, laser_in_base_xytheta: FloatArray, cfg: OdometryConfig
) -> FloatArray:
    """:func:`scan_points_base` of scan ``i`` of ``scans`` with the range limits of ``cfg``: (P, 2)."""
    return scan_points_base(
        scans.ranges_m[i],
        scans.angles_rad[i],
        scans.range_min_m[i],
        scans.range_max_m[i],
        laser_in_base_xytheta,
        cfg.min_range_m,
        cfg.max_range_m,
    )


def sensor_reach_m(points_base: Sequence[FloatArray]) -> float:
    """The farthest of the (P_i, 2) base-frame points of any scan from its base (m; 0 without points): how
    far a submap must reach around the pose it is centred on."""
    pts = np.concatenate([np.zeros((0, 2)), *points_base])
    return math.sqrt(float(np.max(np.einsum("ij,ij->i", pts, pts), initial=0.0)))


# the widest spacing along the scan that match_subset tries (Cartographer's adaptive voxel filter: 0.5 m)
MAX_MATCH_SPACING_M = 0.5


@nb.njit(cache=True)
def _spaced(points_xy: FloatArray, spacing_m: float, out: NDArray[np.int64]) -> int:
    """Walk the scan in beam order and keep a point when it lies at least ``spacing_m`` from the last kept
    one; the kept indices go to the front of ``out``, their count is returned."""
    s2 = spacing_m * spacing_m
    m = 0
    lx = 0.0
    ly = 0.0
    for k in range(points_xy.shape[0]):
        dx = points_xy[k, 0] - lx
        dy = points_xy[k, 1] - ly
        if m == 0 or dx * dx + dy * dy >= s2:
            out[m] = k
            m += 1
            lx = points_xy[k, 0]
            ly = points_xy[k, 1]
    return m


@nb.njit(cache=True)
def _widest_spaced(
    points_xy: FloatArray, min_points: int, max_spacing_m: float, out: NDArray[np.int64]
) -> int:
    """:func:`_spaced` at the widest spacing up to ``max_spacing_m`` (bisected to 1/4096 of it) that keeps
    at least ``min_points`` points; every point when there are no more than that."""
    n = points_xy.shape[0]
    if n <= min_points:
        for k in range(n):
            out[k] = k
        return n
    m = _spaced(points_xy, max_spacing_m, out)
    if m >= min_points:
        return m
    lo = 0.0  # keeps every point
    hi = max_spacing_m
    for _ in range(12):
        mid = 0.5 * (lo + hi)
        if _spaced(points_xy, mid, out) >= min_points:
            lo = mid
        else:
            hi = mid
    return _spaced(points_xy, lo, out)


def match_subset(points_base: FloatArray, target_points: int) -> NDArray[np.int64]:
    """Indices (M,), in beam order, of the points of a scan ((P, 2), beam order) that register it: all of
    them when ``P <= target_points`` (or ``target_points`` is 0), else those kept by walking the scan and
    taking a point when it lies at least ``s`` from the last one taken, with the widest ``s`` up to
    :data:`MAX_MATCH_SPACING_M` that keeps at least ``target_points``.

    A dense scanner's neighbouring beams (0.5 deg: 360 points) hit the same few centimetres of a nearby
    wall: they repeat one another's constraint at twice the cost, and they weight the registration by
    angular density, toward what is near the sensor. Thinned along the scan, points are spread evenly over
    the surfaces seen (the aim of Cartographer's adaptive voxel filter, Hess et al., ICRA 2016, which keeps
    200 points per scan).
    """
    n = points_base.shape[0]
    if target_points <= 0 or n <= target_points:
        return np.arange(n)
    out = np.empty(n, dtype=np.int64)
    m = _widest_spaced(
        np.ascontiguousarray(points_base, dtype=np.float64), target_points, MAX_MATCH_SPACING_M, out
    )
    return out[:m]


def wheel_increment_cov(inc_xytheta: FloatArray, cfg: OdometryConfig) -> FloatArray:
    """(3, 3) child-frame covariance of one wheel increment: sigmas grow with travel and turn."""
    d = math.hypot(inc_xytheta[0], inc_xytheta[1])
    s_xy = cfg.wheel_sigma_xy_m + cfg.wheel_sigma_xy_per_m * d
    s_th = cfg.wheel_sigma_theta_rad + cfg.wheel_sigma_theta_per_rad * abs(inc_xytheta[2])
    return np.diag([s_xy**2, s_xy**2, s_th**2])


class _Submaps:
    """Two overlapping submap grids; scans are matched against the older one. Grids are recycled.

    A grid is centred on the first pose inserted into it. It reaches twice ``reach_m`` (the farthest point
    the scans hold, :func:`sensor_reach_m`) plus 5 m, at most ``max_range_m`` plus 5 m: a point of a later
    scan of the submap falls on it while that scan lies within the reach (plus 5 m) of the centre. Sized by
    the sensor's reach, a short-range scanner's grids take a few megabytes instead of the tens that the
    configured range calls for.
    """

    def __init__(self, cfg: OdometryConfig, reach_m: float | None = None) -> None:
        self.cfg = cfg
        self.grids: list[PointGrid] = []
        self.counts: list[int] = []
        self._pool: list[PointGrid] = []
        # half a side: the sensor's reach around a pose up to as far again from the grid's centre (travel
        # within one submap), never more than max_range_m + 5 m
        half_m = cfg.max_range_m + 5.0
        if reach_m is not None:
            half_m = min(half_m, 2.0 * reach_m + 5.0)
        # cells a side, plus one where needed so that the cell edges fall where those of the widest grid
        # would (a grid is centred on a pose): the same cells, only fewer of them
        widest = math.ceil(2.0 * (cfg.max_range_m + 5.0) / cfg.resolution_m)
        cells = math.ceil(2.0 * half_m / cfg.resolution_m)
        self.cells = cells + (widest - cells) % 2

    @property
    def target(self) -> PointGrid | None:
        return self.grids[0] if self.grids else None

    def insert(self, pose: FloatArray, points_base: FloatArray, normals_base: FloatArray) -> None:
        k = self.cfg.submap_scans
        if not self.grids or self.counts[-1] >= k:
            if self._pool:
                grid = self._pool.pop()
                grid.reset(pose[:2] - 0.5 * grid.shape[0] * grid.resolution_m)
            else:
                grid = PointGrid(
                    pose[:2] - 0.5 * self.cells * self.cfg.resolution_m,
                    (self.cells, self.cells),
                    resolution_m=self.cfg.resolution_m,
                    radius_m=self.cfg.max_correspondence_m,
                    sigma_m=self.cfg.resolution_m,
                )
            self.grids.append(grid)
            self.counts.append(0)
        rot = se2.rot3(pose[2])[:2, :2]
        pts_w = points_base @ rot.T + pose[:2]
        nrm_w = normals_base @ rot.T
        for grid in self.grids:
            grid.insert(pts_w, nrm_w)
        self.counts = [c + 1 for c in self.counts]
        if self.counts[0] >= 2 * k and len(self.grids) > 1:
            self._pool.append(self.grids.pop(0))
            self.counts.pop(0)

    def clear(self) -> None:
        """Drop every submap (their grids go back to the pool): the next insertion starts afresh."""
        self._pool.extend(self.grids)
        self.grids = []
        self.counts = []


class _KissRegistration:
    """KISS-ICP's voxel map and registration driven directly (pybind core), 2D poses in and out."""

    def __init__(self, cfg: OdometryConfig) -> None:
        from kiss_icp.pybind import kiss_icp_pybind as kiss

        self._kiss = kiss
        self.cfg = cfg
        self.reset()
        self.reg = kiss._Registration(max_num_iterations=500, convergence_criterion=1e-4, max_num_threads=1)

    @staticmethod
    def _t(pose: FloatArray) -> FloatArray:
        t = np.eye(4)
        t[:2, :2] = se2.rot3(pose[2])[:2, :2]
        t[:2, 3] = pose[:2]
        return t

    def _lift(self, points_base: FloatArray):
        pts = np.zeros((points_base.shape[0], 3))
        pts[:, :2] = points_base
        return self._kiss._Vector3dVector(pts)

    def align(self, points_base: FloatArray, guess: FloatArray) -> FloatArray:
        t = np.asarray(
            self.reg._align_points_to_map(
                points=self._lift(points_base),
                voxel_map=self.map,
                initial_guess=self._t(guess),
                max_correspondance_distance=3.0 * self.cfg.voxel_size_m,
                kernel=self.cfg.voxel_size_m,
            )
        )
        return np.array([t[0, 3], t[1, 3], math.atan2(t[1, 0], t[0, 0])])

    def insert(self, pose: FloatArray, points_base: FloatArray) -> None:
        self.map._update(self._lift(points_base), self._t(pose))

    def reset(self) -> None:
        """An empty voxel map."""
        self.map = self._kiss._VoxelHashMap(
            voxel_size=self.cfg.voxel_size_m, max_distance=self.cfg.max_range_m, max_points_per_voxel=20
        )


#: Dense steps without wheels registered before their window adapts to the model's errors.
MODEL_MIN_STEPS = 10

#: Translation windows of at most this many cells each side are searched exhaustively (correlative_search
#: without its coarse-to-fine stage).
EXHAUSTIVE_MAX_CELLS = 4


def search_window(
    target: PointGrid,
    points_xy: FloatArray,
    center_xytheta: FloatArray,
    window_m: float,
    window_rad: float,
    theta_step_rad: float,
    sigma_xytheta: tuple[float, float] | None = None,
    prior_weight: float = 0.0,
    thin: bool = False,
) -> SearchResult:
    """Correlative search of ``center +- window``: exhaustive when the translation window spans a few
    cells and no motion prior is weighed (the wheel-seeded search, and its retry over every heading within
    ``retry_window_rad``: there the exhaustive pass costs less than the score pyramid branch and bound would
    build over the scan's whole reach), else by branch and bound (no wheels, sparse scans), which is exact
    too, much faster in wide windows, and weighs the score against the motion prior ``(sigma_xy_m,
    sigma_theta_rad)`` of the centre (:func:`slam.scan_matching.branch_and_bound_search`). Wide rotation
    windows use a step of at least 0.25 deg (the refinement that follows recovers the rest); ``thin``
    searches with one point per 2 x 2 cells (dense scans, branch and bound)."""
    step = max(theta_step_rad, math.radians(0.25)) if window_rad > 0.2 else theta_step_rad
    if thin:
        # one point per 2x2 cells, as a dense scanner's neighbouring beams score the same cells (681 beams
        # within 5.6 m)
        points_xy = points_xy[voxel_thin(points_xy, 2.0 * target.resolution_m)]
    few_cells = math.ceil(window_m / target.resolution_m) <= EXHAUSTIVE_MAX_CELLS
    if few_cells and (window_rad <= 0.2 or prior_weight == 0.0):
        return correlative_search(
            target, points_xy, center_xytheta, window_m, window_rad, step, coarse_factor=EXHAUSTIVE_MAX_CELLS
        )
    sxy, sth = sigma_xytheta if sigma_xytheta is not None else (None, None)
    return branch_and_bound_search(
        target,
        points_xy,
        center_xytheta,
        window_m,
        window_rad,
        step,
        prior_sigma_xy_m=sxy,
        prior_sigma_theta_rad=sth,
        prior_weight=prior_weight,
    )


def remap_degenerate(
    prediction_xytheta: FloatArray, pose_xytheta: FloatArray, hessian: FloatArray, min_ratio: float
) -> tuple[FloatArray, FloatArray]:
    """Keep a registration only along the translation directions that the scan constrains.

    ``hessian`` (3, 3) is the scan's point-to-line information (world frame, x, y, theta). Translation
    directions whose eigenvalue is below ``min_ratio`` times the largest one (the axis of a featureless
    corridor, where a few door jambs or noise decide the match) are degenerate: the pose keeps the
    prediction along them and the returned information (3, 3) is zero along them, so the covariance there
    is the wheel prior's. This is the solution remapping of Zhang, Kaess & Singh, "On degeneracy of
    optimization-based state estimation problems" (ICRA 2016), on the translation block. Returns
    ``(pose (3,), information (3, 3))``.
    """
    h = np.asarray(hessian, dtype=np.float64)
    val, vec = np.linalg.eigh(h[:2, :2])
    if val[-1] <= 0.0:
        return np.asarray(prediction_xytheta, dtype=np.float64).copy(), np.zeros((3, 3))
    deg = vec[:, val < min_ratio * val[-1]]
    if deg.shape[1] == 0:
        return np.asarray(pose_xytheta, dtype=np.float64), h
    proj = np.eye(3)
    proj[:2, :2] -= deg @ deg.T
    delta = np.asarray(pose_xytheta, dtype=np.float64) - prediction_xytheta
    delta[2] = se2.wrap(delta[2])
    pose = prediction_xytheta + proj @ delta
    pose[2] = se2.wrap(pose[2])
    return pose, proj.T @ h @ proj


def _refine(
    target: PointGrid,
    points_xy: FloatArray,
    start_xytheta: FloatArray,
    prediction_xytheta: FloatArray,
    prior_information: FloatArray,
    normals_xy: FloatArray | None,
    cfg: OdometryConfig,
    iterate: bool,
    weight: float = 1.0,
) -> tuple[Alignment, FloatArray, FloatArray]:
    """Point-to-line refinement of ``start`` with the prediction as prior (``iterate`` False: the start's
    information only, as for KISS-ICP's result), then the degenerate directions kept where the prediction
    puts them. Each point counts ``weight`` times (a thinned scan's points stand for those dropped: the
    same optimum and information as ``weight`` copies of each). Returns ``(alignment, pose (3,),
    information (3, 3))``."""
    al = refine_point_to_line(
        target,
        points_xy,
        start_xytheta,
        max_dist_m=cfg.max_correspondence_m,
        kernel_m=cfg.kernel_m,
        point_sigma_m=cfg.point_sigma_m / math.sqrt(weight),
        prior_xytheta=prediction_xytheta,
        prior_information=prior_information,
        max_iterations=30 if iterate else 0,
        normals_xy=normals_xy,
    )
    if weight != 1.0:
        al = replace(al, hessian=al.hessian * weight)
    if not iterate:
        return al, np.asarray(start_xytheta, dtype=np.float64), al.hessian
    if cfg.degenerate_ratio > 0:
        return (al, *remap_degenerate(prediction_xytheta, al.pose_xytheta, al.hessian, cfg.degenerate_ratio))
    return al, al.pose_xytheta, al.hessian


def run_odometry(
    points_base: list[FloatArray],
    wheel_poses_xytheta: FloatArray | None,
    cfg: OdometryConfig,
    progress: ProgressLike | None = None,
) -> OdometryResult:
    """Register every scan (list of (P_i, 2) base-frame points, in scan order) against its submap.

    ``wheel_poses_xytheta`` (N, 3): the wheel odometry at each scan, or None; a NaN row marks a gap in the
    wheel records (the steps into and out of that scan are registered as without wheels). Per scan, the
    named steps of :class:`_Odometer`: thin a dense scan (:func:`match_subset`), predict the pose, register
    the scan around the prediction (search, refinement, gates, a wider retry), keep the registration or
    fall back on the prediction, then keep the submaps (a fresh start after a run of rejections, the scan
    inserted when it moved enough). Returns an :class:`OdometryResult`.
    """
    n = len(points_base)
    odometer = _Odometer(n, wheel_poses_xytheta, cfg, sensor_reach_m(points_base))
    chunk = max(1, n // 200)
    with stage(progress, "odometry", n) as bar:
        for i in range(n):
            pts = points_base[i]
            sub = odometer.use_scan(pts)
            if i == 0:
                odometer.first(pts)
            else:
                motion = odometer.predict(i)
                odometer.record(i, pts, motion, odometer.register(i, sub, motion))
            odometer.keep_submaps(i)
            if (i + 1) % chunk == 0:
                bar.advance(chunk)
        if n % chunk:
            bar.advance(n % chunk)
    return odometer.result(points_base)


@dataclass(frozen=True)
class _Motion:
    """The predicted pose of scan ``i``: from the wheels (``wheels``) or the last increment; ``inc`` (3,)
    the increment used, ``cov_inc`` (3, 3) its child-frame covariance, ``pose`` (3,) the prediction and
    ``prior_info`` (3, 3) its world-frame information (the registration's prior)."""

    wheels: bool
    inc: FloatArray
    cov_inc: FloatArray
    pose: FloatArray
    prior_info: FloatArray


@dataclass
class _Registration:
    """One scan's registration: the refinement's alignment, pose (3,) and information (3, 3), the fraction
    of its points matched, and whether the gates keep it."""

    al: Alignment
    pose: FloatArray
    hessian: FloatArray
    frac: float
    accepted: bool


class _Odometer:
    """The state of :func:`run_odometry` while it walks the scans, and its steps."""

    def __init__(
        self,
        n: int,
        wheel_poses_xytheta: FloatArray | None,
        cfg: OdometryConfig,
        reach_m: float,
    ) -> None:
        self.cfg = cfg
        self.poses = np.zeros((n, 3))
        self.covs = np.zeros((n, 3, 3))
        self.status = np.zeros(n, dtype=np.int8)
        self.inliers = np.zeros(n)
        self.rms = np.full(n, np.nan)
        self.submaps = _Submaps(cfg, reach_m)
        self.kiss = _KissRegistration(cfg) if cfg.matcher == "kiss_icp" else None
        self.wheel_inc: FloatArray | None = None
        if wheel_poses_xytheta is not None:
            wheel = np.asarray(wheel_poses_xytheta, dtype=np.float64)
            self.wheel_inc = se2.between(wheel[:-1], wheel[1:])
            if np.all(np.isfinite(wheel[0])):
                self.poses[0] = wheel[0]
        self.last_inc = np.zeros(3)
        self.velocity_known = False  # without wheels: last_inc comes from two registered scans
        self.fallback_run = 0  # consecutive rejected registrations
        self.short_steps = 0  # consecutive registered steps within no_wheels_dense_step_*
        self.model_sq = np.zeros(2)  # dense steps: sums of squared guess deviations (xy m^2, rad^2) ...
        self.model_count = 0  # ... over this many steps
        self.restarts = 0
        self.retries = 0
        self.last_insert: FloatArray | None = None
        self.full = np.zeros((0, 2))  # the current scan's points (use_scan)
        self.normals: FloatArray | None = None  # ... their normals, once computed
        self.sel = np.zeros(0, dtype=np.int64)  # ... the indices of those that register it
        self.weight = 1.0  # ... and how many points each of those stands for
        self.timings = {"odometry_match_s": 0.0, "odometry_insert_s": 0.0, "odometry_normals_s": 0.0}

    def use_scan(self, pts: FloatArray) -> FloatArray:
        """Scan ``pts`` (P, 2) becomes the current one: returns the points (M, 2) that register it, each
        standing for ``P / M`` points in the registration's information: those of :func:`match_subset` with
        wheel odometry, and without it once the steps are dense (a compact search around the guess, as
        with wheels); otherwise every point (the refinement after a wide search from a constant-velocity
        guess needs them). The submaps get every point."""
        self.full = pts
        compact = self.wheel_inc is not None or self._dense_steps()
        self.sel = match_subset(pts, self.cfg.match_points if compact else 0)
        self.weight = pts.shape[0] / max(self.sel.shape[0], 1)
        self.normals = None
        return pts[self.sel]

    def first(self, pts: FloatArray) -> None:
        """The first scan: the origin of the odometry (or the first wheel pose)."""
        self.status[0] = FIRST if pts.shape[0] >= self.cfg.min_points else TOO_FEW_POINTS

    def predict(self, i: int) -> _Motion:
        """Scan ``i``'s pose predicted by the wheels, or without them (a NaN increment: a gap in the wheel
        records) by the last increment, with the covariance of that increment."""
        cfg = self.cfg
        wheels = self.wheel_inc is not None and bool(np.all(np.isfinite(self.wheel_inc[i - 1])))
        inc = self.wheel_inc[i - 1] if wheels else self.last_inc
        pred = se2.compose(self.poses[i - 1], inc)
        cov_inc = wheel_increment_cov(inc, cfg)
        if not wheels:
            cov_inc = np.diag([cfg.no_wheels_sigma_m**2] * 2 + [cfg.no_wheels_sigma_rad**2])
        prior_info = np.linalg.inv(se2.rotate_cov_to_world(pred, cov_inc))
        return _Motion(wheels, inc, cov_inc, pred, prior_info)

    def _windows(self, motion: _Motion) -> tuple[float, float, bool]:
        """``(window_m, window_rad, dense)`` of the search around the prediction."""
        cfg = self.cfg
        if motion.wheels:  # the window covers 3 sigma of the wheel increment (sparse logs: ~1 m steps)
            window_m = max(cfg.search_window_m, 3.0 * math.sqrt(motion.cov_inc[0, 0]))
            return window_m, cfg.search_window_rad + 0.3 * abs(motion.inc[2]), False
        # a constant-velocity guess: search wide, prefer the guess
        window_m = max(cfg.search_window_m, cfg.no_wheels_window_m)
        window_rad = max(cfg.search_window_rad, cfg.no_wheels_window_rad)
        dense = self._dense_steps()
        if dense:  # scans a few centimetres apart: a compact window suffices
            window_m = min(window_m, cfg.no_wheels_dense_window_m)
            window_rad = min(window_rad, cfg.no_wheels_dense_window_rad)
        return window_m, window_rad, dense

    def _dense_steps(self) -> bool:
        """Without wheels: the last three steps were registered and short (10 Hz scanners), so the next
        scan is searched in a compact window around the constant-velocity guess."""
        return self.velocity_known and self.short_steps >= 3

    def register(self, i: int, pts: FloatArray, motion: _Motion) -> _Registration | None:
        """Scan ``i`` registered against the older submap around the prediction: the correlative search
        (or KISS-ICP), the point-to-line refinement with the prediction as prior, the gates, and a wider
        retry of a poor or rejected wheel-seeded match. A dense step without wheels is first searched in the
        window its guess's recent errors call for (:meth:`_model_window`), and again in the dense window
        when that match is rejected or lands beyond half of it. None when there is no submap or too few
        points."""
        cfg = self.cfg
        target = self.submaps.target
        if target is None or self.full.shape[0] < cfg.min_points:
            return None
        normals = self._normals()[self.sel] if cfg.normal_check else None
        t0 = time.perf_counter()
        window_m, window_rad, dense = self._windows(motion)
        reg = None
        tight = self._model_window() if dense and self.kiss is None else None
        if tight is not None:  # dense scans: first the window the model's recent errors call for
            reg = self._match(target, pts, normals, motion, *tight, dense)
            dev = se2.between(motion.pose, reg.pose)
            inside = math.hypot(dev[0], dev[1]) <= 0.5 * tight[0] and abs(dev[2]) <= 0.5 * tight[1]
            if reg.accepted and inside:
                self._model_deviation(dev)
            else:
                reg = None
        if reg is None:
            reg = self._match(target, pts, normals, motion, window_m, window_rad, dense)
            if dense and reg.accepted:
                self._model_deviation(se2.between(motion.pose, reg.pose))
        if (
            motion.wheels
            and self.kiss is None
            and (reg.frac < cfg.retry_below_inliers or not reg.accepted)
            and window_rad < cfg.retry_window_rad
        ):
            reg = self._retry(target, pts, normals, motion, window_m, reg)
        self.timings["odometry_match_s"] += time.perf_counter() - t0
        self.inliers[i] = reg.frac
        self.rms[i] = reg.al.rms_m
        return reg

    def _match(
        self,
        target: PointGrid,
        pts: FloatArray,
        normals: FloatArray | None,
        motion: _Motion,
        window_m: float,
        window_rad: float,
        dense: bool,
    ) -> _Registration:
        """The search within ``+- window`` of the prediction, the refinement, and the gates."""
        cfg = self.cfg
        if self.kiss is not None:
            start = self.kiss.align(pts, motion.pose)
        else:
            # the motion prior of a wide search; none before the velocity is known
            sigma = (math.sqrt(motion.cov_inc[0, 0]), math.sqrt(motion.cov_inc[2, 2]))
            w = cfg.search_prior_weight if motion.wheels or self.velocity_known else 0.0
            start = search_window(
                target, pts, motion.pose, window_m, window_rad, cfg.search_step_rad, sigma, w, dense
            ).pose_xytheta
        al, pose, hessian = _refine(
            target,
            pts,
            start,
            motion.pose,
            motion.prior_info,
            normals,
            cfg,
            self.kiss is None,
            self.weight,
        )
        reg = _Registration(al, pose, hessian, al.inliers / pts.shape[0], False)
        dev = se2.between(motion.pose, pose)
        if motion.wheels:
            reg.accepted = (
                reg.frac >= cfg.min_inlier_fraction
                and math.hypot(dev[0], dev[1]) <= self._gate_xy_m(window_m)
                and abs(dev[2]) <= max(cfg.gate_theta_rad, window_rad)
            )
        else:  # the guess is no fallback: a match better than chance is kept
            reach_m = math.sqrt(2.0) * window_m + cfg.gate_xy_m
            reg.accepted = reg.frac >= cfg.no_wheels_min_inliers and math.hypot(dev[0], dev[1]) <= reach_m
        return reg

    def _gate_xy_m(self, window_m: float) -> float:
        """The largest accepted translational deviation from the wheel prediction of a search within
        ``+- window_m``: ``gate_xy_m``, or the window's diagonal where that is wider."""
        return max(self.cfg.gate_xy_m, math.sqrt(2.0) * window_m)

    def _model_deviation(self, dev: FloatArray) -> None:
        """A registered dense step's deviation (3,) from the constant-velocity guess, into the running sums
        of :meth:`_model_window`."""
        self.model_sq += np.array([dev[0] ** 2 + dev[1] ** 2, dev[2] ** 2])
        self.model_count += 1

    def _model_window(self) -> tuple[float, float] | None:
        """The compact window of a dense step: three times the RMS deviation of the constant-velocity guess
        from the registered poses so far (KISS-ICP's adaptive threshold, Vizzo et al. 2023), at least
        ``search_window_*``; None until enough steps were seen or where it is no smaller than the dense
        window."""
        cfg = self.cfg
        if self.model_count < MODEL_MIN_STEPS:
            return None
        rms = np.sqrt(self.model_sq / self.model_count)
        window_m = max(cfg.search_window_m, 3.0 * float(rms[0]))
        window_rad = max(cfg.search_window_rad, 3.0 * float(rms[1]))
        if window_m >= cfg.no_wheels_dense_window_m and window_rad >= cfg.no_wheels_dense_window_rad:
            return None
        return min(window_m, cfg.no_wheels_dense_window_m), min(window_rad, cfg.no_wheels_dense_window_rad)

    def _retry(
        self,
        target: PointGrid,
        pts: FloatArray,
        normals: FloatArray | None,
        motion: _Motion,
        window_m: float,
        reg: _Registration,
    ) -> _Registration:
        """A poor match or a rejected one: the wheels may have turned wrong by more than the window (sparse
        logs: 10-20 deg between keyframes); search every heading within retry_window_rad, without a prior,
        and keep that match if it explains more of the scan, or if it passes the gates (rotation: that
        window) where the first did not."""
        cfg = self.cfg
        wide = search_window(
            target, pts, motion.pose, window_m, cfg.retry_window_rad, cfg.search_step_rad
        ).pose_xytheta
        al2, pose2, hessian2 = _refine(
            target, pts, wide, motion.pose, motion.prior_info, normals, cfg, True, self.weight
        )
        frac2 = al2.inliers / pts.shape[0]
        dev2 = se2.between(motion.pose, pose2)
        self.retries += 1
        if (
            frac2 >= cfg.min_inlier_fraction
            and (frac2 > reg.frac or not reg.accepted)
            and math.hypot(dev2[0], dev2[1]) <= self._gate_xy_m(window_m)
            and abs(dev2[2]) <= cfg.retry_window_rad
        ):
            return _Registration(al2, pose2, hessian2, frac2, True)
        return reg

    def record(self, i: int, pts: FloatArray, motion: _Motion, reg: _Registration | None) -> None:
        """Scan ``i``'s pose and covariance: the kept registration's, ``(H / sigma^2 + Lambda)^-1``, or the
        prediction with the wheel uncertainty accumulated since the last registered scan."""
        cfg = self.cfg
        if reg is not None and reg.accepted:
            self.poses[i] = reg.pose
            sigma = (
                max(reg.al.rms_m, cfg.min_point_sigma_m) if cfg.sigma_from_residuals else cfg.point_sigma_m
            )
            self.covs[i] = np.linalg.inv(reg.hessian / sigma**2 + motion.prior_info)
            self.status[i] = MATCHED
        else:
            self.poses[i] = motion.pose
            cov_prev_body = se2.rotate_cov_to_body(self.poses[i - 1], self.covs[i - 1])
            self.covs[i] = se2.rotate_cov_to_world(
                motion.pose, se2.compose_cov_body(cov_prev_body, motion.inc, motion.cov_inc)
            )
            self.status[i] = FALLBACK if pts.shape[0] >= cfg.min_points else TOO_FEW_POINTS
        self.last_inc = se2.between(self.poses[i - 1], self.poses[i])
        self.velocity_known = self.status[i] == MATCHED
        short = (
            self.velocity_known
            and math.hypot(self.last_inc[0], self.last_inc[1]) <= cfg.no_wheels_dense_step_m
            and abs(self.last_inc[2]) <= cfg.no_wheels_dense_step_rad
        )
        self.short_steps = self.short_steps + 1 if short else 0

    def keep_submaps(self, i: int) -> None:
        """A run of rejected registrations means the submap no longer covers the scans (the robot left it):
        start a new one from the current pose, or the odometry never recovers. A registered scan that moved
        enough since the last insertion (and the first scan of a new submap) goes into the submaps, every
        point of it."""
        cfg = self.cfg
        rejected = self.status[i] in (FALLBACK, TOO_FEW_POINTS)
        self.fallback_run = self.fallback_run + 1 if rejected else 0
        enough = self.full.shape[0] >= cfg.min_points
        restart = self.fallback_run >= cfg.submap_restart_fallbacks and enough
        if restart:
            self.submaps.clear()
            if self.kiss is not None:
                self.kiss.reset()
            self.fallback_run = 0
            self.restarts += 1
        last = self.last_insert
        moved = (
            last is None
            or math.hypot(*(self.poses[i, :2] - last[:2])) >= cfg.insert_distance_m
            or abs(se2.wrap(self.poses[i, 2] - last[2])) >= cfg.insert_rotation_rad
        )
        if not (restart or (self.status[i] in (FIRST, MATCHED) and moved)):
            return
        normals = self._normals()
        t0 = time.perf_counter()
        self.submaps.insert(self.poses[i], self.full, normals)
        if self.kiss is not None:
            self.kiss.insert(self.poses[i], self.full)
        self.timings["odometry_insert_s"] += time.perf_counter() - t0
        self.last_insert = self.poses[i].copy()

    def _normals(self) -> FloatArray:
        """(P, 2) normals of the current scan's points, computed once per scan."""
        if self.normals is None:
            t0 = time.perf_counter()
            cfg = self.cfg
            self.normals = scan_normals(
                self.full,
                cfg.normal_radius_m,
                cfg.normal_max_neighbours,
                radius_per_m=cfg.normal_radius_per_m,
            )
            self.timings["odometry_normals_s"] += time.perf_counter() - t0
        return self.normals

    def result(self, points_base: list[FloatArray]) -> OdometryResult:
        return OdometryResult(
            self.poses,
            self.covs,
            self.status,
            self.inliers,
            self.rms,
            points_base,
            dict(self.timings),
            self.restarts,
            self.retries,
        )
