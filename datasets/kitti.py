"""Reader of KITTI odometry Velodyne frames (one ``.bin`` or a folder of them) into a Recording.

A frame ``NNNNNN.bin`` is float32 ``x y z reflectance`` rows in the Velodyne frame. Beside the frames:

- ``times*.txt``: one time in seconds per line, line k for frame k; without it frames are 10 Hz by index;
- ``poses*.txt``: one 3x4 row-major pose per line (camera 0 frame, line k for frame k), moved into the
  Velodyne frame with ``Tr`` (velodyne -> camera) of ``calib.txt``: ``T_velo = inv(Tr) @ T_cam @ Tr``.

Nothing heavy is read up front: ``clouds`` load one frame per access, and ``scans`` (the
``InputConfig.cloud_*`` height band of each cloud turned into a planar scan by
:func:`datasets.cloud.cloud_to_scan`) are computed on first access and the last few kept, so a
4,541-frame sequence costs its stamps until scans are asked for.

Bad side files are a KittiError naming the file and line: times that are not decimal seconds or lie beyond
the years 1740-2200 (``datasets.validate.MAX_STAMP_NS``, also for 10 Hz stamps of large frame numbers),
non-finite numbers, a singular ``Tr``, Velodyne-frame poses that overflow or lie beyond
``datasets.validate.MAX_COORDINATE_M``. A frame with non-finite values fails when it is loaded.
"""

from __future__ import annotations

import re
from collections import OrderedDict
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from datasets.cloud import cloud_to_scan
from datasets.config import InputConfig
from datasets.errors import DatasetError, shown, shown_names
from datasets.stamps import StampRangeError, decimal_to_ns
from datasets.types import CloudSequence, PointCloud, Recording, ScanSequence, Trajectory, beam_angles_rad
from datasets.validate import MAX_COORDINATE_M, MAX_STAMP_NS

FRAME_ID = "velodyne"
DEFAULT_PERIOD_NS = 100_000_000  # 10 Hz, the Velodyne HDL-64E rate of KITTI
_POINT_BYTES = 16  # float32 x y z reflectance


class KittiError(DatasetError):
    """KITTI frames or their side files are missing or malformed (the message names the file)."""


