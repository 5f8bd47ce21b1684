"""A Rerun recording (``.rrd``) of a finished run folder, to look at a run in the Rerun viewer.

Everything comes from the run folder alone (SPEC section 4), so any old run can be viewed:

- ``world/scan``: the valid returns of each scan, in the world frame at the scan's pose after loop closure
  (``trajectory/optimized.tum``, and the laser mounting of ``scans.npz``), one frame per scan on the
  timelines ``stamp`` (the scan stamps) and ``scan`` (the scan index);
- ``world/pose`` and ``world/pose/covariance``: the current base pose (an arrow along its heading) and the
  2-sigma ellipse of its (x, y) covariance after loop closure, on the same timelines;
- ``world/trajectories/{odometry,optimized,...}``: every TUM file of ``trajectory/`` as one line strip;
- ``world/covariances``: the 2-sigma (x, y) ellipses of every ``ellipse_every``-th scan after loop closure;
- ``world/loop_closures``: one segment per accepted loop closure of ``summary.json``, between the positions
  of its two scans on the optimised trajectory;
- ``world/maps/{before,after,...}/occupancy`` and ``.../variance``: each map of ``maps/*/layers.npz`` as a
  Rerun ``GridMap`` in the world frame: p(occupied) as 0..100 (``round(100 p)``, unknown where the exports
  call a cell unknown or p is NaN; RViz's map colours) and the GP variance (float, viridis);
- ``summary``: the run's summary table as text.

Maps are drawn on Rerun's 3D view, whose ``GridMap`` is made for occupancy maps; the vector data lie in the
plane z = 0 and the maps just below it (``MAP_Z_M``), so that the maps never hide them. The blueprint gives
one top-down tab per map layer and the summary beside them.

A remap folder (``remap RUN_DIR``) holds no scans: they are read from its source run (``run_dir`` of its
summary) when that folder is still there, and left out otherwise (the summary text says so).
"""

from __future__ import annotations

import math
import os
import select
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from datasets import se2
from datasets.errors import GpomError, first_line
from datasets.files import atomic_output
from datasets.types import Trajectory
from mapping.exports import MapLayers, read_layers_npz
from pipeline.artifacts import (
    COVARIANCES_NPZ,
    OPTIMIZED_TUM,
    SCANS_FILE,
    TRAJECTORY_DIR,
    StoredScans,
    covariances_at,
    read_scan_covariances,
    read_scans,
)
from pipeline.errors import PipelineError
from pipeline.run_folder import read_summary, writable_ancestor
from slam.trajectory_io import read_tum

APPLICATION_ID = "gpom"
TIMELINE_STAMP = "stamp"
TIMELINE_SCAN = "scan"
ELLIPSE_SIGMA = 2.0
ELLIPSE_VERTICES = 48
#: The longest wait for the recording to reach its file (s); a stalled writer is then an error, not a hang.
RERUN_FLUSH_TIMEOUT_S = 120.0
#: How long a child that reported its recording may take to exit before it is killed (s).
CHILD_EXIT_S = 30.0
#: The child's line for a complete recording.
RECORDED = "recorded"
#: The prefix of the child's line for a run folder file it could not read (the error's message follows).
UNREADABLE = "unreadable: "
#: A disk with less than this free is full (bytes): a write that failed or stalled there failed for room.
FULL_DISK_BYTES = 2**20
#: A recording whose file has not grown for STALL_S (s) on a full disk has stalled: given up without
#: waiting for the flush timeout.
STALL_S = 10.0
MAX_STATIC_ELLIPSES = 150
MAP_Z_M = -0.05
#: Stamps from 2001-09-09 on are read as Unix time (a timestamp timeline), earlier ones as time since an
#: arbitrary start (a duration timeline): simulated or re-stamped logs often start at zero.
UNIX_STAMP_MIN_NS = 10**18
UNKNOWN_U8 = 255  # int8 -1 of a nav_msgs/OccupancyGrid, as RViz's map colours read it

TRAJECTORY_COLORS = {
    "odometry": (230, 140, 30),
    "optimized": (40, 110, 230),
    "remap": (40, 170, 80),
}
SCAN_COLOR = (220, 40, 40)
POSE_COLOR = (20, 20, 20)
COVARIANCE_COLOR = (150, 60, 200)
CLOSURE_COLOR = (0, 190, 190)


