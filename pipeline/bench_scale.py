"""The scale part of ``bench`` (issue 8): a 100-million-cell map streamed to disk under a memory budget, tile
throughput, and the speed-up of incremental updates after a loop closure on the Intel run.

Large map. A synthetic city (not realistic, but a real workload): 1 km x 1 km of blocks on a 50 m street grid,
each block split into one to four buildings with random setbacks; a robot drives every east-west street in a
lawnmower pattern (~20 km) and scans every 2 m with a 181-beam, 360-degree, 30 m laser (~1.8 M beams, 11x the
Intel ``gfs`` log). GPFOL (hyperparameters learnt by the default training on its first scans) renders it at
0.1 m, 10,000 x 10,000 = 10^8 cells, in tiles of 128 cells streamed into a :class:`mapping.tiling.TileStore`
(1.2 GB of float32 layers on disk). This runs in a fresh Python process so that its peak resident memory
(its own high-water mark, :func:`pipeline.bench.peak_rss_mib`; everything included: world, beams, index,
training, rendering) is the map's alone: ``large_map_peak_rss_mib``; ``tiles_per_s`` is its tile throughput.
It takes tens of minutes on 2 cores.

Incremental speed-up. The SLAM stage runs on ``intel.clf``; its final pose graph is replayed into iSAM2
(:class:`slam.graph.PoseGraph`) factor by factor in keyframe order, as an online system builds it. Just before
the last accepted loop closure the map of every scan so far is rendered (tiled); the closure is added, iSAM2
updates, and the map is updated incrementally (:meth:`mapping.tiling.IncrementalMap.update_poses`) and, for
comparison, recomputed in full. ``incremental_speedup`` is the full time over the incremental time at the
default pose tolerance (1 um: the result equals the full recomputation bit for bit). iSAM2 moves most
keyframes by a little when a loop closes (the last closure of the Intel run: 87% of them by more than 1 mm,
at most 3 cm) and the lab is small, so every tile is recomputed and there is nothing to gain: the figure
measures the overhead of the change detection (~1). Beside it: the same at 1 mm and 1 cm (fewer beams count
as moved; the map then differs from the full recomputation, by the reported largest difference of p(occ)),
and ``incremental_add_scans_speedup``, online mapping: the last ``ADDED_SCANS`` mapped scans added to the map
of the others (:meth:`~mapping.tiling.IncrementalMap.add_scans`, equal to the full map bit for bit).

Timings depend on the machine's load (the machine may be shared).
"""

from __future__ import annotations

import copy
import itertools
import json
import math
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from datasets.paths import SHARED_DATA_DIR
from pipeline.bench import peak_rss_mib
from pipeline.progress import Progress

ROOT = Path(__file__).resolve().parent.parent
INTEL_CLF = SHARED_DATA_DIR / "intel" / "intel.clf.bz2"

CITY_SIZE_M = 1000.0
CITY_RESOLUTION_M = 0.1
CITY_TILE_CELLS = 128
CITY_STREET_PITCH_M = 50.0
CITY_STREET_WIDTH_M = 10.0
CITY_SCAN_STEP_M = 2.0
CITY_BEAMS = 181
CITY_RANGE_MAX_M = 30.0
# pose tolerances of the incremental benchmark: the default (``incremental_speedup``) to 1 cm (0.1 cell)
INCREMENTAL_TOLERANCES_M = (1e-6, 1e-3, 1e-2)
ADDED_SCANS = 10


# ---------------------------------------------------------------------------------------------------------
# the synthetic city


