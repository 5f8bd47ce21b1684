"""``remap RUN_DIR``: new maps from a run folder with other poses, without the bag (SPEC section 3).

Inputs come from the run folder: the scans (``scans.npz``), the configuration, the learnt GP parameters
(``maps/params.json``), the trajectory (``trajectory/optimized.tum``) and the covariances
(``trajectory/covariances.npz``). ``--poses`` replaces the trajectory:

- a TUM file gives a pose per stamp; scans take the pose at their stamp (interpolated between stamps; a scan
  outside the file's time span is an error);
- a g2o file gives the keyframe poses of the run's pose graph (vertex ``k`` is keyframe ``k``, as in
  ``trajectory/pose_graph.g2o``, also after a round trip through GTSAM's ``readG2o`` / ``writeG2o``); scans
  between keyframes keep their offset from their keyframe in the run's optimised trajectory.

``--covariances`` replaces the covariances GPPOL maps with (``mapping.gppol.pose_covariances``: the
per-scan ``scan_relative_after`` arrays, else the world-frame ``scan_after`` or keyframe ``after`` ones, see
:mod:`pipeline.artifacts`). The scans mapped are those the run mapped (selected by motion along the run's
odometry trajectory, as ``run`` selects them).

Only what changed is recomputed (:class:`mapping.tiling.IncrementalMap`): when the grid (bounds,
resolution), the mapping settings and the tile size are the run's, the run's ``after`` map is taken as it is
and only the tiles that a moved beam (or, for GPPOL, a beam whose scan covariance changed) can reach are
rendered again. The result is a full rendering, bit for bit, of beams each within ``scale.pose_tolerance_m``
(default 1 um: text round trips of poses are not exact) of the new ones; with tolerances of 0 it equals a full
rendering of the new beams bit for bit. ``summary.json["tiles"]`` reports the
fraction of tiles recomputed. Otherwise (``--recompute``, other bounds, resolution or settings) every tile
is rendered.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

import numpy as np

from datasets.progress import StageTimer
from datasets.types import Trajectory
from mapping.build import Bounds, MapBuilder
from mapping.exports import read_layers_npz
from mapping.gppol import RigidGroups
from mapping.placement import with_placement
from mapping.train import GPParams, ParamsFileError
from pipeline.artifacts import (
    COVARIANCES_NPZ,
    ODOMETRY_TUM,
    OPTIMIZED_TUM,
    SCANS_FILE,
    TRAJECTORY_DIR,
    covariances_at,
    read_keyframe_indices,
    read_mapper_covariances,
    read_rigid_groups,
    read_scan_covariances,
    read_scans,
)
from pipeline.config import load_config, write_config
from pipeline.errors import PipelineError, stage_boundary
from pipeline.map_bounds import check_map_cells, parse_numbers
from pipeline.map_exports import write_maps
from pipeline.progress import Progress
from pipeline.report import write_report
from pipeline.run_folder import (
    SUMMARY_NAME,
    check_output_dir,
    params_path,
    read_summary,
    staged_run_folder,
    write_summary,
)
from pipeline.scale import engine_name, tile_engine
from slam.keyframes import scan_poses_from_keyframes
from slam.trajectory_io import read_g2o, read_tum, write_tum

MAP_NAME = "remap"


def parse_bounds(text: str | None) -> Bounds | None:
    """``"XMIN,YMIN,XMAX,YMAX"`` in metres (None passes through); PipelineError if malformed."""
    if text is None:
        return None
    values = parse_numbers(text, 4)
    if values is None or not (values[2] > values[0] and values[3] > values[1]):
        raise PipelineError(
            f"--bounds must be XMIN,YMIN,XMAX,YMAX with XMAX > XMIN and YMAX > YMIN, got {text!r}"
        )
    return values[0], values[1], values[2], values[3]


def stored_bounds(summary: Any, run_dir: Path) -> Bounds:
    """The map bounds ``map.bounds_xy_m`` of a run's summary, checked (a PipelineError names the file)."""
    where = f"{Path(run_dir) / SUMMARY_NAME}"
    try:
        values = [float(v) for v in summary["map"]["bounds_xy_m"]]
    except (TypeError, KeyError, ValueError, IndexError):
        raise PipelineError(
            f"{where}: no map bounds (map.bounds_xy_m): damaged, or not a run folder"
        ) from None
    if len(values) != 4 or not np.isfinite(values).all() or values[2] <= values[0] or values[3] <= values[1]:
        raise PipelineError(f"{where}: map.bounds_xy_m is not XMIN, YMIN, XMAX, YMAX: {values}")
    return values[0], values[1], values[2], values[3]


def poses_from_tum(path: Path, scan_stamps_ns: np.ndarray) -> np.ndarray:
    """(N, 3) base poses of the scans from a TUM file (exact at equal stamps, interpolated between)."""
    stamps, poses = read_tum(path)
    if len(stamps) == 0:
        raise PipelineError(f"{path}: no poses")
    if np.array_equal(stamps, scan_stamps_ns):
        return poses
    order = np.argsort(stamps, kind="stable")
    stamps, poses = stamps[order], poses[order]
    outside = (scan_stamps_ns < stamps[0]) | (scan_stamps_ns > stamps[-1])
    if outside.any():
        raise PipelineError(
            f"{path}: {int(outside.sum())} scans lie outside the trajectory's time span "
            f"({stamps[0]} .. {stamps[-1]} ns)"
        )
    return Trajectory(stamps, poses).interpolate(scan_stamps_ns)