@dataclass(frozen=True)
class RunView:
    """What a run folder holds for the viewer, read and checked; poses (N, 3) x, y (m), theta (rad)."""

    run_dir: Path
    summary: dict[str, Any]
    stamps_ns: NDArray[np.int64]
    scan_poses_xytheta: NDArray[np.float64]
    trajectories: dict[str, tuple[NDArray[np.int64], NDArray[np.float64]]]
    scans: StoredScans | None
    cov_xytheta: NDArray[np.float64] | None
    closures_xy_m: NDArray[np.float64]
    maps: dict[str, MapLayers]
    notes: list[str] = field(default_factory=list)


def covariance_ellipses_xy(
    centers_xy_m: NDArray,
    cov_xytheta: NDArray,
    sigma: float = ELLIPSE_SIGMA,
    vertices: int = ELLIPSE_VERTICES,
) -> NDArray[np.float64]:
    """(N, vertices + 1, 2) closed outlines of the ``sigma`` ellipses of the (x, y) block of (N, 3, 3)
    world-frame covariances (m^2) around (N, 2) centres (m); the first vertex is repeated at the end."""
    centers = np.asarray(centers_xy_m, dtype=np.float64).reshape(-1, 2)
    cov = np.asarray(cov_xytheta, dtype=np.float64)[:, :2, :2]
    cov = 0.5 * (cov + np.swapaxes(cov, 1, 2))
    eigval, eigvec = np.linalg.eigh(cov)  # (N, 2), (N, 2, 2) columns are the axes
    half_axes_m = sigma * np.sqrt(np.clip(eigval, 0.0, None))
    t = np.linspace(0.0, 2.0 * np.pi, vertices + 1)
    t[-1] = 0.0  # closed exactly
    unit = np.stack([np.cos(t), np.sin(t)], axis=1)  # (V+1, 2)
    local = unit[None, :, :] * half_axes_m[:, None, :]  # (N, V+1, 2) along the axes
    return centers[:, None, :] + np.einsum("nij,nvj->nvi", eigvec, local)


def scan_points_world(scans: StoredScans, base_poses_xytheta: NDArray) -> list[NDArray[np.float64]]:
    """Per scan, the (P_i, 2) world positions (m) of its valid returns seen from its base pose (N, 3).

    A return is valid when finite, at least the scan's ``range_min`` and below its ``range_max`` (no-return
    beams carry no end point, SPEC section 2); the laser sits at ``scans.laser_in_base_xytheta`` on the base.
    """
    seq = scans.scans
    n = len(seq)
    if n == 0:
        return []
    counts = seq.beam_counts()
    ranges_m = np.concatenate(seq.ranges_m).astype(np.float64)
    angles_rad = np.concatenate(seq.angles_rad).astype(np.float64)
    scan_of_beam = np.repeat(np.arange(n), counts)
    with np.errstate(invalid="ignore"):
        valid = (
            np.isfinite(ranges_m)
            & (ranges_m >= seq.range_min_m[scan_of_beam])
            & (ranges_m < seq.range_max_m[scan_of_beam])
        )
    laser_poses = se2.compose(np.asarray(base_poses_xytheta, np.float64), scans.laser_in_base_xytheta)
    r, a, idx = ranges_m[valid], angles_rad[valid], scan_of_beam[valid]
    points_laser = np.stack([r * np.cos(a), r * np.sin(a)], axis=1)
    points_world = se2.transform_points(laser_poses[idx], points_laser)
    return np.split(points_world, np.cumsum(np.bincount(idx, minlength=n))[:-1])


def occupancy_u8(probability: NDArray, unknown: NDArray | None = None) -> NDArray[np.uint8]:
    """(H, W) p(occupied) as ``nav_msgs/OccupancyGrid``-style unsigned bytes for RViz's colours:
    ``round(100 p)`` in 0..100, 255 (int8 -1, unknown) where p is not finite or ``unknown`` (H, W) bool is
    set (the exports' classification: :attr:`mapping.exports.MapLayers.unknown`)."""
    p = np.asarray(probability, dtype=np.float64)
    out = np.full(p.shape, UNKNOWN_U8, dtype=np.uint8)
    ok = np.isfinite(p)
    if unknown is not None:
        ok &= ~np.asarray(unknown, dtype=bool)
    out[ok] = np.clip(np.round(100.0 * p[ok]), 0, 100).astype(np.uint8)
    return out


