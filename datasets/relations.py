"""Relations files of the SLAM benchmark of Kuemmerle et al. (Autonomous Robots 27, 2009): read and write.

One relation per line, ``#`` comments and blank lines allowed::

    t1 t2 x y z roll pitch yaw

the relative pose of the robot at time ``t2`` seen from its pose at time ``t1`` (metres, radians).
Timestamps are parsed from their decimal text to exact integer nanoseconds; floats are written with the
shortest text that reads back to the same float64, so a write / read round trip is exact.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from datasets.errors import DatasetError, shown
from datasets.files import write_text_atomic
from datasets.stamps import NS_PER_S, ns_to_decimal, stamp_field_ns
from datasets.validate import MAX_COORDINATE_M

FIELDS = "t1 t2 x y z roll pitch yaw"


class RelationsError(DatasetError):
    """A relations file is missing, unreadable or malformed (the message names the file and line)."""


@dataclass(frozen=True)
class Relations:
    """R relative-pose measurements between pairs of timestamps.

    ``stamps1_ns`` / ``stamps2_ns`` (R,) int64 exact nanoseconds (``stamps1_s`` / ``stamps2_s`` as float
    seconds), ``xyz_m`` (R, 3) translation and ``rpy_rad`` (R, 3) roll, pitch, yaw of pose 2 in the frame
    of pose 1.
    """

    stamps1_ns: NDArray[np.int64]
    stamps2_ns: NDArray[np.int64]
    xyz_m: NDArray[np.float64]
    rpy_rad: NDArray[np.float64]

    def __post_init__(self) -> None:
        s1 = np.asarray(self.stamps1_ns, dtype=np.int64).reshape(-1)
        s2 = np.asarray(self.stamps2_ns, dtype=np.int64).reshape(-1)
        xyz = np.asarray(self.xyz_m, dtype=np.float64)
        rpy = np.asarray(self.rpy_rad, dtype=np.float64)
        n = s1.shape[0]
        if s2.shape != (n,) or xyz.shape != (n, 3) or rpy.shape != (n, 3):
            raise DatasetError(
                f"relations: {n} first stamps, {s2.shape[0]} second stamps, xyz {xyz.shape}, rpy {rpy.shape}"
            )
        for name, value in (("stamps1_ns", s1), ("stamps2_ns", s2), ("xyz_m", xyz), ("rpy_rad", rpy)):
            object.__setattr__(self, name, value)

    def __len__(self) -> int:
        return int(self.stamps1_ns.shape[0])

    @property
    def stamps1_s(self) -> NDArray[np.float64]:
        """(R,) first timestamps in float seconds (rounded; use ``stamps1_ns`` to match stamps exactly)."""
        return self.stamps1_ns / NS_PER_S

    @property
    def stamps2_s(self) -> NDArray[np.float64]:
        return self.stamps2_ns / NS_PER_S


def read_relations(path: str | Path) -> Relations:
    """Read a relations file; RelationsError (one line, file and line number) on bad input."""
    path = Path(path)
    try:
        text = path.read_text(encoding="ascii")
    except FileNotFoundError:
        raise RelationsError(f"{path}: no such file or directory") from None
    except IsADirectoryError:
        raise RelationsError(f"{path}: is a directory, not a relations file") from None
    except PermissionError:
        raise RelationsError(f"{path}: cannot read the file: permission denied") from None
    except UnicodeDecodeError:
        raise RelationsError(f"{path}: not a relations file (not plain text)") from None
    except OSError as exc:
        raise RelationsError(f"{path}: cannot read the file: {exc.strerror or exc}") from None
    s1: list[int] = []
    s2: list[int] = []
    values: list[list[float]] = []
    for number, line in enumerate(text.splitlines(), start=1):
        toks = line.split()
        if not toks or toks[0].startswith("#"):
            continue
        if len(toks) != 8:
            raise RelationsError(f"{path}: line {number}: expected 8 fields ({FIELDS}), found {len(toks)}")
        t1, t2 = (_stamp(path, number, tok) for tok in toks[:2])
        row = []
        for tok in toks[2:]:
            try:
                value = float(tok)
            except ValueError:
                raise RelationsError(f"{path}: line {number}: {shown(tok)} is not a number") from None
            if not np.isfinite(value):
                raise RelationsError(f"{path}: line {number}: non-finite value {shown(tok)}")
            row.append(value)
        _check_relation(path, number, t1, t2, row)
        s1.append(t1)
        s2.append(t2)
        values.append(row)
    if not values:
        raise RelationsError(f"{path}: no relations ({FIELDS} per line)")
    v = np.array(values, dtype=np.float64)
    return Relations(np.array(s1, np.int64), np.array(s2, np.int64), v[:, :3], v[:, 3:])


#: |roll|, |pitch|, |yaw| of a relation beyond this is damage (the benchmark's lie within +-2 pi).
MAX_RELATION_ANGLE_RAD = 1e3


def _check_relation(path: Path, number: int, t1: int, t2: int, row: list[float]) -> None:
    """RelationsError naming the line for a relation no benchmark holds: a translation beyond
    :data:`~datasets.validate.MAX_COORDINATE_M`, an angle beyond :data:`MAX_RELATION_ANGLE_RAD`, or a scan
    related to itself by a motion (the same stamp twice with a non-zero relative pose)."""
    xyz, rpy = row[:3], row[3:]
    if max(abs(v) for v in xyz) > MAX_COORDINATE_M:
        raise RelationsError(f"{path}: line {number}: translation beyond {MAX_COORDINATE_M:g} m")
    if max(abs(v) for v in rpy) > MAX_RELATION_ANGLE_RAD:
        raise RelationsError(f"{path}: line {number}: angle beyond {MAX_RELATION_ANGLE_RAD:g} rad")
    if t1 == t2 and any(v != 0.0 for v in row):
        raise RelationsError(
            f"{path}: line {number}: relates a scan to itself (both stamps {_stamp_text(t1)}) by a motion"
        )


def _stamp(path: Path, number: int, token: str) -> int:
    """Exact nanoseconds of one timestamp field; RelationsError naming the line if it is not one."""
    try:
        return stamp_field_ns(token)
    except ValueError as exc:
        raise RelationsError(f"{path}: line {number}: timestamp {shown(token)} {exc}") from None


def _stamp_text(stamp_ns: int) -> str:
    text = ns_to_decimal(stamp_ns).rstrip("0")
    return text + "0" if text.endswith(".") else text


def write_relations(path: str | Path, relations: Relations) -> None:
    """Write ``relations`` to ``path`` (through a temporary file renamed at the end: never half written)."""
    path = Path(path)
    if not (np.all(np.isfinite(relations.xyz_m)) and np.all(np.isfinite(relations.rpy_rad))):
        raise RelationsError(f"{path}: cannot write relations with non-finite values")
    lines = [f"# {FIELDS}"]
    for t1, t2, xyz, rpy in zip(
        relations.stamps1_ns.tolist(),
        relations.stamps2_ns.tolist(),
        relations.xyz_m.tolist(),
        relations.rpy_rad.tolist(),
        strict=True,
    ):
        numbers = " ".join(repr(float(v)) for v in (*xyz, *rpy))
        lines.append(f"{_stamp_text(t1)} {_stamp_text(t2)} {numbers}")
    try:
        write_text_atomic(path, "\n".join(lines) + "\n", encoding="ascii")
    except OSError as exc:
        raise RelationsError(f"{path}: cannot write: {exc.strerror or exc}") from None
