"""The mapping part of ``bench`` (SPEC section 7): GPFOL and GPPOL query points per second on the Intel lab
map at 0.1 m with 15 + 15 neighbours, end to end (neighbour search included), and occupancy-grid cells per
second, with a breakdown of where the time goes.

GPPOL runs the default configuration (``mapping.gppol.kernel`` / ``mapping.gppol.expectation``) with the pose
covariance of the Intel perturbation experiment, ``diag(0.1^2, 0.1^2, 0.02^2)`` for every scan (the
Hilbert-maps reference's ``perturb_data``; the rate does not depend on the covariance's size), and the
configured laser noise. Its breakdown: the unscented transform of every beam (``gppol_inputs_s``, once per
map), the neighbour search (shared with GPFOL) and the kernel expectations + solves. ``gppol_choices``
times the other kernel-expectation choices on the first ``CHOICE_QUERIES`` cells of the same map (their
AUCs: `evaluate map`, docs/results.md; not measured here).

The map covers the lab as in the mapping figures (:func:`pipeline.figure_data.robust_bounds`: the central
99.6% of the returns in x and y, grown by 1 m; ``map_shape``); the rate over the bounds of every return (a
few are seen far away through windows, much of that map empty) is reported beside it
(``full_bounds_*``). Numba compilation (or loading it from the cache) is timed apart, by a warm-up call on a
few points, and excluded from the rates.

The machine may be shared: each render (and the search alone) is timed ``RENDER_RUNS`` times and the rates
come from the median run (the single runs, ``*_wall_s_runs``, vary by 10-30 % on a shared 2-core machine);
wall-clock rates are reported beside the CPU time the work took (CPU seconds summed over threads), whose
rate ``*_per_cpu_s`` is less sensitive to other processes.
"""

from __future__ import annotations

import resource
import time
from pathlib import Path
from typing import Any

import numba
import numpy as np

from datasets.errors import DatasetError
from datasets.paths import SHARED_DATA_DIR
from mapping.build import MapBuilder
from mapping.gpmap import GPOccupancyMap, grid_centres, tile_order
from pipeline.config import load_config
from pipeline.evaluate_map import make_beams, reference_base_poses
from pipeline.figure_data import INTEL_GFS_LOG, robust_bounds
from pipeline.progress import Progress

RESOLUTION_M = 0.1
PERTURB_COV = np.diag([0.1**2, 0.1**2, 0.02**2])  # the Intel perturbation experiment's pose covariance
CHOICE_QUERIES = 20_000
RENDER_RUNS = 5
GPPOL_CHOICES = (  # (mapping.gppol.kernel, .expectation, .gh_level)
    ("se", "girard", 3),
    ("se", "gauss_hermite", 3),
    ("nn", "sigma_points", 3),
    ("nn", "gauss_hermite", 2),
    ("nn", "gauss_hermite", 3),
)


def _cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


class _Timer:
    def __enter__(self) -> _Timer:
        self.wall0, self.cpu0 = time.perf_counter(), _cpu_s()
        return self

    def __exit__(self, *exc: object) -> None:
        self.wall = time.perf_counter() - self.wall0
        self.cpu = _cpu_s() - self.cpu0


class _Runs:
    """``runs`` timings of ``fn()``: ``wall`` and ``cpu`` are the medians, ``walls`` every run's wall time,
    ``result`` the last run's return value."""

    def __init__(self, fn: Any, runs: int = RENDER_RUNS) -> None:
        self.walls: list[float] = []
        cpus = []
        for _ in range(runs):
            with _Timer() as t:
                self.result = fn()
            self.walls.append(t.wall)
            cpus.append(t.cpu)
        self.wall = float(np.median(self.walls))
        self.cpu = float(np.median(cpus))


