"""The mapping figures of ``docs/figures/mapping`` (regenerate with ``python -m pipeline.mapping_figures``).

- the Intel lab (``intel.gfs.log``, corrected poses) at 0.1 m: probability, variance, classified;
- the ROC curves of GPFOL and the grid on the Intel hold-out protocol (seed 0);
- the paper's Figure 6 panels on the simulated ``street`` world, and its ROC curves (Figure 7) for GPFOL and
  the occupancy grid with widened and with narrow beams (``python -m pipeline.mapping_figures street`` makes
  only these);
- the paper's Figures 9 and 10 on the simulated ``two-platform`` world: grid, GPFOL and GPPOL p(occupied) and
  classified maps, GPFOL and GPPOL variance (``python -m pipeline.mapping_figures two-platform`` makes only
  these).
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import numpy as np

from mapping.build import MapBuilder
from mapping.evaluation import (
    holdout_split,
    holdout_test_points,
    is_carmen_180,
    observed_cells,
    raster_cell_centres,
)
from mapping.exports import MapLayers
from mapping.figures import (
    plot_classified,
    plot_layer,
    plot_method_rows,
    plot_roc,
    plot_street_panels,
    plot_variance_pair,
)
from mapping.grid import OccupancyGrid
from mapping.metrics import roc_auc, roc_curve
from pipeline.config import load_config
from pipeline.evaluate_map import ground_truth_noise, make_beams, reference_base_poses, reference_laser_poses
from pipeline.figure_data import INTEL_GFS_PATH, robust_bounds

REPO = Path(__file__).resolve().parent.parent
OUT_DIR = REPO / "docs" / "figures" / "mapping"
STREET_CONFIG = REPO / "mapping" / "configs" / "street.yaml"


def intel_figures(out: Path) -> dict[str, Any]:
    from datasets.registry import open_dataset

    cfg = load_config().mapping
    path = INTEL_GFS_PATH
    rec = open_dataset(path)
    poses = reference_base_poses(rec, path)
    laser = reference_laser_poses(rec, path)
    n = len(rec.scans)
    beams = make_beams(rec, poses, np.arange(n), cfg)
    builder = MapBuilder.from_config(cfg, "gpfol")
    params = builder.fit(beams)
    gp = builder.gp_map(beams, params)
    bounds = robust_bounds(beams.hit_xy_m)
    layers = gp.render(bounds, 0.1)
    plot_layer(layers, "probability", out / "intel_probability.png", "Intel lab, GPFOL p(occupied), 0.1 m")
    plot_layer(layers, "variance", out / "intel_variance.png", "Intel lab, GPFOL variance, 0.1 m")
    plot_classified(layers, out / "intel_classified.png", cfg.occupied_threshold, cfg.free_threshold)
    # hold-out ROC, seed 0
    held = holdout_split(n, 0)
    train = np.setdiff1d(np.arange(n), held)
    carmen = is_carmen_180(rec.scans.angles_rad[0])
    pts, labels = holdout_test_points(rec.scans.ranges_m, rec.scans.angles_rad, laser, held, 0, carmen)
    tb = make_beams(rec, poses, train, cfg)
    builder = MapBuilder.from_config(cfg, "gpfol")
    p_gp = builder.gp_map(tb, builder.fit(tb)).query(pts).probability
    p_grid = builder.grid(tb).query(pts)
    curves = {
        "GPFOL": (*roc_curve(p_gp, labels)[:2], roc_auc(p_gp, labels)),
        "occupancy grid": (*roc_curve(p_grid, labels)[:2], roc_auc(p_grid, labels)),
    }
    plot_roc(curves, out / "intel_holdout_roc.png", "Intel hold-out protocol, seed 0")
    return {"intel_auc_seed0": {k: v[2] for k, v in curves.items()}, "intel_map_shape": layers.shape}


def street_figures(out: Path, seed: int = 0) -> dict[str, Any]:
    """The paper's Figure 6 panels and Figure 7 ROC curves on the ``street`` world (``STREET_CONFIG``): GPFOL,
    the paper's grid baseline (beams widened, 0.25 m cells) and the same grid with narrow beams."""
    from datasets.simulation import make_world

    cfg = load_config(STREET_CONFIG).mapping
    run = make_world("street", seed)
    rec = run.recording
    gt = run.ground_truth
    poses = reference_base_poses(rec, Path("street"))
    beams = make_beams(rec, poses, np.arange(len(rec.scans)), cfg)
    builder = MapBuilder.from_config(cfg, "gpfol")
    params = builder.fit(beams)
    gp = builder.gp_map(beams, params)
    occ = np.asarray(gt.occupancy).astype(bool)
    res = float(gt.resolution_m)
    ox, oy = (float(v) for v in gt.origin_xy_m)
    bounds = gt.bounds_xy_m
    layers = gp.render(bounds, res)
    grid = OccupancyGrid.from_config(beams, cfg.grid, bounds)
    narrow = OccupancyGrid.from_config(beams, cfg.grid.model_copy(update={"beam_width_deg": 0.0}), bounds)
    grid_layers = MapLayers(grid.probability, grid.probability, grid.probability, grid.resolution_m, (ox, oy))
    plot_street_panels(
        occ.astype(np.uint8), (ox, oy), res, beams.hit_xy_m, poses[:, :2], grid_layers, layers,
        out / "street_figure6.png", cfg.occupied_threshold, cfg.free_threshold,
    )  # fmt: skip
    centres = raster_cell_centres(occ.shape, np.array([ox, oy]), res)
    p_gp = layers.probability.ravel().astype(np.float64)
    labels = occ.ravel()
    width = f"{cfg.grid.beam_width_deg:g} deg"
    scores = {
        "GPFOL": p_gp,
        f"occupancy grid, beams widened to {width}, {cfg.grid.resolution_m:g} m": grid.query(centres),
        f"occupancy grid, narrow beams, {cfg.grid.resolution_m:g} m": narrow.query(centres),
    }
    curves = {k: (*roc_curve(p, labels)[:2], roc_auc(p, labels)) for k, p in scores.items()}
    plot_roc(curves, out / "street_roc.png", f"street world (seed {seed}), every raster cell")
    return {"street_auc": {k: v[2] for k, v in curves.items()}, "street_params": params.kernel.as_dict()}


