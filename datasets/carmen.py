"""Reader of CARMEN logs (``.clf``, ``.log``, either optionally ``.gz`` / ``.bz2``) into a Recording.

Records read (one per line, fields separated by white space; ``#`` lines are comments)::

    FLASER / RLASER  n r1..rn x y theta odom_x odom_y odom_theta ipc_timestamp hostname logger_timestamp
    ROBOTLASER1      laser_type start_angle fov angular_resolution max_range accuracy remission_mode
                     n r1..rn m e1..em laser_x laser_y laser_theta robot_x robot_y robot_theta
                     tv rv forward_safety_dist side_safety_dist turn_axis
                     ipc_timestamp hostname logger_timestamp
    ODOM             x y theta tv rv accel ipc_timestamp hostname logger_timestamp
    PARAM            name value ...            (kept as strings in ``meta["params"]``)

Every other record type (SYNC, NMEA-GGA, TRUEPOS, NEFF, ...) is ignored and counted in
``meta["ignored_records"]``; ``InputConfig.carmen_laser`` picks the laser record type ("auto": the most
frequent one present).

Beams. FLASER / RLASER carry no angles: an n-beam scan covers 180 degrees with
``angle_i = -pi/2 + i * pi / n`` in the laser frame (the convention of the published continuous-map
reference code; checked on ``intel.gfs.log`` by ``tests/test_carmen.py``). ROBOTLASER1 carries its start
angle, resolution and maximum range. No returns: ranges at or beyond the record's own maximum range
(ROBOTLASER1), else beyond the log's repeated maximum reading (:mod:`datasets.no_return`: 51.15 m in the
Radish logs of a 50 m laser) or ``InputConfig.carmen_range_max_m``, whichever is lower (FLASER);
``meta["no_return"]`` says which rule gave which value. Ranges are kept as logged.

Poses and frames. The first pose of a laser record is the laser's, the second the robot base's (odometry).
``scan_poses`` (and ``reference`` for a corrected log) are the **base** poses, and
``laser_in_base_xytheta`` is the fixed mounting measured from the records (median of the laser pose in the
base frame), so that ``laser = base (+) laser_in_base``: zero for intel.clf, x = -0.04 m for fr079.clf.
Corrected logs write one pose twice, so their offset is zero and their poses are the laser's: on
``freiburg-079-corrected.log.gz`` (whose PARAM robot_frontlaser_offset says -0.04 m) endpoints of nearby
scans agree best with a zero offset (mean clipped nearest-neighbour distance 0.0706 m at 0, 0.0738 m at
-0.04 m, 0.0735 m at +0.04 m). The first pose of each record is kept in ``meta["laser_poses_xytheta"]``.

Timestamps. ``stamp_ns`` comes from the ipc timestamp parsed exactly from its decimal text; the raw ipc and
logger timestamps of the scans are kept in ``meta["ipc_stamps_ns"]`` and ``meta["logger_stamps_ns"]``
(``meta["odometry_logger_stamps_ns"]`` for ODOM). **Line order is the truth**; timestamps are not always
monotone in real logs, so the rule is:

- raw logs: the stamps of each record kind (laser, ODOM) may step back from the latest earlier stamp of
  that kind by at most ``InputConfig.carmen_stamp_jitter_s`` (default 1 s; ``intel.clf`` steps back 631
  times among its scans and 602 times among its ODOM records, by up to 0.90 s: it logs arrival times, in
  bursts). A larger step back (a concatenated or clock-reset log) is an error.
- corrected logs (:func:`is_corrected_log`): any stamps are accepted (``freiburg-079-corrected.log.gz``
  writes ODOM stamps of 0, 9e-67 and negative values).
- then, in both cases, the stamps of each kind are made strictly increasing
  (:func:`datasets.stamps.monotone_stamps_ns`: the longest increasing run keeps its stamps, the other
  records are re-stamped between their neighbours in line order); ``meta["restamped"]`` counts them
  (intel.clf: 787 of 13,631 scans, 1,250 of 26,915 ODOM records). A corrected log whose stamps cannot be
  put in order within the usable years is stamped by line order (``meta["stamps_by_line_order"]``).
- finally, when a stamp of any kind is negative (re-stamping extrapolates the records before the first
  kept stamp: ``orebro-corrected.log`` logs every scan at 0 s and gets -236 ns .. 0; a raw log may log
  negative stamps), every kind is shifted by one whole number of seconds so that the earliest stamp lies
  in [0, 1 s): ROS time cannot be negative and such a clock offset carries no information; scans and
  odometry keep their relative timing. ``meta["stamp_shift_ns"]`` holds the shift (0 for most logs).

To find the scans of a corrected keyframe log in its raw log use :func:`match_keyframe_scans` (or
:func:`match_scans` for the indices alone; both in :mod:`datasets.keyframe_match`, re-exported here), not
the nearest logger stamp: corrected logs round stamps to 6 significant digits, and some carry relative,
synthetic or unreliable stamps, so scans are matched by content within the stamp window, else by content
and line order.

In a corrected log the ODOM records are the SLAM's pose estimates, not wheel odometry; they are still
returned as ``odometry`` (``meta["odometry_is_corrected"]`` says so).

Damaged values are a CarmenError naming the line and field, never a warning or an overflow further on:
non-finite numbers; ranges beyond float32; pose coordinates beyond ``datasets.validate.MAX_COORDINATE_M``;
headings beyond 1e6 rad; ROBOTLASER1 start angles or resolutions beyond 1e3 rad, resolutions not above 0,
and maximum ranges beyond
float32 or not above ``InputConfig.carmen_range_min_m``; ipc stamps beyond the years 1740-2200
(``datasets.validate.MAX_STAMP_NS``; logger stamps only need to fit int64 nanoseconds).
"""

