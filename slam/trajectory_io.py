"""Trajectory files: TUM, g2o pose graphs and the covariance archive of a run folder (SPEC section 4).

- TUM (``evo`` reads it): one pose per line, ``t x y z qx qy qz qw``, ``t`` in seconds; 2D poses are
  written with ``z = 0`` and a yaw-only quaternion. Stamps are written from integer nanoseconds exactly
  (``sec.nanosec``) and read back exactly.
- g2o: ``VERTEX_SE2 id x y theta`` and ``EDGE_SE2 i j dx dy dtheta I11 I12 I13 I22 I23 I33`` (upper triangle
  of the information matrix in the measurement's child frame); loop closures are edges like the others.
  ``FIX id`` marks an anchored vertex (the prior).
- Numbers are written as the shortest text that reads back bit for bit (Python's ``repr``, as exact as
  ``%.17g``): g2o vertices and measurements and TUM positions round-trip exactly; a TUM yaw goes through its
  quaternion and comes back within an ulp or two. (GTSAM's ``writeG2o`` keeps 6 significant digits.)
- covariances ``.npz``: ``before`` / ``after`` (K, 3, 3) world-frame keyframe marginals, ``stamps_ns`` (K,)
  and the scan ``indices`` (K,) of the keyframes.

Readers raise :class:`TrajectoryFormatError` (a DatasetError: one line naming the file and line) on bad input.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from datasets.errors import DatasetError, first_line, shown
from datasets.files import atomic_output, write_text_atomic
from datasets.stamps import stamp_field_ns
from slam.graph import Edge

FloatArray = NDArray[np.float64]
NS_PER_S = 1_000_000_000


class TrajectoryFormatError(DatasetError):
    """A trajectory, pose-graph or covariance file is missing or malformed."""


def _read_lines(path: Path) -> list[str]:
    try:
        return Path(path).read_text().splitlines()
    except FileNotFoundError:
        raise TrajectoryFormatError(f"{path}: no such file or directory") from None
    except IsADirectoryError:
        raise TrajectoryFormatError(f"{path}: is a directory") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise TrajectoryFormatError(f"{path}: cannot read: {first_line(exc)}") from None


def _stamp_text(stamp_ns: int) -> str:
    sign = "-" if stamp_ns < 0 else ""
    s, ns = divmod(abs(int(stamp_ns)), NS_PER_S)
    return f"{sign}{s}.{ns:09d}"


def _parse_stamp(path: Path, number: int, text: str) -> int:
    """Exact nanoseconds of a stamp field in decimal seconds; TrajectoryFormatError naming the line."""
    try:
        return stamp_field_ns(text)
    except ValueError as exc:
        raise TrajectoryFormatError(f"{path}: line {number}: stamp {shown(text)} {exc}") from None


def _finite_floats(path: Path, number: int, fields: list[str], what: str) -> list[float]:
    """The float values of ``fields``; TrajectoryFormatError naming the line if one is not a finite number."""
    out = []
    for text in fields:
        try:
            value = float(text)
        except ValueError:
            raise TrajectoryFormatError(
                f"{path}: line {number}: {what} {shown(text)} is not a number"
            ) from None
        if not math.isfinite(value):
            raise TrajectoryFormatError(f"{path}: line {number}: {what} {shown(text)} is not finite")
        out.append(value)
    return out


def _vertex_id(path: Path, number: int, text: str) -> int:
    """A g2o vertex id (an int64); TrajectoryFormatError naming the line otherwise."""
    if not _INT_RE.fullmatch(text):
        raise TrajectoryFormatError(f"{path}: line {number}: vertex id {shown(text)} is not an integer")
    value = int(text)
    if not -(2**63) <= value < 2**63:
        raise TrajectoryFormatError(f"{path}: line {number}: vertex id {shown(text)} is out of range (int64)")
    return value


_INT_RE = re.compile(r"[+-]?[0-9]{1,30}")


# --------------------------------------------------------------------------------------------------- TUM


def write_tum(path: str | Path, stamps_ns: NDArray[np.int64], poses_xytheta: FloatArray) -> None:
    """Write (N,) stamps and (N, 3) poses as a TUM file (atomically)."""
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    poses = np.asarray(poses_xytheta, dtype=np.float64)
    if poses.shape != (stamps.shape[0], 3):
        raise ValueError(f"write_tum: {stamps.shape[0]} stamps but poses of shape {poses.shape}")
    half = 0.5 * poses[:, 2]
    lines = ["# t x y z qx qy qz qw"]
    for t, (x, y, _), qz, qw in zip(
        stamps, poses.tolist(), np.sin(half).tolist(), np.cos(half).tolist(), strict=True
    ):
        lines.append(f"{_stamp_text(t)} {x!r} {y!r} 0.0 0.0 0.0 {qz!r} {qw!r}")
    write_text_atomic(path, "\n".join(lines) + "\n")


#: A TUM quaternion whose norm is within this of 1 is read (printed with few decimals); others are refused.
QUATERNION_NORM_TOLERANCE = 1e-2


def read_tum(path: str | Path) -> tuple[NDArray[np.int64], FloatArray]:
    """(N,) stamps_ns and (N, 3) poses (x, y, yaw) of a TUM file (the yaw of the quaternion, which must be
    a unit one within :data:`QUATERNION_NORM_TOLERANCE`)."""
    path = Path(path)
    stamps: list[int] = []
    poses: list[tuple[float, float, float]] = []
    for number, line in enumerate(_read_lines(path), start=1):
        text = line.strip()
        if not text or text.startswith("#"):
            continue
        fields = text.split()
        if len(fields) != 8:
            raise TrajectoryFormatError(
                f"{path}: line {number}: expected 8 fields (t x y z qx qy qz qw), got {len(fields)}"
            )
        t = _parse_stamp(path, number, fields[0])
        try:
            x, y, _z, qx, qy, qz, qw = (float(v) for v in fields[1:])
        except ValueError:
            raise TrajectoryFormatError(
                f"{path}: line {number}: not a number in {shown(text, 100)}"
            ) from None
        if not all(np.isfinite([x, y, qx, qy, qz, qw])):
            raise TrajectoryFormatError(f"{path}: line {number}: NaN or infinite value")
        with np.errstate(all="ignore"):  # a huge quaternion overflows to a NaN yaw, rejected below
            yaw = np.arctan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))
        if not np.isfinite(yaw):
            raise TrajectoryFormatError(f"{path}: line {number}: quaternion too large for a yaw angle")
        norm = math.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
        if abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE:
            raise TrajectoryFormatError(
                f"{path}: line {number}: not a unit quaternion (qx qy qz qw = {qx:g} {qy:g} {qz:g} {qw:g}, "
                f"norm {norm:.6g})"
            )
        stamps.append(t)
        poses.append((x, y, float(yaw)))
    return np.asarray(stamps, dtype=np.int64), np.asarray(poses, dtype=np.float64).reshape(-1, 3)


# --------------------------------------------------------------------------------------------------- g2o


@dataclass(frozen=True)
class G2oGraph:
    """A 2D pose graph read from g2o: (K, 3) vertices (ids 0..K-1 in file order), edges, fixed vertex ids."""

    ids: NDArray[np.int64]
    vertices_xytheta: FloatArray
    edges: tuple[Edge, ...]
    fixed: tuple[int, ...]


def write_g2o(path: str | Path, vertices_xytheta: FloatArray, edges: list[Edge] | tuple[Edge, ...]) -> None:
    """Write ``VERTEX_SE2`` lines for (K, 3) vertices (ids 0..K-1) and ``EDGE_SE2`` lines for the between
    edges (odometry and loop closures, with their information); priors become ``FIX`` lines, written last
    (GTSAM's ``readG2o`` reads the file completely only then)."""
    lines = []
    fixed = []
    for k, (x, y, th) in enumerate(np.asarray(vertices_xytheta, dtype=np.float64).tolist()):
        lines.append(f"VERTEX_SE2 {k} {x!r} {y!r} {th!r}")
    for e in edges:
        if e.kind == "prior":
            fixed.append(f"FIX {e.key_from}")
            continue
        info = e.information
        info = 0.5 * (info + info.T)
        dx, dy, dth = (float(v) for v in e.measurement_xytheta)
        upper = (info[0, 0], info[0, 1], info[0, 2], info[1, 1], info[1, 2], info[2, 2])
        lines.append(
            f"EDGE_SE2 {e.key_from} {e.key_to} {dx!r} {dy!r} {dth!r} "
            + " ".join(repr(float(v)) for v in upper)
        )
    # FIX lines last: GTSAM's readG2o stops reading edges at a FIX line that precedes them.
    write_text_atomic(path, "\n".join(lines + fixed) + "\n")


def read_g2o(path: str | Path) -> G2oGraph:
    """Read a 2D g2o file (``VERTEX_SE2``, ``EDGE_SE2``, ``FIX``); other tags are an error."""
    path = Path(path)
    ids: list[int] = []
    verts: list[tuple[float, float, float]] = []
    raw_edges: list[tuple[int, int, tuple[float, ...], int]] = []
    fixed: list[tuple[int, int]] = []  # (vertex id, line number)
    for number, line in enumerate(_read_lines(path), start=1):
        fields = line.split()
        if not fields or fields[0].startswith("#"):
            continue
        tag = fields[0]
        if tag == "VERTEX_SE2":
            if len(fields) != 5:
                raise TrajectoryFormatError(f"{path}: line {number}: VERTEX_SE2 needs 4 values")
            ids.append(_vertex_id(path, number, fields[1]))
            x, y, theta = _finite_floats(path, number, fields[2:], "VERTEX_SE2 value")
            verts.append((x, y, theta))
        elif tag == "EDGE_SE2":
            if len(fields) != 12:
                raise TrajectoryFormatError(f"{path}: line {number}: EDGE_SE2 needs 11 values")
            i, j = (_vertex_id(path, number, v) for v in fields[1:3])
            vals = tuple(_finite_floats(path, number, fields[3:], "EDGE_SE2 value"))
            raw_edges.append((i, j, vals, number))
        elif tag == "FIX":
            fixed.extend((_vertex_id(path, number, v), number) for v in fields[1:])
        else:
            raise TrajectoryFormatError(f"{path}: line {number}: unsupported g2o record {shown(tag)}")
    index = {v: k for k, v in enumerate(ids)}
    if len(index) != len(ids):
        raise TrajectoryFormatError(f"{path}: duplicate vertex ids")
    edges = []
    for i, j, vals, number in raw_edges:
        if i not in index or j not in index:
            raise TrajectoryFormatError(f"{path}: line {number}: edge between unknown vertices {i} and {j}")
        info = np.array(
            [[vals[3], vals[4], vals[5]], [vals[4], vals[6], vals[7]], [vals[5], vals[7], vals[8]]],
            dtype=np.float64,
        )
        try:
            with np.errstate(all="ignore"):
                cov = np.linalg.inv(info)
        except np.linalg.LinAlgError:
            raise TrajectoryFormatError(f"{path}: line {number}: singular information matrix") from None
        if not np.all(np.isfinite(cov)):
            raise TrajectoryFormatError(f"{path}: line {number}: information matrix with no finite inverse")
        kind = "odometry" if index[j] == index[i] + 1 else "loop"  # g2o does not say; consecutive ids
        edges.append(Edge(kind, index[i], index[j], np.array(vals[:3]), cov))
    for vertex, number in fixed:
        if vertex not in index:
            raise TrajectoryFormatError(f"{path}: line {number}: FIX of unknown vertex {vertex}")
    return G2oGraph(
        np.asarray(ids, dtype=np.int64),
        np.asarray(verts, dtype=np.float64).reshape(-1, 3),
        tuple(edges),
        tuple(vertex for vertex, _ in fixed),
    )


# ------------------------------------------------------------------------------------------- covariances


def save_covariances(
    path: str | Path,
    stamps_ns: NDArray[np.int64],
    before: FloatArray,
    after: FloatArray,
    indices: NDArray[np.int64] | None = None,
) -> None:
    """Write (K, 3, 3) world-frame marginals before / after loop closure with their (K,) stamps."""
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    k = stamps.shape[0]
    b = np.asarray(before, dtype=np.float64)
    a = np.asarray(after, dtype=np.float64)
    if b.shape != (k, 3, 3) or a.shape != (k, 3, 3):
        raise ValueError(f"save_covariances: {k} stamps, before {b.shape}, after {a.shape}")
    idx = np.arange(k, dtype=np.int64) if indices is None else np.asarray(indices, dtype=np.int64)
    with atomic_output(path, suffix=".npz") as tmp:
        np.savez(tmp, stamps_ns=stamps, before=b, after=a, indices=idx, frame="world", order="x y theta")


def load_covariances(path: str | Path) -> dict[str, NDArray]:
    """The arrays written by :func:`save_covariances` (``stamps_ns``, ``before``, ``after``, ``indices``)."""
    path = Path(path)
    try:
        with np.load(path) as data:
            out = {k: np.asarray(data[k]) for k in ("stamps_ns", "before", "after", "indices")}
    except FileNotFoundError:
        raise TrajectoryFormatError(f"{path}: no such file or directory") from None
    except KeyError as exc:
        raise TrajectoryFormatError(f"{path}: missing array {shown(exc.args[0])}") from None
    except (OSError, ValueError) as exc:
        raise TrajectoryFormatError(f"{path}: not a covariance archive ({first_line(exc)})") from None
    k = out["stamps_ns"].shape[0]
    for name in ("before", "after"):
        if out[name].shape != (k, 3, 3):
            raise TrajectoryFormatError(f"{path}: {name} has shape {out[name].shape}, expected ({k}, 3, 3)")
    return out


def yaw_quaternion(theta_rad: FloatArray) -> FloatArray:
    """(N, 4) quaternions (qx, qy, qz, qw) of yaw angles."""
    half = 0.5 * np.asarray(theta_rad, dtype=np.float64)
    z = np.zeros_like(half)
    return np.stack([z, z, np.sin(half), np.cos(half)], axis=-1)
