"""Configuration of the SLAM stage (odometry, keyframes, loop closure, pose graph).

Defaults were chosen by measurement on ``intel.clf`` against ``intel.gfs.log`` and on the simulated ``loop``
world (see ``pipeline/evaluate_slam.py`` and the tests); the units are in the names.
"""

from __future__ import annotations

from typing import Any, ClassVar, Literal

from pydantic import Field, field_validator, model_validator

from datasets.config import StageConfig, refuse_moved_keys

RobustKernel = Literal["cauchy", "huber", "dcs", "none"]


class OdometryConfig(StageConfig):
    """Scan-to-submap odometry: every scan is registered against a local map of the recent scans."""

    matcher: Literal["point_to_line", "kiss_icp"] = Field(
        "point_to_line",
        description="registration of each scan: 'point_to_line' (correlative search + point-to-line "
        "Gauss-Newton on a grid submap) or 'kiss_icp' (KISS-ICP's voxel map and robust point-to-point ICP, "
        "scans lifted to z = 0, deskew off), both seeded by the wheel odometry and gated",
    )
    max_range_m: float = Field(
        60.0,
        gt=0,
        description="beams longer than this are not used for matching (no-return readings are dropped by "
        "the readers' range_max, so long real returns can serve: halls and atria need them)",
    )
    min_range_m: float = Field(0.05, ge=0, description="beams shorter than this are not used")
    match_points: int = Field(
        200,
        ge=0,
        description="with wheel odometry (without: once the steps are dense), a scan with more valid points "
        "is registered with about this many (at least): those at the widest spacing along the scan (at most "
        "0.5 m) that keeps this many, each "
        "standing for the points it replaces in the registration's information (Cartographer's adaptive "
        "voxel filter keeps 200); the submaps get every point; 0: every point",
    )
    resolution_m: float = Field(0.05, gt=0, le=1, description="cell size of the submap grids")
    voxel_size_m: float = Field(0.1, gt=0, le=5, description="KISS-ICP voxel size (matcher 'kiss_icp')")
    submap_scans: int = Field(
        10,
        ge=1,
        le=1000,
        description="scans inserted per submap; a scan is matched to a submap holding "
        "between this many and twice this many scans",
    )
    insert_distance_m: float = Field(
        0.1, ge=0, description="insert a scan into the submaps after this travel"
    )
    insert_rotation_rad: float = Field(0.1, ge=0, description="... or after this rotation")
    normal_radius_m: float = Field(
        0.3, gt=0, description="point normals from the scan neighbours within this radius"
    )
    normal_radius_per_m: float = Field(
        0.03,
        ge=0,
        description="... widened to this fraction of the point's range (far points of a 1-deg scanner are "
        "tens of cm apart)",
    )
    normal_max_neighbours: int = Field(
        2, ge=1, le=500, description="... walking at most this many beams each way from the point"
    )
    normal_check: bool = Field(
        False,
        description="skip map points whose normal faces away from the scan point's (the far face of a "
        "thin wall); off: with the 5-beam normals of a dense scanner (fr079) it drops good matches",
    )
    degenerate_ratio: float = Field(
        0.02,
        ge=0,
        lt=1,
        description="a translation direction whose scan information is below this fraction of the best "
        "one is degenerate (a featureless corridor's axis): the wheel prediction and its uncertainty are "
        "kept along it (0: off)",
    )
    search_window_m: float = Field(
        0.1, ge=0, description="correlative search half-window around the prediction"
    )
    search_window_rad: float = Field(0.05, ge=0, description="rotational half-window (plus 30% of the turn)")
    no_wheels_window_m: float = Field(
        2.0,
        ge=0,
        description="without wheel odometry: translational half-window of the search around the "
        "constant-velocity guess (branch and bound: a wide window costs little)",
    )
    no_wheels_window_rad: float = Field(
        3.1416, ge=0, description="... and its rotational half-window (every heading: turns on the spot)"
    )
    no_wheels_dense_step_m: float = Field(
        0.2,
        ge=0,
        description="without wheels, after three steps this short (and no_wheels_dense_step_rad) the scans "
        "are dense (10 Hz and more) and the next search uses the compact no_wheels_dense_window_* (a sparse "
        "log's single short step is often a turn on the spot before a large one)",
    )
    no_wheels_dense_step_rad: float = Field(0.2, ge=0, description="... and this small a turn")
    no_wheels_dense_window_m: float = Field(0.6, ge=0, description="compact translational half-window")
    no_wheels_dense_window_rad: float = Field(0.5, ge=0, description="compact rotational half-window")
    no_wheels_sigma_m: float = Field(
        0.5,
        gt=0,
        description="standard deviation of the constant-velocity guess, translation: the search's motion "
        "prior and the refinement's prior (sparse logs, a scan a metre: the guess errs by 0.1-0.9 m)",
    )
    no_wheels_sigma_rad: float = Field(
        1.0, gt=0, description="... and rotation (such logs turn up to 1.7 rad between scans)"
    )
    no_wheels_min_inliers: float = Field(
        0.1,
        ge=0,
        le=1,
        description="without wheels, the least fraction of matched points to keep a registration (there is "
        "no wheel prediction to fall back on)",
    )
    search_prior_weight: float = Field(
        0.1,
        ge=0,
        description="wide (branch-and-bound) searches maximise the mean score minus this / 2 times the "
        "squared Mahalanobis distance from the prediction (a far pose must match clearly better)",
    )
    search_step_rad: float = Field(0.0044, gt=0, description="rotation step of the correlative search")
    point_sigma_m: float = Field(0.05, gt=0, description="noise of one point-to-line residual (information)")
    sigma_from_residuals: bool = Field(
        True, description="covariance from the residual RMS of each alignment instead of point_sigma_m"
    )
    min_point_sigma_m: float = Field(0.005, gt=0, description="floor of the residual-based point sigma")
    kernel_m: float = Field(0.05, gt=0, description="Cauchy kernel width of the point-to-line residuals")
    max_correspondence_m: float = Field(0.3, gt=0, description="farthest accepted nearest map point")
    min_inlier_fraction: float = Field(
        0.15,
        ge=0,
        le=1,
        description="fewer matched points: registration failed (a 1-deg scanner in a hospital's halls "
        "matches 25-50 % of its points against the older submap)",
    )
    min_points: int = Field(
        20, ge=3, description="fewer usable points: registration skipped (wheel fallback)"
    )
    wheel_sigma_xy_m: float = Field(
        0.02, gt=0, description="wheel increment noise per scan, translation (base)"
    )
    wheel_sigma_xy_per_m: float = Field(0.1, ge=0, description="... plus this fraction of the travel")
    wheel_sigma_theta_rad: float = Field(0.0175, gt=0, description="wheel increment noise per scan, rotation")
    wheel_sigma_theta_per_rad: float = Field(0.2, ge=0, description="... plus this fraction of the turn")
    retry_below_inliers: float = Field(
        0.3,
        ge=0,
        le=1,
        description="a wheel-seeded registration matching fewer of its points, or rejected by the gates, is "
        "searched again over every heading within retry_window_rad (the wheels of a sparse log turn "
        "10-20 deg wrong between keyframes): kept if it explains more of the scan, or if the first was "
        "rejected and it passes the gates with that window",
    )
    retry_window_rad: float = Field(
        0.5, ge=0, description="... rotational half-window of that search, without a motion prior (0: off)"
    )
    gate_xy_m: float = Field(0.3, gt=0, description="largest accepted deviation from the wheel prediction")
    gate_theta_rad: float = Field(0.2, gt=0, description="largest accepted rotational deviation from it")
    submap_restart_fallbacks: int = Field(
        3,
        ge=1,
        description="after this many rejected registrations in a row the submaps are started afresh from "
        "the wheel pose (the robot has left them; without a restart the odometry never recovers)",
    )