REGIONS = ("platform I", "platform II only", "neither")


def two_platform_result(seed: int = 0, every: int = 1, config_path: Path | None = None) -> dict[str, Any]:
    """GPPOL, GPFOL and the grid on the ``two-platform`` world (the paper's dataset II, section 4.1.2), laser
    noise per platform from the simulator (the ground truth's ``sources``), exact poses.

    Scores every ``every``-th row and column of the ground-truth raster: ``auc`` over those cells (SPEC
    section 6), ``auc_observed`` over the cells some beam observed, and by region ``REGIONS`` (cells observed
    by platform I; by platform II only; by neither), with the median variance of the ground-truth FREE cells
    of each region (``median_variance``). Returns also the layers (probability, mean, variance) of each
    mapper on that raster, the tracks of both platforms and the parameters. ``config_path``: a configuration
    file (default: the built-in defaults), e.g. ``mapping/configs/gppol_nn.yaml``."""
    from datasets.simulation import make_world

    run = make_world("two-platform", seed)
    rec, gt = run.recording, run.ground_truth
    cfg = ground_truth_noise(load_config(config_path).mapping, gt)
    poses = reference_base_poses(rec, Path("two-platform"))
    beams = make_beams(rec, poses, np.arange(len(rec.scans)), cfg)
    occ = np.asarray(gt.occupancy).astype(bool)
    res = float(gt.resolution_m)
    origin = np.asarray(gt.origin_xy_m, dtype=np.float64)
    bounds = gt.bounds_xy_m
    centres = gt.cell_centers_xy_m()[::every, ::every]
    shape = centres.shape[:2]
    centres = centres.reshape(-1, 2)
    labels = occ[::every, ::every].ravel()
    seen = [
        observed_cells(beams.subset(beams.source_index == s), bounds, res)[::every, ::every].ravel()
        for s in range(2)
    ]
    regions = {
        REGIONS[0]: seen[0],
        REGIONS[1]: seen[1] & ~seen[0],
        REGIONS[2]: ~seen[0] & ~seen[1],
    }
    observed = seen[0] | seen[1]
    sub_origin = origin + 0.5 * res * (every - 1)
    out: dict[str, Any] = {"auc": {}, "auc_observed": {}, "auc_by_region": {}, "median_variance": {}}
    out["layers"], out["params"] = {}, {}
    for mapper in ("gppol", "gpfol"):
        builder = MapBuilder.from_config(cfg, mapper)
        params = builder.fit(beams)
        pred = builder.gp_map(beams, params).query(centres, sort=False)
        p = pred.probability
        out["params"][mapper] = {"kernel": params.kernel.name, **params.kernel.as_dict()}
        out["layers"][mapper] = MapLayers(
            p.reshape(shape), pred.mean.reshape(shape), pred.variance.reshape(shape), res * every, sub_origin
        )
        out["median_variance"][mapper] = {
            k: float(np.median(pred.variance[r & ~labels])) for k, r in regions.items()
        }
        out["auc_by_region"][mapper] = {k: roc_auc(p[r], labels[r]) for k, r in regions.items()}
        out["auc"][mapper] = roc_auc(p, labels)
        out["auc_observed"][mapper] = roc_auc(p[observed], labels[observed])
    p_grid = MapBuilder.from_config(cfg).grid(beams, bounds).query(centres)
    out["auc"]["grid"] = roc_auc(p_grid, labels)
    out["auc_observed"]["grid"] = roc_auc(p_grid[observed], labels[observed])
    out["layers"]["grid"] = MapLayers(
        p_grid.reshape(shape), p_grid.reshape(shape), p_grid.reshape(shape), res * every, sub_origin
    )
    out["region_cells"] = {k: int(r.sum()) for k, r in regions.items()}
    out["tracks"] = {
        f"platform {'I' * (s + 1)}": beams.origins_xy_m[beams.source_index == s][::37] for s in range(2)
    }
    out["sensor_noise"] = {name: c.model_dump() for name, c in cfg.sources.items()}
    return out