from __future__ import annotations

import bz2
import gzip
import zlib
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from datasets import se2
from datasets.config import InputConfig
from datasets.errors import DatasetError, shown
from datasets.keyframe_match import ScanMatch, match_keyframe_scans, match_scans
from datasets.no_return import repeated_maximum_m
from datasets.numtext import NumberParseError, parse_floats, parse_stamps_ns
from datasets.stamps import NS_PER_S, monotone_stamps_ns, ns_to_decimal
from datasets.types import Recording, ScanSequence, Trajectory, beam_angles_rad, wrap_angle_rad
from datasets.validate import MAX_COORDINATE_M, MAX_STAMP_NS

LASER_RECORDS = ("FLASER", "RLASER", "ROBOTLASER1")
_FLASER_FIXED_FIELDS = 11  # name, n, 6 pose values, ipc, host, logger
_ROBOTLASER_FIXED_FIELDS = 24  # name, 7 settings, n, m, 6 pose values, 5 motion values, ipc, host, logger
_ODOM_FIELDS = 10
_FLOAT32_MAX = float(np.finfo(np.float32).max)  # ranges are kept as float32
_MAX_HEADING_RAD = 1e6  # |theta| of a pose beyond this is damage (unwrapped odometry stays far below)
_MAX_ANGLE_RAD = 1e3  # ROBOTLASER1 angle settings beyond this are damage (and lose all precision in float32)
_GZIP_MAGIC = b"\x1f\x8b"
_BZIP2_MAGIC = b"BZh"
__all__ = [
    "LASER_RECORDS",
    "CarmenError",
    "ScanMatch",
    "is_corrected_log",
    "match_keyframe_scans",
    "match_scans",
    "read_carmen",
]


class CarmenError(DatasetError):
    """A CARMEN log is malformed; the message names the file and, where useful, the line."""


def is_corrected_log(path: str | Path) -> bool:
    """True for a SLAM-corrected log, by name: ``*.gfs.log*`` (GMapping) or ``*corrected*``.

    The poses logged in such a file are the corrected poses and become the recording's ``reference``.
    """
    name = Path(path).name.lower()
    return ".gfs." in name or "corrected" in name


ANCHOR_TOLERANCE = 1e-6  # m and rad: an ODOM record re-anchored at a scan repeats that scan's logged pose


def corrected_log_odometry(recording: Recording) -> tuple[Trajectory | None, str]:
    """The raw wheel odometry hidden in a SLAM-corrected log's ODOM records, one pose per scan.

    GMapping-corrected logs (the Radish ``*-corrected.log`` files) re-anchor their ODOM stream at every
    scan: the first ODOM record after a scan repeats its corrected pose, and the records up to the next
    scan integrate the raw wheel motion from there. So the motion from that first record to the last one
    before the next scan is the wheels' own increment between the two scans (a rigid motion of the raw
    chain: no correction leaks into it). Chained from the origin, these increments are wheel odometry.

    An interval whose records do not start at the scan's pose, or hold fewer than two records (a gap in
    the wheel records), has no known increment: the scan it leads to gets a NaN pose, so the steps into and
    out of it are registered without wheels. Returns ``(Trajectory at the scan stamps or None, phrase)``:
    None when the log is not such a corrected log or fewer than half of its steps are known (e.g. ODOM
    records that only repeat the corrected poses).
    """
    meta = recording.meta if isinstance(recording.meta, dict) else {}
    none = "none: the log is SLAM-corrected (its odometry fields are the corrected poses)"
    if not meta.get("corrected") or recording.odometry is None or "odometry_line_numbers" not in meta:
        return None, none
    scans_at = np.asarray(recording.scan_poses.poses_xytheta, dtype=np.float64)
    n = scans_at.shape[0]
    if n < 2:
        return None, none
    odom = np.asarray(recording.odometry.poses_xytheta, dtype=np.float64)
    # interval k (from scan k to scan k + 1) holds the ODOM records between their lines
    scan_lines = np.asarray(meta["line_numbers"])
    interval = np.searchsorted(scan_lines, np.asarray(meta["odometry_line_numbers"])) - 1
    inside = (interval >= 0) & (interval < n - 1)
    rows = np.flatnonzero(inside)
    k_of = interval[rows]
    counts = np.bincount(k_of, minlength=n - 1)
    first = np.full(n - 1, -1)
    last = np.full(n - 1, -1)
    first[k_of[::-1]] = rows[::-1]  # the earliest row of each interval wins
    last[k_of] = rows  # the latest row of each interval wins
    known = counts >= 2
    ks = np.flatnonzero(known)
    gap = odom[first[ks]] - scans_at[ks]
    anchored = (np.hypot(gap[:, 0], gap[:, 1]) <= ANCHOR_TOLERANCE) & (
        np.abs(wrap_angle_rad(gap[:, 2])) <= ANCHOR_TOLERANCE
    )
    known[ks[~anchored]] = False
    n_known = int(known.sum())
    if n_known < 0.5 * (n - 1):
        return None, none + f"; its ODOM records give the wheel motion of {n_known} of {n - 1} steps only"
    inc = np.zeros((n - 1, 3))
    ks = np.flatnonzero(known)
    inc[ks] = se2.between(odom[first[ks]], odom[last[ks]])
    chained = np.zeros((n, 3))
    for k in range(n - 1):  # an unknown step continues the chain (zero motion) and marks its scan NaN
        chained[k + 1] = se2.compose(chained[k], inc[k])
    chained[1:][~known] = np.nan
    phrase = (
        f"the raw wheel odometry of the corrected log's ODOM records (re-anchored at every scan): "
        f"{n_known} of {n - 1} steps"
        + (f", {n - 1 - n_known} without wheel records" if n_known < n - 1 else "")
    )
    return Trajectory(recording.scans.stamps_ns, chained, frame_id="odom"), phrase


