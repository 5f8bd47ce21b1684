"""The files of a run folder that ``remap`` reads back (SPEC section 4): the scans and the trajectories.

- ``scans.npz``: every scan's ranges and angles (ragged, stored flat with offsets), stamps, range limits,
  frame ids, sources, and the laser mounting -- everything a mapper needs, so ``remap`` never reads the bag;
- ``trajectory/odometry.tum`` / ``optimized.tum``: base poses of every scan before / after loop closure;
- ``trajectory/pose_graph.g2o``: the optimised graph (keyframes), loop closures included;
- ``trajectory/covariances.npz``: world-frame (x, y, theta) keyframe marginals before / after (SPEC keys
  ``stamps_ns``, ``before``, ``after``, ``indices``) plus the per-scan covariances ``scan_before`` /
  ``scan_after`` (N, 3, 3) and ``scan_stamps_ns`` (N,), and the covariances GPPOL maps with,
  ``scan_relative_before`` / ``scan_relative_after`` (N, 3, 3): each scan's pose relative to the earlier
  passes over the places it observes (:mod:`slam.consistency`), world frame.
"""

from __future__ import annotations

import zipfile
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from datasets.files import atomic_output
from datasets.types import ScanSequence
from mapping.gppol import RigidGroups
from pipeline.errors import PipelineError
from slam.keyframes import keyframe_of_scan
from slam.result import SlamResult
from slam.trajectory_io import TrajectoryFormatError, write_g2o, write_tum

TRAJECTORY_DIR = "trajectory"
SCANS_FILE = "scans.npz"
ODOMETRY_TUM = "odometry.tum"
OPTIMIZED_TUM = "optimized.tum"
POSE_GRAPH_G2O = "pose_graph.g2o"
COVARIANCES_NPZ = "covariances.npz"


def _savez_atomic(path: Path, **arrays: object) -> None:
    with atomic_output(path, suffix=".npz") as tmp:
        np.savez_compressed(tmp, **arrays)


@dataclass(frozen=True)
class StoredScans:
    """The scans of a run folder and the laser mounting (3,) on the base."""

    scans: ScanSequence
    laser_in_base_xytheta: NDArray[np.float64]


def write_scans(path: Path, scans: ScanSequence, laser_in_base_xytheta: NDArray) -> Path:
    """Write ``scans.npz``: flat float32 ranges and angles with (N+1,) offsets, and the per-scan fields."""
    counts = scans.beam_counts()
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    _savez_atomic(
        Path(path),
        ranges_m=np.concatenate(scans.ranges_m) if len(scans) else np.zeros(0, np.float32),
        angles_rad=np.concatenate(scans.angles_rad) if len(scans) else np.zeros(0, np.float32),
        offsets=offsets,
        stamps_ns=scans.stamps_ns,
        range_min_m=scans.range_min_m,
        range_max_m=scans.range_max_m,
        frame_ids=np.asarray(scans.frame_ids, dtype=np.str_),
        source_index=scans.source_index,
        sources=np.asarray(scans.sources, dtype=np.str_),
        laser_in_base_xytheta=np.asarray(laser_in_base_xytheta, dtype=np.float64),
    )
    return Path(path)


def read_scans(path: Path) -> StoredScans:
    """Read a ``scans.npz`` written by :func:`write_scans` (PipelineError if it is not one)."""
    try:
        with np.load(Path(path)) as z:
            off = z["offsets"]
            ranges = z["ranges_m"]
            angles = z["angles_rad"]
            laser = np.asarray(z["laser_in_base_xytheta"], dtype=np.float64)
            _check_stored_scans(off, ranges, angles, z["stamps_ns"], laser)
            n = off.shape[0] - 1
            scans = ScanSequence(
                [ranges[off[i] : off[i + 1]] for i in range(n)],
                [angles[off[i] : off[i + 1]] for i in range(n)],
                z["stamps_ns"],
                z["range_min_m"],
                z["range_max_m"],
                [str(f) for f in z["frame_ids"]],
                z["source_index"],
                [str(s) for s in z["sources"]],
            )
            return StoredScans(scans, laser)
    except FileNotFoundError:
        raise PipelineError(f"{path}: no such file (not a run folder?)") from None
    except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
        raise PipelineError(f"{path}: not a scans archive ({exc})") from None