def check_run_folder(run_dir: Path) -> dict[str, Any]:
    """The summary of the complete run (or remap) folder ``run_dir``, checked to hold trajectories, without
    reading the rest; PipelineError if it is not one."""
    run_dir = Path(run_dir)
    summary = read_summary(run_dir)
    if not any((run_dir / TRAJECTORY_DIR).glob("*.tum")):
        raise PipelineError(f"{run_dir}: not a complete run folder (no trajectory/*.tum)")
    return summary


def read_run_view(run_dir: Path) -> RunView:
    """Read what :func:`write_rerun` shows from a complete run (or remap) folder; PipelineError if the folder
    is not one or a file in it is damaged."""
    run_dir = Path(run_dir)
    summary = check_run_folder(run_dir)
    notes: list[str] = []
    traj_dir = run_dir / TRAJECTORY_DIR
    trajectories: dict[str, tuple[NDArray[np.int64], NDArray[np.float64]]] = {}
    for path in sorted(traj_dir.glob("*.tum")):
        try:
            trajectories[path.stem] = read_tum(path)
        except GpomError as exc:
            raise PipelineError(str(exc) if str(path) in str(exc) else f"{path}: {exc}") from None
    main_name = (
        Path(OPTIMIZED_TUM).stem if Path(OPTIMIZED_TUM).stem in trajectories else next(iter(trajectories))
    )
    main_stamps, main_poses = trajectories[main_name]

    scans = _find_scans(run_dir, summary, notes)
    if scans is not None:
        stamps = scans.scans.stamps_ns
        scan_poses = _poses_at(stamps, main_stamps, main_poses, traj_dir / f"{main_name}.tum")
    else:
        stamps, scan_poses = main_stamps, main_poses

    cov = _find_covariances(run_dir, summary, stamps, notes)
    closures = _closure_segments(summary, scan_poses, run_dir) if scans is not None else np.zeros((0, 2, 2))
    maps: dict[str, MapLayers] = {}
    for path in sorted((run_dir / "maps").glob("*/layers.npz")):
        try:
            maps[path.parent.name] = read_layers_npz(path)
        except GpomError as exc:
            raise PipelineError(str(exc)) from None
    return RunView(run_dir, summary, stamps, scan_poses, trajectories, scans, cov, closures, maps, notes)


def _poses_at(
    stamps_ns: NDArray[np.int64], tum_stamps_ns: NDArray[np.int64], tum_poses: NDArray, path: Path
) -> NDArray[np.float64]:
    """(N, 3) poses of a TUM trajectory at the scan stamps: exact at equal stamps, interpolated between (as
    ``remap --poses`` reads a TUM file); PipelineError for scans outside the trajectory's time span."""
    if np.array_equal(tum_stamps_ns, stamps_ns):
        return np.asarray(tum_poses, np.float64)
    order = np.argsort(tum_stamps_ns, kind="stable")
    traj = Trajectory(np.asarray(tum_stamps_ns, np.int64)[order], np.asarray(tum_poses, np.float64)[order])
    outside = (stamps_ns < traj.stamps_ns[0]) | (stamps_ns > traj.stamps_ns[-1])
    if outside.any():
        raise PipelineError(f"{path}: {int(outside.sum())} scans lie outside the trajectory's time span")
    return traj.interpolate(stamps_ns)


def _find_scans(run_dir: Path, summary: dict[str, Any], notes: list[str]) -> StoredScans | None:
    """The run's ``scans.npz``, or for a remap folder its source run's (None when that is gone)."""
    if (run_dir / SCANS_FILE).is_file():
        return read_scans(run_dir / SCANS_FILE)
    source = summary.get("run_dir")
    if isinstance(source, str):
        for candidate in (Path(source), run_dir.parent / Path(source).name):
            if (candidate / SCANS_FILE).is_file():
                notes.append(f"scans from {candidate / SCANS_FILE}")
                return read_scans(candidate / SCANS_FILE)
        notes.append(f"no scans: the source run {source} is not there")
        return None
    raise PipelineError(f"{run_dir}: not a complete run folder (no {SCANS_FILE})")


