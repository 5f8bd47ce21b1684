"""Training data of the sensor model (paper section 3.4): laser beams in the world frame.

Every beam is a free-space segment from the laser origin ``P`` to an end ``Q``. A beam with a return has an
occupied endpoint (+1) at ``Q``; a beam without one (range >= range_max, inf or NaN: SPEC section 2) is a free
segment of a configured length and has no endpoint. Ranges below ``range_min`` are dropped.

The free training point for a query ``x*`` is the point of a segment closest to it (eqs. 13-14, clamped to the
segment). The free part of a segment can stop ``free_margin_m`` short of its endpoint so that a query just
behind a wall is not given a free point lying on the wall's own occupied endpoint.

A beam that meets a surface at a grazing angle gamma (between the beam and the surface) runs within a band of
half-width delta of that surface for the last delta / sin(gamma) of its length, so a fixed margin lets it free
the surface it grazes. With a band (``grazing_margins_m``: delta(r) = ``band_m`` + r
``band_per_m``, the beam's spread and range noise) the free part of a return stops max(``free_margin_m``,
delta(r) / sin(gamma)) short of its endpoint, the grazing term capped at ``max_m`` and never past the beam's
start. The surface direction at a return is the chord between its neighbouring returns in the same scan; a
return without both neighbours, or at a depth edge or corner, keeps the plain margin.

For GPPOL each beam keeps what the unscented transform (:mod:`mapping.unscented`) needs: its
measured range and bearing in the laser frame, the laser's heading, the laser mounting on the base (so that
the base pose, whose covariance SLAM gives, is recovered exactly), the index of its scan (the caller's pose
covariances are indexed by it) and its sensor (per-source noise settings).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numba as nb
import numpy as np
from numpy.typing import NDArray

from datasets import se2

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Beams:
    """Beams of many scans in the world frame, M of them.

    - ``origins_xy_m`` (M, 2): laser position ``P`` at the scan;
    - ``ends_xy_m`` (M, 2): end ``Q`` of the beam: the endpoint of a return, or the end of the free segment
      of a no-return beam;
    - ``free_ends_xy_m`` (M, 2): end of the free part (for a return, ``Q`` moved ``free_margin_m`` to ``P``,
      or ``grazing_margin_m`` if larger);
    - ``is_hit`` (M,) bool: the beam has a return (its ``ends_xy_m`` is an occupied point);
    - ``ranges_m`` (M,), ``bearings_rad`` (M,): the measurement in the laser frame (no-return beams carry the
      free length as range);
    - ``scan_index`` (M,) int32: index of the scan in the caller's sequence; ``beam_index`` (M,) int32: index
      of the beam within its scan; ``source_index`` (M,) int32: sensor of the scan;
    - ``laser_theta_rad`` (M,): heading of the laser at the scan (world frame);
    - ``laser_in_base_xytheta`` (3,): the laser mounting on the base (one for all beams);
    - ``source_names``: names of the sensors that ``source_index`` points into (e.g. scan topics);
    - ``grazing_margin_m`` (M,): the incidence- and range-dependent part of each return's free margin
      (:func:`grazing_margins_m`; 0 for no-return beams, returns without a surface direction, and when no band
      is configured; None is read as zeros). ``free_margin_m`` is its floor.
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
    grazing_margin_m: FloatArray | None = None

    def __post_init__(self) -> None:
        if self.grazing_margin_m is None:
            object.__setattr__(self, "grazing_margin_m", np.zeros(self.is_hit.shape[0]))

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
            grazing_margin_m=self.grazing_margin_m[m],
        )

    def with_free_margin(self, free_margin_m: float) -> Beams:
        """The same beams with the free part of every return ending ``free_margin_m`` (or its own
        ``grazing_margin_m`` if larger) short of its endpoint (no-return beams keep their whole free
        segment)."""
        d = self.ends_xy_m - self.origins_xy_m
        free_len = free_lengths_m(self.ranges_m, self.is_hit, free_margin_m, self.grazing_margin_m)
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
    out = np.empty_like(p)
    out[:, :2] = se2.transform_points(p, m[:2])
    out[:, 2] = p[:, 2] + m[2]  # not wrapped (unlike se2.compose): base_poses_xytheta subtracts m[2] again
    return out


def free_lengths_m(
    lengths_m: FloatArray,
    is_hit: NDArray[np.bool_],
    free_margin_m: float,
    grazing_margin_m: FloatArray | None = None,
) -> FloatArray:
    """(M,) length of the free part of (M,) beams: a return's stops max(``free_margin_m``,
    ``grazing_margin_m``) (M,) short of its endpoint (never below 0), a no-return beam is free along its whole
    length."""
    margin = free_margin_m if grazing_margin_m is None else np.maximum(free_margin_m, grazing_margin_m)
    return np.where(is_hit, np.maximum(lengths_m - margin, 0.0), lengths_m)


# Depth edges and corners (module docstring): a return's two neighbours give its surface direction only when
# the steps to them point the same way within this angle and neither is this many times longer than the other.
TANGENT_MAX_TURN_RAD = float(np.deg2rad(30.0))
TANGENT_MAX_STEP_RATIO = 3.0


