"""Simulated sensors: a planar laser scanner and drifting wheel odometry, plus smooth robot paths.

Laser model (per beam, independent draws):

- the beam is cast along the nominal bearing plus a Gaussian bearing error (variance
  ``bearing_variance_rad2``) and *reported at the nominal bearing*, as a real scanner does;
- the true distance to the first surface gets a Gaussian range error (variance ``range_variance_m2``);
- **no return**: a beam whose (noisy) range is ``>= range_max_m``, or that hits nothing, is written as
  ``+inf`` (REP 117: "no detection within the sensor's range"), which consumers treat as free space only;
- a (noisy) range below ``range_min_m`` is written as ``0.0``, an invalid reading that consumers drop
  (like the small error codes of real drivers); it never happens unless the robot grazes a wall;
- all beams of a scan are taken at the scan's stamp (no motion distortion: ``time_increment = 0``).

A real scanner does worse than Gaussian noise; :class:`LaserArtifacts` (off unless a spec carries one) adds,
in this order, each with its own random draws after the ones above:

- **grazing incidence**: a beam meeting a surface at an angle of incidence (to the surface normal) beyond
  ``max_incidence_rad`` returns nothing, and with a probability rising linearly from 0 to 1 over the
  ``incidence_fade_rad`` below it (too little light comes back from a wall seen edge-on: a long smooth
  corridor wall is seen only near the robot);
- **mixed pixels**: where two neighbouring beams' true ranges differ by more than ``mixed_pixel_jump_m``
  (a depth edge), the spot straddles both surfaces and, with ``mixed_pixel_probability``, one of the two
  beams reports a range uniformly between them (the "veil" points of real scans);
- **outliers**: with ``outlier_probability`` a beam reports a spurious range uniform between ``range_min_m``
  and its true range (dust, a reflection, a passer-by's leg);
- **dropouts**: with ``dropout_probability`` a beam returns nothing (a dark or specular spot).

Odometry model (differential drive, per odometry step, on the true body-frame increment ``dx, dy, dtheta``
over ``ds = hypot(dx, dy)``; variances scale with the increment, so the drift does not depend on the rate):

- ``dx' = (1 + distance_scale_error) dx + N(0, translation_variance_m2_per_m * ds)``, same for ``dy``
  (``lateral_variance_m2_per_m``);
- ``dtheta' = (1 + rotation_scale_error) dtheta + yaw_bias_rad_per_m * ds
  + N(0, rotation_variance_rad2_per_rad * |dtheta| + rotation_variance_rad2_per_m * ds)``.

``distance_scale_error`` models a wheel-radius error, ``rotation_scale_error`` a wheel-base error and
``yaw_bias_rad_per_m`` unequal wheel radii: together the systematic drift that makes loop closure matter.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np
from numpy.typing import NDArray

from datasets import se2
from datasets.errors import DatasetError
from datasets.simulation.raycast import cast_rays, cast_rays_hit_edges
from datasets.types import beam_angles_rad

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class LaserArtifacts:
    """Effects of a real scanner beyond Gaussian range and bearing noise (see the module docstring)."""

    max_incidence_rad: float = float(np.pi / 2)
    incidence_fade_rad: float = 0.0
    mixed_pixel_jump_m: float = 0.3
    mixed_pixel_probability: float = 0.0
    outlier_probability: float = 0.0
    dropout_probability: float = 0.0


@dataclass(frozen=True)
class LaserSpec:
    """A planar laser scanner: its beams, range limits and noise, and the topic it publishes on.

    ``artifacts``: grazing-incidence losses, mixed pixels, outliers and dropouts (None: none of them).
    """

    topic: str
    num_beams: int
    angle_min_rad: float
    angle_increment_rad: float
    range_min_m: float
    range_max_m: float
    range_variance_m2: float = 0.0
    bearing_variance_rad2: float = 0.0
    frame_id: str = "laser"
    rate_hz: float = 10.0
    artifacts: LaserArtifacts | None = None

    @classmethod
    def sweep(cls, topic: str, num_beams: int, fov_deg: float, **kwargs) -> LaserSpec:
        """Beams evenly spaced over ``fov_deg`` centred on the x axis (both ends included, unless 360 deg)."""
        if num_beams < 2:
            raise DatasetError(f"a laser sweep needs at least 2 beams, got {num_beams}")
        fov = np.deg2rad(fov_deg)
        if np.isclose(fov_deg, 360.0):
            inc = 2 * np.pi / num_beams
            return cls(topic, num_beams, -np.pi, inc, **kwargs)
        return cls(topic, num_beams, -fov / 2, fov / (num_beams - 1), **kwargs)

    def angles_rad(self) -> NDArray[np.float32]:
        """(B,) nominal beam angles in the laser frame (the canonical float32 construction)."""
        return beam_angles_rad(self.angle_min_rad, self.angle_increment_rad, self.num_beams)

    def as_dict(self) -> dict:
        out = asdict(self)
        if self.artifacts is None:  # specs without artifacts describe themselves as before they existed
            del out["artifacts"]
        return out


@dataclass(frozen=True)
class OdometryNoise:
    """Wheel-odometry error model (see the module docstring); all zeros means exact odometry."""

    translation_variance_m2_per_m: float = 0.0
    lateral_variance_m2_per_m: float = 0.0
    rotation_variance_rad2_per_rad: float = 0.0
    rotation_variance_rad2_per_m: float = 0.0
    distance_scale_error: float = 0.0
    rotation_scale_error: float = 0.0
    yaw_bias_rad_per_m: float = 0.0

    def as_dict(self) -> dict[str, float]:
        return {k: float(v) for k, v in asdict(self).items()}


def simulate_ranges(
    edges: FloatArray, laser_poses_xytheta: FloatArray, spec: LaserSpec, rng: np.random.Generator
) -> NDArray[np.float32]:
    """(N, B) float32 measured ranges of ``spec`` from (N, 3) laser poses in the world (see module doc)."""
    poses = np.asarray(laser_poses_xytheta, dtype=np.float64).reshape(-1, 3)
    n, b = poses.shape[0], spec.num_beams
    bearing_err = rng.normal(0.0, np.sqrt(spec.bearing_variance_rad2), (n, b))
    range_err = rng.normal(0.0, np.sqrt(spec.range_variance_m2), (n, b))
    world_angles = poses[:, 2:3] + spec.angles_rad().astype(np.float64)[None, :] + bearing_err
    if spec.artifacts is None:
        true_m = cast_rays(poses[:, None, :2], world_angles, edges)
        measured = true_m + range_err
    else:
        true_m, hit_edge = cast_rays_hit_edges(poses[:, None, :2], world_angles, edges)
        measured = _with_artifacts(true_m, hit_edge, world_angles, edges, range_err, spec, rng)
    out = np.where(np.isfinite(true_m) & (measured < spec.range_max_m), measured, np.inf)
    out = np.where(out < spec.range_min_m, 0.0, out)
    return out.astype(np.float32)


def _with_artifacts(
    true_m: FloatArray,
    hit_edge: NDArray[np.int64],
    world_angles_rad: FloatArray,
    edges: FloatArray,
    range_err_m: FloatArray,
    spec: LaserSpec,
    rng: np.random.Generator,
) -> FloatArray:
    """(N, B) measured ranges with the :class:`LaserArtifacts` of ``spec``; ``inf`` where nothing returns."""
    art = spec.artifacts
    assert art is not None
    n, b = true_m.shape
    hit = hit_edge >= 0
    e = np.asarray(edges, dtype=np.float64)[np.maximum(hit_edge, 0)]
    ex, ey = e[..., 2] - e[..., 0], e[..., 3] - e[..., 1]
    # |cos| of the angle between the beam and the surface normal (-ey, ex)
    cos_inc = np.abs(np.cos(world_angles_rad) * -ey + np.sin(world_angles_rad) * ex) / np.maximum(
        np.hypot(ex, ey), 1e-300
    )
    incidence = np.arccos(np.clip(cos_inc, 0.0, 1.0))
    fade = max(art.incidence_fade_rad, 1e-12)
    p_lost = np.clip((incidence - (art.max_incidence_rad - art.incidence_fade_rad)) / fade, 0.0, 1.0)
    lost = hit & (rng.random((n, b)) < p_lost)
    measured = true_m + range_err_m
    # mixed pixels at depth edges between neighbouring beams (both must return)
    left, right = true_m[:, :-1], true_m[:, 1:]
    with np.errstate(invalid="ignore"):
        edge = np.isfinite(left) & np.isfinite(right) & (np.abs(left - right) > art.mixed_pixel_jump_m)
    mixed = edge & (rng.random((n, b - 1)) < art.mixed_pixel_probability)
    which = rng.random((n, b - 1)) < 0.5  # the left or the right beam of the pair
    frac = rng.random((n, b - 1))
    with np.errstate(invalid="ignore"):
        between = left + frac * (right - left)
    cols = np.arange(b - 1)[None, :] + (~which).astype(np.int64)
    rows = np.broadcast_to(np.arange(n)[:, None], cols.shape)
    measured[rows[mixed], cols[mixed]] = between[mixed]
    # outliers (short spurious returns) and dropouts
    outlier = hit & (rng.random((n, b)) < art.outlier_probability)
    spurious = spec.range_min_m + rng.random((n, b)) * np.maximum(true_m - spec.range_min_m, 0.0)
    measured = np.where(outlier, spurious, measured)
    dropped = rng.random((n, b)) < art.dropout_probability
    return np.where(lost | dropped, np.inf, measured)


def drift_odometry(
    true_poses_xytheta: FloatArray, noise: OdometryNoise, rng: np.random.Generator
) -> FloatArray:
    """(M, 3) wheel odometry integrated from noisy increments of (M, 3) true poses, starting at the first."""
    truth = np.asarray(true_poses_xytheta, dtype=np.float64)
    inc = se2.between(truth[:-1], truth[1:])
    ds = np.hypot(inc[:, 0], inc[:, 1])
    z = rng.standard_normal((inc.shape[0], 3))
    noisy = np.empty_like(inc)
    noisy[:, 0] = (1 + noise.distance_scale_error) * inc[:, 0] + z[:, 0] * np.sqrt(
        noise.translation_variance_m2_per_m * ds
    )
    noisy[:, 1] = (1 + noise.distance_scale_error) * inc[:, 1] + z[:, 1] * np.sqrt(
        noise.lateral_variance_m2_per_m * ds
    )
    noisy[:, 2] = (
        (1 + noise.rotation_scale_error) * inc[:, 2]
        + noise.yaw_bias_rad_per_m * ds
        + z[:, 2]
        * np.sqrt(
            noise.rotation_variance_rad2_per_rad * np.abs(inc[:, 2]) + noise.rotation_variance_rad2_per_m * ds
        )
    )
    out = np.empty_like(truth)
    out[0] = truth[0]
    # sequential composition (cumulative heading, then rotate each increment into the world frame)
    theta = truth[0, 2] + np.concatenate([[0.0], np.cumsum(noisy[:, 2])])
    c, s = np.cos(theta[:-1]), np.sin(theta[:-1])
    out[1:, 0] = truth[0, 0] + np.cumsum(c * noisy[:, 0] - s * noisy[:, 1])
    out[1:, 1] = truth[0, 1] + np.cumsum(s * noisy[:, 0] + c * noisy[:, 1])
    out[:, 2] = se2.wrap_angle(theta)
    return out


class SmoothPath:
    """A path through waypoints with circular-arc corners, sampled by arc length.

    ``waypoints_xy_m`` (P, 2); each interior corner is rounded with ``corner_radius_m`` (shrunk where the
    legs are too short). The heading is the path tangent.
    """

    def __init__(
        self, waypoints_xy_m: Sequence[Sequence[float]], corner_radius_m: float, step_m: float = 0.005
    ) -> None:
        w = np.asarray(waypoints_xy_m, dtype=np.float64)
        if w.ndim != 2 or w.shape[0] < 2 or w.shape[1] != 2:
            raise DatasetError(f"a path needs (P>=2, 2) waypoints, got {w.shape}")
        legs = np.diff(w, axis=0)
        lengths = np.hypot(legs[:, 0], legs[:, 1])
        if np.any(lengths == 0):
            raise DatasetError("a path has two equal consecutive waypoints")
        dirs = legs / lengths[:, None]
        pieces_xy: list[FloatArray] = []
        pieces_th: list[FloatArray] = []
        cursor = w[0]
        for k in range(1, w.shape[0] - 1):
            u1, u2 = dirs[k - 1], dirs[k]
            turn = float(np.arctan2(u1[0] * u2[1] - u1[1] * u2[0], u1 @ u2))
            if abs(turn) < 1e-9:
                continue
            tan_len = corner_radius_m * np.tan(abs(turn) / 2)
            tan_len = min(tan_len, 0.5 * lengths[k - 1], 0.5 * lengths[k])
            radius = tan_len / np.tan(abs(turn) / 2)
            a = w[k] - u1 * tan_len
            self._line(cursor, a, pieces_xy, pieces_th, step_m)
            normal = np.array([-u1[1], u1[0]]) * np.sign(turn)
            centre = a + normal * radius
            th0 = np.arctan2(u1[1], u1[0])
            n = max(2, int(np.ceil(abs(turn) * radius / step_m)))
            phi = np.linspace(0.0, turn, n)
            start = a - centre
            c, s = np.cos(phi), np.sin(phi)
            arc = centre + np.stack([c * start[0] - s * start[1], s * start[0] + c * start[1]], axis=1)
            pieces_xy.append(arc)
            pieces_th.append(th0 + phi)
            cursor = w[k] + u2 * tan_len
        self._line(cursor, w[-1], pieces_xy, pieces_th, step_m)
        xy = np.concatenate(pieces_xy)
        th = np.unwrap(np.concatenate(pieces_th))
        seg = np.hypot(*np.diff(xy, axis=0).T)
        keep = np.concatenate([[True], seg > 1e-12])
        self._xy = xy[keep]
        self._theta = th[keep]
        self._s = se2.path_length_m(self._xy)

    @staticmethod
    def _line(p0, p1, pieces_xy, pieces_th, step_m) -> None:
        d = p1 - p0
        length = float(np.hypot(*d))
        if length < 1e-12:
            return
        n = max(2, int(np.ceil(length / step_m)) + 1)
        t = np.linspace(0.0, 1.0, n)
        pieces_xy.append(p0 + t[:, None] * d)
        pieces_th.append(np.full(n, np.arctan2(d[1], d[0])))

    @property
    def length_m(self) -> float:
        return float(self._s[-1])

    def at(self, s_m: NDArray[np.floating]) -> FloatArray:
        """(N, 3) poses at arc lengths ``s_m`` (clamped to the path)."""
        s = np.clip(np.asarray(s_m, dtype=np.float64), 0.0, self.length_m)
        x = np.interp(s, self._s, self._xy[:, 0])
        y = np.interp(s, self._s, self._xy[:, 1])
        th = np.interp(s, self._s, self._theta)
        return np.stack([x, y, se2.wrap_angle(th)], axis=1)