def read_kitti(path: str | Path, cfg: InputConfig | None = None) -> Recording:
    """Read one KITTI ``.bin`` frame or a folder of them (see the module docstring).

    Returns a Recording with lazy ``clouds`` (N frames), lazy ``scans`` (N planar scans), ``reference``
    (N Velodyne-frame poses as (x, y, yaw)) when a poses file and ``calib.txt`` are present, and
    ``meta["reference_poses_se3"]`` (N, 4, 4). Raises KittiError (one line) on bad input.
    """
    cfg = cfg or InputConfig()
    path = Path(path)
    if not path.exists():
        raise KittiError(f"{path}: no such file or directory")
    folder = path if path.is_dir() else path.parent
    frames = sorted(folder.glob("*.bin")) if path.is_dir() else [path]
    if not frames:
        raise KittiError(f"{path}: no KITTI frames (*.bin) in the folder")
    frames, index = _numbered(frames)

    meta: dict = {"frames": [f.name for f in frames], "frame_index": index}
    times_file = _side_file(folder, "times")
    if times_file is not None:
        all_stamps = _read_times(times_file)
        _check_covered(times_file, len(all_stamps), index, "times")
        stamps = all_stamps[index]
        meta["times_file"] = times_file.name
    else:
        late = np.flatnonzero(index > MAX_STAMP_NS // DEFAULT_PERIOD_NS)
        if late.size:
            raise KittiError(
                f"{frames[late[0]]}: frame number {index[late[0]]} at 10 Hz is beyond the year 2200 "
                "(add a times.txt)"
            )
        stamps = index * DEFAULT_PERIOD_NS
        meta["times_file"] = None
    bad = np.flatnonzero(stamps[1:] <= stamps[:-1])  # not np.diff: it can overflow int64
    if bad.size:
        where = times_file or folder
        raise KittiError(
            f"{where}: timestamps go backwards: frame {index[bad[0] + 1]} is not after frame {index[bad[0]]}"
        )

    reference = None
    poses_file = _side_file(folder, "poses")
    if poses_file is not None:
        calib = folder / "calib.txt"
        if not calib.is_file():
            raise KittiError(
                f"{poses_file}: camera-frame poses need {calib} (its Tr line) for the Velodyne frame"
            )
        velo_in_cam = _read_tr(calib)
        cam_poses = _read_poses(poses_file)
        _check_covered(poses_file, len(cam_poses), index, "poses")
        try:
            cam_in_velo = np.linalg.inv(velo_in_cam)
        except np.linalg.LinAlgError:
            raise KittiError(f"{calib}: Tr is singular (not a rigid transform)") from None
        with np.errstate(all="ignore"):  # huge values overflow to inf / NaN, rejected below
            poses_se3 = cam_in_velo @ cam_poses[index] @ velo_in_cam
        usable = np.isfinite(poses_se3).all(axis=(1, 2)) & (
            np.abs(poses_se3[:, :2, 3]) <= MAX_COORDINATE_M
        ).all(axis=1)
        if not usable.all():
            k = int(np.flatnonzero(~usable)[0])
            raise KittiError(
                f"{poses_file}: line {index[k] + 1}: the pose in the Velodyne frame (with Tr of "
                f"{calib.name}) is not finite or beyond {MAX_COORDINATE_M:g} m"
            )
        xy_yaw = np.stack(
            [poses_se3[:, 0, 3], poses_se3[:, 1, 3], np.arctan2(poses_se3[:, 1, 0], poses_se3[:, 0, 0])],
            axis=1,
        )
        reference = Trajectory(stamps, xy_yaw, frame_id="world")
        meta["reference_poses_se3"] = poses_se3
        meta["poses_file"] = poses_file.name

    clouds = CloudSequence(stamps, lambda i: load_frame(frames[i], int(stamps[i])))
    return Recording(
        source=path,
        format="kitti",
        scans=CloudScans(clouds, cfg),
        reference=reference,
        clouds=clouds,
        meta=meta,
    )


def load_frame(path: Path, stamp_ns: int = 0) -> PointCloud:
    """One Velodyne frame: ``points_xyz_m`` (P, 3) float32 and ``intensity`` (P,) float32 reflectance."""
    try:
        size = path.stat().st_size
        if size == 0 or size % _POINT_BYTES:
            raise KittiError(
                f"{path}: not a KITTI Velodyne frame ({size} bytes is not a positive multiple of 16)"
            )
        raw = np.fromfile(path, dtype=np.float32)
    except FileNotFoundError:
        raise KittiError(f"{path}: no such file or directory") from None
    except OSError as exc:
        raise KittiError(f"{path}: cannot read the file: {exc.strerror or exc}") from None
    points = raw.reshape(-1, 4)
    if not np.all(np.isfinite(points)):
        raise KittiError(f"{path}: non-finite values in the point cloud")
    return PointCloud(
        points_xyz_m=np.ascontiguousarray(points[:, :3]),
        stamp_ns=stamp_ns,
        frame_id=FRAME_ID,
        intensity=np.ascontiguousarray(points[:, 3]),
    )


class _LazyRanges:
    """The ranges of each scan, made from its cloud on first access; the last ``keep`` are cached."""

    def __init__(self, clouds: CloudSequence, cfg: InputConfig, keep: int = 16) -> None:
        self._clouds = clouds
        self._cfg = cfg
        self._keep = keep
        self._cache: OrderedDict[int, NDArray[np.float32]] = OrderedDict()

    def __len__(self) -> int:
        return len(self._clouds)

    def __getitem__(self, i: int | slice) -> NDArray[np.float32] | list[NDArray[np.float32]]:
        if isinstance(i, slice):
            return [self[k] for k in range(*i.indices(len(self)))]
        i = int(i)
        if i < 0:
            i += len(self)
        if not 0 <= i < len(self):
            raise IndexError(i)
        if i in self._cache:
            self._cache.move_to_end(i)
            return self._cache[i]
        cfg = self._cfg
        ranges, _ = cloud_to_scan(
            self._clouds[i].points_xyz_m, cfg.cloud_height_band_m, cfg.cloud_scan_beams, cfg.cloud_range_max_m
        )
        ranges.setflags(write=False)
        self._cache[i] = ranges
        if len(self._cache) > self._keep:
            self._cache.popitem(last=False)
        return ranges

    def __iter__(self):
        return (self[i] for i in range(len(self)))


class CloudScans(ScanSequence):
    """A ScanSequence over 3D clouds whose scans are computed lazily (see :class:`_LazyRanges`).

    Stamps, beam counts and angles are known without reading a cloud; ``packed()`` and ``subset()``
    compute the scans they return.
    """

    def __init__(self, clouds: CloudSequence, cfg: InputConfig) -> None:  # no super().__init__: nothing eager
        n = len(clouds)
        beams = cfg.cloud_scan_beams
        angles = beam_angles_rad(-np.pi, 2.0 * np.pi / beams, beams)  # as cloud_to_scan builds them
        angles.setflags(write=False)
        self._ranges = _LazyRanges(clouds, cfg)  # type: ignore[assignment]
        self._angles = [angles] * n
        self.stamps_ns = np.asarray(clouds.stamps_ns, dtype=np.int64).copy()
        self.range_min_m = np.zeros(n)
        self.range_max_m = np.full(n, cfg.cloud_range_max_m, dtype=np.float32).astype(np.float64)
        self.frame_ids = [FRAME_ID] * n
        self.source_index = np.zeros(n, dtype=np.int32)
        self.sources = [FRAME_ID]
        self._beams = beams

    def beam_counts(self) -> NDArray[np.int64]:
        return np.full(len(self), self._beams, dtype=np.int64)


# -------------------------------------------------------------------------------------------- side files


def _frame_number(frame: Path) -> int | None:
    """The frame number of ``000123.bin`` (its line in times / poses files); None if not a number."""
    stem = frame.stem
    if not (stem.isascii() and stem.isdigit()):
        return None
    if len(stem.lstrip("0")) > 15:
        raise KittiError(f"{frame}: frame number {shown(stem, bare=True)} is out of range")
    return int(stem)


def _numbered(frames: list[Path]) -> tuple[list[Path], NDArray[np.int64]]:
    """The frames in the order of their numbers, and those numbers (N,); frames of which none is named by a
    number take their positions in name order. KittiError for a folder that mixes the two (``frame3.bin``
    beside ``000004.bin``) or names two frames by one number (``5.bin``, ``005.bin``)."""
    numbers = [_frame_number(f) for f in frames]
    if all(n is None for n in numbers):
        return frames, np.arange(len(frames), dtype=np.int64)
    unnumbered = [f for f, n in zip(frames, numbers, strict=True) if n is None]
    if unnumbered:
        raise KittiError(
            f"{unnumbered[0]}: not named by a frame number like the other frames of its folder (000123.bin)"
        )
    order = sorted(range(len(frames)), key=lambda k: numbers[k])
    frames = [frames[k] for k in order]
    index = np.array([numbers[k] for k in order], dtype=np.int64)
    twice = np.flatnonzero(index[1:] == index[:-1])
    if twice.size:
        k = int(twice[0])
        raise KittiError(f"{frames[k + 1]}: frame {index[k]} is also {frames[k].name}")
    return frames, index


def _side_file(folder: Path, prefix: str) -> Path | None:
    """``{prefix}.txt`` or else the single ``{prefix}*.txt`` of ``folder``; KittiError if several."""
    exact = folder / f"{prefix}.txt"
    if exact.is_file():
        return exact
    found = sorted(p for p in folder.glob(f"{prefix}*.txt") if p.is_file())
    if len(found) > 1:
        names = shown_names(p.name for p in found)
        raise KittiError(f"{folder}: several {prefix} files ({names}); keep one or name it {prefix}.txt")
    return found[0] if found else None


def _lines(path: Path) -> list[tuple[int, list[str]]]:
    """(line number, fields) of the non-empty lines of a text file; KittiError if unreadable."""
    try:
        text = path.read_text(encoding="ascii")
    except UnicodeDecodeError:
        raise KittiError(f"{path}: not a text file") from None
    except OSError as exc:
        raise KittiError(f"{path}: cannot read the file: {exc.strerror or exc}") from None
    return [(k, line.split()) for k, line in enumerate(text.splitlines(), start=1) if line.strip()]


def _read_times(path: Path) -> NDArray[np.int64]:
    out = []
    for number, fields in _lines(path):
        if len(fields) != 1:
            raise KittiError(
                f"{path}: line {number}: expected one time in seconds, found {len(fields)} fields"
            )
        try:
            stamp_ns = decimal_to_ns(fields[0])
        except StampRangeError:
            stamp_ns = MAX_STAMP_NS + 1
        except (ValueError, OverflowError):
            raise KittiError(f"{path}: line {number}: {shown(fields[0])} is not a time in seconds") from None
        if abs(stamp_ns) > MAX_STAMP_NS:
            raise KittiError(
                f"{path}: line {number}: time {shown(fields[0])} s is out of range (after the year 2200 or "
                "as far before 1970)"
            )
        out.append(stamp_ns)
    return np.array(out, dtype=np.int64)


def _floats(path: Path, number: int, fields: list[str], count: int, what: str) -> NDArray[np.float64]:
    if len(fields) != count:
        raise KittiError(f"{path}: line {number}: expected {count} numbers ({what}), found {len(fields)}")
    try:
        values = np.array([float(f) for f in fields])
    except ValueError:
        bad = next(f for f in fields if not _is_float(f))
        raise KittiError(f"{path}: line {number}: {shown(bad)} is not a number") from None
    if not np.all(np.isfinite(values)):
        raise KittiError(f"{path}: line {number}: non-finite value in {what}")
    return values


def _is_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _se3(values: NDArray[np.float64]) -> NDArray[np.float64]:
    out = np.eye(4)
    out[:3, :] = values.reshape(3, 4)
    return out


def _read_poses(path: Path) -> NDArray[np.float64]:
    """(K, 4, 4) poses of a KITTI poses file (12 numbers per line, row-major 3x4)."""
    poses = [_se3(_floats(path, n, f, 12, "a row-major 3x4 pose")) for n, f in _lines(path)]
    if not poses:
        raise KittiError(f"{path}: no poses")
    return np.stack(poses)


def _read_tr(path: Path) -> NDArray[np.float64]:
    """(4, 4) ``Tr`` (Velodyne -> camera 0) of a KITTI ``calib.txt``."""
    for number, fields in _lines(path):
        if fields and re.fullmatch(r"Tr:?", fields[0]):
            return _se3(_floats(path, number, fields[1:], 12, "Tr, a row-major 3x4 transform"))
    raise KittiError(f"{path}: no 'Tr:' line (the Velodyne-to-camera transform)")


def _check_covered(path: Path, rows: int, index: NDArray[np.int64], what: str) -> None:
    if index.max() >= rows:
        raise KittiError(
            f"{path}: {rows} {what} lines, but frame {int(index.max())} needs line {int(index.max()) + 1}"
        )