class LoopClosureConfig(StageConfig):
    """Loop-closure candidates, search and verification."""

    enabled: bool = Field(True, description="search loop closures")
    min_separation_m: float = Field(20.0, ge=0, description="least travel between the two keyframes")
    closure_spacing_m: float = Field(
        2.0,
        ge=0,
        description="least travel after an accepted closure before the next search (closures in a "
        "row match the same place: their errors are not independent)",
    )
    search_spacing_m: float = Field(
        2.0,
        ge=0,
        description="least travel between two searches (0: every keyframe); bounds the search's cost",
    )
    overlap_radius_m: float = Field(
        2.0, ge=0, description="keyframes this far apart can still see each other"
    )
    search_cov_inflation: float = Field(
        30.0,
        ge=1,
        description="the candidate gate (on the two marginals) and the search window (on the relative "
        "pose's joint-marginal covariance) use them times this, or times the running variance factor if "
        "larger (a generous search; verification decides)",
    )
    gate_chi2: float = Field(9.21, gt=0, description="Mahalanobis gate of candidates (chi2 2 dof, 99%)")
    max_distance_m: float = Field(
        15.0,
        gt=0,
        description="a candidate is searched when its search window can bring it within this distance "
        "of the query (farther, their views overlap little)",
    )
    max_candidates: int = Field(3, ge=1, le=50, description="candidates matched per keyframe, nearest first")
    max_accepted_per_keyframe: int = Field(1, ge=1, le=50, description="stop after this many accepted")
    target_keyframes: int = Field(
        5, ge=0, le=100, description="keyframes on each side of the target in its map"
    )
    target_stride: int = Field(
        5,
        ge=1,
        le=100,
        description="only every this-many-th keyframe anchors a target map (neighbouring maps overlap; "
        "fewer maps to build and search)",
    )
    search_pool: int = Field(
        2,
        ge=1,
        le=8,
        description="the branch-and-bound search runs on the target's score max-pooled by this many "
        "cells (0.1 m for 0.05 m submaps); the point-to-line refinement then works at full resolution",
    )
    search_prior_weight: float = Field(
        0.02,
        ge=0,
        description="the search maximises the mean score minus this / 2 times the squared Mahalanobis "
        "distance from the predicted relative pose (a weak preference; verification decides)",
    )
    query_keyframes: int = Field(2, ge=0, le=100, description="previous keyframes merged into the query scan")
    window_sigmas: float = Field(3.0, gt=0, description="search half-window in standard deviations")
    min_window_m: float = Field(0.3, ge=0, description="smallest translational search half-window")
    max_window_m: float = Field(
        20.0,
        gt=0,
        description="largest translational search half-window (after a long loop the truth can lie "
        "this far from the prediction)",
    )
    wide_window_m: float = Field(
        6.0, ge=0, description="a search whose translational half-window exceeds this is a wide one"
    )
    wide_min_score: float = Field(
        0.4,
        ge=0,
        le=1,
        description="least mean correlative score of a wide search (it tries many more poses, so a wrong "
        "alignment scores higher by chance: a 20 m window put a hospital's corridor end on another)",
    )
    min_window_rad: float = Field(0.1, ge=0, description="smallest rotational search half-window")
    max_window_rad: float = Field(0.6, gt=0, description="largest rotational search half-window")
    search_step_rad: float = Field(
        0.0044, gt=0, description="rotation step of the search (0.25 deg: 8.7 cm at 20 m, below a cell)"
    )
    query_voxel_m: float = Field(0.1, gt=0, description="query points are thinned to one per voxel")
    search_max_points: int = Field(
        200,
        ge=10,
        description="the search scores at most this many of the query's points (evenly spaced; its cost "
        "grows with them); the refinement and the gates use them all",
    )
    map_range_m: float = Field(
        30.0,
        gt=0,
        description="query and target maps keep the points within this range of their laser (far points "
        "make large, slow maps: 60 m returns in a hospital's halls)",
    )
    min_score: float = Field(0.3, ge=0, le=1, description="least mean correlative score")
    min_hit_fraction: float = Field(
        0.25,
        ge=0,
        le=1,
        description="least fraction of query points within inlier_m of a target point after refinement "
        "(the overlap gate)",
    )
    max_conflict_ratio: float = Field(
        0.1,
        ge=0,
        le=1,
        description="largest fraction of the query points known to the target that lie in space the "
        "target's beams saw free (the free-space gate)",
    )
    free_space_margin_m: float = Field(
        0.15, ge=0, description="beams mark free space up to this short of the hit"
    )
    inlier_m: float = Field(0.1, gt=0, description="inlier distance of the overlap gate")
    max_rms_m: float = Field(0.05, gt=0, description="largest point-to-line residual RMS")
    min_eigen_ratio: float = Field(
        0.1,
        ge=0,
        le=1,
        description="least ratio of the smallest to the largest eigenvalue of the "
        "translational alignment information (a corridor constrains one direction only)",
    )
    consistency_chi2: float = Field(
        100.0, gt=0, description="Mahalanobis gate of the found relative pose against the prediction (3 dof)"
    )
    dense_radius_m: float = Field(
        0.0,
        ge=0,
        description="after the incremental pass, every keyframe is refined and verified (no search) against "
        "the targets within this distance in the optimised graph (0: off)",
    )
    dense_targets: int = Field(2, ge=1, le=20, description="... at most this many, nearest first")
    robust_kernel: RobustKernel = Field(
        "huber",
        description="robust loss of loop-closure factors: Huber is convex, so a true closure that corrects "
        "a large drift still pulls (a redescending loss such as Cauchy leaves it stuck as an 'outlier' "
        "when the drift is many sigmas: fr079 ATE 0.68 m with Cauchy and wide searches), while a false "
        "closure's pull is bounded",
    )
    robust_kernel_width: float = Field(3.0, gt=0, description="kernel width in whitened (sigma) units")


