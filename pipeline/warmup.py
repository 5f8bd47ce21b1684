"""``python -m pipeline.warmup``: fill numba's on-disk cache for every compiled function a run uses.

Numba compiles a function on its first call, once per type signature, and with ``cache=True`` stores the
machine code in the ``__pycache__`` folder beside the module, where later interpreters load it. Without this
warm-up the first run after an install compiles the SLAM, training and mapping cores itself; ``make env``
runs this module once after each install and after each edit of the packages' sources, so that a user's
first ``make demo`` starts warm. Numba keys its cache on the content of each module's source, so a re-run
over unchanged compiled modules only loads them.

A cached function is found again only for the argument types it was compiled for, so the warm-up runs the
real code: :func:`pipeline.run.run_pipeline` with the default configuration (both maps, every export) on a
short recording written as a bag, read back and scored against its ground truth, as ``run.py demo`` does.
The recording is the start of the demo's ``loop`` world driven there and back (:func:`there_and_back`): the
way back passes the start after more than the loop closure's minimum separation, so that loop closure
searches too. A few paths only real recordings take (long-range scans, big maps' figures) are run on small
inputs afterwards (:func:`warm_other_paths`).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from datasets.types import Recording, ScanSequence, Trajectory

#: Scans of the way out (0.5 m apart in the ``loop`` world): 24 m, more than the default loop closure's
#: ``min_separation_m`` (20 m) between the start and the end of the way back.
WARMUP_SCANS = 48
#: Cell size of the ground-truth raster the maps are scored against (coarse: its only use here is to run
#: the scoring code).
GROUND_TRUTH_RESOLUTION_M = 0.5


def _mirrored(traj: Trajectory, turn_ns: int) -> Trajectory:
    """``traj`` up to ``turn_ns`` (its pose there interpolated), then the same poses again in reverse order,
    stamped ``2 turn_ns - t``."""
    before = traj.stamps_ns < turn_ns
    stamps = traj.stamps_ns[before]
    poses = traj.poses_xytheta[before]
    return Trajectory(
        np.concatenate([stamps, [turn_ns], 2 * turn_ns - stamps[::-1]]),
        np.concatenate([poses, traj.interpolate(np.array([turn_ns])), poses[::-1]]),
        traj.frame_id,
    )


def there_and_back(rec: Recording, n_scans: int) -> Recording:
    """The first ``n_scans`` scans of ``rec`` followed by the same scans in reverse order: the robot drives
    out and backs up along the same path to its start (every stream mirrored in time about the last scan
    of the way out; odometry and reference poses likewise)."""
    total = 0 if rec.scans is None else len(rec.scans)
    if rec.scans is None or not 2 <= n_scans <= total:
        raise ValueError(f"there_and_back: {n_scans} scans out of {total}")
    turn_ns = int(rec.scans.stamps_ns[n_scans - 1])
    order = np.concatenate([np.arange(n_scans), np.arange(n_scans - 2, -1, -1)])
    out = rec.scans.subset(order)
    stamps = np.where(np.arange(len(order)) < n_scans, out.stamps_ns, 2 * turn_ns - out.stamps_ns)
    scans = ScanSequence(
        out.ranges_m,
        out.angles_rad,
        stamps,
        out.range_min_m,
        out.range_max_m,
        out.frame_ids,
        out.source_index,
        out.sources,
    )
    reference = None
    if rec.reference is not None:
        ref = rec.reference
        reference = Trajectory(scans.stamps_ns, ref.poses_xytheta[order], ref.frame_id)
    return Recording(
        source=rec.source,
        format=rec.format,
        scans=scans,
        odometry=None if rec.odometry is None else _mirrored(rec.odometry, turn_ns),
        scan_poses=None,
        reference=reference,
        laser_in_base_xytheta=rec.laser_in_base_xytheta.copy(),
        meta=dict(rec.meta),
    )


def write_warmup_bag(bag: Path, n_scans: int = WARMUP_SCANS, seed: int = 0) -> Path:
    """Simulate the ``loop`` world, write :func:`there_and_back` of its first ``n_scans`` scans to ``bag``
    (ROS 2 ``.mcap``) and its ground truth beside it (``bag.gt.npz``, where the pipeline looks for it)."""
    from datasets.rosbag import write_recording
    from datasets.simulation import ground_truth_path, make_world, save_ground_truth

    run = make_world("loop", seed=seed, resolution_m=GROUND_TRUTH_RESOLUTION_M)
    write_recording(there_and_back(run.recording, n_scans), bag)
    save_ground_truth(run.ground_truth, ground_truth_path(bag))
    return bag


def warm_other_paths() -> None:
    """Compile (or load) the signatures that real recordings reach and the short simulated run does not,
    through the same calls: the odometry's exhaustive correlative search (a wheel-seeded window of a few
    cells), a submap reset that empties only the cells around far-spread points (long-range scans), and a
    big map's figure (pasted at one pixel per cell, whose pixels are strided views)."""
    from mapping.exports import MapLayers
    from mapping.figures import layer_figure, save_figure
    from slam.odometry import search_window
    from slam.scan_matching import PointGrid

    grid = PointGrid.around(np.zeros(2), 60.0)
    points = np.array([[-55.0, 0.0], [55.0, 1.0], [0.0, 55.0]])
    grid.insert(points, np.tile([0.0, 1.0], (3, 1)))
    search_window(grid, points, np.array([0.05, 0.0, 0.01]), 0.1, 0.05, 0.004)
    grid.reset(np.full(2, -60.0))
    cells = np.zeros((1200, 2000), dtype=np.float32)
    with tempfile.TemporaryDirectory(prefix="gpom-warmup-") as tmp:
        save_figure(
            layer_figure(MapLayers(cells, cells, cells, 0.1, (0.0, 0.0)), "probability"), Path(tmp) / "m.png"
        )


def warm_up(work_dir: Path | None = None, n_scans: int = WARMUP_SCANS) -> dict[str, Any]:
    """Run the full pipeline (default configuration) on the warm-up recording in ``work_dir`` (default: a
    temporary folder, removed afterwards; a given one keeps ``warmup.mcap`` and the run folder ``run``,
    both replaced if there); returns the run's summary."""
    from datasets.simulation import ground_truth_path
    from pipeline.progress import Progress
    from pipeline.run import run_pipeline

    with tempfile.TemporaryDirectory(prefix="gpom-warmup-") as tmp:
        folder = Path(work_dir) if work_dir is not None else Path(tmp)
        folder.mkdir(parents=True, exist_ok=True)
        bag = folder / "warmup.mcap"
        for old in (bag, ground_truth_path(bag)):
            old.unlink(missing_ok=True)
        write_warmup_bag(bag, n_scans)
        summary = run_pipeline(bag, folder / "run", overwrite=True, progress=Progress())
    warm_other_paths()
    return summary


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m pipeline.warmup", description="Compile numba's cache: the pipeline on a short run."
    )
    parser.add_argument("--scans", type=int, default=WARMUP_SCANS, help="scans of the way out")
    parser.add_argument("--out", type=Path, help="keep the recording and the run here (default: discarded)")
    args = parser.parse_args(argv)
    t0 = time.perf_counter()
    summary = warm_up(args.out, args.scans)
    print(
        f"numba cache warm: pipeline on {summary['counts']['scans']} simulated scans "
        f"in {time.perf_counter() - t0:.0f} s",
        file=sys.stderr,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