def _find_covariances(
    run_dir: Path, summary: dict[str, Any], stamps_ns: NDArray[np.int64], notes: list[str]
) -> NDArray[np.float64] | None:
    """(N, 3, 3) world-frame covariances after loop closure at ``stamps_ns``, or None when there are none."""
    candidates = [run_dir / TRAJECTORY_DIR / COVARIANCES_NPZ]
    if isinstance(summary.get("covariances"), str):
        candidates.append(Path(summary["covariances"]))
    for path in candidates:
        if path.is_file():
            try:
                cov_stamps, cov = read_scan_covariances(path, "after")
                return covariances_at(stamps_ns, cov_stamps, cov)
            except GpomError as exc:
                raise PipelineError(str(exc) if str(path) in str(exc) else f"{path}: {exc}") from None
    notes.append("no pose covariances")
    return None


def _closure_segments(summary: dict[str, Any], poses_xytheta: NDArray, run_dir: Path) -> NDArray[np.float64]:
    """(C, 2, 2) positions (m) of the two scans of every loop closure listed in the summary."""
    closures = summary.get("loop_closures") or []
    n = len(poses_xytheta)
    try:
        pairs = np.array([[int(c["query_scan"]), int(c["target_scan"])] for c in closures], dtype=np.int64)
    except (TypeError, KeyError, ValueError):
        raise PipelineError(
            f"{run_dir}/summary.json: loop_closures are not query_scan / target_scan pairs"
        ) from None
    pairs = pairs.reshape(-1, 2)
    if ((pairs < 0) | (pairs >= n)).any():
        raise PipelineError(f"{run_dir}/summary.json: a loop closure names a scan outside 0..{n - 1}")
    return np.asarray(poses_xytheta, np.float64)[pairs][:, :, :2]


def check_rerun_path(rrd_path: Path, overwrite: bool = False, reads: tuple[Path | None, ...] = ()) -> None:
    """Fail before any work if ``rrd_path`` cannot take a Rerun recording: its name must end in ``.rrd``, an
    existing file is replaced only with ``overwrite`` (and never one the command reads), and the nearest
    existing folder above it must be writable. PipelineError naming the path."""
    rrd_path = Path(rrd_path)
    if rrd_path.suffix != ".rrd":
        raise PipelineError(f"{rrd_path}: a Rerun recording must end in .rrd")
    if rrd_path.is_dir():
        raise PipelineError(f"{rrd_path}: is a folder, not a Rerun recording")
    if rrd_path.exists():
        if not overwrite:
            raise PipelineError(f"{rrd_path}: already exists (use --overwrite to replace it)")
        if any(read is not None and Path(read).resolve() == rrd_path.resolve() for read in reads):
            raise PipelineError(f"{rrd_path}: is what this command reads; --overwrite would replace it")
    writable_ancestor(rrd_path)


def write_rerun(run_dir: Path, rrd_path: Path, ellipse_every: int | None = None) -> Path:
    """Write a Rerun recording of the complete run folder ``run_dir`` to ``rrd_path`` (``.rrd``); returns it.

    The layout is the module docstring's. ``ellipse_every`` spaces the static covariance ellipses (default:
    at most ``MAX_STATIC_ELLIPSES`` of them). The file is written beside its name and renamed when complete;
    no viewer is started. The recording is made in a child process: when its disk fills, the SDK's file
    writer can stop and leave the recording stream waiting for it forever, deaf to signals, and only a
    process can be stopped from outside. PipelineError on a folder that is not a complete run or an output
    that cannot be written.
    """
    rrd_path = Path(rrd_path)
    if rrd_path.suffix != ".rrd":
        raise PipelineError(f"{rrd_path}: a Rerun recording must end in .rrd")
    if ellipse_every is not None and ellipse_every < 1:
        raise PipelineError(f"ellipse_every must be at least 1, got {ellipse_every}")
    check_run_folder(run_dir)  # a bad run folder fails here, before any process or file
    if not rrd_path.parent.is_dir():
        raise PipelineError(f"{rrd_path}: no such folder {rrd_path.parent}")
    try:
        with atomic_output(rrd_path, suffix=".rrd") as tmp:
            failure = _record_in_child(Path(run_dir), tmp, ellipse_every)
            if failure is not None and failure.startswith(UNREADABLE):
                raise PipelineError(failure.removeprefix(UNREADABLE))
            if failure is not None:
                raise PipelineError(f"{rrd_path}: cannot write ({failure})")
    except OSError as exc:
        raise PipelineError(f"{rrd_path}: cannot write ({exc.strerror or exc})") from None
    return rrd_path