class GraphConfig(StageConfig):
    """Pose-graph noise and solver."""

    odometry_cov_scale: float = Field(
        0.5,
        gt=0,
        description="scale of the alignment covariances in odometry factors (chosen on the simulated loop "
        "world, seed 0: ATE after loop closure 0.041 m, average NEES 1.08 (3 is consistent); 0.3 for both "
        "scales gives NEES 1.44 but ATE 0.050 m)",
    )
    loop_cov_scale: float = Field(0.5, gt=0, description="scale of loop-closure alignment covariances")
    loop_min_sigma_xy_m: float = Field(
        0.0, ge=0, description="floor of loop-closure standard deviations, translation (added in quadrature)"
    )
    loop_min_sigma_theta_rad: float = Field(
        0.0, ge=0, description="floor of loop-closure standard deviations, rotation (added in quadrature)"
    )
    min_sigma_xy_m: float = Field(0.002, gt=0, description="floor of factor standard deviations, translation")
    min_sigma_theta_rad: float = Field(
        0.0005, gt=0, description="floor of factor standard deviations, rotation"
    )
    prior_sigma_xy_m: float = Field(1e-3, gt=0, description="prior on the first keyframe, translation")
    prior_sigma_theta_rad: float = Field(1e-4, gt=0, description="prior on the first keyframe, rotation")
    estimate_variance_factor: bool = Field(
        True,
        description="scale every factor covariance by the a-posteriori variance factor of the adjustment "
        "(sum of squared whitened residuals over the redundancy), so marginals match the data",
    )
    variance_factor_min_loops: int = Field(
        30, ge=1, description="least agreeing loop closures to estimate it (below: the calibrated scales)"
    )
    variance_factor_min: float = Field(
        1.0, gt=0, description="floor of the variance factor (1: the data may inflate the covariances only)"
    )
    variance_factor_gate_chi2: float = Field(
        200.0,
        gt=0,
        description="loop closures beyond this whitened error (x the factor) are not counted: only gross "
        "blunders; real residuals are heavy-tailed and the robust loss already guards the solution",
    )
    variance_factor_iterations: int = Field(
        4, ge=1, le=20, description="re-weight and re-solve at most this often"
    )
    final_optimizer: Literal["levenberg_marquardt", "none"] = Field(
        "levenberg_marquardt", description="batch optimisation after the incremental (iSAM2) pass"
    )
    max_iterations: int = Field(100, ge=1, description="Levenberg-Marquardt iterations")
    outlier_rejection: Literal["gnc", "none"] = Field(
        "gnc",
        description="how the final optimisation decides which loop closures stay: 'gnc' graduated "
        "non-convexity with a truncated least-squares loss over the closures (odometry and prior known "
        "inliers; slam.graph.gnc_loop_inliers), 'none' keep every verified closure under its robust loss",
    )
    gnc_inlier_probability: float = Field(
        0.99,
        gt=0,
        lt=1,
        description="a closure stays an inlier of the graduated non-convexity solve while its whitened "
        "error (covariances x the variance factor) is within this chi-square quantile (3 dof)",
    )


