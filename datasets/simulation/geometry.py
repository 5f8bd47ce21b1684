"""2D world model: solid polygons (buildings, vehicles, walls, pillars) in the world frame.

A world is a set of closed, simple polygons; everything inside a polygon or on its boundary is occupied,
everything else is free. Polygons are ``(K, 2)`` float64 arrays of vertices in metres, in order (either
orientation), the closing edge implied. Walls are thin rectangles, so every obstacle has an inside and the
ground-truth raster and the ray caster agree on what is solid.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from datasets.errors import DatasetError

FloatArray = NDArray[np.float64]


def rectangle(
    center_xy_m: Sequence[float], length_m: float, width_m: float, heading_rad: float = 0.0
) -> FloatArray:
    """(4, 2) corners of a ``length x width`` rectangle centred on ``center_xy_m``, length along heading."""
    c, s = np.cos(heading_rad), np.sin(heading_rad)
    half = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]], dtype=np.float64) * [length_m / 2, width_m / 2]
    rot = np.array([[c, -s], [s, c]])
    return half @ rot.T + np.asarray(center_xy_m, dtype=np.float64)


def box(xmin_m: float, ymin_m: float, xmax_m: float, ymax_m: float) -> FloatArray:
    """(4, 2) corners of the axis-aligned box ``[xmin, xmax] x [ymin, ymax]`` (counter-clockwise)."""
    if not (xmax_m > xmin_m and ymax_m > ymin_m):
        raise DatasetError(f"empty box ({xmin_m}, {ymin_m}, {xmax_m}, {ymax_m})")
    return np.array(
        [[xmin_m, ymin_m], [xmax_m, ymin_m], [xmax_m, ymax_m], [xmin_m, ymax_m]], dtype=np.float64
    )


def wall(start_xy_m: Sequence[float], end_xy_m: Sequence[float], thickness_m: float = 0.2) -> FloatArray:
    """(4, 2) a straight wall from ``start`` to ``end`` (its centre line), ``thickness_m`` thick.

    The wall is extended by half its thickness past both ends, so walls meeting at a corner close it.
    """
    p0 = np.asarray(start_xy_m, dtype=np.float64)
    p1 = np.asarray(end_xy_m, dtype=np.float64)
    d = p1 - p0
    length = float(np.hypot(*d))
    if length == 0.0:
        raise DatasetError(f"wall of zero length at {p0.tolist()}")
    return rectangle((p0 + p1) / 2, length + thickness_m, thickness_m, float(np.arctan2(d[1], d[0])))


def wall_with_gaps(
    start_xy_m: Sequence[float],
    end_xy_m: Sequence[float],
    gaps_m: Iterable[tuple[float, float]],
    thickness_m: float = 0.2,
) -> list[FloatArray]:
    """Wall pieces along ``start -> end`` leaving open ``gaps_m`` = [(distance from start, width), ...].

    Used for door openings in corridor walls. Returns the list of (4, 2) wall pieces.
    """
    p0 = np.asarray(start_xy_m, dtype=np.float64)
    p1 = np.asarray(end_xy_m, dtype=np.float64)
    length = float(np.hypot(*(p1 - p0)))
    u = (p1 - p0) / length
    cuts = [0.0]
    for offset, width in sorted(gaps_m):
        if not (cuts[-1] <= offset and offset + width <= length):
            raise DatasetError(f"wall gap at {offset} m (width {width} m) outside the wall or overlapping")
        cuts += [offset, offset + width]
    cuts.append(length)
    pieces = []
    for a, b in zip(cuts[0::2], cuts[1::2], strict=True):
        if b - a > 1e-9:
            # pieces end flush with the gap (no half-thickness extension into the door)
            pieces.append(rectangle(p0 + u * (a + b) / 2, b - a, thickness_m, float(np.arctan2(u[1], u[0]))))
    # the outer ends keep the corner-closing extension of wall()
    if pieces and cuts[1] > 0:
        pieces[0] = _extend(pieces[0], p0, u, -thickness_m / 2)
    if pieces and cuts[-2] < length:
        pieces[-1] = _extend(pieces[-1], p1, u, thickness_m / 2)
    return pieces


def _extend(piece: FloatArray, end_xy: FloatArray, u: FloatArray, amount_m: float) -> FloatArray:
    """Move the two corners of a wall piece that lie at ``end_xy`` by ``amount_m`` along ``u``."""
    out = piece.copy()
    along = (piece - end_xy) @ u
    near = np.abs(along) < 1e-6
    out[near] += u * amount_m
    return out


def regular_polygon(center_xy_m: Sequence[float], radius_m: float, sides: int, phase_rad: float = 0.0):
    """(sides, 2) a regular polygon (round pillars, tree trunks) inscribed in a circle of ``radius_m``."""
    a = phase_rad + 2 * np.pi * np.arange(sides) / sides
    return np.stack([np.cos(a), np.sin(a)], axis=1) * radius_m + np.asarray(center_xy_m, dtype=np.float64)


def polygon_area_m2(polygon: FloatArray) -> float:
    """Area of a simple polygon (shoelace formula), always >= 0."""
    x, y = polygon[:, 0], polygon[:, 1]
    return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


@dataclass(frozen=True)
class World:
    """A 2D world: solid polygons, what each one is, and the rectangle the ground truth covers.

    ``bounds_xy_m`` = (xmin, ymin, xmax, ymax) of the scene (the ground-truth raster's extent);
    ``polygons[i]`` (K_i, 2) vertices; ``kinds[i]`` e.g. ``"building"``, ``"car"``, ``"van"``, ``"wall"``.
    """

    name: str
    polygons: tuple[FloatArray, ...]
    kinds: tuple[str, ...]
    bounds_xy_m: tuple[float, float, float, float]

    def __post_init__(self) -> None:
        if len(self.polygons) != len(self.kinds):
            raise DatasetError(
                f"world {self.name}: {len(self.polygons)} polygons but {len(self.kinds)} kinds"
            )
        polys = []
        for i, p in enumerate(self.polygons):
            a = np.ascontiguousarray(p, dtype=np.float64)
            if a.ndim != 2 or a.shape[1] != 2 or a.shape[0] < 3:
                raise DatasetError(f"world {self.name}: polygon {i} has shape {a.shape}, expected (K>=3, 2)")
            polys.append(a)
        object.__setattr__(self, "polygons", tuple(polys))
        xmin, ymin, xmax, ymax = (float(v) for v in self.bounds_xy_m)
        if not (xmax > xmin and ymax > ymin):
            raise DatasetError(f"world {self.name}: empty bounds {self.bounds_xy_m}")
        object.__setattr__(self, "bounds_xy_m", (xmin, ymin, xmax, ymax))

    @property
    def area_m2(self) -> float:
        """Area of the scene rectangle (the ground truth's extent)."""
        xmin, ymin, xmax, ymax = self.bounds_xy_m
        return (xmax - xmin) * (ymax - ymin)

    def edges(self) -> FloatArray:
        """(E, 4) every polygon edge as ``x0, y0, x1, y1`` (the input of the ray caster)."""
        if not self.polygons:
            return np.zeros((0, 4))
        return np.concatenate([np.concatenate([p, np.roll(p, -1, axis=0)], axis=1) for p in self.polygons])

    def select(self, kind: str) -> list[FloatArray]:
        """The polygons of one kind."""
        return [p for p, k in zip(self.polygons, self.kinds, strict=True) if k == kind]

    def without(self, *kinds: str) -> World:
        """This world without the polygons of ``kinds`` (e.g. what a laser sees: no glass)."""
        keep = [i for i, k in enumerate(self.kinds) if k not in kinds]
        return replace(
            self, polygons=tuple(self.polygons[i] for i in keep), kinds=tuple(self.kinds[i] for i in keep)
        )