def read_carmen(path: str | Path, cfg: InputConfig | None = None) -> Recording:
    """Read the CARMEN log at ``path`` (see the module docstring for records, frames and the stamp rule).

    Returns a Recording with ``scans`` (N scans), ``odometry`` (ODOM records, or None),
    ``scan_poses`` (N base poses at the scan stamps), ``reference`` (the same poses for a corrected log,
    else None), ``laser_in_base_xytheta`` (3,) and ``meta``. Raises a DatasetError subclass with one line
    naming the file (and the line) on bad input.
    """
    cfg = cfg or InputConfig()
    path = Path(path)
    lines, rows_by_type = _index_records(path, _load_text(path))
    counts = {name: len(rows) for name, rows in rows_by_type.items()}
    kind = _choose_laser(path, counts, cfg.carmen_laser)
    corrected = is_corrected_log(path)
    jitter_s = cfg.carmen_stamp_jitter_s
    # a jitter beyond int64 ns (up to inf) allows any step back
    jitter_ns = round(jitter_s * NS_PER_S) if jitter_s * NS_PER_S < 2.0**64 else 1 << 64

    laser = _parse_laser(path, kind, lines, rows_by_type[kind], cfg)
    if not corrected:
        _check_backsteps(path, kind, laser["ipc_ns"], laser["line_numbers"], jitter_ns, cfg)
    scan_stamps, scan_restamped, line_order = _monotone(
        path, kind, laser["ipc_ns"], laser["line_numbers"], corrected
    )

    odometry = None
    odom_meta: dict = {}
    odom_restamped = 0
    if rows_by_type.get("ODOM"):
        odom = _parse_odom(path, lines, rows_by_type["ODOM"])
        if not corrected:
            _check_backsteps(path, "ODOM", odom["ipc_ns"], odom["line_numbers"], jitter_ns, cfg)
        odom_stamps, restamped, odom_line_order = _monotone(
            path, "ODOM", odom["ipc_ns"], odom["line_numbers"], corrected
        )
        if line_order or odom_line_order:  # one clock for every kind: line order
            line_order = True
            scan_stamps = laser["line_numbers"].astype(np.int64) * LINE_ORDER_STEP_NS
            odom_stamps = odom["line_numbers"].astype(np.int64) * LINE_ORDER_STEP_NS
            scan_restamped, restamped = np.ones(len(scan_stamps), bool), np.ones(len(odom_stamps), bool)
        odom_restamped = int(restamped.sum())
        odometry = Trajectory(odom_stamps, odom["poses_xytheta"], frame_id="odom")
        odom_meta = {
            "odometry_ipc_stamps_ns": odom["ipc_ns"],
            "odometry_logger_stamps_ns": odom["logger_ns"],
            "odometry_line_numbers": odom["line_numbers"],
        }

    # ROS time cannot be negative: every kind moved by one shift (scans and odometry stay on one clock)
    odom_stamps = odometry.stamps_ns if odometry is not None else None
    was_line_order = line_order
    scan_stamps, odom_stamps, shift_ns, line_order = _non_negative(
        path,
        laser["line_numbers"],
        scan_stamps,
        odom_meta.get("odometry_line_numbers"),
        odom_stamps,
        corrected,
        line_order,
    )
    if line_order and not was_line_order:  # no shift fits the years: stamped by line order instead
        scan_restamped = np.ones(len(scan_stamps), dtype=bool)
        odom_restamped = 0 if odom_stamps is None else len(odom_stamps)
    if odometry is not None and odom_stamps is not odometry.stamps_ns:
        odometry = Trajectory(odom_stamps, odometry.poses_xytheta, frame_id="odom")

    params = _params(lines, rows_by_type.get("PARAM", []))
    laser_in_base = _laser_in_base(laser["laser_xytheta"], laser["base_xytheta"])
    scan_poses = Trajectory(scan_stamps, laser["base_xytheta"], frame_id="odom")
    reference = Trajectory(scan_stamps, laser["base_xytheta"], frame_id="map") if corrected else None

    n_scans = len(laser["ranges"])
    scans = ScanSequence(
        laser["ranges"],
        laser["angles"],
        scan_stamps,
        # limits rounded to float32 as in a sensor_msgs/LaserScan, so they survive a bag round trip
        np.full(n_scans, cfg.carmen_range_min_m, dtype=np.float32).astype(np.float64),
        laser["range_max_m"].astype(np.float32).astype(np.float64),
        frame_ids="laser",
        sources=(kind,),
    )
    meta = {
        "carmen_laser": kind,
        "record_counts": counts,
        "ignored_records": {name: c for name, c in counts.items() if name not in (kind, "ODOM", "PARAM")},
        "corrected": corrected,
        "no_return": laser["no_return"],
        "params": params,
        "ipc_stamps_ns": laser["ipc_ns"],
        "logger_stamps_ns": laser["logger_ns"],
        "line_numbers": laser["line_numbers"],
        "laser_poses_xytheta": laser["laser_xytheta"],
        "restamped": {"laser": int(scan_restamped.sum()), "odometry": odom_restamped},
        "stamps_by_line_order": line_order,
        "stamp_shift_ns": shift_ns,
        "odometry_is_corrected": corrected and odometry is not None,
        **odom_meta,
    }
    return Recording(
        source=path,
        format="carmen",
        scans=scans,
        odometry=odometry,
        scan_poses=scan_poses,
        reference=reference,
        laser_in_base_xytheta=laser_in_base,
        meta=meta,
    )


