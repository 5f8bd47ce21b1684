"""``run`` and ``demo``: read -> odometry -> pose graph -> marginals and the mapper's covariances (each
scan relative to the earlier passes over its places) -> GP maps before and after loop closure -> the run
folder of SPEC section 4.

Stages and their owners: reading (:mod:`datasets`), SLAM (:func:`slam.system.run_slam_recording`), maps
(:class:`mapping.build.MapBuilder`), exports (:mod:`pipeline.map_exports`). This module
only sequences them, times them and writes the run folder (staged, ``summary.json`` last).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from datasets.errors import DatasetError
from datasets.progress import StageTimer
from datasets.registry import guess_format, open_dataset
from datasets.se2 import path_length_m
from datasets.types import Recording, Trajectory
from mapping.beams import beams_from_scan_sequence
from mapping.build import Bounds, MapBuilder, check_mapper
from mapping.evaluation import ground_truth_auc_over, pass_masks, rendered_ground_truth_auc
from mapping.exports import MapLayers
from mapping.gppol import RigidGroups
from mapping.placement import with_placement
from mapping.tiling import IncrementalMap, TileRenderer, render_serial
from mapping.train import GPParams
from pipeline.artifacts import (
    SCANS_FILE,
    TRAJECTORY_DIR,
    mapper_covariances,
    mapper_rigid_groups,
    write_scans,
    write_trajectories,
)
from pipeline.config import Config, load_config, write_config
from pipeline.errors import PipelineError, stage_boundary
from pipeline.map_bounds import check_map_cells, map_cells, scan_reach_m, snap_to_lattice, union_bounds
from pipeline.map_exports import classify_layers, write_maps
from pipeline.memory import keeping_freed_memory, pretouch_heap
from pipeline.progress import Progress
from pipeline.report import write_report
from pipeline.run_folder import check_output_dir, params_path, staged_run_folder, write_summary
from pipeline.scale import engine_name, tile_engine
from slam.metrics import ate_rmse
from slam.result import SlamResult
from slam.system import run_slam_recording, wheel_poses_of
from slam.trajectory_io import read_tum

if TYPE_CHECKING:
    from datasets.simulation.raster import GroundTruth

MAP_MARGIN_M = 1.0
# Memory the map stages and the export take beyond what the process holds when SLAM starts, per map cell,
# a little under fr-clinic's (docs/evaluation.md, "Memory is time on some machines")
PRETOUCH_BYTES_PER_CELL = 160
PRETOUCH_SCAN_STEP = 10  # every 10th scan spans the map's bounds well enough for an estimate


def read_input(input_path: Path, config: Config) -> Recording:
    """The recording, checked to hold scans (a DatasetError naming the file otherwise)."""
    rec = open_dataset(input_path, config.input)
    if rec.scans is None or len(rec.scans) == 0:
        raise DatasetError(f"{input_path}: no laser scans to map")
    return rec


def loop_closure_segments(slam: SlamResult) -> np.ndarray:
    """(C, 2, 2) positions of the two scans of every accepted loop closure on the optimised trajectory."""
    p = slam.poses_after_xytheta
    segs = [[p[c.query_scan, :2], p[c.target_scan, :2]] for c in slam.loop_closures]
    return np.asarray(segs, dtype=np.float64).reshape(-1, 2, 2)


def build_maps(
    rec_scans,
    laser_in_base: np.ndarray,
    trajectories: dict[str, tuple[np.ndarray, np.ndarray | None]],
    config: Config,
    timer: StageTimer,
    progress: Progress,
    params: GPParams | None = None,
    bounds: Bounds | None = None,
    selected: np.ndarray | None = None,
    renderer: TileRenderer = render_serial,
    render_stats: dict[str, dict[str, float]] | None = None,
    rigid_groups: RigidGroups | None = None,
) -> tuple[dict[str, MapLayers], dict[str, IncrementalMap], GPParams, Bounds]:
    """GP maps for each named trajectory ``{name: (base poses (N,3), covariances (N,3,3) | None)}``.

    The scans mapped are ``selected`` (default: selected by motion along the first trajectory,
    :meth:`MapBuilder.select_scans`), the same for every map. Hyperparameters are learnt once (on the first
    trajectory's beams) unless ``params`` is given; every map is rendered on the same grid (``bounds``:
    default the union of the data bounds grown to the world lattice of cells, :func:`snap_to_lattice`),
    tile by tile (:mod:`pipeline.scale`) with the engine ``renderer``.
    Returns the layers, the tiled maps (:class:`mapping.tiling.IncrementalMap`, ready for incremental
    updates), the parameters and the bounds. ``render_stats``, when given, receives per map rendered whole
    the cells solved and those answered with the prior beyond the kernel's reach, with their seconds
    (:attr:`mapping.gpmap.GPOccupancyMap.last_query_stats`). ``rigid_groups``: the scans that share
    one pose error in every GPPOL map (:func:`pipeline.artifacts.mapper_rigid_groups`; None: each scan alone).
    """
    cfg = config.mapping
    builder = MapBuilder.from_config(cfg, None, config.export.unknown_variance_fraction)
    if selected is None:
        selected = builder.select_scans(next(iter(trajectories.values()))[0], laser_in_base)
    beams = {
        name: builder.beams(rec_scans, poses, laser_in_base, selected)
        for name, (poses, _) in trajectories.items()
    }
    if bounds is None:
        data_bounds = union_bounds(*(b.bounds_xy_m(MAP_MARGIN_M) for b in beams.values()))
        bounds = snap_to_lattice(data_bounds, cfg.resolution_m)
    check_map_cells(bounds, cfg.resolution_m, config.scale.max_map_cells, "the maps of the run")
    if params is None:
        with timer("train"), progress.stage("train GP", total=1) as bar:
            first = next(iter(trajectories))
            params = builder.fit(beams[first], trajectories[first][1], rigid_groups=rigid_groups)
            bar.advance()
    layers: dict[str, MapLayers] = {}
    maps: dict[str, IncrementalMap] = {}
    for name, (_, cov) in trajectories.items():
        tiled = partial(
            builder.tiled_map,
            beams[name],
            params,
            bounds,
            config.scale.tile_cells,
            cov,
            renderer,
            rigid_groups=rigid_groups,
        )
        with timer(f"map_{name}"):
            if renderer is render_serial:
                # In one process the whole map at once is faster than tile by tile (one neighbour index
                # instead of one per tile) and gives the same map (bit for bit here; to a float32 ulp on
                # some CPUs: tests/layer_checks.py); the tiled map adopts it, ready for incremental updates.
                with progress.stage(f"map {name}", total=1) as bar:
                    gp = builder.gp_map(beams[name], params, cov, rigid_groups)
                    whole = gp.render(bounds, cfg.resolution_m)
                    bar.advance()
                if render_stats is not None:
                    render_stats[name] = dict(gp.last_query_stats)
                maps[name] = tiled(layers=whole)
                layers[name] = whole  # the tiled map holds its own copy: no second one from layers()
            else:
                maps[name] = tiled()
                with progress.stage(f"map {name}", total=len(maps[name].grid)) as bar:
                    maps[name].render_all(on_tile=lambda _r, bar=bar: bar.advance())
                layers[name] = maps[name].layers()
    return layers, maps, params, bounds


def tiles_summary(maps: dict[str, IncrementalMap], config: Config) -> dict[str, Any]:
    """``summary.json["tiles"]``: the tiling and the engine of the maps. ``rendering`` is ``"whole map"``
    when the serial engine rendered each map at once and the tiled maps adopted it (then no tile has its own
    support: the per-tile figures are None), else ``"tile by tile"``."""
    first = next(iter(maps.values()))
    whole = all(m.adopted for m in maps.values())
    return {
        "tile_cells": config.scale.tile_cells,
        "count": len(first.grid),
        "engine": engine_name(config.scale),
        "rendering": "whole map" if whole else "tile by tile",
        "support_beams_mean": None if whole else {k: float(m.support_beams.mean()) for k, m in maps.items()},
        "tile_seconds_sum": None if whole else {k: float(m.tile_seconds.sum()) for k, m in maps.items()},
    }


def default_run_dir(input_path: Path) -> Path:
    """Where ``run`` writes when no ``--out`` is given: ``out/<input name without extensions>``."""
    return Path("out") / Path(input_path).name.split(".")[0]


def run_pipeline(
    input_path: Path,
    out_dir: Path | None = None,
    config: Config | None = None,
    overwrite: bool = False,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """The full pipeline on one recording with ``config`` (default: ``pipeline/default.yaml``; the command
    line builds it with :func:`pipeline.config.load_config` from ``--config`` and its options); writes the
    run folder ``out_dir`` (default ``out/<input name>``) and returns its summary."""
    progress = progress or Progress()
    timer = StageTimer()
    input_path = Path(input_path)
    config = config if config is not None else load_config()
    out_dir = Path(out_dir) if out_dir is not None else default_run_dir(input_path)
    guess_format(input_path)  # a missing or unknown input fails before anything else
    check_output_dir(out_dir, overwrite, reads=[input_path])
    check_mapper(config.mapping.mapper)

    with timer("read"), progress.stage("read", total=1) as bar, stage_boundary("reading", input_path):
        rec = read_input(input_path, config)
        bar.advance()
    MapBuilder.from_config(config.mapping).check_sources(rec.scans.sources, str(input_path))
    longest_return_m = scan_reach_m(rec.scans)
    if longest_return_m <= 0.0:
        raise PipelineError(
            f"{input_path}: no scan has a return (every range is below its range_min, or at or above its "
            "range_max: a no-return reading): nothing to map"
        )
    reach_m = longest_return_m + MAP_MARGIN_M  # no map of this run is smaller than one scan's disc
    check_map_cells(
        (-reach_m, -reach_m, reach_m, reach_m),
        config.mapping.resolution_m,
        config.scale.max_map_cells,
        f"{input_path}: the map of a single scan",
    )
    with (
        timer("slam"),
        stage_boundary("SLAM", input_path),
        pretouch_heap(pretouch_estimate_bytes(rec, config) if keeping_freed_memory() else 0) as pretouched,
    ):
        slam = run_slam_recording(rec, config.slam, progress)

    with (
        stage_boundary("writing", out_dir, name_known_errors=False),
        staged_run_folder(out_dir, overwrite, reads=[input_path]) as stage,
    ):
        write_config(config, stage / "config.yaml")
        write_scans(stage / SCANS_FILE, rec.scans, rec.laser_in_base_xytheta)
        files = write_trajectories(stage / TRAJECTORY_DIR, slam)
        # Map with the poses as the run folder stores them (TUM text), so that ``remap`` with the run's own
        # trajectory reproduces these maps bit for bit.
        stored = {"before": read_tum(files["odometry"]), "after": read_tum(files["optimized"])}
        mode = config.mapping.gppol.pose_covariances
        trajectories = {
            which: (stored[which][1], mapper_covariances(slam, which, mode)) for which in ("before", "after")
        }
        render_stats: dict[str, dict[str, float]] = {}
        with stage_boundary("mapping", input_path), tile_engine(config.scale) as renderer:
            layers, maps, params, bounds = build_maps(
                rec.scans,
                rec.laser_in_base_xytheta,
                trajectories,
                config,
                timer,
                progress,
                renderer=renderer,
                render_stats=render_stats,
                rigid_groups=mapper_rigid_groups(slam, config.mapping.gppol.rigid_groups),
            )
        (stage / "maps").mkdir()
        params.save(params_path(stage / "maps"))
        with timer("evaluate"):
            metrics = evaluate_run(input_path, rec, slam, maps, layers, config.slam.consistency.revisit_gap_m)
        with timer("export"), progress.stage("export", total=1) as bar:
            # each map's placement layer in a thread of its own (its raster walk releases the GIL)
            with ThreadPoolExecutor(max_workers=2, thread_name_prefix="placement") as pool:
                placed = {
                    name: pool.submit(
                        with_placement, m, maps[name].beams, mapper_covariances(slam, name, "world")
                    )
                    for name, m in layers.items()
                }
                layers = {name: future.result() for name, future in placed.items()}
            write_maps(
                stage / "maps",
                layers,
                {k: Trajectory(stamps, poses, "map") for k, (stamps, poses) in stored.items()},
                loop_closure_segments(slam),
                config.mapping,
                config.export,
                int(rec.scans.stamps_ns[-1]),
                params,
                ate_m=metrics["ate_rmse_m"],
            )
            bar.advance()
        shares = {
            name: classify_layers(m, params, config.mapping, config.export).cell_shares()
            for name, m in layers.items()
        }
        summary = make_summary(
            input_path, rec, slam, config, layers["after"], bounds, params, metrics, timer, shares
        )
        summary["tiles"] = tiles_summary(maps, config)
        summary["pretouched_mib"] = round(pretouched["bytes"] / 2**20, 1)
        summary["map"]["render"] = render_stats
        if config.export.png:
            write_report(stage, summary, maps=layers)
        write_summary(stage, summary)
    return summary


def pretouch_estimate_bytes(rec: Recording, config: Config) -> int:
    """What the map stages and the export of ``rec`` will take beyond SLAM's memory (bytes), for
    :func:`pipeline.memory.pretouch_heap`: :data:`PRETOUCH_BYTES_PER_CELL` per cell of the map that every
    :data:`PRETOUCH_SCAN_STEP`-th scan's beams span at the recording's own poses (its logged scan poses,
    else its wheel odometry); 0 without either."""
    if rec.scans is None or len(rec.scans) == 0:
        return 0
    poses = rec.scan_poses.poses_xytheta if rec.scan_poses is not None else wheel_poses_of(rec)
    if poses is None or len(poses) != len(rec.scans) or not np.all(np.isfinite(poses)):
        return 0
    builder = MapBuilder.from_config(config.mapping)
    indices = np.arange(0, len(rec.scans), PRETOUCH_SCAN_STEP)
    beams = builder.beams(rec.scans, poses, rec.laser_in_base_xytheta, indices)
    if len(beams) == 0:
        return 0
    bounds = snap_to_lattice(beams.bounds_xy_m(MAP_MARGIN_M), config.mapping.resolution_m)
    nx, ny = map_cells(bounds, config.mapping.resolution_m)
    return int(min(nx * ny, config.scale.max_map_cells)) * PRETOUCH_BYTES_PER_CELL


def evaluate_run(
    input_path: Path,
    rec: Recording,
    slam: SlamResult,
    maps: dict[str, IncrementalMap],
    layers: dict[str, MapLayers],
    revisit_gap_m: float,
) -> dict[str, Any]:
    """ATE before / after against the recording's reference poses, AUC before / after against a
    ground-truth raster beside the input (simulated worlds: the rendered ``layers`` where the raster's cells
    are theirs, the GP map elsewhere); None where there is no reference. With both, also ``auc_by_cells``:
    the AUC over the raster's cells a beam observed at the reference poses, over those two passes observed
    (:func:`mapping.evaluation.pass_masks`, ``revisit_gap_m``) and over those only one pass did."""
    metrics: dict[str, Any] = {"ate_rmse_m": None, "auc": None}
    if rec.reference is not None and len(rec.reference) == len(slam.stamps_ns):
        ref = rec.reference.poses_xytheta
        metrics["ate_rmse_m"] = {
            "before": ate_rmse(slam.poses_before_xytheta, ref),
            "after": ate_rmse(slam.poses_after_xytheta, ref),
        }
    from datasets.simulation import ground_truth_path, load_ground_truth

    gt_path = ground_truth_path(input_path)
    if gt_path.is_file():
        gt = load_ground_truth(gt_path)
        metrics["auc"] = {
            name: rendered_ground_truth_auc(
                layers[name],
                gt.occupancy,
                gt.origin_xy_m,
                gt.resolution_m,
                lambda xy_m, m=m: m.factory(m.beams, m.cov_xytheta).query(xy_m, sort=False).probability,
            )
            for name, m in maps.items()
        }
        metrics["auc_ground_truth"] = str(gt_path)
        if rec.reference is not None and len(rec.reference) == len(rec.scans):
            metrics["auc_by_cells"] = auc_by_cells(rec, gt, layers, revisit_gap_m)
    return metrics


def auc_by_cells(
    rec: Recording, gt: GroundTruth, layers: dict[str, MapLayers], revisit_gap_m: float
) -> dict[str, Any]:
    """Per map, the AUC against the ground truth ``gt`` over the raster's cells ``observed`` by a beam of
    ``rec`` at its reference poses, ``revisited`` by a second pass, ``seen_once``; with the cell counts."""
    ref = rec.reference.poses_xytheta
    beams = beams_from_scan_sequence(rec.scans, ref, rec.laser_in_base_xytheta)
    path_m = path_length_m(ref[:, :2])
    observed, revisited = pass_masks(
        beams, path_m, revisit_gap_m, gt.occupancy.shape, gt.origin_xy_m, gt.resolution_m
    )
    cells = {"observed": observed, "revisited": revisited, "seen_once": observed & ~revisited}
    out: dict[str, Any] = {
        name: ground_truth_auc_over(m, gt.occupancy, gt.origin_xy_m, gt.resolution_m, cells)
        for name, m in layers.items()
    }
    out["cells"] = {name: int(np.count_nonzero(mask)) for name, mask in cells.items()}
    return out


def make_summary(
    input_path: Path,
    rec: Recording,
    slam: SlamResult,
    config: Config,
    after: MapLayers,
    bounds: Bounds,
    params: GPParams,
    metrics: dict[str, Any],
    timer: StageTimer,
    cell_shares: dict[str, dict[str, float]] | None = None,
) -> dict[str, Any]:
    """``summary.json``: counts, timings, loop closures, metrics, map geometry, the shares of each map's
    cells the planners' classification calls occupied / free / unknown (``cell_shares``, by map name:
    :meth:`mapping.exports.MapLayers.cell_shares`), how the reader recognised no-return readings
    (``no_return``: the reader's ``meta["no_return"]``, None if it says nothing), and a ``table``."""
    timings = dict(timer.seconds)
    no_return = rec.meta.get("no_return") if isinstance(rec.meta, dict) else None
    timings["total"] = timer.total()
    data_s = (rec.scans.stamps_ns[-1] - rec.scans.stamps_ns[0]) / 1e9
    s = slam.summary()
    ate = metrics["ate_rmse_m"]
    auc = metrics["auc"]
    table: dict[str, Any] = {
        "input": str(input_path),
        "scans": s["scans"],
        "keyframes": s["keyframes"],
        "loop closures (accepted / rejected)": (
            f"{s['loop_closures_accepted']} / {s['loop_closures_rejected']}"
        ),
        "scans without a scan match (placed by prediction)": f"{s['odometry_fallbacks']} of {s['scans']}",
        "ATE before / after loop closure (m)": "-"
        if ate is None
        else f"{ate['before']:.3f} / {ate['after']:.3f}",
        "map AUC before / after loop closure": "-"
        if auc is None
        else f"{auc['before']:.4f} / {auc['after']:.4f}",
        "map": (
            f"{after.shape[1]} x {after.shape[0]} cells at {after.resolution_m} m ({config.mapping.mapper}"
            + (
                f", {config.mapping.gppol.pose_covariances} pose covariances)"
                if config.mapping.mapper == "gppol"
                else ")"
            )
        ),
        "no-return readings": _no_return_text(no_return),
    }
    notes = input_notes(rec.meta)
    if notes:
        table["input notes"] = "; ".join(notes)
    for name, share in (cell_shares or {}).items():
        table[f"cells occupied / free / unknown, {name} (%)"] = (
            f"{100 * share['occupied']:.1f} / {100 * share['free']:.1f} / {100 * share['unknown']:.1f}"
        )
    for name, sec in timings.items():
        table[f"wall time {name} (s)"] = round(sec, 2)
    table["real-time factor"] = round(data_s / timings["total"], 1) if timings["total"] > 0 else None
    user_s, system_s = timer.total_cpu()
    table["CPU time user / system (s)"] = f"{user_s:.1f} / {system_s:.1f}"
    return {
        "input": str(input_path),
        "format": rec.format,
        "no_return": no_return,
        "input_notes": notes,
        "mapper": config.mapping.mapper,
        "counts": {
            "scans": s["scans"],
            "beams": int(rec.scans.beam_counts().sum()),
            "keyframes": s["keyframes"],
            "loop_closures": s["loop_closures_accepted"],
            "loop_closures_rejected": s["loop_closures_rejected"],
        },
        "loop_closures": [
            {"query_scan": int(c.query_scan), "target_scan": int(c.target_scan)} for c in slam.loop_closures
        ],
        "metrics": metrics,
        "map": {
            "resolution_m": after.resolution_m,
            "origin_xy_m": list(after.origin_xy_m),
            "shape_hw": list(after.shape),
            "bounds_xy_m": list(bounds),
            # p(occ) the link gives where no data reach (mu = 0, prior variance): unobserved cells read so
            "unseen_probability": params.unseen_probability,
            "pose_covariances": config.mapping.gppol.pose_covariances,
            "cell_shares": cell_shares or {},
        },
        "params": params.to_dict(),
        "slam": s,
        "data_duration_s": data_s,
        "timings_s": timings,
        "cpu_s": timer.cpu_summary(),
        "realtime_factor": data_s / timings["total"] if timings["total"] > 0 else None,
        "table": table,
    }


def input_notes(meta: Any) -> list[str]:
    """One line per repair or choice the reader made that a user should know of (a reader's ``meta``): a
    damaged bag index bypassed, header stamps replaced by the bag's receive times, a CARMEN log's stamps
    shifted or put in line order, scans outside the odometry's time span."""
    if not isinstance(meta, dict):
        return []
    notes = [str(note) for note in meta.get("notes") or []]
    notes += [
        f"header stamps of {topic} all equal: stamped with the bag's receive times"
        for topic in meta.get("bag_time_topics") or []
    ]
    shift_ns = meta.get("stamp_shift_ns") or 0
    if shift_ns:
        notes.append(
            f"stamps shifted by {shift_ns / 1e9:+.0f} s to start at 0 (the log's clock starts negative)"
        )
    if meta.get("stamps_by_line_order"):
        notes.append("stamps in line order (the log's own cannot be put in order)")
    notes += [
        f"{count} scans outside the time span of odometry {topic}: registered without wheels"
        for topic, count in (meta.get("scans_outside_odometry") or {}).items()
        if count
    ]
    return notes


def _no_return_text(no_return: Any) -> str:
    """The summary table's cell for a reader's ``meta["no_return"]``."""
    if isinstance(no_return, dict) and "range_m" in no_return:
        return f">= {no_return['range_m']:.2f} m ({no_return.get('rule', '?')})"
    return "-" if no_return is None else str(no_return)


def run_demo(
    out: Path = Path("out/demo"),
    seed: int = 0,
    overwrite: bool = False,
    progress: Progress | None = None,
    scheduler: str | None = None,
) -> dict[str, Any]:
    """Simulate the ``loop`` world into ``OUT/input/loop.mcap`` and run the full pipeline into ``OUT/run``."""
    from datasets.simulation import simulate

    out = Path(out)
    run_dir = out / "run"
    bag = out / "input" / f"loop-seed{seed}.mcap"
    check_output_dir(run_dir, overwrite, reads=[bag])
    if not bag.exists():
        bag.parent.mkdir(parents=True, exist_ok=True)
        simulate("loop", bag, seed=seed)
    config = load_config(overrides={"scale": {"scheduler": scheduler}})
    return run_pipeline(bag, run_dir, config, overwrite=overwrite, progress=progress)