def bench_mapping(progress: Progress | None = None, data_dir: Path | None = None) -> dict[str, Any]:
    """Run the mapping benchmark on the Intel lab (``intel.gfs.log``, corrected poses)."""
    from datasets.registry import open_dataset

    progress = progress or Progress()
    path = (data_dir or SHARED_DATA_DIR) / INTEL_GFS_LOG
    if not path.is_file():
        raise DatasetError(f"{path}: benchmark data missing (shared data folder beside the checkout)")
    cfg = load_config().mapping
    with progress.stage("bench mapping", total=7) as bar:
        rec = open_dataset(path)
        base = reference_base_poses(rec, path)
        beams = make_beams(rec, base, np.arange(len(rec.scans)), cfg)
        with _Timer() as t_train:
            params = MapBuilder.from_config(cfg, "gpfol").fit(beams)
        bar.advance()
        with _Timer() as t_index:
            gp = GPOccupancyMap(beams, params, cfg.k_occupied, cfg.k_free, cfg.jitter, cfg.index_cell_m)
        bounds = robust_bounds(beams.hit_xy_m)  # the lab, as in docs/figures/mapping/intel_*.png
        pts, _, (h, w) = grid_centres(bounds, RESOLUTION_M)
        full_bounds = gp.bounds_xy_m()  # every return, incl. a few seen far away through windows
        with _Timer() as t_compile:  # first call: compile or load the compiled core from numba's cache
            gp.query(pts[:64], sort=False)
            gp.index.gather(pts[:64], cfg.k_occupied, cfg.k_free)
        bar.advance()
        t_map = _Runs(lambda: gp.render(bounds, RESOLUTION_M))
        layers = t_map.result
        bar.advance()
        n = pts.shape[0]
        in_render_order = pts[tile_order(int(h), int(w))]  # the search alone, in the order render uses
        t_gather = _Runs(lambda: gp.index.gather(in_render_order, cfg.k_occupied, cfg.k_free))
        with _Timer() as t_full:
            full = gp.render(full_bounds, RESOLUTION_M)
        bar.advance()
        MapBuilder.from_config(cfg).grid(beams.subset(np.arange(10)), bounds)  # warm-up (compile / cache)
        with _Timer() as t_grid:
            grid = MapBuilder.from_config(cfg).grid(beams, bounds)
        bar.advance()
        gppol = _bench_gppol(beams, cfg, bounds, pts, t_gather.wall)
        bar.advance()
        gppol["gppol_choices"] = _bench_gppol_choices(beams, cfg, pts[:CHOICE_QUERIES])
        bar.advance()
    grid_cells = int(np.prod(grid.log_odds.shape))
    solve_s = max(t_map.wall - t_gather.wall, 0.0)
    return {
        "gpfol_queries_per_s": n / t_map.wall,
        "gppol_queries_per_s": gppol["gppol_queries_per_s"],
        "grid_cells_per_s": grid.cell_updates / t_grid.wall,
        "mapping_bench": {
            "input": str(path),
            "scans": len(rec.scans),
            "beams": len(beams),
            "occupied_points": int(beams.is_hit.sum()),
            "map_shape": [int(h), int(w)],
            "resolution_m": RESOLUTION_M,
            "bounds_xy_m": list(bounds),
            "neighbours": [cfg.k_occupied, cfg.k_free],
            "kernel": params.kernel.name,
            "threads": numba.get_num_threads(),
            "gpfol_queries": n,
            "gpfol_wall_s": t_map.wall,
            "gpfol_wall_s_runs": t_map.walls,
            "gpfol_cpu_s": t_map.cpu,
            "gpfol_queries_per_cpu_s": n / max(t_map.cpu, 1e-9),
            "neighbour_search_wall_s": t_gather.wall,
            "neighbour_search_wall_s_runs": t_gather.walls,
            "gp_solve_wall_s": solve_s,
            "neighbour_search_share": t_gather.wall / max(t_map.wall, 1e-9),
            "compile_or_cache_load_s": t_compile.wall,
            "index_build_s": t_index.wall,
            "train_s": t_train.wall,
            "grid_wall_s": t_grid.wall,
            "grid_cell_updates": grid.cell_updates,
            "grid_map_cells": grid_cells,
            "grid_map_cells_per_s": grid_cells / t_grid.wall,
            "probability_range": [float(layers.probability.min()), float(layers.probability.max())],
            "full_bounds_xy_m": list(full_bounds),
            "full_bounds_queries": int(np.prod(full.shape)),
            "full_bounds_queries_per_s": float(np.prod(full.shape)) / t_full.wall,
            **{k: v for k, v in gppol.items() if k != "gppol_queries_per_s"},
        },
    }