# ----------------------------------------------------------------------------------------------- file


def _load_text(path: Path) -> bytes:
    """The decompressed bytes of ``path`` (gzip / bzip2 recognised by their magic bytes)."""
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise DatasetError(f"{path}: no such file or directory") from None
    except IsADirectoryError:
        raise DatasetError(f"{path}: is a directory, not a CARMEN log") from None
    except PermissionError:
        raise DatasetError(f"{path}: cannot read the file: permission denied") from None
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read the file: {exc.strerror or exc}") from None
    suffix = path.suffix.lower()
    if raw.startswith(_GZIP_MAGIC):
        try:
            return gzip.decompress(raw)
        except EOFError:
            raise CarmenError(
                f"{path}: truncated or corrupt gzip file (the data ends before its end marker)"
            ) from None
        except (OSError, zlib.error):
            raise CarmenError(f"{path}: corrupt gzip file (bad compressed data or checksum)") from None
        except MemoryError:
            raise CarmenError(f"{path}: the decompressed log does not fit in memory") from None
    if raw.startswith(_BZIP2_MAGIC):
        try:
            return bz2.decompress(raw)
        except (EOFError, ValueError):
            raise CarmenError(
                f"{path}: truncated or corrupt bzip2 file (the data ends before its end marker)"
            ) from None
        except OSError:
            raise CarmenError(f"{path}: corrupt bzip2 file (bad compressed data)") from None
        except MemoryError:
            raise CarmenError(f"{path}: the decompressed log does not fit in memory") from None
    if suffix == ".gz":
        raise CarmenError(f"{path}: not a gzip file (named .gz but no gzip header)")
    if suffix == ".bz2":
        raise CarmenError(f"{path}: not a bzip2 file (named .bz2 but no bzip2 header)")
    return raw


def _index_records(path: Path, data: bytes) -> tuple[list[bytes], dict[str, list[int]]]:
    """The lines of the log and, per record name, the indices of its lines (line number = index + 1)."""
    if not data.strip():
        raise CarmenError(f"{path}: empty file, not a CARMEN log")
    if b"\x00" in data[:65536]:
        raise CarmenError(f"{path}: binary data, not a CARMEN log (expected text records such as FLASER)")
    # (a log saved with classic Mac line ends, CR only, has no LF; CRLF lines keep their CR as whitespace)
    lines = data.split(b"\n" if b"\n" in data or b"\r" not in data else b"\r")
    rows_by_type: dict[bytes, list[int]] = {}
    for i, line in enumerate(lines):
        head = line.split(None, 1)
        if not head or head[0].startswith(b"#"):
            continue
        rows = rows_by_type.get(head[0])
        if rows is None:
            rows_by_type[head[0]] = [i]
        else:
            rows.append(i)
    return lines, {name.decode("ascii", "replace"): rows for name, rows in rows_by_type.items()}


def _choose_laser(path: Path, counts: dict[str, int], wanted: str) -> str:
    present = {k: counts[k] for k in LASER_RECORDS if counts.get(k)}
    if not present:
        raise CarmenError(f"{path}: not a CARMEN log: no FLASER, RLASER or ROBOTLASER1 records")
    if wanted == "auto":
        return max(present, key=lambda k: present[k])  # ties: the first of LASER_RECORDS
    if wanted not in present:
        found = ", ".join(f"{k} ({c})" for k, c in present.items())
        raise CarmenError(f"{path}: no {wanted} records (input.carmen_laser); the log has {found}")
    return wanted