def _record_in_child(run_dir: Path, tmp: Path, ellipse_every: int | None) -> str | None:
    """Record ``run_dir`` into ``tmp`` in a child interpreter (``python -m pipeline.viewer``); None on
    success, else why it failed. The child reports in one line (:func:`_await_report`); after a complete
    recording it is given ``CHILD_EXIT_S`` to exit, otherwise (and on an interrupt) it is killed at once.
    ``GPOM_TRACEBACK=1`` shows its stderr."""
    repo = str(Path(__file__).resolve().parents[1])
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (repo, os.environ.get("PYTHONPATH")) if p)}
    args = [sys.executable, "-m", "pipeline.viewer", str(run_dir), str(tmp), str(ellipse_every or 0)]
    # the SDK's own log lines go with the child's stderr: the parent reports a failure in one line
    stderr = None if os.environ.get("GPOM_TRACEBACK") else subprocess.DEVNULL
    child = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=stderr, env=env, text=True)
    try:
        report = _await_report(child, tmp)
        try:
            child.wait(CHILD_EXIT_S if report == RECORDED else 0)  # a stalled child is stopped at once
        except subprocess.TimeoutExpired:
            pass
    finally:
        if child.poll() is None:
            child.kill()
        child.wait()
        child.stdout.close()
    if report == RECORDED:
        return None
    return report or f"the recording process ended with status {child.returncode}"


def _await_report(child: subprocess.Popen, tmp: Path) -> str:
    """The child's one line, or why it was given up: its file stopped growing for ``STALL_S`` on a disk with
    less than ``FULL_DISK_BYTES`` free (the SDK's writer stalls there until the flush times out)."""
    last_size, since = -1, time.monotonic()
    while True:
        ready, _, _ = select.select([child.stdout], [], [], 1.0)
        if ready:
            return child.stdout.readline().strip()
        try:
            size, free = tmp.stat().st_size, shutil.disk_usage(tmp.parent).free
        except OSError:
            continue
        if size != last_size:
            last_size, since = size, time.monotonic()
        elif free < FULL_DISK_BYTES and time.monotonic() - since > STALL_S:
            return "no space left on its disk"


def _record(run_dir: Path, tmp: Path, ellipse_every: int | None) -> None:
    """The child of :func:`_record_in_child`: writes the recording and prints :data:`RECORDED`; on a
    failure prints why (one line) and leaves at once, status 1 (the recording stream's teardown would wait
    for a stopped writer)."""
    import rerun as rr  # imported here: a run without --rerun never loads it

    try:
        view = read_run_view(run_dir)
        rec = rr.RecordingStream(APPLICATION_ID)
        rec.save(tmp, default_blueprint=_blueprint(view))
        _log_run(rec, view, ellipse_every)
        # bounded: when the disk fills, the SDK's file writer can stop without telling the flush
        rec.flush(timeout_sec=RERUN_FLUSH_TIMEOUT_S)
        rec.disconnect()
    except GpomError as exc:  # a damaged file of the run folder: its own message, said as it is
        print(UNREADABLE + " ".join(str(exc).split()), flush=True)
        os._exit(1)
    except (OSError, RuntimeError, TimeoutError) as exc:
        # the SDK reports a failed file write as a RuntimeError ("File-writer thread shut down
        # prematurely") or a flush timeout; judged while the partial file still holds its disk
        print(_write_failure(exc, tmp), flush=True)
        os._exit(1)
    print(RECORDED, flush=True)