def _check_stored_scans(
    offsets: NDArray, ranges_m: NDArray, angles_rad: NDArray, stamps_ns: NDArray, laser_xytheta: NDArray
) -> None:
    """ValueError unless the arrays of a ``scans.npz`` fit together: (N+1,) integer offsets from 0, never
    decreasing, ending at the number of beams; as many ranges as angles, none negative; N stamps; a finite
    (3,) mounting."""
    if offsets.ndim != 1 or offsets.shape[0] < 1 or not np.issubdtype(offsets.dtype, np.integer):
        raise ValueError("offsets is not a list of beam indices")
    if offsets[0] != 0 or np.any(np.diff(offsets) < 0) or offsets[-1] != ranges_m.shape[0]:
        raise ValueError(
            f"offsets do not split its {ranges_m.shape[0]} beams (from {offsets[0]} to {offsets[-1]}, "
            "never decreasing)"
        )
    if angles_rad.shape != ranges_m.shape:
        raise ValueError(f"{ranges_m.shape[0]} ranges but {angles_rad.shape[0]} angles")
    negative = np.isfinite(ranges_m) & (ranges_m < 0)  # -inf is REP 117's "too close", kept by the readers
    if np.any(negative):
        raise ValueError(f"negative ranges (beam {int(np.argmax(negative))})")
    if stamps_ns.shape != (offsets.shape[0] - 1,):
        raise ValueError(f"{offsets.shape[0] - 1} scans but {stamps_ns.shape[0]} stamps")
    if laser_xytheta.shape != (3,) or not np.all(np.isfinite(laser_xytheta)):
        raise ValueError(f"laser_in_base_xytheta is not a finite x, y, theta: {laser_xytheta.tolist()}")


def write_trajectories(folder: Path, slam: SlamResult) -> dict[str, Path]:
    """Write the four trajectory files of a run folder; returns their paths by name."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    paths = {
        "odometry": folder / ODOMETRY_TUM,
        "optimized": folder / OPTIMIZED_TUM,
        "pose_graph": folder / POSE_GRAPH_G2O,
        "covariances": folder / COVARIANCES_NPZ,
    }
    write_tum(paths["odometry"], slam.stamps_ns, slam.poses_before_xytheta)
    write_tum(paths["optimized"], slam.stamps_ns, slam.poses_after_xytheta)
    write_g2o(paths["pose_graph"], slam.graph_vertices_xytheta, slam.graph_edges)
    _savez_atomic(
        paths["covariances"],
        stamps_ns=slam.keyframe_stamps_ns,
        before=slam.keyframe_cov_before,
        after=slam.keyframe_cov_after,
        indices=slam.keyframe_scans,
        scan_stamps_ns=slam.stamps_ns,
        scan_before=slam.cov_before_xytheta,
        scan_after=slam.cov_after_xytheta,
        scan_relative_before=slam.relative_cov_before_xytheta,
        scan_relative_after=slam.relative_cov_after_xytheta,
        **(
            {"scan_keyframe_offset_body": slam.keyframe_offset_cov_body}
            if slam.keyframe_offset_cov_body is not None
            else {}
        ),
        frame="world",
        order="x y theta",
    )
    return paths


#: What ``mapping.gppol.pose_covariances`` can name (:func:`mapper_covariances`).
POSE_COVARIANCES = ("relative", "world", "none")


def mapper_covariances(slam: SlamResult, which: str, mode: str) -> NDArray[np.float64] | None:
    """(N, 3, 3) the covariances a map ``which`` (``"before"`` / ``"after"`` loop closure) is built with,
    as ``mapping.gppol.pose_covariances`` (``mode``) names them: ``"relative"`` (to the earlier passes over
    each place), ``"world"`` (the marginals) or ``"none"`` (None: exact poses)."""
    if which not in ("before", "after"):
        raise ValueError(f"which must be 'before' or 'after', not {which!r}")
    if mode == "none":
        return None
    if mode == "relative":
        return getattr(slam, f"relative_cov_{which}_xytheta")
    if mode == "world":
        return getattr(slam, f"cov_{which}_xytheta")
    raise ValueError(f"pose covariances must be one of {POSE_COVARIANCES}, not {mode!r}")


#: What ``mapping.gppol.rigid_groups`` can name (:func:`mapper_rigid_groups`).
RIGID_GROUPS = ("scan", "keyframe")


def _keyframe_groups(mode: str) -> bool:
    """Whether ``mapping.gppol.rigid_groups`` (``mode``) asks for the keyframes (ValueError if unknown)."""
    if mode not in RIGID_GROUPS:
        raise ValueError(f"rigid groups must be one of {RIGID_GROUPS}, not {mode!r}")
    return mode == "keyframe"


def rigid_groups_label(mode: str) -> str:
    """What the tables add to the name of GPPOL's pose covariances under ``mapping.gppol.rigid_groups``."""
    return ", shared within keyframes" if _keyframe_groups(mode) else ""


