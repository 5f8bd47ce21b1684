"""Glue between the recording, the trajectory and the mapper: beams, learnt parameters, map objects.

Shared by ``run``, ``remap`` and ``evaluate map``; the algorithms live in :mod:`mapping`.
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from datasets.errors import ConfigError
from datasets.types import ScanSequence
from mapping.beams import Beams, beams_from_scan_sequence
from mapping.calibration import holdout_link
from mapping.config import MappingConfig
from mapping.gpmap import GPOccupancyMap
from mapping.gppol import GaussianInputs, SensorNoise, input_moments
from mapping.grid import OccupancyGrid
from mapping.kernels import KERNELS, Kernel, make_kernel
from mapping.metrics import roc_auc
from mapping.noisy_kernels import GAUSS_HERMITE, GIRARD, InputExpectation
from mapping.train import GPParams, ParamsFileError, train_gp
from mapping.unscented import UTParams
from pipeline.errors import PipelineError

MAPPERS = ("gppol", "gpfol")

Bounds = tuple[float, float, float, float]


def parse_numbers(text: str, count: int) -> list[float] | None:
    """``count`` comma-separated finite numbers of a command-line option, or None if ``text`` is not that."""
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        return None
    return values if len(values) == count and all(np.isfinite(values)) else None


def load_params(cfg: MappingConfig) -> GPParams | None:
    """The stored GP parameters of ``cfg.params_file`` (None when not set); ConfigError if unreadable."""
    if cfg.params_file is None:
        return None
    try:
        return GPParams.load(cfg.params_file)
    except ParamsFileError as exc:
        raise ConfigError(f"{cfg.params_file}: {exc}") from None


def sensor_noise(cfg: MappingConfig, source_names: tuple[str, ...] | list[str]) -> list[SensorNoise]:
    """The laser noise of each source: ``cfg.sources[name]`` where named, else ``cfg.default_source``."""
    out = []
    for name in source_names:
        s = cfg.sources.get(name, cfg.default_source)
        out.append(SensorNoise(s.range_var_m2, s.bearing_var_rad2))
    return out


def input_expectation(cfg: MappingConfig, kernel: Kernel) -> InputExpectation:
    """How GPPOL integrates ``kernel`` over its inputs (``auto``: Girard's eq. 19 for SE, else
    Gauss-Hermite)."""
    method = cfg.gppol_expectation
    if method == "auto":
        method = GIRARD if kernel.name == "se" else GAUSS_HERMITE
    return InputExpectation(method, cfg.gppol_gh_level)


def gaussian_inputs(
    beams: Beams, cfg: MappingConfig, cov_xytheta: NDArray | None, kernel: Kernel
) -> GaussianInputs:
    """The GPPOL inputs of ``beams``: the UT of every beam with the (N, 3, 3) world-frame base-pose
    covariances of the scans (indexed by ``beams.scan_index``; None: exact poses) and the per-source laser
    noise of ``cfg``."""
    ut = UTParams(cfg.ut_alpha, cfg.ut_beta, cfg.ut_kappa)
    noise = sensor_noise(cfg, beams.source_names)
    try:
        moments = input_moments(beams, cov_xytheta, noise, ut)
        free = None
        if not cfg.gppol_free_range_noise:
            no_range = [SensorNoise(0.0, s.bearing_var_rad2) for s in noise]
            free = input_moments(beams, cov_xytheta, no_range, ut)
    except ValueError as exc:
        raise PipelineError(f"cannot build the GPPOL inputs: {exc}") from None
    return GaussianInputs(moments, input_expectation(cfg, kernel), free)


def fit_params(
    beams: Beams,
    cfg: MappingConfig,
    seed_offset: int = 0,
    mapper: str | None = None,
    cov_xytheta: NDArray | None = None,
) -> GPParams:
    """Stored parameters if configured, else hyperparameters and PLS link learnt from the first scans for
    ``mapper`` (default ``cfg.mapper``): GPFOL with ``cfg.kernel``; GPPOL with ``cfg.gppol_kernel`` on the
    beams' input Gaussians (pose covariances ``cov_xytheta`` (N, 3, 3) by scan, None: exact poses). The
    training problems' free segments stop ``cfg.train_free_margin_m`` short of the endpoints if it is set (or
    each beam's grazing margin, kept from ``beams``, if larger)."""
    stored = load_params(cfg)
    if stored is not None:
        return stored
    params = _train_params(beams, cfg, seed_offset, mapper, cov_xytheta)
    if cfg.pls_link == "holdout":
        params = _holdout_link(params, beams, cfg, seed_offset, mapper, cov_xytheta)
    return params