def _write_failure(exc: BaseException, path: Path) -> str:
    """Why ``path`` could not be written, in a few words: a full disk when its folder's disk is."""
    if isinstance(exc, OSError) and exc.strerror:
        return exc.strerror
    try:
        full = shutil.disk_usage(path.parent).free < FULL_DISK_BYTES
    except OSError:
        full = False
    return "no space left on its disk" if full else first_line(exc)


def _time_columns(stamps_ns: NDArray[np.int64]) -> list[Any]:
    import rerun as rr

    stamps = np.asarray(stamps_ns, np.int64)
    if len(stamps) and stamps.min() >= UNIX_STAMP_MIN_NS:
        stamp = rr.TimeColumn(TIMELINE_STAMP, timestamp=stamps.astype("datetime64[ns]"))
    else:
        stamp = rr.TimeColumn(TIMELINE_STAMP, duration=stamps.astype("timedelta64[ns]"))
    return [stamp, rr.TimeColumn(TIMELINE_SCAN, sequence=np.arange(len(stamps)))]


def _xyz(points_xy: NDArray, z_m: float = 0.0) -> NDArray[np.float32]:
    """(..., 3) float32 points from (..., 2) ones at height ``z_m``."""
    p = np.asarray(points_xy, dtype=np.float32)
    return np.concatenate([p, np.full((*p.shape[:-1], 1), z_m, np.float32)], axis=-1)


def _log_run(rec: Any, view: RunView, ellipse_every: int | None) -> None:
    import rerun as rr

    rec.send_recording_name(f"gpom {view.run_dir}")
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    _log_summary(rec, view)
    for name, layers in view.maps.items():
        _log_map(rec, name, layers)
    for name, (_stamps, poses) in view.trajectories.items():
        color = TRAJECTORY_COLORS.get(name, (90, 90, 90))
        rec.log(
            f"world/trajectories/{name}",
            rr.LineStrips3D([_xyz(poses[:, :2])], colors=[color], radii=[-1.5], labels=[name]),
            static=True,
        )
    if len(view.closures_xy_m):
        rec.log(
            "world/loop_closures",
            rr.LineStrips3D(_xyz(view.closures_xy_m), colors=[CLOSURE_COLOR], radii=[-2.0]),
            static=True,
        )

    n = len(view.stamps_ns)
    times = _time_columns(view.stamps_ns)
    poses = view.scan_poses_xytheta
    if view.scans is not None and n > 0:
        points = scan_points_world(view.scans, poses)
        rec.log("world/scan", rr.Points3D.from_fields(colors=[SCAN_COLOR], radii=[-1.5]), static=True)
        rec.send_columns(
            "world/scan",
            indexes=times,
            columns=rr.Points3D.columns(positions=_xyz(np.concatenate(points))).partition(
                [len(p) for p in points]
            ),
        )
    heading = np.stack([np.cos(poses[:, 2]), np.sin(poses[:, 2])], axis=1) * 0.5
    rec.log("world/pose", rr.Arrows3D.from_fields(colors=[POSE_COLOR], radii=[0.04]), static=True)
    rec.send_columns(
        "world/pose",
        indexes=times,
        columns=rr.Arrows3D.columns(origins=_xyz(poses[:, :2]), vectors=_xyz(heading)),
    )
    if view.cov_xytheta is None:
        return
    outlines = covariance_ellipses_xy(poses[:, :2], view.cov_xytheta)
    rec.log(
        "world/pose/covariance",
        rr.LineStrips3D.from_fields(colors=[COVARIANCE_COLOR], radii=[-1.5]),
        static=True,
    )
    rec.send_columns(
        "world/pose/covariance",
        indexes=times,
        columns=rr.LineStrips3D.columns(strips=list(_xyz(outlines))).partition(np.ones(n, dtype=np.int64)),
    )
    every = ellipse_every or max(1, math.ceil(n / MAX_STATIC_ELLIPSES))
    rec.log(
        "world/covariances",
        rr.LineStrips3D(list(_xyz(outlines[::every])), colors=[COVARIANCE_COLOR], radii=[-1.0]),
        static=True,
    )


