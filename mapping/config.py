"""Configuration of the mapping stage."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

from pydantic import Field, model_validator

from datasets.config import StageConfig, refuse_moved_keys


class GridBaselineConfig(StageConfig):
    """The occupancy-grid baseline (Thrun et al. 2005 inverse sensor model)."""

    resolution_m: float = Field(0.1, gt=0, le=100, description="cell size of the baseline grid")
    p_occupied: float = Field(0.7, gt=0.5, lt=1, description="inverse sensor model: p(occ) at an endpoint")
    p_free: float = Field(0.4, gt=0, lt=0.5, description="inverse sensor model: p(occ) along a beam")
    p_clamp: float = Field(0.97, gt=0.5, lt=1, description="log-odds clamped to logit(+-p_clamp)")
    beam_width_deg: float = Field(
        0.0,
        ge=0,
        lt=180,
        description="0: each beam is a ray; > 0: a cone of this full width (the paper widens the beams of "
        "its sparse street data by bearing noise, section 4.1.1)",
    )


class SourceNoiseConfig(StageConfig):
    """Measurement noise of one laser (GPPOL): variances of its range and bearing readings."""

    range_var_m2: float = Field(1e-4, ge=0, le=100, description="range variance (m^2)")
    bearing_var_rad2: float = Field(3e-6, ge=0, le=1, description="bearing variance (rad^2)")


class FreeSpaceConfig(StageConfig):
    """Where a beam says "free" (the continuous free-space model of section 3.5 runs along these segments)."""

    no_return_length_m: float | None = Field(
        2.0,
        ge=0,
        le=1000,
        description="free segment of a beam without return (null: the scan's range_max; 0: none). Real "
        "lasers miss glass and dark surfaces, so a short length; a simulated laser can use range_max",
    )
    margin_m: float = Field(
        0.1,
        ge=0,
        le=10,
        description="free segments of returns stop this short of the endpoint (the floor of the grazing "
        "margin below)",
    )
    band_m: float = Field(
        0.2,
        ge=0,
        le=10,
        description="half-width delta0 of the band around a surface that a grazing beam's free segment must "
        "not enter: a return whose beam meets its surface (the chord between its neighbouring returns) at "
        "angle gamma stops max(margin_m, delta(r) / sin(gamma)) short, delta(r) = band_m + r band_per_m "
        "(0 and 0: the plain margin_m). 0.2: the best mean hold-out AUC over the ten development logs of "
        "0.02, 0.05, 0.1, 0.2, 0.4 (docs/mapping.md)",
    )
    band_per_m: float = Field(
        0.0,
        ge=0,
        le=1,
        description="growth of that band per metre of range (beam spread and range noise, e.g. "
        "tan(bearing sigma))",
    )
    margin_max_m: float | None = Field(
        2.0,
        gt=0,
        le=100,
        description="cap of the grazing margin delta(r) / sin(gamma) (null: none; a beam along its surface "
        "then frees nothing)",
    )


class ScanSelectionConfig(StageConfig):
    """Which scans of a run are mapped: one each time the laser moved or turned enough."""

    min_travel_m: float = Field(
        0.5,
        ge=0,
        le=100,
        description="a run maps the scans taken after the laser moved this far (or turned min_rotation_rad) "
        "since the last mapped scan; 0 and 0 map every scan",
    )
    min_rotation_rad: float = Field(
        0.25, ge=0, le=7, description="see min_travel_m (like GMapping's linear/angularUpdate)"
    )


class TrainingConfig(StageConfig):
    """Hyperparameter learning (eq. 9) on local problems drawn from runs of scans spread over a recording."""

    scans: int = Field(50, ge=1, description="hyperparameters are learnt from N scans")
    windows: int = Field(
        10,
        ge=1,
        le=10_000,
        description="the N scans are this many runs of consecutive scans spread evenly over the recording "
        "(1: the first N scans, which can be one corner of the scene; docs/mapping.md)",
    )
    problems: int = Field(64, ge=1, le=100_000, description="local neighbourhoods in the training set")
    anneal_evaluations: int = Field(
        200, ge=0, le=1_000_000, description="dual-annealing budget (likelihood evaluations; 0 skips it)"
    )
    lbfgs_iterations: int = Field(100, ge=1, le=100_000, description="L-BFGS-B iterations after it")
    seed: int = Field(0, ge=0, description="seed of the training subsample and of the annealer")
    free_margin_m: float | None = Field(
        None,
        ge=0,
        le=10,
        description="free_space.margin_m of the training problems only (kernel hyperparameters and PLS "
        "link; null: free_space.margin_m; the grazing margin of free_space.band_m applies there too). "
        "With an exact laser, free points right up to the surfaces make eq. (9) prefer short length "
        "scales that shape the local step at a surface rather than the world's structure; training with "
        "a wider margin than the map uses keeps the length scales of that structure",
    )


class PlsConfig(StageConfig):
    """The probabilistic least-squares link p = Phi((alpha mu + beta) / sqrt(1 + alpha^2 sigma^2))."""

    link: Literal["loo", "holdout"] = Field(
        "loo",
        description="how the PLS link (alpha, beta) is fitted: 'loo' on the training problems' leave-one-out "
        "predictions (eqs. 11-12), 'holdout' on predictions along held-out scans' beams of a map of the "
        "rest (mapping.calibration: the level of space the data never reached is learnt, not implied; "
        "better calibrated and a higher mean hold-out AUC, but lower GPPOL AUC in observed cells: "
        "docs/mapping.md)",
    )
    loo_problems: int = Field(
        4096,
        ge=1,
        le=100_000,
        description="local neighbourhoods whose leave-one-out predictions fit the link ('loo'; with "
        "'holdout', the leave-one-out link it replaces, kept in the parameters' info): the training "
        "problems plus fresh ones from the same scans. 4096: of 64 (train.problems), 1024 and "
        "4096, the best mean hold-out AUC over the eleven reference-pose logs, and no log lower "
        "(docs/mapping.md)",
    )
    holdout_fraction: float = Field(
        0.1, gt=0, lt=1, description="share of the mapped scans held out ('holdout')"
    )
    holdout_block_scans: int = Field(
        10, ge=1, le=10_000, description="consecutive scans per held-out block ('holdout')"
    )


class UnscentedConfig(StageConfig):
    """The unscented transform of each beam (Algorithm 3 of the paper)."""

    alpha: float = Field(0.3, gt=0, le=10, description="spread of the sigma points (the paper's xi)")
    beta: float = Field(2.0, ge=0, le=10, description="prior knowledge of the distribution (2: Gaussian)")
    kappa: float = Field(0.0, ge=0, le=10, description="secondary scaling")


class GppolConfig(StageConfig):
    """GPPOL: training inputs are Gaussians (paper section 3.6), from the unscented transform of each beam."""

    kernel: Literal["nn", "se", "matern32", "matern52"] = Field(
        "se",
        description="covariance function of GPPOL (GPFOL uses mapping.kernel); SE integrates in closed form "
        "(eq. 19), the others by Gauss-Hermite quadrature (eq. 23)",
    )
    expectation: Literal["auto", "girard", "gauss_hermite", "sigma_points"] = Field(
        "auto",
        description="how the kernel is integrated over the inputs: Girard's closed form (SE only), "
        "Gauss-Hermite quadrature (gh_level), the 5-node sigma-point rule, or auto (Girard for SE, "
        "else Gauss-Hermite)",
    )
    gh_level: int = Field(
        3, ge=1, le=10, description="Gauss-Hermite nodes per input dimension (1: the kernel at the means)"
    )
    free_range_noise: bool = Field(
        True,
        description="free points get the range variance too (Algorithm 3, steps 5-8); false: only bearing "
        "and pose noise (the free point's distance along the beam is chosen, not measured)",
    )
    pose_covariances: Literal["relative", "world", "none"] = Field(
        "relative",
        description="which pose covariance of each scan the run hands GPPOL: 'relative' to the earlier "
        "passes over the places it observes (slam.consistency: sharp where the passes agree, uncertain "
        "where they disagree; gauge invariant), 'world' the world-frame marginal (relative to the first "
        "pose: grows with the distance from it), 'none' exact poses (laser noise only)",
    )
    rigid_groups: Literal["scan", "keyframe"] = Field(
        "scan",
        description="which scans GPPOL treats as sharing one pose error: each 'scan' alone, or the scans "
        "of one SLAM 'keyframe' (the pose graph moves them rigidly with it; each strays from it by its "
        "odometry from the keyframe, whose covariance two scans of one keyframe are integrated over)",
    )
    ut: UnscentedConfig = Field(default_factory=UnscentedConfig)

    @model_validator(mode="after")
    def _girard_is_se(self) -> GppolConfig:
        if self.expectation == "girard" and self.kernel != "se":
            raise ValueError(f"expectation 'girard' is the SE kernel's closed form, not {self.kernel}")
        return self


#: Where each key of the former flat mapping section lives now (a configuration that still uses one is
#: refused with this hint, rather than with "unknown key").
MOVED_KEYS: dict[str, str] = {
    "no_return_free_length_m": "free_space.no_return_length_m",
    "free_margin_m": "free_space.margin_m",
    "free_band_m": "free_space.band_m",
    "free_band_per_m": "free_space.band_per_m",
    "free_margin_max_m": "free_space.margin_max_m",
    "scan_min_travel_m": "scan_selection.min_travel_m",
    "scan_min_rotation_rad": "scan_selection.min_rotation_rad",
    "train_scans": "train.scans",
    "train_problems": "train.problems",
    "train_anneal_evaluations": "train.anneal_evaluations",
    "train_lbfgs_iterations": "train.lbfgs_iterations",
    "train_seed": "train.seed",
    "train_free_margin_m": "train.free_margin_m",
    "pls_link": "pls.link",
    "pls_holdout_fraction": "pls.holdout_fraction",
    "pls_holdout_block_scans": "pls.holdout_block_scans",
    "gppol_kernel": "gppol.kernel",
    "gppol_expectation": "gppol.expectation",
    "gppol_gh_level": "gppol.gh_level",
    "gppol_free_range_noise": "gppol.free_range_noise",
    "ut_alpha": "gppol.ut.alpha",
    "ut_beta": "gppol.ut.beta",
    "ut_kappa": "gppol.ut.kappa",
}


class MappingConfig(StageConfig):
    """GP occupancy-map settings (paper defaults where the paper gives one)."""

    mapper: Literal["gppol", "gpfol"] = Field("gppol", description="GPPOL (uncertain inputs) or GPFOL")
    resolution_m: float = Field(0.1, gt=0, le=100, description="cell size of rendered maps")
    k_occupied: int = Field(15, ge=1, le=200, description="occupied neighbours per query (paper: 15)")
    k_free: int = Field(15, ge=1, le=200, description="free-space beam neighbours per query (paper: 15)")
    occupied_threshold: float = Field(0.65, gt=0, lt=1, description="p(occ) >= this is occupied")
    free_threshold: float = Field(0.35, gt=0, lt=1, description="p(occ) <= this is free")
    kernel: Literal["nn", "se", "matern32", "matern52"] = Field(
        "nn", description="covariance function: neural network (eq. 7), squared exponential, Matern 3/2, 5/2"
    )
    kernel_bounds: dict[str, tuple[float, float]] = Field(
        default_factory=dict,
        description="bounds of hyperparameters by name (e.g. sigma: [0.01, 1000]); defaults per kernel",
    )
    noise_var: float = Field(
        0.1, gt=0, le=10, description="GP noise variance sigma_n^2 (fixed; the start value if learnt)"
    )
    learn_noise: bool = Field(False, description="learn sigma_n^2 with the kernel by eq. (9)")
    jitter: float = Field(
        1e-8,
        ge=0,
        le=1,
        description="relative jitter added to K's diagonal when a Cholesky fails (retried x10)",
    )
    index_cell_m: float | None = Field(
        None,
        gt=0,
        le=100,
        description="cell size of the neighbour-search grids (null: from the data density)",
    )
    params_file: Path | None = Field(
        None, description="learnt GP parameters (JSON) to reuse instead of training ('trained in advance')"
    )
    free_space: FreeSpaceConfig = Field(default_factory=FreeSpaceConfig)
    scan_selection: ScanSelectionConfig = Field(default_factory=ScanSelectionConfig)
    train: TrainingConfig = Field(default_factory=TrainingConfig)
    pls: PlsConfig = Field(default_factory=PlsConfig)
    grid: GridBaselineConfig = Field(default_factory=GridBaselineConfig)
    gppol: GppolConfig = Field(default_factory=GppolConfig)
    default_source: SourceNoiseConfig = Field(
        default_factory=SourceNoiseConfig,
        description="laser noise of sources not named in 'sources' (default: 1 cm range, 0.1 deg bearing)",
    )
    sources: dict[str, SourceNoiseConfig] = Field(
        default_factory=dict,
        description="laser noise per source (scan topic, e.g. '/platform_2/scan'), so that several "
        "platforms fuse",
    )

    @model_validator(mode="before")
    @classmethod
    def _moved_keys(cls, data: Any) -> Any:
        return refuse_moved_keys(data, MOVED_KEYS)

    @model_validator(mode="after")
    def _thresholds_ordered(self) -> MappingConfig:
        if not self.free_threshold < self.occupied_threshold:
            raise ValueError(
                f"free_threshold ({self.free_threshold}) must be below occupied_threshold "
                f"({self.occupied_threshold})"
            )
        if self.kernel_bounds:
            from mapping.kernels import KERNELS  # only when bounds are given: it loads the compiled core

            known = set(KERNELS[self.kernel].names) | set(KERNELS[self.gppol.kernel].names)
        for name, (lo, hi) in self.kernel_bounds.items():
            if name not in known:
                raise ValueError(
                    f"kernel_bounds.{name}: no such hyperparameter of the {self.kernel} or "
                    f"{self.gppol.kernel} kernel (known: {', '.join(sorted(known))})"
                )
            if not 0 < lo < hi:
                raise ValueError(f"kernel_bounds.{name} must be (low, high) with 0 < low < high")
        return self
