"""The scale part of ``bench``: a 10^8-cell map streamed to disk under a memory budget, tile throughput, and
the speed-up of incremental updates after a loop closure on the Intel run.

Large map. The synthetic city of :mod:`datasets.simulation.city` (not realistic, but a real workload),
1 km x 1 km: a robot drives every east-west street and scans every 2 m with a 181-beam, 360-degree, 30 m
laser. GPFOL (hyperparameters learnt by the default training on its first scans) renders it at 0.1 m,
10,000 x 10,000 = 10^8 cells, in tiles of 128 cells streamed into a :class:`mapping.tiling.TileStore`
(float32 layers on disk). This runs in a fresh Python process so that its peak resident memory (its own
high-water mark, :func:`pipeline.bench.peak_rss_mib`; everything included: world, beams, index, training,
rendering) is the map's alone: ``large_map_peak_rss_mib``; ``tiles_per_s`` is its tile throughput;
``large_map_bench`` has the sizes (scans, beams, bytes on disk) and the time of each step.

Incremental speed-up. The SLAM stage runs on ``intel.clf``; its final pose graph is replayed into iSAM2
(:class:`slam.graph.PoseGraph`) factor by factor in keyframe order, as an online system builds it. Just before
the last accepted loop closure the map of every scan so far is rendered (tiled); the closure is added, iSAM2
updates, and the map is updated incrementally (:meth:`mapping.tiling.IncrementalMap.update_poses`) and, for
comparison, recomputed in full. ``incremental_speedup`` is the full time over the incremental time at the
default pose tolerance (1 um: the result equals the full recomputation bit for bit). iSAM2 moves most
keyframes by a little when a loop closes (``keyframes_moved``, ``keyframe_move_max_m``) and the lab is small,
so nearly every tile is recomputed and there is little to gain: the figure measures the overhead of the
change detection. Beside it: the same at 1 mm and 1 cm (fewer beams count as moved; the map then differs
from the full recomputation, by the reported largest difference of p(occ)), and
``incremental_add_scans_speedup``, online mapping: the last ``ADDED_SCANS`` mapped scans added to the map of
the others (:meth:`~mapping.tiling.IncrementalMap.add_scans`, equal to the full map bit for bit).

Timings depend on the machine's load (the machine may be shared).
"""

from __future__ import annotations

import copy
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from datasets.paths import REPO_DIR, SHARED_DATA_DIR
from datasets.simulation.city import (
    CITY_RANGE_MAX_M,
    CITY_SIZE_M,
    CITY_STREET_PITCH_M,
    city_edges,
    city_path,
    city_ranges,
)
from pipeline.bench import peak_rss_mib
from pipeline.progress import Progress

INTEL_CLF = SHARED_DATA_DIR / "intel" / "intel.clf.bz2"

CITY_RESOLUTION_M = 0.1
CITY_TILE_CELLS = 128
# pose tolerances of the incremental benchmark: the default (``incremental_speedup``) to 1 cm (0.1 cell)
INCREMENTAL_TOLERANCES_M = (1e-6, 1e-3, 1e-2)
ADDED_SCANS = 10


# ---------------------------------------------------------------------------------------------------------
# the large map of the synthetic city