def mapper_rigid_groups(slam: SlamResult, mode: str) -> RigidGroups | None:
    """GPPOL's rigid groups (:class:`mapping.gppol.RigidGroups`) as ``mapping.gppol.rigid_groups``
    (``mode``) names them: None for ``"scan"`` (each scan alone), the keyframe of every scan and its
    offset's covariance for ``"keyframe"``. The pose graph moves the scans between two keyframes rigidly
    with the first (their offsets are the odometry's), so as the graph sees them they share its pose error:
    two points of one keyframe are placed relative to each other up to the laser noise and the odometry
    between them."""
    if not _keyframe_groups(mode):
        return None
    groups = keyframe_of_scan(np.asarray(slam.keyframe_scans, dtype=np.int64), len(slam.stamps_ns))
    return RigidGroups(groups, slam.keyframe_offset_cov_body)


def read_rigid_groups(path: Path, n_scans: int, mode: str) -> RigidGroups | None:
    """:func:`mapper_rigid_groups` of the ``n_scans`` scans of a run's ``covariances.npz``; None (each scan
    its own group) for ``mode`` ``"scan"`` and when the file names no keyframes of these scans (another
    tool's file). A file without the offsets' covariances (``scan_keyframe_offset_body``) gives exactly
    rigid groups."""
    if not _keyframe_groups(mode):
        return None
    try:
        keyframes = read_keyframe_indices(path)
    except TrajectoryFormatError:
        return None
    if keyframes.max() >= n_scans or np.any(np.diff(keyframes) <= 0):
        return None
    key = "scan_keyframe_offset_body"
    offsets = _from_covariance_archive(path, lambda z: np.asarray(z[key], np.float64) if key in z else None)
    if offsets is not None and (offsets.shape != (n_scans, 3, 3) or not np.isfinite(offsets).all()):
        raise TrajectoryFormatError(f"{path}: '{key}' is not {n_scans} finite 3x3 covariances")
    return RigidGroups(keyframe_of_scan(keyframes, n_scans), offsets)


def read_mapper_covariances(path: Path, which: str, mode: str) -> tuple[NDArray[np.int64], NDArray] | None:
    """The per-scan covariances ``(stamps_ns, cov)`` of a ``covariances.npz`` that a map ``which`` is built
    with under ``mode`` (as :func:`mapper_covariances`; None for ``"none"``). ``"relative"`` reads
    ``scan_relative_{which}``; a file without it (written by another tool, or before it existed) gives its
    world-frame covariances (:func:`read_scan_covariances`)."""
    if mode == "none":
        return None
    if mode == "relative":

        def read(z) -> tuple[NDArray[np.int64], NDArray] | None:
            key = f"scan_relative_{which}"
            if key not in z:
                return None
            return np.asarray(z["scan_stamps_ns"], np.int64), np.asarray(z[key], np.float64)

        found = _from_covariance_archive(path, read)
        if found is not None:
            return found
    elif mode != "world":
        raise ValueError(f"pose covariances must be one of {POSE_COVARIANCES}, not {mode!r}")
    return read_scan_covariances(path, which)


