"""The front door of the mapping stage: from a configuration and world-frame beams to maps.

:class:`MapBuilder` holds the recipe that turns a :class:`~mapping.config.MappingConfig` into the objects
of :mod:`mapping`: the beams of a recording at given poses, the learnt GP parameters (hyperparameters by
eq. 9 and the PLS link), the GPPOL inputs (unscented transform of each beam under its scan's pose
covariance and the laser noise, section 4.2), the GP occupancy map, the occupancy-grid baseline and the
tiled, incrementally updatable map. Callers (the pipeline, the benchmarks, the tests) use it and need no
other module's internals.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from datasets.errors import ConfigError, GpomError
from datasets.types import ScanSequence
from mapping.beams import Beams, beams_from_scan_sequence, compose_laser_poses, select_scans_by_motion
from mapping.calibration import holdout_link
from mapping.config import MappingConfig
from mapping.exports import UNKNOWN_VARIANCE_FRACTION, MapLayers
from mapping.gpmap import GPOccupancyMap
from mapping.gppol import GaussianInputs, RigidGroups, SensorNoise, input_moments
from mapping.grid import OccupancyGrid
from mapping.kernels import KERNELS, Kernel, make_kernel
from mapping.noisy_kernels import GAUSS_HERMITE, GIRARD, InputExpectation
from mapping.tiling import ArraySink, IncrementalMap, TileGrid, TileRenderer, render_serial
from mapping.train import GPParams, ParamsFileError, train_gp, training_scans
from mapping.unscented import UTParams

MAPPERS = ("gppol", "gpfol")

#: (xmin, ymin, xmax, ymax) of a map in the world frame (m).
Bounds = tuple[float, float, float, float]


class MappingError(GpomError):
    """A map cannot be built from these beams and settings (e.g. too few beams to train on)."""


def check_mapper(mapper: str) -> None:
    """ConfigError, before any work, when ``mapper`` is not one of :data:`MAPPERS`."""
    if mapper not in MAPPERS:
        raise ConfigError(f"unknown mapper '{mapper}' (known: {', '.join(MAPPERS)})")


@dataclass(frozen=True)
class MapBuilder:
    """Builds the maps of one mapper (``"gppol"`` or ``"gpfol"``) with the settings of ``cfg``.

    Pose covariances, where a method takes them, are (N, 3, 3) world-frame covariances of the base poses
    (x, y, theta in m, m, rad) of the N scans of the recording, indexed by ``beams.scan_index``; None means
    exact poses. GPFOL ignores them. ``unknown_variance_fraction`` is the classification's (the export
    configuration's): the maps read the prior unsolved where their variance provably stays above it
    (:func:`mapping.reach.reach_tolerance`). Picklable (Dask ships it to its workers inside
    :class:`GPMapFactory`).
    """

    cfg: MappingConfig
    mapper: str
    unknown_variance_fraction: float = UNKNOWN_VARIANCE_FRACTION

    @classmethod
    def from_config(
        cls,
        cfg: MappingConfig,
        mapper: str | None = None,
        unknown_variance_fraction: float = UNKNOWN_VARIANCE_FRACTION,
    ) -> MapBuilder:
        """The builder of ``mapper`` (default ``cfg.mapper``); ConfigError if the mapper is unknown."""
        mapper = mapper or cfg.mapper
        check_mapper(mapper)
        return cls(cfg, mapper, unknown_variance_fraction)

    # -- beams ------------------------------------------------------------------------------------------

    def select_scans(self, base_poses_xytheta: NDArray, laser_in_base_xytheta: NDArray) -> NDArray[np.int64]:
        """Indices of the scans to map: a scan each ``scan_selection.min_travel_m`` of laser travel or
        ``min_rotation_rad`` of turn along the laser poses of the (N, 3) base poses (in a run, the
        odometry trajectory, so that the choice does not depend on loop closure)."""
        return select_scans_by_motion(
            compose_laser_poses(base_poses_xytheta, laser_in_base_xytheta),
            self.cfg.scan_selection.min_travel_m,
            self.cfg.scan_selection.min_rotation_rad,
        )

    def beams(
        self,
        scans: ScanSequence,
        base_poses_xytheta: NDArray,
        laser_in_base_xytheta: NDArray,
        indices: NDArray | None = None,
    ) -> Beams:
        """World-frame beams of the scans ``indices`` (default all) at the (N, 3) base poses of every scan,
        the laser at ``laser_in_base_xytheta`` (3,) on the base; free segments shaped as configured."""
        cfg = self.cfg
        idx = np.arange(len(scans)) if indices is None else np.asarray(indices, dtype=np.int64)
        return beams_from_scan_sequence(
            scans.subset(idx),
            np.asarray(base_poses_xytheta, dtype=np.float64)[idx],
            laser_in_base_xytheta,
            no_return_free_length_m=cfg.free_space.no_return_length_m,
            free_margin_m=cfg.free_space.margin_m,
            scan_indices=idx,
            free_band_m=cfg.free_space.band_m,
            free_band_per_m=cfg.free_space.band_per_m,
            free_margin_max_m=cfg.free_space.margin_max_m,
        )

    # -- GPPOL inputs -----------------------------------------------------------------------------------

    def check_sources(self, source_names: tuple[str, ...] | list[str], where: str) -> None:
        """ConfigError when ``mapping.sources`` names a source that is none of ``source_names`` (the
        recording ``where``'s scan sources): its noise would silently go unused."""
        unknown = [name for name in self.cfg.sources if name not in source_names]
        if unknown:
            raise ConfigError(
                f"{where}: mapping.sources names {', '.join(repr(n) for n in unknown)}, which is no scan "
                f"source of it (its sources: {', '.join(repr(n) for n in source_names)})"
            )

    def sensor_noise(self, source_names: tuple[str, ...] | list[str]) -> list[SensorNoise]:
        """The laser noise of each source: ``cfg.sources[name]`` where named, else ``cfg.default_source``."""
        out = []
        for name in source_names:
            s = self.cfg.sources.get(name, self.cfg.default_source)
            out.append(SensorNoise(s.range_var_m2, s.bearing_var_rad2))
        return out

    def input_expectation(self, kernel: Kernel) -> InputExpectation:
        """How GPPOL integrates ``kernel`` over its inputs (``auto``: Girard's eq. 19 for SE, else
        Gauss-Hermite quadrature of eq. 23)."""
        method = self.cfg.gppol.expectation
        if method == "auto":
            method = GIRARD if kernel.name == "se" else GAUSS_HERMITE
        return InputExpectation(method, self.cfg.gppol.gh_level)

    def gaussian_inputs(
        self,
        beams: Beams,
        cov_xytheta: NDArray | None,
        kernel: Kernel,
        rigid_groups: RigidGroups | None = None,
    ) -> GaussianInputs:
        """The GPPOL inputs of ``beams``: the unscented transform of every beam under its scan's pose
        covariance and the per-source laser noise; the free points' inputs without range noise unless
        ``gppol_free_range_noise``. ``rigid_groups``: the scans that share one pose error, and each one's
        offset from it (:class:`mapping.gppol.GaussianInputs`; None: each scan alone; unused without
        covariances)."""
        cfg = self.cfg
        ut = UTParams(cfg.gppol.ut.alpha, cfg.gppol.ut.beta, cfg.gppol.ut.kappa)
        noise = self.sensor_noise(beams.source_names)
        try:
            moments = input_moments(beams, cov_xytheta, noise, ut)
            free = local = local_free = None
            no_range = [SensorNoise(0.0, s.bearing_var_rad2) for s in noise]
            if not cfg.gppol.free_range_noise:
                free = input_moments(beams, cov_xytheta, no_range, ut)
            group = group_free = None
            if cov_xytheta is not None:  # the laser noise alone, for pairs of points of one scan
                local = input_moments(beams, None, noise, ut)
                if not cfg.gppol.free_range_noise:
                    local_free = input_moments(beams, None, no_range, ut)
                offsets = None if rigid_groups is None else rigid_groups.offset_cov_world(beams)
                if offsets is not None:  # and each scan's offset from its group, for pairs of one group
                    group = input_moments(beams, offsets, noise, ut)
                    if not cfg.gppol.free_range_noise:
                        group_free = input_moments(beams, offsets, no_range, ut)
        except ValueError as exc:
            raise MappingError(f"cannot build the GPPOL inputs: {exc}") from None
        groups = None if cov_xytheta is None or rigid_groups is None else rigid_groups.group_of_scan
        return GaussianInputs(
            moments, self.input_expectation(kernel), free, local, local_free, groups, group, group_free
        )

    # -- parameters -------------------------------------------------------------------------------------

    def stored_params(self) -> GPParams | None:
        """The GP parameters of ``cfg.params_file`` (None when not set); ConfigError if unreadable."""
        if self.cfg.params_file is None:
            return None
        try:
            return GPParams.load(self.cfg.params_file)
        except ParamsFileError as exc:
            raise ConfigError(f"{self.cfg.params_file}: {exc}") from None

    def fit(
        self,
        beams: Beams,
        cov_xytheta: NDArray | None = None,
        seed_offset: int = 0,
        rigid_groups: RigidGroups | None = None,
    ) -> GPParams:
        """Stored parameters if configured, else hyperparameters and PLS link learnt from ``train.scans``
        scans of ``beams`` in ``train.windows`` runs spread over the recording: GPFOL with ``cfg.kernel``;
        GPPOL with ``cfg.gppol.kernel`` on the beams' input Gaussians of the laser noise (poses exact,
        :meth:`_train`; ``cov_xytheta`` and ``rigid_groups`` serve the held-out link's maps). The training
        problems' free segments stop ``cfg.train.free_margin_m`` short of the endpoints if it is set (or each
        beam's grazing margin, kept from ``beams``, if larger). ``pls_link: holdout`` refits the link on
        held-out scans."""
        stored = self.stored_params()
        if stored is not None:
            return stored
        params = self._train(beams, seed_offset)
        if self.cfg.pls.link == "holdout":
            params = self._holdout_link(params, beams, cov_xytheta, seed_offset, rigid_groups)
        return params

    def _train(self, beams: Beams, seed_offset: int) -> GPParams:
        """Hyperparameters and the leave-one-out PLS link learnt by :func:`mapping.train.train_gp`.

        GPPOL learns them on input Gaussians of the laser noise alone, with the poses taken as exact. Its
        local training problems are neighbourhoods of one scan and its neighbours in time, placed
        relative to each other up to the laser noise: a scan's pose error moves all its beams together
        (SPEC section 5), so it says nothing of the world's length scales; handed to eq. (9) as independent
        noise on every point, it is explained by longer length scales instead (on the simulated loop world
        with SLAM's covariances: 0.54 m instead of 0.39 m, and a lower AUC). The pose covariances enter
        the maps through the kernels integrated over the inputs (:meth:`gp_map`)."""
        cfg = self.cfg
        gppol = self.mapper == "gppol"
        kernel_name = cfg.gppol.kernel if gppol else cfg.kernel
        names = KERNELS[kernel_name].names
        bounds = {k: v for k, v in cfg.kernel_bounds.items() if k in names} or None
        if cfg.train.free_margin_m is not None:
            beams = beams.with_free_margin(cfg.train.free_margin_m)
        inputs = None
        if gppol:
            # training reads train.scans scans only (train_gp): their beams alone go through the UT
            beams = beams.select_scans(training_scans(beams.scan_index, cfg.train.scans, cfg.train.windows))
            inputs = self.gaussian_inputs(beams, None, make_kernel(kernel_name))
        try:
            return train_gp(
                beams,
                kernel_name=kernel_name,
                kernel_bounds=bounds,
                noise_var=cfg.noise_var,
                k_occ=cfg.k_occupied,
                k_free=cfg.k_free,
                n_scans=cfg.train.scans,
                n_problems=cfg.train.problems,
                maxfun=cfg.train.anneal_evaluations,
                maxiter=cfg.train.lbfgs_iterations,
                seed=cfg.train.seed + seed_offset,
                index_cell_m=cfg.index_cell_m,
                learn_noise=cfg.learn_noise,
                inputs=inputs,
                windows=cfg.train.windows,
                link_problems=cfg.pls.loo_problems,
            )
        except ValueError as exc:
            raise MappingError(f"cannot train the GP: {exc}") from None

    def _holdout_link(
        self,
        params: GPParams,
        beams: Beams,
        cov_xytheta: NDArray | None,
        seed_offset: int,
        rigid_groups: RigidGroups | None = None,
    ) -> GPParams:
        """``params`` with the PLS link refitted on held-out scans of ``beams``
        (:func:`mapping.calibration.holdout_link`); unchanged when too few scans (``params.info["pls"]`` says
        which fit holds)."""
        cfg = self.cfg

        def build(rest: Beams) -> GPOccupancyMap:
            return self.gp_map(rest, params, cov_xytheta, rigid_groups)

        fitted = holdout_link(
            beams, build, cfg.pls.holdout_fraction, cfg.pls.holdout_block_scans, cfg.train.seed + seed_offset
        )
        info = dict(params.info)
        loo = {"alpha": params.alpha, "beta": params.beta, "mean_cap": params.mean_cap}
        if fitted is None:
            info["pls"] = {"fit": "loo (too few scans to hold out)", "loo": loo}
            return replace(params, info=info)
        alpha, beta, mean_cap, used = fitted
        info["pls"] = {"fit": "holdout", "loo": loo, **used}
        return replace(params, alpha=alpha, beta=beta, mean_cap=mean_cap, info=info)

    # -- maps -------------------------------------------------------------------------------------------

    def gp_map(
        self,
        beams: Beams,
        params: GPParams,
        cov_xytheta: NDArray | None = None,
        rigid_groups: RigidGroups | None = None,
    ) -> GPOccupancyMap:
        """The GP occupancy map over ``beams`` with ``params``: GPPOL on the beams' input Gaussians (the
        scans' pose covariances ``cov_xytheta`` (N, 3, 3), shared within ``rigid_groups``), GPFOL on
        the beams as they are."""
        if self.mapper == "gpfol" and "inputs" in params.info:
            raise MappingError("these GP parameters were learnt for GPPOL: learn them with mapper='gpfol'")
        cfg = self.cfg
        gppol = self.mapper == "gppol"
        inputs = self.gaussian_inputs(beams, cov_xytheta, params.kernel, rigid_groups) if gppol else None
        try:
            return GPOccupancyMap(
                beams,
                params,
                cfg.k_occupied,
                cfg.k_free,
                cfg.jitter,
                cfg.index_cell_m,
                inputs=inputs,
                unknown_variance_fraction=self.unknown_variance_fraction,
            )
        except ValueError as exc:
            raise MappingError(f"cannot build the {self.mapper.upper()} map: {exc}") from None

    def grid(self, beams: Beams, bounds: Bounds | None = None) -> OccupancyGrid:
        """The occupancy-grid baseline (Thrun et al. 2005) over ``beams`` (default bounds: the beams')."""
        return OccupancyGrid.from_config(beams, self.cfg.grid, bounds)

    def tiled_map(
        self,
        beams: Beams,
        params: GPParams,
        bounds_xy_m: Bounds,
        tile_cells: int,
        cov_xytheta: NDArray | None = None,
        renderer: TileRenderer = render_serial,
        layers: MapLayers | None = None,
        rigid_groups: RigidGroups | None = None,
    ) -> IncrementalMap:
        """The tiled map of ``beams`` on the grid of ``bounds_xy_m`` at ``cfg.resolution_m`` (tiles of
        ``tile_cells`` cells a side), rendered tile by tile by ``renderer`` and updatable when poses change.
        Covariances are kept only for GPPOL (GPFOL ignores them, so their changes re-render nothing), with
        the scans' ``rigid_groups`` (:meth:`gp_map`).
        ``layers``: a rendering of these beams made earlier with the same settings, adopted instead of
        rendering (call :meth:`IncrementalMap.render_all` otherwise)."""
        grid = TileGrid.from_bounds(bounds_xy_m, self.cfg.resolution_m, tile_cells)
        sink = ArraySink(grid, layers) if layers is not None else None
        cov = None if self.mapper == "gpfol" or cov_xytheta is None else np.asarray(cov_xytheta, np.float64)
        gp = IncrementalMap(
            beams,
            grid,
            GPMapFactory(self, params, rigid_groups),
            self.cfg.k_occupied,
            self.cfg.k_free,
            cov,
            sink=sink,
            renderer=renderer,
        )
        if layers is not None:
            gp.adopt_rendered()
        return gp


@dataclass(frozen=True)
class GPMapFactory:
    """The map factory of a tile (:data:`mapping.tiling.render.MapFactory`): ``builder``'s GP map with the
    learnt ``params`` over the tile's support beams (and the scans' ``rigid_groups``,
    :meth:`MapBuilder.gp_map`). Picklable, so that Dask ships it to its workers."""

    builder: MapBuilder
    params: GPParams
    rigid_groups: RigidGroups | None = None

    def __call__(self, beams: Beams, cov_xytheta: NDArray | None) -> Any:
        return self.builder.gp_map(beams, self.params, cov_xytheta, self.rigid_groups)
