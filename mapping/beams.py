"""Training data of the sensor model (paper section 3.4): laser beams in the world frame.

Every beam is a free-space segment from the laser origin ``P`` to an end ``Q``. A beam with a return has an
occupied endpoint (+1) at ``Q``; a beam without one (range >= range_max, inf or NaN: SPEC section 2) is a free
segment of a configured length and has no endpoint. Ranges below ``range_min`` are dropped.

The free training point for a query ``x*`` is the point of a segment closest to it (eqs. 13-14, clamped to the
segment). The free part of a segment can stop ``free_margin_m`` short of its endpoint so that a query just
behind a wall is not given a free point lying on the wall's own occupied endpoint.

For GPPOL (issue 5) each beam keeps what the unscented transform (:mod:`mapping.unscented`) needs: its
measured range and bearing in the laser frame, the laser's heading, the laser mounting on the base (so that
the
base pose, whose covariance SLAM gives, is recovered exactly), the index of its scan (the caller's pose
covariances are indexed by it) and its sensor (per-source noise settings).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numba as nb
import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Beams:
    """Beams of many scans in the world frame, M of them.

    - ``origins_xy_m`` (M, 2): laser position ``P`` at the scan;
    - ``ends_xy_m`` (M, 2): end ``Q`` of the beam: the endpoint of a return, or the end of the free segment
      of a no-return beam;
    - ``free_ends_xy_m`` (M, 2): end of the free part (for a return, ``Q`` moved ``free_margin_m`` to ``P``);
    - ``is_hit`` (M,) bool: the beam has a return (its ``ends_xy_m`` is an occupied point);
    - ``ranges_m`` (M,), ``bearings_rad`` (M,): the measurement in the laser frame (no-return beams carry the
      free length as range);
    - ``scan_index`` (M,) int32: index of the scan in the caller's sequence; ``beam_index`` (M,) int32: index
      of the beam within its scan; ``source_index`` (M,) int32: sensor of the scan;
    - ``laser_theta_rad`` (M,): heading of the laser at the scan (world frame);
    - ``laser_in_base_xytheta`` (3,): the laser mounting on the base (one for all beams);
    - ``source_names``: names of the sensors that ``source_index`` points into (e.g. scan topics).
    """

    origins_xy_m: FloatArray
    ends_xy_m: FloatArray
    free_ends_xy_m: FloatArray
    is_hit: NDArray[np.bool_]
    ranges_m: FloatArray
    bearings_rad: FloatArray
    scan_index: NDArray[np.int32]
    beam_index: NDArray[np.int32]
    source_index: NDArray[np.int32]
    laser_theta_rad: FloatArray
    laser_in_base_xytheta: FloatArray = field(default_factory=lambda: np.zeros(3))
    source_names: tuple[str, ...] = ("laser",)

    def __len__(self) -> int:
        return int(self.is_hit.shape[0])

    @property
    def hit_xy_m(self) -> FloatArray:
        """(H, 2) occupied endpoints (returns only), in beam order."""
        return self.ends_xy_m[self.is_hit]

    def bounds_xy_m(self, margin_m: float = 0.0) -> tuple[float, float, float, float]:
        """``(xmin, ymin, xmax, ymax)`` of every origin and end, grown by ``margin_m``."""
        pts = np.concatenate([self.origins_xy_m, self.ends_xy_m])
        lo = pts.min(axis=0) - margin_m
        hi = pts.max(axis=0) + margin_m
        return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])

    def select_scans(self, scan_indices: Sequence[int] | NDArray) -> Beams:
        """The beams of the scans in ``scan_indices`` (scan indices are kept, not renumbered)."""
        keep = np.isin(self.scan_index, np.asarray(scan_indices, dtype=np.int64))
        return self.subset(keep)

    def subset(self, mask_or_index: NDArray) -> Beams:
        """The beams selected by a boolean mask or an index array."""
        m = mask_or_index
        return Beams(
            origins_xy_m=self.origins_xy_m[m],
            ends_xy_m=self.ends_xy_m[m],
            free_ends_xy_m=self.free_ends_xy_m[m],
            is_hit=self.is_hit[m],
            ranges_m=self.ranges_m[m],
            bearings_rad=self.bearings_rad[m],
            scan_index=self.scan_index[m],
            beam_index=self.beam_index[m],
            source_index=self.source_index[m],
            laser_theta_rad=self.laser_theta_rad[m],
            laser_in_base_xytheta=self.laser_in_base_xytheta,
            source_names=self.source_names,
        )

    def with_free_margin(self, free_margin_m: float) -> Beams:
        """The same beams with the free part of every return ending ``free_margin_m`` short of its endpoint
        (no-return beams keep their whole free segment)."""
        d = self.ends_xy_m - self.origins_xy_m
        free_len = free_lengths_m(self.ranges_m, self.is_hit, free_margin_m)
        scale = np.divide(free_len, self.ranges_m, out=np.ones(len(self)), where=self.ranges_m > 0)
        return replace(self, free_ends_xy_m=self.origins_xy_m + scale[:, None] * d)

    def base_poses_xytheta(self) -> FloatArray:
        """(M, 3) world pose of the base at each beam's scan (the laser pose with the mounting undone)."""
        m = self.laser_in_base_xytheta
        theta = self.laser_theta_rad - m[2]
        c, s = np.cos(theta), np.sin(theta)
        x = self.origins_xy_m[:, 0] - (c * m[0] - s * m[1])
        y = self.origins_xy_m[:, 1] - (s * m[0] + c * m[1])
        return np.stack([x, y, theta], axis=1)