class CloudLoopClosureConfig(StageConfig):
    """Loop closure of 3D inputs: point-to-point ICP between keyframe clouds, gated, with a robust loss.
    The 2D search of :class:`LoopClosureConfig` does not apply to clouds; names of shared meaning match."""

    search_radius_m: float = Field(
        10.0, ge=0, description="loop candidates: keyframes within this distance (plus 3 sigma)"
    )
    min_separation_m: float = Field(30.0, ge=0, description="least travel between the two keyframes")
    max_rms_m: float = Field(0.2, gt=0, description="largest point-to-point RMS of a verified closure")
    min_inlier_fraction: float = Field(
        0.5, ge=0, le=1, description="least fraction of query points near the target after alignment"
    )
    consistency_chi2: float = Field(
        100.0, gt=0, description="Mahalanobis gate of the found relative pose against the prediction (6 dof)"
    )
    robust_kernel: RobustKernel = Field("cauchy", description="robust loss of 3D loop-closure factors")
    robust_kernel_width: float = Field(1.0, gt=0, description="kernel width in whitened (sigma) units")


#: Where the former flat loop-closure keys of the ``cloud`` section live now.
CLOUD_MOVED_KEYS: dict[str, str] = {
    "loop_search_radius_m": "loop_closure.search_radius_m",
    "loop_min_separation_m": "loop_closure.min_separation_m",
    "loop_max_rms_m": "loop_closure.max_rms_m",
    "loop_min_inlier_fraction": "loop_closure.min_inlier_fraction",
    "loop_consistency_chi2": "loop_closure.consistency_chi2",
    "robust_kernel": "loop_closure.robust_kernel",
    "robust_kernel_width": "loop_closure.robust_kernel_width",
}


