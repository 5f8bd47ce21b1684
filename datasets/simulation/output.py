"""``simulate``: write a simulated run as a bag plus its ground truth (``PATH.gt.npz``, ``PATH.gt.png``)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from datasets.errors import DatasetError
from datasets.simulation.raster import (
    PNG_SUFFIX,
    ground_truth_path,
    save_ground_truth,
    save_ground_truth_png,
)
from datasets.simulation.scenarios import make_world


def _partial(path: Path) -> Path:
    return path.with_name(f".{path.name}.partial-{os.getpid()}")


def simulate(world: str, out: str | Path, seed: int = 0, progress: Any = None) -> dict[str, Any]:
    """Simulate ``world`` and write it to the bag ``out`` (``.bag`` ROS1; ``.mcap`` or a folder ROS2) with
    ``out.gt.npz`` and ``out.gt.png`` beside it.

    Refuses (DatasetError, nothing written) when any of the three outputs exists. Returns a small report:
    ``world``, ``seed``, ``scans``, ``odometry`` (messages), ``ground_truth_poses``, ``area_m2``, ``raster``.
    """
    out = Path(out)
    gt_path = ground_truth_path(out)
    png_path = out.with_name(out.name + PNG_SUFFIX)
    for p in (out, gt_path, png_path):
        if p.exists():
            raise DatasetError(f"{p}: already exists; will not overwrite it")
    if not out.parent.is_dir():
        raise DatasetError(f"{out.parent}: no such output directory")
    from datasets.rosbag import check_output_path, write_recording

    check_output_path(out)  # (the bag's name and a writable folder, before the world is made)
    run = make_world(world, seed)

    write_recording(run.recording, out, progress=progress)
    try:
        for final, write in ((gt_path, save_ground_truth), (png_path, save_ground_truth_png)):
            tmp = _partial(final)
            try:
                write(run.ground_truth, tmp)
                tmp.rename(final)
            finally:
                tmp.unlink(missing_ok=True)
    except BaseException:
        # a bag without its ground truth would look complete: remove what this call wrote
        _remove(out)
        gt_path.unlink(missing_ok=True)
        raise
    gt = run.ground_truth
    h, w = gt.occupancy.shape
    scans = run.recording.scans
    return {
        "world": world,
        "seed": seed,
        "scans": len(scans) if scans is not None else 0,
        "odometry": run.odometry_messages(),
        "ground_truth_poses": len(run.true_poses),
        "area_m2": round(run.world.area_m2, 1),
        "raster": f"{h}x{w} cells of {gt.resolution_m:g} m",
    }


def _remove(path: Path) -> None:
    import shutil

    if path.is_dir():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)