def _holdout_link(
    params: GPParams,
    beams: Beams,
    cfg: MappingConfig,
    seed_offset: int,
    mapper: str | None,
    cov_xytheta: NDArray | None,
) -> GPParams:
    """``params`` with the PLS link refitted on held-out scans of ``beams`` (``pls_link: holdout``,
    :func:`mapping.calibration.holdout_link`); unchanged when too few scans (``params.info["pls"]`` says which
    fit holds)."""

    def build(rest: Beams) -> GPOccupancyMap:
        return build_gp_map(rest, params, cfg, cov_xytheta, mapper)

    fitted = holdout_link(
        beams, build, cfg.pls_holdout_fraction, cfg.pls_holdout_block_scans, cfg.train_seed + seed_offset
    )
    info = dict(params.info)
    loo = {"alpha": params.alpha, "beta": params.beta}
    if fitted is None:
        info["pls"] = {"fit": "loo (too few scans to hold out)", "loo": loo}
        return replace(params, info=info)
    alpha, beta, used = fitted
    info["pls"] = {"fit": "holdout", "loo": loo, **used}
    return replace(params, alpha=alpha, beta=beta, info=info)


def _train_params(
    beams: Beams,
    cfg: MappingConfig,
    seed_offset: int,
    mapper: str | None,
    cov_xytheta: NDArray | None,
) -> GPParams:
    """Hyperparameters and the leave-one-out PLS link learnt by :func:`mapping.train.train_gp`."""
    gppol = (mapper or cfg.mapper) == "gppol"
    kernel_name = cfg.gppol_kernel if gppol else cfg.kernel
    names = KERNELS[kernel_name].names
    bounds = {k: v for k, v in cfg.kernel_bounds.items() if k in names} or None
    if cfg.train_free_margin_m is not None:
        beams = beams.with_free_margin(cfg.train_free_margin_m)
    inputs = None
    if gppol:
        # training reads the first train_scans scans only (train_gp): their beams alone go through the UT
        beams = beams.select_scans(np.unique(beams.scan_index)[: cfg.train_scans])
        inputs = gaussian_inputs(beams, cfg, cov_xytheta, make_kernel(kernel_name))
    try:
        return train_gp(
            beams,
            kernel_name=kernel_name,
            kernel_bounds=bounds,
            noise_var=cfg.noise_var,
            k_occ=cfg.k_occupied,
            k_free=cfg.k_free,
            n_scans=cfg.train_scans,
            n_problems=cfg.train_problems,
            maxfun=cfg.train_anneal_evaluations,
            maxiter=cfg.train_lbfgs_iterations,
            seed=cfg.train_seed + seed_offset,
            index_cell_m=cfg.index_cell_m,
            learn_noise=cfg.learn_noise,
            inputs=inputs,
        )
    except ValueError as exc:
        raise PipelineError(f"cannot train the GP: {exc}") from None


def make_beams(
    scans: ScanSequence,
    base_poses_xytheta: NDArray,
    laser_in_base_xytheta: NDArray,
    cfg: MappingConfig,
    indices: NDArray | None = None,
) -> Beams:
    """World-frame beams of the scans ``indices`` (default all) at base poses (N, 3) of every scan."""
    idx = np.arange(len(scans)) if indices is None else np.asarray(indices, dtype=np.int64)
    return beams_from_scan_sequence(
        scans.subset(idx),
        np.asarray(base_poses_xytheta, dtype=np.float64)[idx],
        laser_in_base_xytheta,
        no_return_free_length_m=cfg.no_return_free_length_m,
        free_margin_m=cfg.free_margin_m,
        scan_indices=idx,
        free_band_m=cfg.free_band_m,
        free_band_per_m=cfg.free_band_per_m,
        free_margin_max_m=cfg.free_margin_max_m,
    )