def two_platform_figures(out: Path, seed: int = 0, every: int = 2) -> dict[str, Any]:
    """The paper's Figures 9 (p(occupied) and classified maps of the grid, GPFOL and GPPOL) and 10 (GPFOL and
    GPPOL variance) on the ``two-platform`` world, on every ``every``-th cell of its 0.1 m raster."""
    r = two_platform_result(seed, every)
    cfg = load_config().mapping
    lay = r["layers"]
    rows = {
        f"grid (AUC {r['auc']['grid']:.3f})": lay["grid"],
        f"GPFOL (AUC {r['auc']['gpfol']:.3f})": lay["gpfol"],
        f"GPPOL (AUC {r['auc']['gppol']:.3f})": lay["gppol"],
    }
    plot_method_rows(
        rows, out / "two_platform_figure9.png", cfg.occupied_threshold, cfg.free_threshold, r["tracks"]
    )
    plot_variance_pair({"GPFOL": lay["gpfol"], "GPPOL": lay["gppol"]}, out / "two_platform_figure10.png")
    keys = ("auc", "auc_observed", "auc_by_region", "median_variance", "region_cells", "params")
    return {f"two_platform_{k}": r[k] for k in keys}


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    only = args[0] if args and args[0] in ("street", "two-platform") else None
    args = args[1:] if only else args
    out = Path(args[0]) if args else OUT_DIR
    if only == "street":
        report = street_figures(out)
    elif only == "two-platform":
        report = two_platform_figures(out)
    else:
        report = {**street_figures(out), **intel_figures(out), **two_platform_figures(out)}
    sys.stdout.write(f"{report}\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
