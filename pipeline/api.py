"""A Python front door to a run folder (SPEC section 4), for notebooks and scripts.

``load_run(run_dir)`` opens a folder written by ``run`` or ``demo`` and gives its stored products (summary,
configuration, trajectories, covariances, rendered layers) and the GP map itself, rebuilt from the folder
exactly as the run built it -- the same scans (``scans.npz``, selected by motion along the odometry
trajectory), poses (the TUM files), per-scan covariances, learnt parameters (``maps/params.json``) and
mapping settings (``config.yaml``) -- so that it can be queried anywhere and rendered on any grid. Its
p(occ) at the centres of the stored grid equals ``maps/<map>/layers.npz`` (to a float32 ulp, see
``tests/layer_checks.py``). Everything is read on first use; the GP map is built on the first query.

The project runs from its checkout: put the checkout's root on ``sys.path`` (``python`` started there does).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from mapping.build import Bounds, MapBuilder
from mapping.exports import MapLayers, read_layers_npz
from mapping.gpmap import GPOccupancyMap
from mapping.gppol import RigidGroups
from mapping.train import GPParams, ParamsFileError
from pipeline.artifacts import (
    COVARIANCES_NPZ,
    ODOMETRY_TUM,
    OPTIMIZED_TUM,
    SCANS_FILE,
    TRAJECTORY_DIR,
    StoredScans,
    checked_covariances,
    covariances_at,
    read_mapper_covariances,
    read_rigid_groups,
    read_scan_covariances,
    read_scans,
)
from pipeline.config import Config, load_config
from pipeline.errors import PipelineError, stage_boundary
from pipeline.map_bounds import check_map_cells
from pipeline.remap import stored_bounds
from pipeline.run_folder import params_path, read_summary
from slam.trajectory_io import read_tum

__all__ = [
    "MAPS",
    "MapQuery",
    "RunCovariances",
    "RunTrajectories",
    "RunView",
    "cell_centres_xy_m",
    "load_run",
]

#: The maps of a run folder: on the odometry trajectory (before loop closure) and on the optimised one.
MAPS = ("before", "after")


class MapQuery(NamedTuple):
    """The GP map at P points, each (P,) float64: latent mean (eq. 2), latent variance (eq. 3), p(occ)."""

    mean: NDArray[np.float64]
    variance: NDArray[np.float64]
    probability: NDArray[np.float64]


@dataclass(frozen=True)
class RunTrajectories:
    """The base pose of every scan: ``stamps_ns`` (N,) int64, ``poses_before_xytheta`` (N, 3) on the
    odometry trajectory, ``poses_after_xytheta`` (N, 3) after loop closure (world frame; m, m, rad)."""

    stamps_ns: NDArray[np.int64]
    poses_before_xytheta: NDArray[np.float64]
    poses_after_xytheta: NDArray[np.float64]


@dataclass(frozen=True)
class RunCovariances:
    """The pose covariance of every scan, world frame, order (x, y, theta) (m^2, rad^2): ``stamps_ns`` (N,),
    ``before`` / ``after`` (N, 3, 3) before / after loop closure: the marginals, relative to the graph's
    anchor (GPPOL maps with :attr:`RunView.mapper_covariances`)."""

    stamps_ns: NDArray[np.int64]
    before: NDArray[np.float64]
    after: NDArray[np.float64]


def cell_centres_xy_m(layers: MapLayers) -> NDArray[np.float64]:
    """(H*W, 2) world-frame centres (m) of the cells of ``layers``, row-major (row 0 at the lowest y), as
    the renderer computes them: ``query(cell_centres_xy_m(l)).probability.reshape(l.shape)`` is ``l``'s."""
    h, w = layers.shape
    x0, y0 = layers.origin_xy_m
    xs = x0 + (np.arange(w) + 0.5) * layers.resolution_m
    ys = y0 + (np.arange(h) + 0.5) * layers.resolution_m
    gx, gy = np.meshgrid(xs, ys)
    return np.stack([gx.ravel(), gy.ravel()], axis=1)


