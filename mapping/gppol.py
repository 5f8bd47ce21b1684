"""GPPOL inputs (paper section 3.6.3, Algorithm 3): every beam's training points as Gaussians.

:func:`input_moments` runs the unscented transform (:mod:`mapping.unscented`) on every beam with its scan's
world-frame base-pose covariance (the FULL 3x3, e.g. a SLAM marginal) and its sensor's range and bearing
variances (per source, so that recordings of several platforms fuse). :class:`GaussianInputs` pairs those
per-beam coefficients with the way the kernel is integrated over them
(:class:`mapping.noisy_kernels.InputExpectation`); :class:`mapping.gpmap.GPOccupancyMap` given one is GPPOL,
without one GPFOL -- the same map object and the same compiled core (:mod:`mapping.core`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba as nb
import numpy as np
from numpy.typing import NDArray

from datasets import se2
from mapping.beams import Beams
from mapping.core import (
    INPUTS_GH_DIFFERENCE,
    INPUTS_GH_NODES,
    INPUTS_GIRARD,
    OCC_COLUMNS,
    OCC_COLUMNS_GROUPED,
    SEG_COLUMNS,
    SEG_COLUMNS_GROUPED,
)
from mapping.kernels import Kernel
from mapping.noisy_kernels import GIRARD, InputExpectation
from mapping.unscented import BeamMoments, UTParams, beam_moments

FloatArray = NDArray[np.float64]
DEFAULT_EXPECTATION = InputExpectation()


@dataclass(frozen=True)
class SensorNoise:
    """Measurement noise of one laser: range variance (m^2) and bearing variance (rad^2)."""

    range_var_m2: float = 0.0
    bearing_var_rad2: float = 0.0


def input_moments(
    beams: Beams,
    pose_cov_xytheta: FloatArray | None,
    noise_by_source: list[SensorNoise] | tuple[SensorNoise, ...],
    ut: UTParams | None = None,
) -> BeamMoments:
    """UT coefficients of every beam (eqs. 24-28, exact in the distance along the beam).

    ``pose_cov_xytheta`` (N, 3, 3): world-frame covariance of the BASE pose of each scan, indexed by
    ``beams.scan_index`` (None: poses are exact); ``noise_by_source``: one :class:`SensorNoise` per entry of
    ``beams.source_names`` (indexed by ``beams.source_index``)."""
    M = len(beams)
    if pose_cov_xytheta is None:
        cov, cov_of_beam = np.zeros((1, 3, 3)), np.zeros(M, dtype=np.int64)
    else:
        cov = np.asarray(pose_cov_xytheta, dtype=np.float64).reshape(-1, 3, 3)
        if M and int(beams.scan_index.max()) >= cov.shape[0]:
            raise ValueError(
                f"{cov.shape[0]} pose covariances, but beams of scan {int(beams.scan_index.max())}"
            )
        cov_of_beam = beams.scan_index
    if M and int(beams.source_index.max()) >= len(noise_by_source):
        raise ValueError(f"{len(noise_by_source)} sensor noise settings for sources {beams.source_names}")
    var_r = np.array([s.range_var_m2 for s in noise_by_source], dtype=np.float64)
    var_b = np.array([s.bearing_var_rad2 for s in noise_by_source], dtype=np.float64)
    src = beams.source_index.astype(np.int64)
    return beam_moments(
        beams.bearings_rad,
        beams.base_poses_xytheta(),
        cov,
        var_r[src] if M else np.zeros(0),
        var_b[src] if M else np.zeros(0),
        beams.laser_in_base_xytheta,
        ut or UTParams(),
        cov_of_beam,
    )


@dataclass(frozen=True)
class RigidGroups:
    """Which scans share one pose error, and how far each strays from it (N scans).

    ``group_of_scan`` (N,) int64: each scan's group (in a pose graph, its keyframe: the graph moves the
    scans between two keyframes rigidly with the first). ``offset_cov_body`` (N, 3, 3) or None: the
    covariance of each scan's pose relative to its group's (the odometry from the keyframe to the scan;
    zero for the keyframe itself), in the scan's own frame, so that it holds for any map of the scans
    (:meth:`offset_cov_world`); None takes every group as exactly rigid."""

    group_of_scan: NDArray[np.int64]
    offset_cov_body: FloatArray | None = None

    def __post_init__(self) -> None:
        groups = np.asarray(self.group_of_scan, dtype=np.int64).reshape(-1)
        object.__setattr__(self, "group_of_scan", groups)
        if self.offset_cov_body is not None:
            cov = np.asarray(self.offset_cov_body, dtype=np.float64)
            if cov.shape != (groups.size, 3, 3):
                raise ValueError(f"{groups.size} rigid groups, but offset covariances of shape {cov.shape}")
            object.__setattr__(self, "offset_cov_body", cov)

    def offset_cov_world(self, beams: Beams) -> FloatArray | None:
        """(N, 3, 3) world-frame offset covariances of the scans as ``beams`` place them (each scan turned by
        its base heading); None when the groups are exactly rigid."""
        if self.offset_cov_body is None:
            return None
        theta = np.zeros(len(self))
        theta[beams.scan_index] = beams.base_poses_xytheta()[:, 2]
        rot = se2.rot3(theta)
        return rot @ self.offset_cov_body @ np.swapaxes(rot, 1, 2)

    def __len__(self) -> int:
        return int(self.group_of_scan.size)

    def take(self, rows: NDArray[np.int64]) -> RigidGroups:
        """The groups of the scans ``rows`` (M,), in that order."""
        cov = None if self.offset_cov_body is None else self.offset_cov_body[rows]
        return RigidGroups(self.group_of_scan[rows], cov)

    def placed_on(self, n_scans: int, rows: NDArray[np.int64]) -> RigidGroups:
        """The groups of ``n_scans`` other scans of which ``rows[i]`` is our scan ``i`` (another
        trajectory's rows for our scans); a row without one of ours is a group of its own, exactly rigid."""
        groups = np.arange(n_scans, dtype=np.int64) + (int(self.group_of_scan.max()) + 1 if len(self) else 0)
        at = np.asarray(rows, dtype=np.int64)
        groups[at] = self.group_of_scan
        cov = None
        if self.offset_cov_body is not None:
            cov = np.zeros((n_scans, 3, 3))
            cov[at] = self.offset_cov_body
        return RigidGroups(groups, cov)

    @staticmethod
    def equal(a: RigidGroups | None, b: RigidGroups | None) -> bool:
        """Whether ``a`` and ``b`` hold the same groups and offset covariances (None: each scan alone)."""
        if a is None or b is None:
            return a is b
        if not np.array_equal(a.group_of_scan, b.group_of_scan):
            return False
        ca, cb = a.offset_cov_body, b.offset_cov_body
        return (ca is None and cb is None) or (ca is not None and cb is not None and np.array_equal(ca, cb))


@dataclass(frozen=True)
class GaussianInputs:
    """What makes a map GPPOL: the per-beam input Gaussians and how kernels are integrated over them.

    ``moments`` (and ``free_moments`` for the free points, where they differ) hold each beam's full input
    Gaussian: the laser noise and its scan's pose covariance. ``local_moments`` / ``local_free_moments``
    hold the laser noise alone (None: the same as the full ones, as without pose covariances). The beams
    of one scan share its pose error (SPEC section 5): a rigid motion keeps the distance between two of
    its points, so for a stationary isotropic kernel their expected kernel is the one over the laser noise
    alone; two points of different scans, whose pose errors are taken as independent, integrate over both
    full covariances (eq. 17); the test point is deterministic. ``rigid_groups`` (N,), indexed like the
    covariances by ``beams.scan_index``, groups scans that share one pose error (in a pose graph the scans
    of one keyframe: they move with it rigidly); two points of different scans of one group integrate over
    ``group_moments`` / ``group_free_moments`` (the laser noise and each scan's offset from the group: the
    odometry from the keyframe; None: the laser noise alone). None: each scan is its own group."""

    moments: BeamMoments
    expectation: InputExpectation = DEFAULT_EXPECTATION
    free_moments: BeamMoments | None = None  # free points' coefficients if they differ (no range noise)
    local_moments: BeamMoments | None = None  # the laser noise alone (same-scan pairs)
    local_free_moments: BeamMoments | None = None
    rigid_groups: NDArray[np.int64] | None = None
    group_moments: BeamMoments | None = None  # the laser noise and the offset from the group (group pairs)
    group_free_moments: BeamMoments | None = None

    def free(self) -> BeamMoments:
        """The coefficients of the free points (default: those of the endpoints, as Algorithm 3)."""
        return self.moments if self.free_moments is None else self.free_moments

    def local(self) -> BeamMoments:
        """The endpoints' coefficients of the laser noise alone (default: the full ones)."""
        return self.moments if self.local_moments is None else self.local_moments

    def local_free(self) -> BeamMoments:
        """The free points' coefficients of the laser noise alone (default: the full ones)."""
        if self.local_free_moments is not None:
            return self.local_free_moments
        return self.free() if self.local_moments is None else self.local_moments

    def group(self) -> BeamMoments:
        """The endpoints' coefficients within their rigid group (default: the laser noise alone)."""
        return self.local() if self.group_moments is None else self.group_moments

    def group_free(self) -> BeamMoments:
        """The free points' coefficients within their rigid group (default: the laser noise alone)."""
        if self.group_free_moments is not None:
            return self.group_free_moments
        return self.local_free() if self.group_moments is None else self.group_moments

    def core_mode(self, kernel: Kernel) -> int:
        """The GPPOL mode of :func:`mapping.core.predict_batch` for ``kernel``."""
        self.expectation.check(kernel)
        if self.expectation.method == GIRARD:
            return INPUTS_GIRARD
        return INPUTS_GH_DIFFERENCE if kernel.stationary else INPUTS_GH_NODES

    def rule(self) -> tuple[FloatArray, FloatArray]:
        """The 2-D quadrature nodes (m, 2) and weights (m,) the core uses (unused by Girard's form)."""
        z, w = self.expectation.rule()
        return np.ascontiguousarray(z), np.ascontiguousarray(w)

    def core_arrays(self, beams: Beams, hit_beam: NDArray[np.int64]) -> tuple[FloatArray, FloatArray]:
        """``occ_mom`` (H, OCC_COLUMNS): mean, packed covariance, packed covariance of the laser noise alone
        and rigid group of the endpoints ``hit_beam`` (in the point index's order); ``seg_mom``
        (M, SEG_COLUMNS): per beam ``a, b, C0, C1, C2``, the length of its free part, the laser noise's
        ``C0, C1, C2`` and the scan's rigid group (:func:`mapping.core._gaussian_inputs`). With
        ``group_moments`` the rows are grouped (OCC_COLUMNS_GROUPED, SEG_COLUMNS_GROUPED): the scan in place
        of the group, then the covariance within the group and the group."""
        mo, lo, go = self.moments, self.local(), self.group()
        fm, fl, fg = self.free(), self.local_free(), self.group_free()
        grouped = self.group_moments is not None and self.rigid_groups is not None
        hits = np.ascontiguousarray(hit_beam, dtype=np.int64)
        occ = np.empty((hits.size, OCC_COLUMNS_GROUPED if grouped else OCC_COLUMNS))
        seg = np.empty((len(beams), SEG_COLUMNS_GROUPED if grouped else SEG_COLUMNS))
        group = beams.scan_index
        if self.rigid_groups is not None:
            groups = np.asarray(self.rigid_groups, dtype=np.int64)
            if len(beams) and int(beams.scan_index.max()) >= groups.size:
                raise ValueError(
                    f"{groups.size} rigid groups, but beams of scan {int(beams.scan_index.max())}"
                )
            group = groups[beams.scan_index]
        # one pass over the rows, in parallel: column by column, a 24-column array is walked 24 times
        _pack_inputs(
            *(np.ascontiguousarray(m.a) for m in (mo, fm)),
            *(np.ascontiguousarray(m.b) for m in (mo, fm)),
            *(
                np.ascontiguousarray(getattr(m, c))
                for m in (mo, lo, go, fm, fl, fg)
                for c in ("c0", "c1", "c2")
            ),
            np.ascontiguousarray(beams.ranges_m, dtype=np.float64),
            np.ascontiguousarray(beams.origins_xy_m, dtype=np.float64),
            np.ascontiguousarray(beams.free_ends_xy_m, dtype=np.float64),
            np.ascontiguousarray(beams.scan_index if grouped else group, dtype=np.int64),
            np.ascontiguousarray(group, dtype=np.int64),
            hits,
            occ,
            seg,
        )
        return occ, seg


@nb.njit(cache=True, parallel=True)
def _pack_inputs(
    a, fa, b, fb, c0, c1, c2, lc0, lc1, lc2, gc0, gc1, gc2, fc0, fc1, fc2, flc0, flc1, flc2, fgc0, fgc1,
    fgc2, ranges, origins, free_ends, scan, group, hits, occ, seg,
):  # fmt: skip
    """The rows of :meth:`GaussianInputs.core_arrays`: ``occ`` of the endpoints ``hits`` (the mean
    ``a + d b`` and the packed covariances ``C0 + d (C1 + d C2)`` at their ranges, full and of the laser
    noise alone, and ``scan``), ``seg`` of every beam (the free points' ``a, b, C0, C1, C2``, the free
    part's length, the laser noise's ``C0, C1, C2``, ``scan``); grouped rows (wider) add the within-group
    covariance and ``group``."""
    grouped = occ.shape[1] == OCC_COLUMNS_GROUPED
    for h in nb.prange(hits.shape[0]):
        j = hits[h]
        d = ranges[j]
        occ[h, 0] = a[j, 0] + d * b[j, 0]
        occ[h, 1] = a[j, 1] + d * b[j, 1]
        for c in range(3):
            occ[h, 2 + c] = c0[j, c] + d * (c1[j, c] + d * c2[j, c])
            occ[h, 5 + c] = lc0[j, c] + d * (lc1[j, c] + d * lc2[j, c])
        occ[h, 8] = scan[j]
        if grouped:
            for c in range(3):
                occ[h, 9 + c] = gc0[j, c] + d * (gc1[j, c] + d * gc2[j, c])
            occ[h, 12] = group[j]
    for j in nb.prange(seg.shape[0]):
        row = seg[j]
        row[0] = fa[j, 0]
        row[1] = fa[j, 1]
        row[2] = fb[j, 0]
        row[3] = fb[j, 1]
        for c in range(3):
            row[4 + c] = fc0[j, c]
            row[7 + c] = fc1[j, c]
            row[10 + c] = fc2[j, c]
            row[14 + c] = flc0[j, c]
            row[17 + c] = flc1[j, c]
            row[20 + c] = flc2[j, c]
        row[13] = math.hypot(free_ends[j, 0] - origins[j, 0], free_ends[j, 1] - origins[j, 1])
        row[23] = scan[j]
        if grouped:
            for c in range(3):
                row[24 + c] = fgc0[j, c]
                row[27 + c] = fgc1[j, c]
                row[30 + c] = fgc2[j, c]
            row[33] = group[j]