def select_scans_by_motion(
    poses_xytheta: FloatArray, min_travel_m: float, min_rotation_rad: float
) -> NDArray[np.int64]:
    """Indices of the scans to map: the first one, then each scan whose pose (N, 3) moved at least
    ``min_travel_m`` or turned at least ``min_rotation_rad`` since the last selected one (both 0: all scans).

    A robot standing still logs the same scan again and again; mapping them all costs time and adds no
    information (and would over-weight those places).
    """
    p = np.asarray(poses_xytheta, dtype=np.float64).reshape(-1, 3)
    n = p.shape[0]
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    if min_travel_m <= 0 and min_rotation_rad <= 0:
        return np.arange(n, dtype=np.int64)
    return _select_by_motion(p, float(min_travel_m), float(min_rotation_rad))


@nb.njit(cache=True)
def _select_by_motion(p, min_travel, min_rot):  # pragma: no cover - compiled
    n = p.shape[0]
    out = np.empty(n, dtype=np.int64)
    out[0] = 0
    m = 1
    last = 0
    for i in range(1, n):
        dx = p[i, 0] - p[last, 0]
        dy = p[i, 1] - p[last, 1]
        dth = abs((p[i, 2] - p[last, 2] + np.pi) % (2.0 * np.pi) - np.pi)
        if (min_travel > 0 and dx * dx + dy * dy >= min_travel * min_travel) or (
            min_rot > 0 and dth >= min_rot
        ):
            out[m] = i
            m += 1
            last = i
    return out[:m]


def compose_laser_poses(poses_xytheta: FloatArray, laser_in_base_xytheta: FloatArray) -> FloatArray:
    """(N, 3) world poses of the laser from (N, 3) base poses and the (3,) laser mounting in the base."""
    p = np.asarray(poses_xytheta, dtype=np.float64).reshape(-1, 3)
    m = np.asarray(laser_in_base_xytheta, dtype=np.float64).reshape(3)
    c, s = np.cos(p[:, 2]), np.sin(p[:, 2])
    out = np.empty_like(p)
    out[:, 0] = p[:, 0] + c * m[0] - s * m[1]
    out[:, 1] = p[:, 1] + s * m[0] + c * m[1]
    out[:, 2] = p[:, 2] + m[2]
    return out


def free_lengths_m(lengths_m: FloatArray, is_hit: NDArray[np.bool_], free_margin_m: float) -> FloatArray:
    """(M,) length of the free part of (M,) beams: a return's stops ``free_margin_m`` short of its endpoint
    (never below 0), a no-return beam is free along its whole length."""
    return np.where(is_hit, np.maximum(lengths_m - free_margin_m, 0.0), lengths_m)