def _log_map(rec: Any, name: str, layers: MapLayers) -> None:
    """The occupancy and variance GridMaps of one map (rows flipped: a GridMap's row 0 is its top, +y)."""
    import rerun as rr

    height, width = layers.shape
    corner = [float(layers.origin_xy_m[0]), float(layers.origin_xy_m[1]), MAP_Z_M]
    variance = np.asarray(layers.variance, np.float32)
    finite = np.isfinite(variance)
    fill = float(variance[finite].max()) if finite.any() else 0.0
    images = {
        "occupancy": (occupancy_u8(layers.probability, layers.unknown), "U8", rr.components.Colormap.RvizMap),
        "variance": (np.where(finite, variance, np.float32(fill)), "F32", rr.components.Colormap.Viridis),
    }
    for layer, (image, dtype, colormap) in images.items():
        rec.log(
            f"world/maps/{name}/{layer}",
            rr.GridMap(
                data=np.ascontiguousarray(image[::-1]).tobytes(),
                format=rr.components.ImageFormat(
                    width=width, height=height, color_model="L", channel_datatype=dtype
                ),
                cell_size=float(layers.resolution_m),
                translation=corner,
                colormap=colormap,
            ),
            static=True,
        )


def _log_summary(rec: Any, view: RunView) -> None:
    import rerun as rr

    table = view.summary.get("table")
    lines = [f"# {view.run_dir}", ""]
    if isinstance(table, dict):
        lines += ["| | |", "|---|---|"] + [f"| {k} | {v} |" for k, v in table.items()]
    lines += [f"\n- {note}" for note in view.notes]
    rec.log("summary", rr.TextDocument("\n".join(lines), media_type=rr.MediaType.MARKDOWN), static=True)


def _blueprint(view: RunView) -> Any:
    """One top-down 3D tab per map layer (vector data in every tab) and the summary text beside them."""
    import rerun.blueprint as rrb

    x0, y0, x1, y1 = _extent_xy_m(view)
    cx, cy, size = 0.5 * (x0 + x1), 0.5 * (y0 + y1), max(x1 - x0, y1 - y0, 1.0)
    # Looking down from a little south of the centre: +y is up on the screen, +x to the right.
    eye = rrb.EyeControls3D(position=[cx, cy - 0.02 * size, 0.9 * size], look_target=[cx, cy, 0.0])
    tabs = []
    layers = [(name, layer) for name in view.maps for layer in ("occupancy", "variance")] or [(None, None)]
    for name, layer in layers:
        contents = ["+ /world/**", "- /world/maps/**"]
        if name is not None:
            contents.append(f"+ /world/maps/{name}/{layer}")
        tabs.append(
            rrb.Spatial3DView(
                origin="/world",
                contents=contents,
                name=f"{name}: {'p(occupied)' if layer == 'occupancy' else 'variance'}" if name else "world",
                eye_controls=eye,
                line_grid=rrb.LineGrid3D(visible=False),
            )
        )
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Tabs(*tabs), rrb.TextDocumentView(origin="/summary", name="summary"), column_shares=[4, 1]
        ),
        collapse_panels=False,
    )


def _extent_xy_m(view: RunView) -> tuple[float, float, float, float]:
    """(xmin, ymin, xmax, ymax) of the maps, or of the trajectories when there is no map (m)."""
    boxes = []
    for m in view.maps.values():
        h, w = m.shape
        ox, oy = m.origin_xy_m
        boxes.append((ox, oy, ox + w * m.resolution_m, oy + h * m.resolution_m))
    if not boxes:
        xy = np.concatenate([p[:, :2] for _, p in view.trajectories.values()])
        boxes.append((*xy.min(axis=0), *xy.max(axis=0)))
    b = np.asarray(boxes, dtype=np.float64)
    return float(b[:, 0].min()), float(b[:, 1].min()), float(b[:, 2].max()), float(b[:, 3].max())


if __name__ == "__main__":  # the child of _record_in_child: RUN_DIR TMP ELLIPSE_EVERY (0: the default)
    _record(Path(sys.argv[1]), Path(sys.argv[2]), int(sys.argv[3]) or None)