# ---------------------------------------------------------------------------------------------- parse


def _laser_layout(kind: str, toks: list[bytes]) -> tuple[int, int, int]:
    """(n beams, m remissions, expected number of fields) of one laser line; ValueError if unreadable."""
    if kind == "ROBOTLASER1":
        if len(toks) < 10:
            raise ValueError(f"ROBOTLASER1 with {len(toks)} fields is too short")
        n = _count(toks[8], "reading count")
        if len(toks) < 10 + n:
            raise ValueError(f"ROBOTLASER1 says {n} readings but has {len(toks)} fields")
        m = _count(toks[9 + n], "remission count")
        return n, m, _ROBOTLASER_FIXED_FIELDS + n + m
    if len(toks) < 2:
        raise ValueError(f"{kind} without a reading count")
    n = _count(toks[1], "reading count")
    return n, 0, _FLASER_FIXED_FIELDS + n


def _count(token: bytes, what: str) -> int:
    text = token.decode("ascii", "replace")
    try:
        value = int(text)
    except ValueError:
        raise ValueError(f"{what} {shown(text)} is not an integer") from None
    if value < 0:
        raise ValueError(f"negative {what} {value}")
    return value


def _parse_floats(
    path: Path, kind: str, rows: Sequence[int], pieces: list[bytes], per_row: NDArray
) -> NDArray:
    """Numeric fields of many lines at once: ``pieces`` holds each row's fields, ``per_row`` their count."""
    try:
        return parse_floats(b" ".join(pieces))
    except NumberParseError as exc:
        j = int(np.searchsorted(np.cumsum(per_row), exc.index, side="right"))
        field = exc.index - int(np.sum(per_row[:j])) + 2  # values start at the record's second field
        raise CarmenError(
            f"{path}: line {rows[j] + 1}: {kind} field {field} {shown(exc.token)} is not a number"
        ) from None


def _check_finite(
    path: Path, kind: str, lines: list[bytes], rows: Sequence[int], values: NDArray, offsets: NDArray
) -> None:
    """CarmenError at the first non-finite value; ``offsets`` (R+1,) are the rows' starts in ``values``."""
    _reject_first(path, kind, lines, rows, ~np.isfinite(values), offsets, "is not finite")


def _reject_first(
    path: Path,
    kind: str,
    lines: list[bytes],
    rows: Sequence[int],
    bad: NDArray[np.bool_],
    offsets: NDArray,
    why: str,
) -> None:
    """CarmenError naming line and field of the first True of ``bad`` (a mask over the rows' values)."""
    where = np.flatnonzero(bad)
    if where.size == 0:
        return
    j = int(np.searchsorted(offsets, where[0], side="right") - 1)
    field = int(where[0] - offsets[j]) + 2  # values start at the second field
    token = lines[rows[j]].split()[field - 1].decode("ascii", "replace")
    raise CarmenError(f"{path}: line {rows[j] + 1}: {kind} field {field} {why} ({shown(token)})")


def _value_mask(size: int, index: NDArray) -> NDArray[np.bool_]:
    """(size,) False with True at ``index`` (any shape)."""
    out = np.zeros(size, dtype=bool)
    out[np.asarray(index, dtype=np.int64).ravel()] = True
    return out


def _check_in_range(
    path: Path,
    kind: str,
    lines: list[bytes],
    rows: Sequence[int],
    values: NDArray,
    offsets: NDArray,
    checks: Sequence[tuple[NDArray, float, str]],
) -> None:
    """CarmenError at the first value out of range; ``checks``: (value indices, largest |value|, what)."""
    first: tuple[int, str] | None = None
    for index, limit, what in checks:
        index = np.asarray(index, dtype=np.int64).ravel()
        over = index[np.abs(values[index]) > limit]
        if over.size and (first is None or int(over.min()) < first[0]):
            first = (int(over.min()), f"{what} is out of range (|value| > {limit:g})")
    if first is not None:
        _reject_first(path, kind, lines, rows, _value_mask(values.shape[0], first[0]), offsets, first[1])


def _check_stamp_range(path: Path, kind: str, stamps_ns: NDArray, rows: Sequence[int], what: str) -> None:
    """CarmenError at the first stamp beyond the year 2200 (or as far before 1970)."""
    bad = np.flatnonzero(np.abs(stamps_ns) > MAX_STAMP_NS)
    if bad.size:
        j = int(bad[0])
        raise CarmenError(
            f"{path}: line {rows[j] + 1}: {kind} {what} {ns_to_decimal(int(stamps_ns[j]))} s is out of range "
            "(after the year 2200 or as far before 1970)"
        )


def _stamps(path: Path, kind: str, tokens: list[bytes], rows: Sequence[int], what: str) -> NDArray[np.int64]:
    try:
        return parse_stamps_ns(b" ".join(tokens))
    except NumberParseError as exc:
        raise CarmenError(f"{path}: line {rows[exc.index] + 1}: {kind} {what} {exc}") from None


