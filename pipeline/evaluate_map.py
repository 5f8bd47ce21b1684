"""``evaluate map INPUT``: AUC of the GP maps and of the occupancy-grid baseline (SPEC section 6).

Ground-truth protocol when ``INPUT.gt.npz`` lies beside the input (simulated worlds: every cell of the
raster scored), the hold-out protocol otherwise (blocks of scans held out, test points along their beams).
Maps are built from the input's reference poses; a recording without them is mapped on the optimised
trajectory of the SLAM stage, and the output says so (``poses``). GPPOL lands with issue 5: its AUC is
``None`` until then.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from datasets.errors import DatasetError
from datasets.types import Recording
from mapping.beams import Beams, compose_laser_poses
from mapping.config import MappingConfig
from mapping.evaluation import holdout_split, holdout_test_points, is_carmen_180, raster_cell_centres
from mapping.metrics import roc_auc
from pipeline import mapping_stage as ms
from pipeline.config import load_config
from pipeline.errors import PipelineError
from pipeline.progress import Progress

DEFAULT_SEEDS = [0, 1, 2, 3, 4]


def make_beams(rec: Recording, laser_poses: np.ndarray, indices: np.ndarray, cfg: MappingConfig) -> Beams:
    """World-frame beams of the scans ``indices`` of ``rec`` at ``laser_poses`` (N, 3)."""
    return ms.make_beams(rec.scans, laser_poses, np.zeros(3), cfg, indices)


def reference_laser_poses(rec: Recording, input_path: Path) -> np.ndarray:
    """(N, 3) laser poses from the recording's reference poses (PipelineError when it has none)."""
    if rec.scans is None or len(rec.scans) == 0:
        raise DatasetError(f"{input_path}: no laser scans to map")
    if rec.reference is None:
        raise PipelineError(f"{input_path}: no reference poses (ground truth or corrected log)")
    if len(rec.reference) != len(rec.scans):
        raise DatasetError(f"{input_path}: {len(rec.reference)} reference poses for {len(rec.scans)} scans")
    return compose_laser_poses(rec.reference.poses_xytheta, rec.laser_in_base_xytheta)


def mapping_laser_poses(
    rec: Recording, input_path: Path, slam_config: Any = None, progress: Progress | None = None
) -> tuple[np.ndarray, str]:
    """(N, 3) laser poses to map with, and where they come from: the reference poses when the recording has
    them (``"reference"``), else the optimised trajectory of the SLAM stage (``"slam"``, SPEC section 6)."""
    if rec.scans is None or len(rec.scans) == 0:
        raise DatasetError(f"{input_path}: no laser scans to map")
    if rec.reference is not None:
        return reference_laser_poses(rec, input_path), "reference"
    from slam.system import run_slam_recording

    result = run_slam_recording(rec, slam_config, progress)
    return compose_laser_poses(result.poses_after_xytheta, rec.laser_in_base_xytheta), "slam"


def evaluate_holdout(
    rec: Recording, laser_poses: np.ndarray, seeds: list[int], cfg: MappingConfig, progress: Progress
) -> dict[str, Any]:
    """The hold-out protocol of SPEC section 6 for GPFOL and the grid, one entry per seed."""
    scans = rec.scans
    n = len(scans)
    carmen = rec.format == "carmen" and all(is_carmen_180(a) for a in scans.angles_rad[: min(n, 10)])
    per_seed = []
    with progress.stage("evaluate map", total=len(seeds)) as bar:
        for seed in seeds:
            held = np.asarray(holdout_split(n, seed), dtype=np.int64)
            if held.size == 0:
                raise PipelineError(f"{rec.source}: {n} scans are too few for the hold-out protocol (< 400)")
            train = np.setdiff1d(np.arange(n), held)
            pts, labels = holdout_test_points(
                scans.ranges_m, scans.angles_rad, laser_poses, held.tolist(), seed, carmen_180=carmen
            )
            beams = make_beams(rec, laser_poses, train, cfg)
            t0 = time.perf_counter()
            params = ms.fit_params(beams, cfg, seed_offset=seed)
            t1 = time.perf_counter()
            gp = ms.build_gp_map(beams, params, cfg, mapper="gpfol")
            p_gp = gp.query(pts).probability
            t2 = time.perf_counter()
            grid = ms.build_grid(beams, cfg)
            p_grid = grid.query(pts)
            t3 = time.perf_counter()
            per_seed.append(
                {
                    "seed": seed,
                    "held_out_scans": int(held.size),
                    "test_points": int(labels.size),
                    "occupied_test_points": int(labels.sum()),
                    "auc_gpfol": roc_auc(p_gp, labels),
                    "auc_grid": roc_auc(p_grid, labels),
                    "train_s": t1 - t0,
                    "gpfol_map_and_query_s": t2 - t1,
                    "grid_s": t3 - t2,
                    "hyperparameters": params.kernel.as_dict(),
                    "pls": {"alpha": params.alpha, "beta": params.beta},
                    "params": params.to_dict(),  # save as JSON and set mapping.params_file to reuse
                }
            )
            bar.advance()
    return {"per_seed": per_seed}