def read_scan_covariances(path: Path, which: str = "after") -> tuple[NDArray[np.int64], NDArray]:
    """Per-scan covariances ``(stamps_ns (N,), cov (N, 3, 3))`` of a run's ``covariances.npz``.

    Falls back to the keyframe marginals (``stamps_ns``, ``before`` / ``after``) when the per-scan arrays
    are absent (e.g. a file written by another tool): each scan then takes the covariance of the latest
    keyframe at or before it (see :func:`covariances_at`).
    """

    def read(z) -> tuple[NDArray[np.int64], NDArray]:
        if f"scan_{which}" in z:
            return np.asarray(z["scan_stamps_ns"], np.int64), np.asarray(z[f"scan_{which}"], np.float64)
        return np.asarray(z["stamps_ns"], np.int64), np.asarray(z[which], np.float64)

    return _from_covariance_archive(path, read)


def _from_covariance_archive(path: Path, read: Callable[[Any], Any]) -> Any:
    """``read(archive)`` of the covariance archive ``path``; TrajectoryFormatError if missing or malformed."""
    try:
        with np.load(Path(path)) as z:
            return read(z)
    except FileNotFoundError:
        raise TrajectoryFormatError(f"{path}: no such file or directory") from None
    except (OSError, KeyError, ValueError) as exc:
        raise TrajectoryFormatError(f"{path}: not a covariance archive ({exc})") from None


#: Relative tolerance of :func:`_not_covariances` (float rounding of a stored covariance).
COVARIANCE_TOLERANCE = 1e-6


def _not_covariances(cov: NDArray[np.float64]) -> int | None:
    """The index of the first (3, 3) matrix of ``cov`` (N, 3, 3) that is not symmetric positive
    semi-definite (to :data:`COVARIANCE_TOLERANCE` of its largest entry), or None."""
    scale = np.abs(cov).max(axis=(1, 2)) + 1e-300
    asym = np.abs(cov - np.transpose(cov, (0, 2, 1))).max(axis=(1, 2)) > COVARIANCE_TOLERANCE * scale
    low = np.linalg.eigvalsh(0.5 * (cov + np.transpose(cov, (0, 2, 1))))[:, 0] < -COVARIANCE_TOLERANCE * scale
    bad = np.flatnonzero(asym | low)
    return int(bad[0]) if bad.size else None


def read_keyframe_indices(path: Path) -> NDArray[np.int64]:
    """The scan index of every keyframe (``indices``, (K,)) of a run's ``covariances.npz``."""
    indices = _from_covariance_archive(path, lambda z: np.asarray(z["indices"]))
    if indices.ndim != 1 or indices.dtype.kind not in "iu" or len(indices) == 0 or (indices < 0).any():
        raise TrajectoryFormatError(f"{path}: 'indices' is not a list of scan indices")
    return indices.astype(np.int64)


def checked_covariances(cov: NDArray, count: int) -> NDArray[np.float64]:
    """``cov`` as (count, 3, 3) float64; PipelineError unless it has that shape (count > 0) and every entry
    is a finite, symmetric positive semi-definite matrix."""
    cov = np.asarray(cov, dtype=np.float64)
    if cov.ndim != 3 or cov.shape[1:] != (3, 3) or cov.shape[0] != count or count == 0:
        raise PipelineError(f"covariances of shape {cov.shape} for {count} stamps")
    if not np.isfinite(cov).all():
        raise PipelineError("covariances: not every entry is finite")
    bad = _not_covariances(cov)
    if bad is not None:
        raise PipelineError(f"covariances: entry {bad} is not symmetric positive semi-definite")
    return cov


def covariances_at(
    stamps_ns: NDArray[np.int64], cov_stamps_ns: NDArray[np.int64], cov: NDArray
) -> NDArray[np.float64]:
    """(N, 3, 3) covariances at ``stamps_ns``: those of the latest stamp at or before each (the first one
    before the start). Exact when ``cov_stamps_ns`` are the scan stamps themselves."""
    cov = checked_covariances(cov, len(cov_stamps_ns))
    order = np.argsort(cov_stamps_ns, kind="stable")
    s = np.asarray(cov_stamps_ns, np.int64)[order]
    idx = np.searchsorted(s, np.asarray(stamps_ns, np.int64), side="right") - 1
    return cov[order][np.clip(idx, 0, len(s) - 1)]