class RunView:
    """One map (``"before"`` or ``"after"``) of a run folder and everything stored beside it; see
    :func:`load_run`. Attributes are read on first use and kept."""

    def __init__(self, run_dir: str | Path, map: str = "after") -> None:
        self.run_dir = Path(run_dir)
        if map not in MAPS:
            raise PipelineError(f"{self.run_dir}: no map {map!r} in a run folder (its maps: before, after)")
        self.map_name = map
        summary = read_summary(self.run_dir)  # PipelineError unless a complete run folder
        if not (self.run_dir / SCANS_FILE).is_file():
            origin = summary.get("run_dir") if isinstance(summary, dict) else None
            hint = f" (a remap output? load the run it came from, {origin})" if origin else ""
            raise PipelineError(f"{self.run_dir}: no {SCANS_FILE}: not the folder of a run or demo{hint}")
        self.summary: dict[str, Any] = summary

    def __repr__(self) -> str:
        return f"RunView({str(self.run_dir)!r}, map={self.map_name!r})"

    # -- what the run stored ----------------------------------------------------------------------------

    @cached_property
    def config(self) -> Config:
        """The run's resolved configuration (``config.yaml``)."""
        return load_config(self.run_dir / "config.yaml")

    @cached_property
    def layers(self) -> MapLayers:
        """The stored rendering ``maps/<map>/layers.npz``: float32 (H, W) probability, mean, variance."""
        path = self.run_dir / "maps" / self.map_name / "layers.npz"
        with stage_boundary("reading", path):
            return read_layers_npz(path)

    @cached_property
    def bounds_xy_m(self) -> Bounds:
        """(xmin, ymin, xmax, ymax) of the run's map grid in the world frame (m)."""
        return stored_bounds(self.summary, self.run_dir)

    @property
    def resolution_m(self) -> float:
        """The cell size of the run's maps (m)."""
        return self.config.mapping.resolution_m

    @cached_property
    def scans(self) -> StoredScans:
        """The run's scans (``scans.npz``) and the laser mounting on the base."""
        with stage_boundary("reading", self.run_dir):
            return read_scans(self.run_dir / SCANS_FILE)

    @cached_property
    def trajectory(self) -> RunTrajectories:
        """The base pose of every scan before and after loop closure (the run's TUM files)."""
        folder = self.run_dir / TRAJECTORY_DIR
        stamps = self.scans.scans.stamps_ns
        poses = {}
        with stage_boundary("reading", self.run_dir):
            for name in (ODOMETRY_TUM, OPTIMIZED_TUM):
                file_stamps, poses[name] = read_tum(folder / name)
                if not np.array_equal(file_stamps, stamps):
                    raise PipelineError(f"{folder / name}: its stamps are not those of {SCANS_FILE}")
        return RunTrajectories(stamps, poses[ODOMETRY_TUM], poses[OPTIMIZED_TUM])

    @cached_property
    def covariances(self) -> RunCovariances:
        """The pose covariance of every scan before and after loop closure (``covariances.npz``; each scan
        takes its keyframe's where the file holds keyframe marginals only)."""
        path = self.run_dir / TRAJECTORY_DIR / COVARIANCES_NPZ
        stamps = self.scans.scans.stamps_ns
        cov = {}
        with stage_boundary("reading", path):
            for which in MAPS:
                cov_stamps, values = read_scan_covariances(path, which)
                # the run's own per-scan arrays are taken as they are (covariances_at picks one of
                # duplicate stamps for both)
                same = np.array_equal(cov_stamps, stamps) and values.shape == (len(stamps), 3, 3)
                cov[which] = (
                    checked_covariances(values, len(stamps))
                    if same
                    else covariances_at(stamps, cov_stamps, values)
                )
        return RunCovariances(stamps, cov["before"], cov["after"])

    @cached_property
    def mapper_covariances(self) -> NDArray[np.float64] | None:
        """(N, 3, 3) the covariances this run's ``map`` was built with (``mapping.gppol.pose_covariances``:
        by default each scan's pose relative to the earlier passes over its places; None: exact poses)."""
        path = self.run_dir / TRAJECTORY_DIR / COVARIANCES_NPZ
        stamps = self.scans.scans.stamps_ns
        with stage_boundary("reading", path):
            found = read_mapper_covariances(path, self.map_name, self.config.mapping.gppol.pose_covariances)
            if found is None:
                return None
            cov_stamps, values = found
            if np.array_equal(cov_stamps, stamps) and values.shape == (len(stamps), 3, 3):
                return checked_covariances(values, len(stamps))
            return covariances_at(stamps, cov_stamps, values)

    @cached_property
    def rigid_groups(self) -> RigidGroups | None:
        """The scans this run's GPPOL treated as sharing one pose error (``mapping.gppol.rigid_groups``: each
        scan's keyframe and its offset's covariance, :func:`pipeline.artifacts.mapper_rigid_groups`; None:
        each scan alone)."""
        path = self.run_dir / TRAJECTORY_DIR / COVARIANCES_NPZ
        mode = self.config.mapping.gppol.rigid_groups
        return read_rigid_groups(path, len(self.scans.scans.stamps_ns), mode)

    @cached_property
    def params(self) -> GPParams:
        """The GP parameters the run learnt (``maps/params.json``): kernel, noise and PLS link."""
        path = params_path(self.run_dir / "maps")
        try:
            return GPParams.load(path)
        except (OSError, ParamsFileError) as exc:
            raise PipelineError(f"{path}: cannot read the learnt GP parameters ({exc})") from None

    # -- the GP map ---------------------------------------------------------------------------------------

    @cached_property
    def gp_map(self) -> GPOccupancyMap:
        """The GP occupancy map of this run's ``map``, built as the run built it (the scans selected along
        the odometry trajectory, at this map's poses and covariances, with the stored parameters)."""
        builder = MapBuilder.from_config(
            self.config.mapping, None, self.config.export.unknown_variance_fraction
        )
        laser = self.scans.laser_in_base_xytheta
        traj = self.trajectory
        before = self.map_name == "before"
        poses = traj.poses_before_xytheta if before else traj.poses_after_xytheta
        cov = self.mapper_covariances
        params = self.params
        with stage_boundary("mapping", self.run_dir):
            selected = builder.select_scans(traj.poses_before_xytheta, laser)
            beams = builder.beams(self.scans.scans, poses, laser, selected)
            return builder.gp_map(beams, params, cov, self.rigid_groups)

    def query(self, xy_m: ArrayLike) -> MapQuery:
        """The map at (P, 2) world-frame points (m): mean, variance and p(occ), each (P,) float64."""
        pts = np.asarray(xy_m, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 2:
            raise PipelineError(f"query: points must be an array of shape (P, 2), got {pts.shape}")
        if not np.isfinite(pts).all():
            raise PipelineError("query: points must be finite")
        gp = self.gp_map
        with stage_boundary("mapping", self.run_dir):
            pred = gp.query(pts)
        return MapQuery(pred.mean, pred.variance, pred.probability)

    def render(self, bounds_xy_m: Bounds | None = None, resolution_m: float | None = None) -> MapLayers:
        """The map on a grid of ``resolution_m`` (m; default the run's) over ``(xmin, ymin, xmax, ymax)``
        (m; default the run's bounds): float32 (H, W) layers. The defaults give the stored layers again."""
        bounds = self.bounds_xy_m if bounds_xy_m is None else tuple(float(v) for v in bounds_xy_m)
        res = self.resolution_m if resolution_m is None else float(resolution_m)
        if (
            len(bounds) != 4
            or not np.isfinite(bounds).all()
            or bounds[2] <= bounds[0]
            or bounds[3] <= bounds[1]
        ):
            raise PipelineError(
                f"render: bounds must be (xmin, ymin, xmax, ymax) with max > min, got {bounds}"
            )
        if not (np.isfinite(res) and res > 0):
            raise PipelineError(f"render: resolution_m must be a positive number of metres, got {res}")
        check_map_cells(bounds, res, self.config.scale.max_map_cells, "render")
        gp = self.gp_map
        with stage_boundary("mapping", self.run_dir):
            return gp.render(bounds, res)


def load_run(run_dir: str | Path, map: str = "after") -> RunView:
    """Open the run folder ``run_dir`` (written by ``run`` or ``demo``) on its ``map`` (``"after"``: after
    loop closure, or ``"before"``); PipelineError if it is not a complete run folder."""
    return RunView(run_dir, map)