def _gppol_map(beams: Any, cfg: Any, cov: np.ndarray) -> tuple[Any, Any, float]:
    """Trained GPPOL parameters, the map, and the seconds of the map build (UT of every beam + index)."""
    builder = MapBuilder.from_config(cfg, "gppol")
    params = builder.fit(beams, cov)
    with _Timer() as t_build:
        gp = builder.gp_map(beams, params, cov)
    return params, gp, t_build.wall


def _bench_gppol(
    beams: Any, cfg: Any, bounds: tuple[float, ...], pts: np.ndarray, gather_s: float
) -> dict[str, Any]:
    """GPPOL (default configuration) on the same map as GPFOL, with the perturbation's pose covariance."""
    n_scans = int(beams.scan_index.max()) + 1
    cov = np.tile(PERTURB_COV, (n_scans, 1, 1))
    with _Timer() as t_train:
        params, gp, build_s = _gppol_map(beams, cfg, cov)
    builder = MapBuilder.from_config(cfg, "gppol")
    with _Timer() as t_inputs:
        builder.gaussian_inputs(beams, cov, params.kernel)  # the UT of every beam alone
    gp.query(pts[:64], sort=False)  # compile / load from cache
    t_map = _Runs(lambda: gp.render(bounds, RESOLUTION_M))
    n = pts.shape[0]
    return {
        "gppol_queries_per_s": n / t_map.wall,
        "gppol_kernel": params.kernel.name,
        "gppol_expectation": {"method": gp.inputs.expectation.method, "level": gp.inputs.expectation.level},
        "gppol_queries": n,
        "gppol_wall_s": t_map.wall,
        "gppol_wall_s_runs": t_map.walls,
        "gppol_cpu_s": t_map.cpu,
        "gppol_queries_per_cpu_s": n / max(t_map.cpu, 1e-9),
        "gppol_neighbour_search_wall_s": gather_s,
        "gppol_kernels_and_solve_wall_s": max(t_map.wall - gather_s, 0.0),
        "gppol_inputs_s": t_inputs.wall,
        "gppol_map_build_s": build_s,
        "gppol_train_s": t_train.wall - build_s,
        "gppol_pose_cov_diag": [float(v) for v in np.diag(PERTURB_COV)],
    }


def _bench_gppol_choices(beams: Any, cfg: Any, pts: np.ndarray) -> list[dict[str, Any]]:
    """Queries per second of each kernel-expectation choice of :data:`GPPOL_CHOICES` on ``pts``."""
    n_scans = int(beams.scan_index.max()) + 1
    cov = np.tile(PERTURB_COV, (n_scans, 1, 1))
    out = []
    for kernel, method, level in GPPOL_CHOICES:
        choice = {"kernel": kernel, "expectation": method, "gh_level": level}
        c = cfg.model_copy(update={"gppol": cfg.gppol.model_copy(update=choice)})
        _, gp, _ = _gppol_map(beams, c, cov)
        gp.query(pts[:64], sort=False)  # compile / load from cache
        with _Timer() as t:
            gp.query(pts, sort=False)
        out.append(
            {
                "kernel": kernel,
                "expectation": method,
                "level": level if method == "gauss_hermite" else None,
                "nodes_per_input": int(gp.inputs.rule()[1].size) if method != "girard" else None,
                "queries": int(pts.shape[0]),
                "queries_per_s": pts.shape[0] / t.wall,
                "queries_per_cpu_s": pts.shape[0] / max(t.cpu, 1e-9),
            }
        )
    return out