def poses_from_g2o(path: Path, run_poses: np.ndarray, keyframe_scans: np.ndarray) -> np.ndarray:
    """(N, 3) base poses of the scans from a g2o graph of the run's keyframes (see the module docstring)."""
    graph = read_g2o(path)
    k = len(keyframe_scans)
    if len(graph.vertices_xytheta) != k:
        raise PipelineError(
            f"{path}: {len(graph.vertices_xytheta)} vertices, but the run's pose graph has {k} keyframes"
        )
    order = np.argsort(graph.ids, kind="stable")
    if not np.array_equal(graph.ids[order], np.arange(k)):
        raise PipelineError(f"{path}: vertex ids must be 0..{k - 1} (the run's keyframes)")
    return scan_poses_from_keyframes(graph.vertices_xytheta[order], keyframe_scans, run_poses)


def default_remap_dir(run_dir: Path) -> Path:
    """Where ``remap`` writes when no ``--out`` is given: ``RUN_DIR/remap``."""
    return Path(run_dir) / "remap"


def remap_run(
    run_dir: Path,
    poses: Path | None = None,
    covariances: Path | None = None,
    resolution_m: float | None = None,
    bounds: str | None = None,
    out_dir: Path | None = None,
    overwrite: bool = False,
    recompute: bool = False,
    progress: Progress | None = None,
    scheduler: str | None = None,
) -> dict[str, Any]:
    """Render a new map from the run folder ``run_dir``; writes ``out_dir`` (default ``RUN_DIR/remap``).

    ``recompute`` renders every tile (instead of updating the run's ``after`` map where poses changed);
    ``scheduler``: where tiles are rendered (``"local"``, a Dask address; default: the configuration).
    """
    progress = progress or Progress()
    timer = StageTimer()
    run_dir = Path(run_dir)
    run_bounds = stored_bounds(read_summary(run_dir), run_dir)
    out_dir = Path(out_dir) if out_dir is not None else default_remap_dir(run_dir)
    reads = [run_dir, poses, covariances]
    check_output_dir(out_dir, overwrite, reads=reads)
    overrides = {"mapping": {"resolution_m": resolution_m}, "scale": {"scheduler": scheduler}}
    config = load_config(run_dir / "config.yaml", overrides)
    cfg = config.mapping
    map_bounds = parse_bounds(bounds) or run_bounds
    given = [f"--resolution {cfg.resolution_m:g}"] if resolution_m is not None else []
    given += [f"--bounds {bounds}"] if bounds is not None else []
    what = f"{run_dir}: the remap" + (f" with {' and '.join(given)}" if given else "")
    check_map_cells(map_bounds, cfg.resolution_m, config.scale.max_map_cells, what)
    with timer("read"), stage_boundary("reading", run_dir):
        stored = read_scans(run_dir / SCANS_FILE)
        scans = stored.scans
        traj_dir = run_dir / TRAJECTORY_DIR
        run_stamps, run_poses = read_tum(traj_dir / OPTIMIZED_TUM)
        if not np.array_equal(run_stamps, scans.stamps_ns):
            raise PipelineError(f"{traj_dir / OPTIMIZED_TUM}: its stamps are not those of {SCANS_FILE}")
        odo_stamps, odo_poses = read_tum(traj_dir / ODOMETRY_TUM)
        if not np.array_equal(odo_stamps, scans.stamps_ns):
            raise PipelineError(f"{traj_dir / ODOMETRY_TUM}: its stamps are not those of {SCANS_FILE}")
        if poses is None:
            new_poses = run_poses
        elif Path(poses).suffix.lower() == ".g2o":
            keyframes = read_keyframe_indices(traj_dir / COVARIANCES_NPZ)
            if keyframes.max() >= len(scans):
                raise PipelineError(
                    f"{traj_dir / COVARIANCES_NPZ}: keyframe indices beyond the {len(scans)} scans"
                )
            new_poses = poses_from_g2o(Path(poses), run_poses, keyframes)
        elif Path(poses).suffix.lower() == ".tum":
            new_poses = poses_from_tum(Path(poses), scans.stamps_ns)
        else:
            raise PipelineError(f"{poses}: --poses must be a .g2o or a .tum file")
        cov_file = Path(covariances) if covariances is not None else traj_dir / COVARIANCES_NPZ
        mode = cfg.gppol.pose_covariances
        new_cov = run_cov = None
        # the scans GPPOL treats as sharing one pose error: the keyframes of the covariances' run
        new_groups = run_groups = None
        world_cov = None  # the placement layer's (mapping.placement): none without a covariance file
        if mode != "none" or cov_file.is_file():
            world_stamps, world_cov = read_scan_covariances(cov_file, "after")
            world_cov = covariances_at(scans.stamps_ns, world_stamps, world_cov)
        if mode != "none":
            cov_stamps, cov = read_mapper_covariances(cov_file, "after", mode)
            new_cov = covariances_at(scans.stamps_ns, cov_stamps, cov)
            _, run_cov = read_mapper_covariances(traj_dir / COVARIANCES_NPZ, "after", mode)
            new_groups = read_rigid_groups(cov_file, len(scans), cfg.gppol.rigid_groups)
            run_groups = read_rigid_groups(traj_dir / COVARIANCES_NPZ, len(scans), cfg.gppol.rigid_groups)
        try:
            params = GPParams.load(params_path(run_dir / "maps"))
        except (OSError, ParamsFileError) as exc:
            raise PipelineError(f"{run_dir}: cannot read the learnt GP parameters ({exc})") from None
    run_config = load_config(run_dir / "config.yaml")
    # the run's after map can be updated in place when it lies on the same tiles with the same settings
    incremental = (
        not recompute
        and tuple(map_bounds) == run_bounds
        and cfg == run_config.mapping
        and config.export.unknown_variance_fraction == run_config.export.unknown_variance_fraction
        and config.scale.tile_cells == run_config.scale.tile_cells
        and RigidGroups.equal(new_groups, run_groups)
    )
    laser = stored.laser_in_base_xytheta
    builder = MapBuilder.from_config(cfg, None, config.export.unknown_variance_fraction)
    selected = builder.select_scans(odo_poses, laser)
    with (
        stage_boundary("writing", out_dir, name_known_errors=False),
        staged_run_folder(out_dir, overwrite, reads) as stage,
    ):
        write_config(config, stage / "config.yaml")
        (stage / TRAJECTORY_DIR).mkdir()
        write_tum(stage / TRAJECTORY_DIR / "remap.tum", scans.stamps_ns, new_poses)
        new_beams = builder.beams(scans, new_poses, laser, selected)
        sc = config.scale
        with timer(f"map_{MAP_NAME}"), stage_boundary("mapping", run_dir), tile_engine(sc) as renderer:
            if incremental:
                run_layers = read_layers_npz(run_dir / "maps" / "after" / "layers.npz")
                run_beams = builder.beams(scans, run_poses, laser, selected)
                gp = builder.tiled_map(
                    run_beams,
                    params,
                    map_bounds,
                    sc.tile_cells,
                    run_cov,
                    renderer,
                    layers=run_layers,
                    rigid_groups=run_groups,
                )
                with progress.stage("remap tiles", total=None) as bar:
                    report = gp.update_poses(
                        new_beams,
                        new_cov,
                        sc.pose_tolerance_m,
                        sc.covariance_tolerance,
                        on_tile=lambda _r: bar.advance(),
                    )
            else:
                gp = builder.tiled_map(
                    new_beams, params, map_bounds, sc.tile_cells, new_cov, renderer, rigid_groups=new_groups
                )
                with progress.stage("remap tiles", total=len(gp.grid)) as bar:
                    report = gp.render_all(on_tile=lambda _r: bar.advance())
        layers = {MAP_NAME: with_placement(gp.layers(), new_beams, world_cov)}
        (stage / "maps").mkdir()
        shutil.copyfile(params_path(run_dir / "maps"), params_path(stage / "maps"))
        with timer("export"):
            write_maps(
                stage / "maps",
                layers,
                {MAP_NAME: Trajectory(scans.stamps_ns, new_poses, "map")},
                None,
                cfg,
                config.export,
                int(scans.stamps_ns[-1]),
                params,
            )
        m = layers[MAP_NAME]
        summary = {
            "run_dir": str(run_dir),
            "poses": str(poses) if poses is not None else str(traj_dir / OPTIMIZED_TUM),
            "covariances": str(cov_file),
            "recomputed": report.tiles_recomputed > 0,
            "tiles": {
                **report.to_dict(),
                "tile_cells": sc.tile_cells,
                "incremental": incremental,
                "pose_tolerance_m": sc.pose_tolerance_m,
                "covariance_tolerance": sc.covariance_tolerance,
                "engine": engine_name(sc),
            },
            "mapper": cfg.mapper,
            "counts": {"scans": len(scans), "beams": int(scans.beam_counts().sum())},
            "map": {
                "resolution_m": m.resolution_m,
                "origin_xy_m": list(m.origin_xy_m),
                "shape_hw": list(m.shape),
                "bounds_xy_m": list(map_bounds),
            },
            "timings_s": {**timer.seconds, "total": timer.total()},
            "cpu_s": timer.cpu_summary(),
        }
        summary["table"] = {
            "run": str(run_dir),
            "poses": summary["poses"],
            "tiles recomputed": f"{report.tiles_recomputed} of {report.tiles_total}"
            + (" (the run's map updated where poses changed)" if incremental else " (full rendering)"),
            "map": f"{m.shape[1]} x {m.shape[0]} cells at {m.resolution_m} m ({cfg.mapper})",
            "wall time (s)": round(timer.total(), 2),
        }
        if config.export.png:
            write_report(stage, summary, maps=layers)
        write_summary(stage, summary)
    return summary