def _parse_laser(path: Path, kind: str, lines: list[bytes], rows: list[int], cfg: InputConfig) -> dict:
    """Ranges, angles, poses and stamps of the laser records at ``rows`` (indices into ``lines``)."""
    n_rows = len(rows)
    beams = np.empty(n_rows, dtype=np.int64)
    remissions = np.zeros(n_rows, dtype=np.int64)
    pieces: list[bytes] = []
    ipc: list[bytes] = []
    logger: list[bytes] = []
    for j, row in enumerate(rows):
        toks = lines[row].split()
        try:
            n, m, expected = _laser_layout(kind, toks)
        except ValueError as exc:
            raise CarmenError(f"{path}: line {row + 1}: {exc}") from None
        if n == 0:
            raise CarmenError(f"{path}: line {row + 1}: empty scan ({kind} with 0 readings)")
        if len(toks) != expected:
            raise CarmenError(
                f"{path}: line {row + 1}: {kind} says {n} readings but has {len(toks)} fields "
                f"instead of {expected}"
            )
        beams[j], remissions[j] = n, m
        pieces.append(b" ".join(toks[1:-3]))
        ipc.append(toks[-3])
        logger.append(toks[-1])
    per_row = beams + remissions + (_ROBOTLASER_FIXED_FIELDS - 4 if kind == "ROBOTLASER1" else 7)
    offsets = np.concatenate([[0], np.cumsum(per_row)])
    values = _parse_floats(path, kind, rows, pieces, per_row)
    _check_finite(path, kind, lines, rows, values, offsets)

    starts = offsets[:-1]
    first_range = starts + (8 if kind == "ROBOTLASER1" else 1)
    pose_start = first_range + beams + (remissions + 1 if kind == "ROBOTLASER1" else 0)
    before = np.concatenate([[0], np.cumsum(beams)[:-1]])
    range_index = np.repeat(first_range - before, beams) + np.arange(int(beams.sum()))
    xy_index = pose_start[:, None] + np.array([0, 1, 3, 4])
    checks = [
        (range_index, _FLOAT32_MAX, "range"),
        (xy_index, MAX_COORDINATE_M, "pose coordinate (m)"),
        (pose_start[:, None] + np.array([2, 5]), _MAX_HEADING_RAD, "pose heading (rad)"),
    ]
    if kind == "ROBOTLASER1":  # start angle, angular resolution, maximum range
        checks.append((starts[:, None] + np.array([1, 3]), _MAX_ANGLE_RAD, "angle (rad)"))
        checks.append((starts + 4, _FLOAT32_MAX, "maximum range"))
    _check_in_range(path, kind, lines, rows, values, offsets, checks)
    if kind == "ROBOTLASER1":  # beams spread from the start angle by a positive step (0: all one angle)
        res_index = starts + 3
        not_positive = _value_mask(values.shape[0], res_index[~(values[res_index] > 0)])
        _reject_first(path, kind, lines, rows, not_positive, offsets, "angular resolution is not positive")
    flat_ranges = values[range_index]
    negative = np.flatnonzero(flat_ranges < 0)
    if negative.size:
        j = int(np.searchsorted(before, negative[0], side="right") - 1)
        beam = int(negative[0] - before[j])
        raise CarmenError(
            f"{path}: line {rows[j] + 1}: negative range {flat_ranges[negative[0]]:g} m "
            f"(beam {beam} of the {kind} scan)"
        )
    ranges = np.split(flat_ranges.astype(np.float32), np.cumsum(beams)[:-1])
    poses = values[pose_start[:, None] + np.arange(6)]

    if kind == "ROBOTLASER1":
        start_rad, res_rad, max_m = (values[starts + k] for k in (1, 3, 4))
        keys = list(zip(start_rad.tolist(), res_rad.tolist(), beams.tolist(), strict=True))
        declared = np.where(max_m > 0, max_m, cfg.carmen_range_max_m)
        low = np.flatnonzero(declared.astype(np.float32) <= np.float32(cfg.carmen_range_min_m))
        if low.size:
            j = int(low[0])
            raise CarmenError(
                f"{path}: line {rows[j] + 1}: ROBOTLASER1 maximum range {max_m[j]:g} m is not above "
                f"input.carmen_range_min_m = {cfg.carmen_range_min_m:g} m"
            )
        rule = "the maximum range declared in each ROBOTLASER1 record"
    else:  # FLASER / RLASER: 180 degrees, angle_i = -pi/2 + i*pi/n; no declared maximum
        keys = [(-np.pi / 2, np.pi / n, n) for n in beams.tolist()]
        declared = np.full(n_rows, cfg.carmen_range_max_m)
        rule = "input.carmen_range_max_m"
    # a reading the log repeats at the top of its range is its no-return code (fr-clinic logs 81.83 m
    # beside its declared 81.9 m); below the declared maximum it takes over
    repeated = repeated_maximum_m(flat_ranges)
    if repeated is not None and cfg.carmen_range_min_m < repeated.value_m < float(np.min(declared)):
        range_max = np.minimum(declared, repeated.value_m)
        no_return = {
            "rule": "the log's repeated maximum reading",
            "range_m": repeated.value_m,
            "values_m": list(repeated.values_m),
            "readings": list(repeated.counts),
        }
    else:
        range_max = declared
        no_return = {"rule": rule, "range_m": float(np.min(declared))}
        if repeated is not None:
            no_return["repeated_maximum_m"] = list(repeated.values_m)
    angle_cache: dict[tuple, NDArray[np.float32]] = {}  # scans with equal settings share one array
    for k in set(keys):
        with np.errstate(all="ignore"):  # checked below
            angle_cache[k] = beam_angles_rad(*k)
        if not np.isfinite(angle_cache[k]).all():
            j = keys.index(k)
            raise CarmenError(
                f"{path}: line {rows[j] + 1}: {kind} beam angles are not finite (start angle {k[0]:g} rad, "
                f"resolution {k[1]:g} rad, {k[2]} beams)"
            )
    angles = [angle_cache[k] for k in keys]
    return {
        "ranges": ranges,
        "angles": angles,
        "range_max_m": range_max,
        "no_return": no_return,
        "laser_xytheta": poses[:, :3].copy(),
        "base_xytheta": poses[:, 3:].copy(),
        "ipc_ns": _ipc_stamps(path, kind, ipc, rows),
        "logger_ns": _stamps(path, kind, logger, rows, "logger timestamp"),
        "line_numbers": np.asarray(rows, dtype=np.int64) + 1,
    }