def evaluate_ground_truth(
    rec: Recording, laser_poses: np.ndarray, gt_path: Path, cfg: MappingConfig, progress: Progress
) -> dict[str, Any]:
    """Score every cell of the ground-truth raster ``gt_path`` (SPEC section 6, simulated worlds)."""
    from datasets.simulation import load_ground_truth

    gt = load_ground_truth(gt_path)
    occ = np.asarray(gt.occupancy).astype(bool)
    res = float(gt.resolution_m)
    origin = np.asarray(gt.origin_xy_m, dtype=np.float64)
    with progress.stage("evaluate map", total=3) as bar:
        beams = make_beams(rec, laser_poses, np.arange(len(rec.scans)), cfg)
        t0 = time.perf_counter()
        params = ms.fit_params(beams, cfg)
        bar.advance()
        t1 = time.perf_counter()
        gp = ms.build_gp_map(beams, params, cfg, mapper="gpfol")
        centres = raster_cell_centres(occ.shape, origin, res)
        p_gp = gp.query(centres, sort=False).probability
        bar.advance()
        t2 = time.perf_counter()
        h, w = occ.shape
        bounds = (origin[0], origin[1], origin[0] + w * res, origin[1] + h * res)
        grid = ms.build_grid(beams, cfg, bounds)
        p_grid = grid.query(centres)
        bar.advance()
        t3 = time.perf_counter()
    labels = occ.ravel()
    return {
        "per_seed": [
            {
                "seed": None,
                "test_points": int(labels.size),
                "occupied_test_points": int(labels.sum()),
                "auc_gpfol": roc_auc(p_gp, labels),
                "auc_grid": roc_auc(p_grid, labels),
                "train_s": t1 - t0,
                "gpfol_map_and_query_s": t2 - t1,
                "grid_s": t3 - t2,
                "hyperparameters": params.kernel.as_dict(),
                "pls": {"alpha": params.alpha, "beta": params.beta},
                "params": params.to_dict(),
            }
        ],
    }


def evaluate_map(
    input_path: Path,
    seeds: list[int] | None = None,
    config_path: Path | None = None,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """Evaluate the mappers on ``input_path``; returns the SPEC section 3 keys (``protocol``, ``seeds``,
    ``auc``: {gppol, gpfol, grid} as means over seeds) plus ``per_seed`` details and a ``table``."""
    from datasets.registry import open_dataset

    progress = progress or Progress()
    config = load_config(config_path)
    cfg = config.mapping
    input_path = Path(input_path)
    rec = open_dataset(input_path, config.input)
    laser_poses, pose_source = mapping_laser_poses(rec, input_path, config.slam, progress)
    gt_path = Path(str(input_path) + ".gt.npz")
    if gt_path.is_file():
        protocol = "ground_truth"
        used_seeds: list[int] = []
        out = evaluate_ground_truth(rec, laser_poses, gt_path, cfg, progress)
    else:
        protocol = "holdout"
        used_seeds = list(seeds) if seeds else list(DEFAULT_SEEDS)
        out = evaluate_holdout(rec, laser_poses, used_seeds, cfg, progress)
    rows = out["per_seed"]
    auc = {
        "gppol": None,
        "gpfol": float(np.mean([r["auc_gpfol"] for r in rows])),
        "grid": float(np.mean([r["auc_grid"] for r in rows])),
    }
    table = {
        "protocol": protocol,
        "seeds": ",".join(map(str, used_seeds)) or "-",
        "poses": "the input's reference poses" if pose_source == "reference" else "SLAM (no reference)",
    }
    table.update({f"AUC {k}": ("not available (issue 5)" if v is None else v) for k, v in auc.items()})
    for r in rows:
        tag = "" if r["seed"] is None else f" seed {r['seed']}"
        table[f"AUC gpfol / grid{tag}"] = f"{r['auc_gpfol']:.4f} / {r['auc_grid']:.4f}"
    return {
        "protocol": protocol,
        "seeds": used_seeds,
        "auc": auc,
        "input": str(input_path),
        "poses": pose_source,
        "notes": "gppol is None until GPPOL lands (issue 5)",
        "per_seed": rows,
        "table": table,
    }