class CloudOdometryConfig(StageConfig):
    """3D inputs (point clouds): KISS-ICP odometry on the clouds as they are, and the ``Pose3`` graph."""

    voxel_size_m: float | None = Field(
        None, gt=0, le=5, description="KISS-ICP voxel size; None: max_range_m / 100 (KISS-ICP's own default)"
    )
    max_range_m: float = Field(100.0, gt=0, description="points farther than this are dropped")
    min_range_m: float = Field(0.0, ge=0, description="points nearer than this are dropped")
    deskew: bool = Field(
        False,
        description="motion compensation with per-point times from the azimuth of a spinning lidar (KITTI "
        "frames are already motion-compensated, so off by default)",
    )
    keyframe_distance_m: float = Field(1.0, gt=0, description="new 3D keyframe after this much travel")
    keyframe_rotation_rad: float = Field(0.2, gt=0, description="... or this much rotation")
    min_point_sigma_m: float = Field(0.01, gt=0, description="floor of the residual-based point sigma")
    odometry_cov_scale: float = Field(
        1.0, gt=0, description="scale of the registration covariances in the odometry factors"
    )
    loop_closure: CloudLoopClosureConfig = Field(default_factory=CloudLoopClosureConfig)

    @model_validator(mode="before")
    @classmethod
    def _moved_keys(cls, data: Any) -> Any:
        return refuse_moved_keys(data, CLOUD_MOVED_KEYS)


class ConsistencyConfig(StageConfig):
    """The covariances the mapper receives (:mod:`slam.consistency`): each scan's pose relative to the
    earlier passes over the places it observes, not to the graph's anchor."""

    cell_m: float = Field(
        1.0, gt=0, le=100, description="cell size of the places keyframes observe (their scan endpoints)"
    )
    revisit_gap_m: float = Field(
        10.0,
        ge=0,
        description="a place (cell) is visited again when the robot travelled this far without seeing it "
        "(a corridor seen along its length over one pass is one visit of each of its cells)",
    )
    min_shared: float = Field(
        0.25,
        gt=0,
        le=1,
        description="an earlier keyframe is another pass over a keyframe's place when it saw at least this "
        "share of the keyframe's cells in an earlier visit",
    )
    max_partners: int = Field(
        4, ge=1, le=100, description="earlier passes tried per keyframe (the most overlapping ones)"
    )


class SlamConfig(StageConfig):
    """Odometry, keyframing, loop closure and pose-graph settings."""

    bool_keys: ClassVar[frozenset[str]] = frozenset({"wheel_odometry"})  # (YAML's off: see _yaml_off)

    keyframe_distance_m: float = Field(0.5, gt=0, description="new keyframe after this much travel")
    keyframe_rotation_rad: float = Field(0.5, gt=0, description="new keyframe after this much rotation")
    wheel_odometry: Literal["auto", "off"] = Field(
        "auto",
        description="'auto': the recording's wheel odometry seeds and steadies the scan matching when it has "
        "one (slam.system.wheel_odometry says which); 'off': scans only, as for a robot whose wheels slip "
        "or whose odometry is missing or broken",
    )
    odometry: OdometryConfig = Field(default_factory=OdometryConfig)
    loop_closure: LoopClosureConfig = Field(default_factory=LoopClosureConfig)
    graph: GraphConfig = Field(default_factory=GraphConfig)
    consistency: ConsistencyConfig = Field(default_factory=ConsistencyConfig)
    cloud: CloudOdometryConfig = Field(default_factory=CloudOdometryConfig)

    @field_validator("wheel_odometry", mode="before")
    @classmethod
    def _yaml_off(cls, value: Any) -> Any:
        """YAML reads an unquoted ``off`` as false (and ``on`` as true): take them as meant."""
        if isinstance(value, bool):
            return "auto" if value else "off"
        return value

    @model_validator(mode="after")
    def _ranges(self) -> SlamConfig:
        o = self.odometry
        if o.min_range_m >= o.max_range_m:
            raise ValueError(
                f"odometry.min_range_m ({o.min_range_m}) must be below max_range_m ({o.max_range_m})"
            )
        lc = self.loop_closure
        if lc.min_window_m > lc.max_window_m or lc.min_window_rad > lc.max_window_rad:
            raise ValueError("loop_closure: min_window_* must not exceed max_window_*")
        return self