def _ipc_stamps(path: Path, kind: str, tokens: list[bytes], rows: Sequence[int]) -> NDArray[np.int64]:
    """The ipc stamps (the records' stamps): exact, and within the years a recording can have."""
    stamps_ns = _stamps(path, kind, tokens, rows, "ipc timestamp")
    _check_stamp_range(path, kind, stamps_ns, rows, "ipc timestamp")
    return stamps_ns


def _parse_odom(path: Path, lines: list[bytes], rows: list[int]) -> dict:
    """Poses and stamps of the ODOM records at ``rows``."""
    pieces: list[bytes] = []
    ipc: list[bytes] = []
    logger: list[bytes] = []
    for row in rows:
        toks = lines[row].split()
        if len(toks) != _ODOM_FIELDS:
            raise CarmenError(
                f"{path}: line {row + 1}: ODOM has {len(toks)} fields instead of {_ODOM_FIELDS} "
                "(x y theta tv rv accel ipc_timestamp hostname logger_timestamp)"
            )
        pieces.append(b" ".join(toks[1:7]))
        ipc.append(toks[7])
        logger.append(toks[9])
    values = _parse_floats(path, "ODOM", rows, pieces, np.full(len(rows), 6))
    offsets = np.arange(len(rows) + 1) * 6
    _check_finite(path, "ODOM", lines, rows, values, offsets)
    checks = [
        (offsets[:-1, None] + np.array([0, 1]), MAX_COORDINATE_M, "coordinate (m)"),
        (offsets[:-1] + 2, _MAX_HEADING_RAD, "heading (rad)"),
    ]
    _check_in_range(path, "ODOM", lines, rows, values, offsets, checks)
    return {
        "poses_xytheta": values.reshape(-1, 6)[:, :3].copy(),
        "ipc_ns": _ipc_stamps(path, "ODOM", ipc, rows),
        "logger_ns": _stamps(path, "ODOM", logger, rows, "logger timestamp"),
        "line_numbers": np.asarray(rows, dtype=np.int64) + 1,
    }


def _params(lines: list[bytes], rows: list[int]) -> dict[str, str]:
    out: dict[str, str] = {}
    for row in rows:
        toks = lines[row].split()
        if len(toks) >= 3:
            out[toks[1].decode("ascii", "replace")] = toks[2].decode("ascii", "replace")
    return out


# ------------------------------------------------------------------------------------- frames, stamps


def _laser_in_base(laser_xytheta: NDArray, base_xytheta: NDArray) -> NDArray[np.float64]:
    """(3,) laser mounting in the base frame: the median laser pose seen from the base pose."""
    d = laser_xytheta - base_xytheta
    c, s = np.cos(base_xytheta[:, 2]), np.sin(base_xytheta[:, 2])
    local = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], wrap_angle_rad(d[:, 2])], axis=1)
    offset = np.median(local, axis=0)
    offset[np.abs(offset) < 1e-9] = 0.0
    return offset


#: Stamp spacing of the records of a corrected log whose stamps carry no time at all (ns per line).
LINE_ORDER_STEP_NS = 100_000_000


