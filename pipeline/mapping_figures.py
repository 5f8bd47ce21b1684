"""The mapping figures of ``docs/figures/mapping`` (regenerate with ``python -m pipeline.mapping_figures``).

- the Intel lab (``intel.gfs.log``, corrected poses) at 0.1 m: probability, variance, classified;
- the ROC curves of GPFOL and the grid on the Intel hold-out protocol (seed 0);
- the paper's Figure 6 panels on the simulated ``street`` world, and its ROC curves (Figure 7) for GPFOL and
  the occupancy grid with widened and with narrow beams (``python -m pipeline.mapping_figures street`` makes
  only these).
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import numpy as np

from mapping.evaluation import holdout_split, holdout_test_points, is_carmen_180, raster_cell_centres
from mapping.exports import MapLayers
from mapping.figures import plot_classified, plot_layer, plot_roc, plot_street_panels
from mapping.grid import OccupancyGrid
from mapping.metrics import roc_auc, roc_curve
from pipeline.bench_mapping import DATA_DIR, INTEL, robust_bounds
from pipeline.config import load_config
from pipeline.evaluate_map import make_beams, reference_laser_poses
from pipeline.mapping_stage import build_gp_map, build_grid, fit_params

REPO = Path(__file__).resolve().parent.parent
OUT_DIR = REPO / "docs" / "figures" / "mapping"
STREET_CONFIG = REPO / "mapping" / "configs" / "street.yaml"


def intel_figures(out: Path) -> dict[str, Any]:
    from datasets.registry import open_dataset

    cfg = load_config().mapping
    path = DATA_DIR / INTEL
    rec = open_dataset(path)
    poses = reference_laser_poses(rec, path)
    n = len(rec.scans)
    beams = make_beams(rec, poses, np.arange(n), cfg)
    params = fit_params(beams, cfg)
    gp = build_gp_map(beams, params, cfg, mapper="gpfol")
    bounds = robust_bounds(beams.hit_xy_m)
    layers = gp.render(bounds, 0.1)
    plot_layer(layers, "probability", out / "intel_probability.png", "Intel lab, GPFOL p(occupied), 0.1 m")
    plot_layer(layers, "variance", out / "intel_variance.png", "Intel lab, GPFOL variance, 0.1 m")
    plot_classified(layers, out / "intel_classified.png", cfg.occupied_threshold, cfg.free_threshold)
    # hold-out ROC, seed 0
    held = holdout_split(n, 0)
    train = np.setdiff1d(np.arange(n), held)
    carmen = is_carmen_180(rec.scans.angles_rad[0])
    pts, labels = holdout_test_points(rec.scans.ranges_m, rec.scans.angles_rad, poses, held, 0, carmen)
    tb = make_beams(rec, poses, train, cfg)
    p_gp = build_gp_map(tb, fit_params(tb, cfg), cfg, mapper="gpfol").query(pts).probability
    p_grid = build_grid(tb, cfg).query(pts)
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
    poses = reference_laser_poses(rec, Path("street"))
    beams = make_beams(rec, poses, np.arange(len(rec.scans)), cfg)
    params = fit_params(beams, cfg)
    gp = build_gp_map(beams, params, cfg, mapper="gpfol")
    occ = np.asarray(gt.occupancy).astype(bool)
    h, w = occ.shape
    res = float(gt.resolution_m)
    ox, oy = (float(v) for v in gt.origin_xy_m)
    bounds = (ox, oy, ox + w * res, oy + h * res)
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


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    only_street = bool(args) and args[0] == "street"
    args = args[1:] if only_street else args
    out = Path(args[0]) if args else OUT_DIR
    report = street_figures(out) if only_street else {**street_figures(out), **intel_figures(out)}
    sys.stdout.write(f"{report}\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
