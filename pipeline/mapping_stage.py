"""Glue between the recording, the trajectory and the mapper: beams, learnt parameters, map objects.

Shared by ``run``, ``remap`` and ``evaluate map``; the algorithms live in :mod:`mapping`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from datasets.errors import ConfigError
from datasets.types import ScanSequence
from mapping.beams import Beams, beams_from_scan_sequence
from mapping.config import MappingConfig
from mapping.gpmap import GPOccupancyMap
from mapping.grid import OccupancyGrid
from mapping.metrics import roc_auc
from mapping.train import GPParams, ParamsFileError, train_gp
from pipeline.errors import NotYetAvailableError, PipelineError

Bounds = tuple[float, float, float, float]


def load_params(cfg: MappingConfig) -> GPParams | None:
    """The stored GP parameters of ``cfg.params_file`` (None when not set); ConfigError if unreadable."""
    if cfg.params_file is None:
        return None
    try:
        return GPParams.load(cfg.params_file)
    except ParamsFileError as exc:
        raise ConfigError(f"{cfg.params_file}: {exc}") from None


def fit_params(beams: Beams, cfg: MappingConfig, seed_offset: int = 0) -> GPParams:
    """Stored parameters if configured, else hyperparameters and PLS link learnt from the first scans."""
    stored = load_params(cfg)
    if stored is not None:
        return stored
    try:
        return train_gp(
            beams,
            kernel_name=cfg.kernel,
            kernel_bounds=cfg.kernel_bounds or None,
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
    )


def check_mapper_available(mapper: str) -> None:
    """Fail before any work when ``mapper`` has not landed yet."""
    if mapper == "gppol":
        raise NotYetAvailableError(
            "mapper 'gppol' is not available yet: GPPOL lands with issue #5 (use --mapper gpfol)"
        )


def build_gp_map(
    beams: Beams,
    params: GPParams,
    cfg: MappingConfig,
    cov_xytheta: NDArray | None = None,
    mapper: str | None = None,
) -> GPOccupancyMap:
    """The GP map of ``mapper`` (default ``cfg.mapper``) over ``beams``. GPPOL needs the (N, 3, 3)
    world-frame base-pose covariances of the scans (indexed by ``beams.scan_index``)."""
    check_mapper_available(mapper or cfg.mapper)
    return GPOccupancyMap(beams, params, cfg.k_occupied, cfg.k_free, cfg.jitter, cfg.index_cell_m)


def build_grid(beams: Beams, cfg: MappingConfig, bounds: Bounds | None = None) -> OccupancyGrid:
    """The occupancy-grid baseline (Thrun et al. 2005) over ``beams``, beams widened as configured."""
    return OccupancyGrid.from_config(beams, cfg.grid, bounds)


def union_bounds(*bounds: Bounds) -> Bounds:
    """The smallest box holding every box of ``bounds``."""
    b = np.asarray(bounds, dtype=np.float64)
    return float(b[:, 0].min()), float(b[:, 1].min()), float(b[:, 2].max()), float(b[:, 3].max())


def ground_truth_auc(
    gp: GPOccupancyMap, occupancy: NDArray, origin_xy_m: NDArray, resolution_m: float
) -> float:
    """AUC of p(occ) over every cell of a ground-truth raster (SPEC section 6, simulated worlds)."""
    from mapping.evaluation import raster_cell_centres

    centres = raster_cell_centres(occupancy.shape, np.asarray(origin_xy_m, np.float64), resolution_m)
    return roc_auc(gp.query(centres, sort=False).probability, np.asarray(occupancy).astype(bool).ravel())


def params_path(folder: Path) -> Path:
    return Path(folder) / "params.json"