def _monotone(
    path: Path, kind: str, stamps_ns: NDArray, line_numbers: NDArray, corrected: bool
) -> tuple[NDArray[np.int64], NDArray[np.bool_], bool]:
    """:func:`monotone_stamps_ns` of one record kind; ``(stamps, restamped, by_line_order)``.

    When re-stamping cannot put the records in order within the usable years (a log whose stamps are
    nearly all one placeholder, as ``infinite-corridor-corrected.log`` with 1,937 of its 1,941 scans at
    4.29497e+09 s), a corrected log is stamped by line order instead (line order is the truth there:
    ``LINE_ORDER_STEP_NS`` per line, every record of every kind on one clock); a raw log, whose stamps
    associate odometry with scans, is then a CarmenError.
    """
    stamps, restamped = monotone_stamps_ns(stamps_ns)
    if stamps.size and (
        np.any(stamps[1:] <= stamps[:-1]) or max(abs(int(stamps[0])), abs(int(stamps[-1]))) > MAX_STAMP_NS
    ):
        if corrected:
            by_line = np.asarray(line_numbers, dtype=np.int64) * LINE_ORDER_STEP_NS
            return by_line, np.ones(stamps.shape[0], dtype=bool), True
        raise CarmenError(
            f"{path}: the {kind} timestamps cannot be put in order within the years 1740-2200 "
            f"({int(restamped.sum())} records re-stamped): the stamps are damaged"
        )
    return stamps, restamped, False


def _non_negative(
    path: Path,
    scan_lines: NDArray,
    scan_stamps: NDArray[np.int64],
    odom_lines: NDArray | None,
    odom_stamps: NDArray[np.int64] | None,
    corrected: bool,
    line_order: bool,
) -> tuple[NDArray[np.int64], NDArray[np.int64] | None, int, bool]:
    """Stamps of every record kind shifted by one amount so that none is negative.

    Re-stamping extrapolates records before the first kept stamp one median step apart
    (:func:`datasets.stamps.monotone_stamps_ns`): the placeholder stamps of ``orebro-corrected.log`` (every
    scan at 0 s) become -236 ns .. 0, and its ODOM records reach -2115.9 s; a raw log may log negative stamps
    itself. ROS time cannot be negative, and the clock offset of such a log carries no information, so
    scans and odometry are moved together (their relative timing unchanged) by the whole number of seconds
    that brings the earliest stamp to [0, 1 s). Returns ``(scan stamps, odometry stamps, shift in ns,
    by_line_order)``; the shift is 0 (and the arrays untouched) when no stamp is negative. A shift that
    would carry the latest stamp beyond the year 2200 stamps a corrected log by line order instead (as
    :func:`_monotone` does; shift 0) and is a CarmenError for a raw log.
    """
    kinds = [scan_stamps] + ([odom_stamps] if odom_stamps is not None and odom_stamps.size else [])
    earliest = min(int(k.min()) for k in kinds if k.size)
    if earliest >= 0:
        return scan_stamps, odom_stamps, 0, line_order
    shift = -(earliest // NS_PER_S) * NS_PER_S  # whole seconds: the decimals of every stamp are kept
    latest = max(int(k.max()) for k in kinds if k.size)
    if latest + shift > MAX_STAMP_NS:
        if corrected:
            by_line = np.asarray(scan_lines, dtype=np.int64) * LINE_ORDER_STEP_NS
            odom = (
                None if odom_stamps is None else np.asarray(odom_lines, dtype=np.int64) * LINE_ORDER_STEP_NS
            )
            return by_line, odom, 0, True
        raise CarmenError(
            f"{path}: the timestamps run from {ns_to_decimal(earliest)} s to {ns_to_decimal(latest)} s: "
            "shifted to start at 0 s they end after the year 2200 (ROS time cannot be negative): "
            "the stamps are damaged"
        )
    shifted = scan_stamps + np.int64(shift)
    return shifted, None if odom_stamps is None else odom_stamps + np.int64(shift), shift, line_order


def _check_backsteps(
    path: Path, kind: str, stamps_ns: NDArray, line_numbers: NDArray, jitter_ns: int, cfg: InputConfig
) -> None:
    """CarmenError when a stamp lies more than the jitter before the latest earlier stamp of its kind."""
    if stamps_ns.shape[0] < 2:
        return
    span_ns = int(stamps_ns.max()) - int(stamps_ns.min())
    if span_ns <= jitter_ns:  # no step back can exceed the jitter (also: an infinite jitter)
        return
    # stamps far apart overflow int64 differences: Python ints then
    work = stamps_ns.astype(object) if span_ns >= 1 << 62 else stamps_ns
    latest = np.maximum.accumulate(work)
    back = latest[:-1] - work[1:]
    bad = np.flatnonzero(back > jitter_ns)  # jitter_ns may exceed int64 only when span_ns <= jitter_ns
    if bad.size == 0:
        return
    j = int(bad[0]) + 1
    k = int(np.argmax(stamps_ns[:j] == latest[j - 1]))
    raise CarmenError(
        f"{path}: line {line_numbers[j]}: timestamps go backwards: {kind} at {ns_to_decimal(stamps_ns[j])} s "
        f"is {back[j - 1] / NS_PER_S:.3f} s before line {line_numbers[k]} "
        f"(more than input.carmen_stamp_jitter_s = {cfg.carmen_stamp_jitter_s:g} s); a SLAM-corrected log "
        "takes any stamps but is known by its name: keep 'corrected' or '.gfs.' in it"
    )