def grazing_margins_m(
    ends_xy_m: FloatArray,
    directions_xy: FloatArray,
    lengths_m: FloatArray,
    is_hit: NDArray[np.bool_],
    scan_of: NDArray[np.integer],
    band_m: float,
    band_per_m: float = 0.0,
    max_m: float | None = None,
) -> FloatArray:
    """(M,) how far short of its endpoint a return's free part must stop not to enter a band of half-width
    delta(r) = ``band_m`` + r ``band_per_m`` around the surface it hit: delta(r) / sin(gamma), gamma the angle
    between the beam and the surface, capped at ``max_m`` (None: no cap); 0 where unknown.

    ``ends_xy_m`` (M, 2) endpoints, ``directions_xy`` (M, 2) unit beam directions, ``lengths_m`` (M,) ranges,
    ``is_hit`` (M,), ``scan_of`` (M,): the beams of every scan in beam order, scans one after another. The
    surface direction at return i is the chord from return i-1 to return i+1 of the same scan; a return
    without both neighbours, or whose steps to them turn by more than ``TANGENT_MAX_TURN_RAD`` or differ in
    length by more than ``TANGENT_MAX_STEP_RATIO`` (a depth edge, a corner, a thin object), gets 0 (the plain
    margin applies)."""
    m = lengths_m.shape[0]
    out = np.zeros(m)
    if m < 3 or (band_m <= 0 and band_per_m <= 0):
        return out
    e = np.asarray(ends_xy_m, np.float64)
    hit = np.asarray(is_hit, bool)
    same = scan_of[1:] == scan_of[:-1]
    # return i (1 <= i <= m-2) with returns of its scan at i-1 and i+1
    ok = hit[1:-1] & hit[:-2] & hit[2:] & same[:-1] & same[1:]
    d1 = e[1:-1] - e[:-2]
    d2 = e[2:] - e[1:-1]
    l1 = np.hypot(d1[:, 0], d1[:, 1])
    l2 = np.hypot(d2[:, 0], d2[:, 1])
    lo, hi = np.minimum(l1, l2), np.maximum(l1, l2)
    with np.errstate(invalid="ignore", divide="ignore"):
        cos_turn = np.einsum("ij,ij->i", d1, d2) / (l1 * l2)
        ok &= (lo > 0) & (hi <= TANGENT_MAX_STEP_RATIO * lo) & (cos_turn >= np.cos(TANGENT_MAX_TURN_RAD))
        t = e[2:] - e[:-2]
        u = directions_xy[1:-1]
        sin_gamma = np.abs(u[:, 0] * t[:, 1] - u[:, 1] * t[:, 0]) / np.hypot(t[:, 0], t[:, 1])
    delta = band_m + band_per_m * lengths_m[1:-1]
    grazing = delta / np.maximum(sin_gamma, 1e-12)  # a beam along its surface: no free part (capped below)
    if max_m is not None:
        grazing = np.minimum(grazing, max_m)
    out[1:-1] = np.where(ok, np.minimum(grazing, lengths_m[1:-1]), 0.0)
    return out


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
    free_band_m: float = 0.0,
    free_band_per_m: float = 0.0,
    free_margin_max_m: float | None = None,
) -> Beams:
    """World-frame beams of N scans.

    ``ranges_m`` / ``angles_rad``: N arrays of (B_i,) beams in the laser frame; ``range_min_m`` /
    ``range_max_m``: scalars or (N,); ``poses_xytheta`` (N, 3): base poses in the world;
    ``laser_in_base_xytheta`` (3,): laser mounting (default: the laser is the base). No-return beams give a
    free segment of ``no_return_free_length_m`` (None: the scan's ``range_max``; 0 drops them) and no
    endpoint. ``scan_indices`` (N,) numbers
    the scans (default 0..N-1), e.g. their indices in a longer sequence; ``source_names`` names the sensors
    ``source_index`` (N,) points into. A return's free part stops ``free_margin_m`` short of its endpoint, or
    more where it grazes a surface (:func:`grazing_margins_m` with ``free_band_m``, ``free_band_per_m``,
    ``free_margin_max_m``; both bands 0: never more).
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
    if free_band_m > 0 or free_band_per_m > 0:
        # surface directions from the neighbouring returns, before dropped beams close the gaps they leave
        pose = laser[scan_of]
        ang = pose[:, 2] + a
        u = np.stack([np.cos(ang), np.sin(ang)], axis=1)
        ends = pose[:, :2] + np.where(hit, length, 0.0)[:, None] * u
        grazing = grazing_margins_m(
            ends, u, length, hit, scan_of, free_band_m, free_band_per_m, free_margin_max_m
        )[keep]
    else:
        grazing = np.zeros(int(keep.sum()))
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
    free_len = free_lengths_m(length, hit, free_margin_m, grazing)
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
        grazing_margin_m=grazing,
    )


def beams_from_scan_sequence(
    scans,
    poses_xytheta: FloatArray,
    laser_in_base_xytheta: FloatArray | None = None,
    no_return_free_length_m: float | None = None,
    free_margin_m: float = 0.0,
    scan_indices: Sequence[int] | NDArray | None = None,
    free_band_m: float = 0.0,
    free_band_per_m: float = 0.0,
    free_margin_max_m: float | None = None,
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
        free_band_m=free_band_m,
        free_band_per_m=free_band_per_m,
        free_margin_max_m=free_margin_max_m,
    )


def _empty_beams(mount: FloatArray | None = None, names: tuple[str, ...] = ("laser",)) -> Beams:
    z2 = np.zeros((0, 2))
    z = np.zeros(0)
    zi = np.zeros(0, np.int32)
    m = np.zeros(3) if mount is None else np.asarray(mount, np.float64).copy()
    return Beams(z2, z2, z2, np.zeros(0, bool), z, z, zi, zi, zi, z, m, names)