def city_edges(size_m: float = CITY_SIZE_M, seed: int = 0) -> np.ndarray:
    """(E, 4) building outlines (``x0, y0, x1, y1`` edges) of a city of ``size_m`` x ``size_m`` on a street
    grid of pitch ``CITY_STREET_PITCH_M``: every block holds one to four buildings with random setbacks."""
    rng = np.random.default_rng(seed)
    pitch, street = CITY_STREET_PITCH_M, CITY_STREET_WIDTH_M
    n = int(size_m // pitch)
    boxes = []
    for i in range(n):
        for j in range(n):
            x0, y0 = i * pitch + street, j * pitch + street
            x1, y1 = (i + 1) * pitch, (j + 1) * pitch
            if x1 > size_m or y1 > size_m:
                continue
            nx, ny = rng.integers(1, 3, 2)  # buildings per block along x and y
            xs = np.linspace(x0, x1, nx + 1)
            ys = np.linspace(y0, y1, ny + 1)
            for a in range(nx):
                for b in range(ny):
                    sb = rng.uniform(0.5, 3.0, 4)  # set-backs of the four sides
                    boxes.append((xs[a] + sb[0], ys[b] + sb[1], xs[a + 1] - sb[2], ys[b + 1] - sb[3]))
    edges = []
    for x0, y0, x1, y1 in boxes:
        edges += [(x0, y0, x1, y0), (x1, y0, x1, y1), (x1, y1, x0, y1), (x0, y1, x0, y0)]
    return np.asarray(edges, dtype=np.float64)


def city_path(size_m: float = CITY_SIZE_M, step_m: float = CITY_SCAN_STEP_M) -> np.ndarray:
    """(N, 3) scan poses: every east-west street driven in turn (lawnmower), joined along the west and east
    north-south streets, a pose every ``step_m``."""
    pitch, half = CITY_STREET_PITCH_M, CITY_STREET_WIDTH_M / 2
    rows = np.arange(half, size_m, pitch)
    west, east = half, math.floor((size_m - half) / pitch) * pitch + half
    corners = []
    for k, y in enumerate(rows):
        corners += [(west, y), (east, y)] if k % 2 == 0 else [(east, y), (west, y)]
    pts = []
    for (xa, ya), (xb, yb) in itertools.pairwise(corners):
        n = max(int(math.hypot(xb - xa, yb - ya) // step_m), 1)
        t = np.arange(n) / n
        heading = math.atan2(yb - ya, xb - xa)
        pts.append(np.c_[xa + t * (xb - xa), ya + t * (yb - ya), np.full(n, heading)])
    return np.concatenate(pts)


def city_ranges(poses: np.ndarray, edges: np.ndarray, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(N, B) float32 ranges (inf: no return within ``CITY_RANGE_MAX_M``) and (B,) beam angles of a 360-degree
    laser at ``poses``, ray cast in batches against the edges near each batch."""
    from datasets.simulation import cast_rays

    rng = np.random.default_rng(seed)
    angles = np.linspace(-np.pi, np.pi, CITY_BEAMS, endpoint=False)
    out = np.empty((len(poses), CITY_BEAMS), np.float32)
    lo = np.minimum(edges[:, :2], edges[:, 2:])
    hi = np.maximum(edges[:, :2], edges[:, 2:])
    reach = CITY_RANGE_MAX_M + 1.0
    for start in range(0, len(poses), 32):
        p = poses[start : start + 32]
        a, b = p[:, :2].min(axis=0) - reach, p[:, :2].max(axis=0) + reach
        near = edges[np.all(hi >= a, axis=1) & np.all(lo <= b, axis=1)]
        r = cast_rays(p[:, None, :2], p[:, 2:3] + angles[None, :], near)
        r = r + rng.normal(0.0, 0.01, r.shape)
        out[start : start + 32] = np.where(r < CITY_RANGE_MAX_M, r, np.inf)
    return out, angles


def large_map_child(
    out_dir: str, size_m: float, resolution_m: float, tile_cells: int, result_file: str
) -> None:
    """Runs in a fresh process (see :func:`bench_large_map`): build the city, learn the GP, render the map
    into a tile store in ``out_dir``; writes the figures as JSON to ``result_file``."""
    from mapping.beams import beams_from_scans
    from mapping.tiling import IncrementalMap, TileGrid, TileStore
    from pipeline.config import load_config
    from pipeline.mapping_stage import fit_params
    from pipeline.scale import GPMapFactory

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
        no_return_free_length_m=cfg.no_return_free_length_m,
        free_margin_m=cfg.free_margin_m,
    )
    del ranges
    t_world = time.perf_counter() - t_start
    t0 = time.perf_counter()
    params = fit_params(beams, cfg, mapper="gpfol")
    t_train = time.perf_counter() - t0
    grid = TileGrid.from_bounds((0.0, 0.0, size_m, size_m), resolution_m, tile_cells)
    t0 = time.perf_counter()
    with TileStore.create(Path(out_dir) / "city", grid) as store:
        m = IncrementalMap(
            beams, grid, GPMapFactory(params, cfg, "gpfol"), cfg.k_occupied, cfg.k_free, sink=store
        )
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
            f"import sys; sys.path.insert(0, {str(ROOT)!r}); "
            "from pipeline.bench_scale import large_map_child; "
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
    from pipeline import mapping_stage as ms
    from pipeline.config import load_config
    from pipeline.run import MAP_MARGIN_M, select_scans
    from pipeline.scale import tiled_map
    from slam import geometry as se2
    from slam.keyframes import keyframe_of_scan
    from slam.system import run_slam_recording

    progress = progress or Progress()
    config = load_config(overrides={"mapping": {"mapper": "gpfol"}})
    cfg = config.mapping
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
        owner = keyframe_of_scan(kf[: q + 1], n)
        offset = se2.between(odo[kf[owner]], odo)
        poses_before = se2.compose(kf_before[owner], offset)
        poses_after = se2.compose(kf_after[owner], offset)
        scans = rec.scans.subset(np.arange(n))
        laser = rec.laser_in_base_xytheta
        selected = select_scans(odo, laser, cfg)
        beams_before = ms.make_beams(scans, poses_before, laser, cfg, selected)
        beams_after = ms.make_beams(scans, poses_after, laser, cfg, selected)
        params = ms.fit_params(beams_before, cfg)
        bounds = ms.union_bounds(
            beams_before.bounds_xy_m(MAP_MARGIN_M), beams_after.bounds_xy_m(MAP_MARGIN_M)
        )
        bar.advance()
        m = tiled_map(beams_before, params, cfg, config.scale, bounds, None)
        m.render_all()
        bar.advance()
        # online mapping: the map of every scan but the last ADDED_SCANS mapped ones, then those added
        last = selected[-ADDED_SCANS:]
        prefix = tiled_map(
            beams_before.subset(~np.isin(beams_before.scan_index, last)),
            params,
            cfg,
            config.scale,
            bounds,
            None,
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
            full = tiled_map(beams_after, params, cfg, config.scale, bounds, None)
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