def check_mapper_available(mapper: str) -> None:
    """Fail before any work when ``mapper`` is unknown."""
    if mapper not in MAPPERS:
        raise ConfigError(f"unknown mapper '{mapper}' (known: {', '.join(MAPPERS)})")


def build_gp_map(
    beams: Beams,
    params: GPParams,
    cfg: MappingConfig,
    cov_xytheta: NDArray | None = None,
    mapper: str | None = None,
) -> GPOccupancyMap:
    """The GP map of ``mapper`` (default ``cfg.mapper``) over ``beams``. GPPOL uses the (N, 3, 3)
    world-frame base-pose covariances of the scans (indexed by ``beams.scan_index``; None: exact poses) and
    the laser noise per source of ``cfg``; GPFOL ignores them."""
    mapper = mapper or cfg.mapper
    check_mapper_available(mapper)
    if mapper == "gpfol" and "inputs" in params.info:
        raise PipelineError("these GP parameters were learnt for GPPOL: learn them with mapper='gpfol'")
    inputs = gaussian_inputs(beams, cfg, cov_xytheta, params.kernel) if mapper == "gppol" else None
    try:
        return GPOccupancyMap(
            beams, params, cfg.k_occupied, cfg.k_free, cfg.jitter, cfg.index_cell_m, inputs=inputs
        )
    except ValueError as exc:
        raise PipelineError(f"cannot build the {mapper.upper()} map: {exc}") from None


def build_grid(beams: Beams, cfg: MappingConfig, bounds: Bounds | None = None) -> OccupancyGrid:
    """The occupancy-grid baseline (Thrun et al. 2005) over ``beams``, beams widened as configured."""
    return OccupancyGrid.from_config(beams, cfg.grid, bounds)


def union_bounds(*bounds: Bounds) -> Bounds:
    """The smallest box holding every box of ``bounds``."""
    b = np.asarray(bounds, dtype=np.float64)
    return float(b[:, 0].min()), float(b[:, 1].min()), float(b[:, 2].max()), float(b[:, 3].max())


def map_cells(bounds: Bounds, resolution_m: float) -> tuple[int, int]:
    """(width, height) in cells of a map over ``bounds`` at ``resolution_m`` (Python ints: never overflow)."""
    xmin, ymin, xmax, ymax = bounds
    return math.ceil((xmax - xmin) / resolution_m), math.ceil((ymax - ymin) / resolution_m)


def check_map_cells(bounds: Bounds, resolution_m: float, max_cells: int, what: str) -> None:
    """PipelineError, before any allocation, when a map over ``bounds`` at ``resolution_m`` would have more
    than ``max_cells`` cells (``scale.max_map_cells``); ``what`` says which map (and how its bounds were
    found) in the message."""
    width, height = map_cells(bounds, resolution_m)
    if width * height > max_cells:
        size_x, size_y = bounds[2] - bounds[0], bounds[3] - bounds[1]
        raise PipelineError(
            f"{what}: {size_x:.4g} x {size_y:.4g} m at {resolution_m:g} m is {width} x {height} = "
            f"{width * height:.3g} cells, above scale.max_map_cells = {max_cells:.3g} (choose a coarser "
            "resolution or smaller bounds, or raise the limit in the configuration)"
        )


def scan_reach_m(scans: ScanSequence) -> float:
    """The longest valid return of ``scans`` (m): the smallest map of a run covers one scan's disc of it."""
    reach = 0.0
    for r, lo, hi in zip(scans.ranges_m, scans.range_min_m, scans.range_max_m, strict=True):
        with np.errstate(invalid="ignore"):
            hits = r[(r >= lo) & (r < hi)]
        if hits.size:
            reach = max(reach, float(hits.max()))
    return reach


def ground_truth_auc(
    gp: GPOccupancyMap, occupancy: NDArray, origin_xy_m: NDArray, resolution_m: float
) -> float:
    """AUC of p(occ) over every cell of a ground-truth raster (SPEC section 6, simulated worlds)."""
    from mapping.evaluation import raster_cell_centres

    centres = raster_cell_centres(occupancy.shape, np.asarray(origin_xy_m, np.float64), resolution_m)
    return roc_auc(gp.query(centres, sort=False).probability, np.asarray(occupancy).astype(bool).ravel())


def params_path(folder: Path) -> Path:
    return Path(folder) / "params.json"