def beams_from_scans(
    ranges_m: Sequence[NDArray],
    angles_rad: Sequence[NDArray],
    range_min_m: NDArray | Sequence[float] | float,
    range_max_m: NDArray | Sequence[float] | float,
    poses_xytheta: FloatArray,
    laser_in_base_xytheta: FloatArray | None = None,
    no_return_free_length_m: float | None = None,
    free_margin_m: float = 0.0,
    source_index: NDArray | None = None,
    scan_indices: Sequence[int] | NDArray | None = None,
    source_names: Sequence[str] | None = None,
) -> Beams:
    """World-frame beams of N scans.

    ``ranges_m`` / ``angles_rad``: N arrays of (B_i,) beams in the laser frame; ``range_min_m`` /
    ``range_max_m``: scalars or (N,); ``poses_xytheta`` (N, 3): base poses in the world;
    ``laser_in_base_xytheta`` (3,): laser mounting (default: the laser is the base). No-return beams give a
    free segment of ``no_return_free_length_m`` (None: the scan's ``range_max``; 0 drops them) and no
    endpoint. ``scan_indices`` (N,) numbers
    the scans (default 0..N-1), e.g. their indices in a longer sequence; ``source_names`` names the sensors
    ``source_index`` (N,) points into.
    """
    n = len(ranges_m)
    poses = np.asarray(poses_xytheta, dtype=np.float64).reshape(-1, 3)
    if poses.shape[0] != n or len(angles_rad) != n:
        raise ValueError(f"{n} scans but {poses.shape[0]} poses and {len(angles_rad)} angle arrays")
    mount = np.zeros(3) if laser_in_base_xytheta is None else np.asarray(laser_in_base_xytheta, np.float64)
    laser = compose_laser_poses(poses, mount)
    rmin = np.broadcast_to(np.asarray(range_min_m, dtype=np.float64), (n,))
    rmax = np.broadcast_to(np.asarray(range_max_m, dtype=np.float64), (n,))
    src = np.zeros(n, np.int32) if source_index is None else np.asarray(source_index, np.int32).reshape(n)
    sidx = np.arange(n) if scan_indices is None else np.asarray(scan_indices, dtype=np.int64).reshape(n)
    counts = np.array([len(r) for r in ranges_m], dtype=np.int64)
    names = tuple(source_names) if source_names is not None else ("laser",)
    if n == 0 or counts.sum() == 0:
        return _empty_beams(mount, names)
    r = np.concatenate([np.asarray(x, dtype=np.float64) for x in ranges_m])
    a = np.concatenate([np.asarray(x, dtype=np.float64) for x in angles_rad])
    scan_of = np.repeat(np.arange(n), counts)
    beam_of = np.concatenate([np.arange(c) for c in counts]).astype(np.int32)
    with np.errstate(invalid="ignore"):
        no_return = ~np.isfinite(r) | (r >= rmax[scan_of])
        hit = ~no_return & (r >= rmin[scan_of])
    nr = no_return_free_length_m
    no_return_len = rmax[scan_of] if nr is None else np.full(r.shape, nr)
    keep = hit | (no_return & (no_return_len > 0))
    length = np.where(hit, r, no_return_len)
    r, a, length, hit, scan_of, beam_of = (
        r[keep],
        a[keep],
        length[keep],
        hit[keep],
        scan_of[keep],
        beam_of[keep],
    )
    pose = laser[scan_of]
    ang = pose[:, 2] + a
    u = np.stack([np.cos(ang), np.sin(ang)], axis=1)
    origins = pose[:, :2].copy()
    ends = origins + length[:, None] * u
    free_len = free_lengths_m(length, hit, free_margin_m)
    free_ends = origins + free_len[:, None] * u
    return Beams(
        origins_xy_m=origins,
        ends_xy_m=ends,
        free_ends_xy_m=free_ends,
        is_hit=hit,
        ranges_m=length,
        bearings_rad=a,
        scan_index=sidx[scan_of].astype(np.int32),
        beam_index=beam_of,
        source_index=src[scan_of],
        laser_theta_rad=pose[:, 2].copy(),
        laser_in_base_xytheta=mount.copy(),
        source_names=names,
    )


def beams_from_scan_sequence(
    scans,
    poses_xytheta: FloatArray,
    laser_in_base_xytheta: FloatArray | None = None,
    no_return_free_length_m: float | None = None,
    free_margin_m: float = 0.0,
    scan_indices: Sequence[int] | NDArray | None = None,
) -> Beams:
    """:func:`beams_from_scans` for any object with ``ranges_m``, ``angles_rad`` (per-scan lists),
    ``range_min_m``, ``range_max_m`` and ``source_index`` (N,) arrays (e.g. a ``ScanSequence``)."""
    return beams_from_scans(
        scans.ranges_m,
        scans.angles_rad,
        scans.range_min_m,
        scans.range_max_m,
        poses_xytheta,
        laser_in_base_xytheta,
        no_return_free_length_m=no_return_free_length_m,
        free_margin_m=free_margin_m,
        source_index=getattr(scans, "source_index", None),
        scan_indices=scan_indices,
        source_names=getattr(scans, "sources", None),
    )


def _empty_beams(mount: FloatArray | None = None, names: tuple[str, ...] = ("laser",)) -> Beams:
    z2 = np.zeros((0, 2))
    z = np.zeros(0)
    zi = np.zeros(0, np.int32)
    m = np.zeros(3) if mount is None else np.asarray(mount, np.float64).copy()
    return Beams(z2, z2, z2, np.zeros(0, bool), z, z, zi, zi, zi, z, m, names)