def large_map_child(
    out_dir: str, size_m: float, resolution_m: float, tile_cells: int, result_file: str
) -> None:
    """Runs in a fresh process (see :func:`bench_large_map`): build the city, learn the GP, render the map
    into a tile store in ``out_dir``; writes the figures as JSON to ``result_file``."""
    from mapping.beams import beams_from_scans
    from mapping.build import GPMapFactory, MapBuilder
    from mapping.tiling import IncrementalMap, TileGrid, TileStore
    from pipeline.config import load_config

    t_start = time.perf_counter()
    cfg = load_config(overrides={"mapping": {"mapper": "gpfol"}}).mapping
    edges = city_edges(size_m)
    poses = city_path(size_m)
    ranges, angles = city_ranges(poses, edges)
    beams = beams_from_scans(
        list(ranges),
        [angles] * len(poses),
        0.05,
        CITY_RANGE_MAX_M,
        poses,
        no_return_free_length_m=cfg.free_space.no_return_length_m,
        free_margin_m=cfg.free_space.margin_m,
    )
    del ranges
    t_world = time.perf_counter() - t_start
    t0 = time.perf_counter()
    builder = MapBuilder.from_config(cfg, "gpfol")
    params = builder.fit(beams)
    t_train = time.perf_counter() - t0
    grid = TileGrid.from_bounds((0.0, 0.0, size_m, size_m), resolution_m, tile_cells)
    t0 = time.perf_counter()
    with TileStore.create(Path(out_dir) / "city", grid) as store:
        m = IncrementalMap(beams, grid, GPMapFactory(builder, params), cfg.k_occupied, cfg.k_free, sink=store)
        t_index = time.perf_counter() - t0
        t0 = time.perf_counter()
        m.render_all()
        t_render = time.perf_counter() - t0
    back = TileStore.open(Path(out_dir) / "city")
    prob = back.layer("probability")
    sample = np.asarray(prob[:: max(1, grid.shape_hw[0] // 500), :: max(1, grid.shape_hw[1] // 500)])
    peak_mib = peak_rss_mib()
    result = {
        "world": f"synthetic city {size_m:g} m x {size_m:g} m, street pitch {CITY_STREET_PITCH_M:g} m",
        "scans": len(poses),
        "beams": len(beams),
        "building_edges": len(edges),
        "map_shape_hw": list(grid.shape_hw),
        "cells": grid.cells,
        "resolution_m": resolution_m,
        "tile_cells": tile_cells,
        "tiles": len(grid),
        "all_tiles_written": bool(back.done().all()),
        "support_beams_mean": float(np.mean(m.support_beams)),
        "support_beams_max": int(np.max(m.support_beams)),
        "world_s": t_world,
        "train_s": t_train,
        "index_s": t_index,
        "render_s": t_render,
        "tiles_per_s": len(grid) / t_render,
        "cells_per_s": grid.cells / t_render,
        "total_s": time.perf_counter() - t_start,
        "peak_rss_mib": peak_mib,
        "beams_mib": sum(v.nbytes for v in vars(beams).values() if isinstance(v, np.ndarray)) / 2**20,
        "store_bytes": sum(f.stat().st_blocks * 512 for f in (Path(out_dir) / "city").iterdir()),
        "probability_sample_fractions": {
            "free (<0.35)": float(np.mean(sample < 0.35)),
            "occupied (>0.65)": float(np.mean(sample > 0.65)),
        },
    }
    Path(result_file).write_text(json.dumps(result))


def bench_large_map(
    size_m: float = CITY_SIZE_M, resolution_m: float = CITY_RESOLUTION_M, tile_cells: int = CITY_TILE_CELLS
) -> dict[str, Any]:
    """Render the city map in a fresh process and return its figures (see the module docstring)."""
    with tempfile.TemporaryDirectory(prefix="gpom-bench-scale-") as tmp:
        result_file = Path(tmp) / "result.json"
        code = (
            f"import sys; sys.path.insert(0, {str(REPO_DIR)!r}); "
            "from pipeline.bench.scale import large_map_child; "
            f"large_map_child({tmp!r}, {size_m!r}, {resolution_m!r}, {tile_cells!r}, {str(result_file)!r})"
        )
        proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
        if proc.returncode != 0 or not result_file.is_file():
            tail = (proc.stderr.strip().splitlines() or ["no output"])[-1]
            raise RuntimeError(f"large-map benchmark failed (exit {proc.returncode}): {tail}")
        return json.loads(result_file.read_text())


# ---------------------------------------------------------------------------------------------------------
# incremental update after a loop closure on the Intel run


def replay_until_closure(slam, closure_index: int) -> tuple[np.ndarray, np.ndarray, int]:
    """Replay the final pose graph of ``slam`` into iSAM2 in keyframe order up to the keyframe of its
    accepted loop closure ``closure_index``; returns the keyframe poses just before and just after that
    closure is added ((q+1, 3) each) and q, the closure's query keyframe."""
    from slam import geometry as se2
    from slam.graph import PoseGraph

    closure = slam.loop_closures[closure_index]
    q = int(closure.query_keyframe)
    edges = list(slam.graph_edges)
    loops = [e for e in edges if e.kind == "loop"]
    target = loops[closure_index]
    odo = {e.key_to: e for e in edges if e.kind == "odometry"}
    loops_at: dict[int, list] = {}
    for e in loops:
        loops_at.setdefault(max(e.key_from, e.key_to), []).append(e)
    prior = next(e for e in edges if e.kind == "prior")
    g = PoseGraph()
    g.add_pose(prior.measurement_xytheta)
    g.add_prior(0, prior.measurement_xytheta, prior.cov)
    g.update()
    est = [g.estimate_of(0)]
    before = None
    for k in range(1, q + 1):
        e = odo[k]
        g.add_pose(se2.compose(est[-1], e.measurement_xytheta))
        g.add_between("odometry", e.key_from, k, e.measurement_xytheta, e.cov)
        g.update()
        for lc in loops_at.get(k, []):
            if lc is target:
                before = g.estimate()
            g.add_between(
                "loop", lc.key_from, lc.key_to, lc.measurement_xytheta, lc.cov, lc.robust, lc.robust_width
            )
        if loops_at.get(k):
            g.update(extra_iterations=1)
        est.append(g.estimate_of(k))
    return before, g.estimate(), q


def _tolerance_runs(m, beams_after, ref) -> dict[str, dict[str, Any]]:
    """Update copies of the tiled map ``m`` to ``beams_after`` with each pose tolerance; compare to ``ref``
    (the speed-ups are filled in by the caller)."""
    runs = {}
    for tol in INCREMENTAL_TOLERANCES_M:
        m_tol = copy.deepcopy(m)
        t0 = time.perf_counter()
        report = m_tol.update_poses(beams_after, tolerance_m=tol)
        t_inc = time.perf_counter() - t0
        got = m_tol.layers()
        runs[f"{tol:g}"] = {
            "incremental_s": t_inc,
            "tiles_recomputed": report.tiles_recomputed,
            "fraction_recomputed": report.fraction_recomputed,
            "beams_moved_over_tolerance": report.changed_beams,
            "max_abs_difference_probability": float(np.max(np.abs(got.probability - ref.probability))),
            "identical_to_full": all(
                np.array_equal(getattr(got, k), getattr(ref, k)) for k in ("probability", "mean", "variance")
            ),
        }
    return runs


def bench_incremental(progress: Progress | None = None, path: Path = INTEL_CLF) -> dict[str, Any]:
    """The incremental speed-up after the last loop closure of the Intel run (see the module docstring)."""
    from datasets.registry import open_dataset
    from mapping.build import MapBuilder
    from pipeline.config import load_config
    from pipeline.map_bounds import union_bounds
    from pipeline.run import MAP_MARGIN_M
    from slam.keyframes import scan_poses_from_keyframes
    from slam.system import run_slam_recording

    progress = progress or Progress()
    config = load_config(overrides={"mapping": {"mapper": "gpfol"}})
    cfg = config.mapping
    builder = MapBuilder.from_config(cfg)
    tiles = config.scale.tile_cells
    with progress.stage("bench incremental", total=4) as bar:
        rec = open_dataset(path, config.input)
        t0 = time.perf_counter()
        slam = run_slam_recording(rec, config.slam)
        t_slam = time.perf_counter() - t0
        bar.advance()
        closure = len(slam.loop_closures) - 1
        kf_before, kf_after, q = replay_until_closure(slam, closure)
        kf = slam.keyframe_scans
        last_scan = int(kf[q + 1] - 1) if q + 1 < len(kf) else len(rec.scans) - 1
        n = last_scan + 1
        odo = slam.poses_before_xytheta[:n]
        poses_before = scan_poses_from_keyframes(kf_before, kf[: q + 1], odo)
        poses_after = scan_poses_from_keyframes(kf_after, kf[: q + 1], odo)
        scans = rec.scans.subset(np.arange(n))
        laser = rec.laser_in_base_xytheta
        selected = builder.select_scans(odo, laser)
        beams_before = builder.beams(scans, poses_before, laser, selected)
        beams_after = builder.beams(scans, poses_after, laser, selected)
        params = builder.fit(beams_before)
        bounds = union_bounds(beams_before.bounds_xy_m(MAP_MARGIN_M), beams_after.bounds_xy_m(MAP_MARGIN_M))
        bar.advance()
        m = builder.tiled_map(beams_before, params, bounds, tiles)
        m.render_all()
        bar.advance()
        # online mapping: the map of every scan but the last ADDED_SCANS mapped ones, then those added
        last = selected[-ADDED_SCANS:]
        prefix = builder.tiled_map(
            beams_before.subset(~np.isin(beams_before.scan_index, last)), params, bounds, tiles
        )
        prefix.render_all()
        t0 = time.perf_counter()
        add_report = prefix.add_scans(beams_before.select_scans(last))
        t_add = time.perf_counter() - t0
        a, b = prefix.layers(), m.layers()
        add_identical = all(
            np.array_equal(getattr(a, k), getattr(b, k)) for k in ("probability", "mean", "variance")
        )
        full_times = []
        for _ in range(2):  # twice (before and after the incremental runs below): the machine may be shared
            t0 = time.perf_counter()
            full = builder.tiled_map(beams_after, params, bounds, tiles)
            full.render_all()
            full_times.append(time.perf_counter() - t0)
            if len(full_times) == 1:
                ref = full.layers()
                runs = _tolerance_runs(m, beams_after, ref)
        t_full = min(full_times)
        for r in runs.values():
            r["speedup"] = t_full / r["incremental_s"]
        bar.advance()
    kf_moved = np.hypot(*(kf_after[:, :2] - kf_before[:, :2]).T)
    return {
        "incremental_speedup": runs[f"{INCREMENTAL_TOLERANCES_M[0]:g}"]["speedup"],
        "incremental_add_scans_speedup": t_full / t_add,
        "incremental_bench": {
            "input": str(path),
            "slam_s": t_slam,
            "loop_closure": {
                "index": closure,
                "of": len(slam.loop_closures),
                "query_keyframe": q,
                "target_keyframe": int(slam.loop_closures[closure].target_keyframe),
            },
            "keyframes": q + 1,
            "keyframes_moved": {
                f"over {t:g} m": int(np.count_nonzero(kf_moved > t)) for t in (0.0, *INCREMENTAL_TOLERANCES_M)
            },
            "keyframe_move_max_m": float(kf_moved.max()),
            "scans_mapped": len(selected),
            "beams": len(beams_after),
            "tile_cells": config.scale.tile_cells,
            "map_shape_hw": list(ref.shape),
            "tiles": len(m.grid),
            "full_s": t_full,
            "full_s_each": full_times,
            "by_pose_tolerance_m": runs,
            "add_scans": {
                "scans_added": ADDED_SCANS,
                "incremental_s": t_add,
                "tiles_recomputed": add_report.tiles_recomputed,
                "fraction_recomputed": add_report.fraction_recomputed,
                "identical_to_full": add_identical,
            },
        },
    }


def bench_scale(progress: Progress | None = None) -> dict[str, Any]:
    """Both parts: the large map (in a fresh process) and the incremental speed-up on Intel."""
    progress = progress or Progress()
    out = bench_incremental(progress)
    with progress.stage("bench large map", total=1) as bar:
        large = bench_large_map()
        bar.advance()
    out.update(
        {
            "tiles_per_s": large["tiles_per_s"],
            "large_map_cells": large["cells"],
            "large_map_peak_rss_mib": large["peak_rss_mib"],
            "large_map_bench": large,
        }
    )
    return out
