"""The Dask engine: a local cluster of two worker processes renders the Intel map (intel.gfs.log,
corrected poses, 0.1 m) as the serial path and the untiled map do (to 2 float32 ulps); a bad scheduler
address is one clear error."""

from __future__ import annotations

import numpy as np
import pytest

from datasets.registry import open_dataset
from mapping.build import GPMapFactory, MapBuilder
from mapping.config import MappingConfig
from mapping.gpmap import GPOccupancyMap
from mapping.tiling import IncrementalMap, TileGrid
from pipeline.errors import PipelineError
from pipeline.evaluate_map import make_beams, reference_laser_poses
from pipeline.scale import DaskEngine, ScaleConfig, tile_engine
from tests.conftest import data_file
from tests.layer_checks import assert_same_map
from tests.test_scale import PARAMS, corridor_scans, make


@pytest.fixture(scope="module")
def intel_beams():
    path = data_file("intel/intel.gfs.log")
    rec = open_dataset(path)
    cfg = MappingConfig(mapper="gpfol")
    return make_beams(rec, reference_laser_poses(rec, path), np.arange(len(rec.scans)), cfg), cfg


@pytest.mark.slow
def test_local_cluster_renders_the_intel_map_like_the_serial_path(intel_beams) -> None:
    beams, cfg = intel_beams
    bounds = beams.bounds_xy_m(1.0)
    grid = TileGrid.from_bounds(bounds, 0.1, 64)
    factory = GPMapFactory(MapBuilder.from_config(cfg, "gpfol"), PARAMS)
    serial = IncrementalMap(beams, grid, factory, cfg.k_occupied, cfg.k_free)
    serial.render_all()
    with tile_engine(ScaleConfig(scheduler="local", workers=2, threads_per_worker=1)) as engine:
        assert isinstance(engine, DaskEngine) and len(engine.client.scheduler_info()["workers"]) == 2
        distributed = IncrementalMap(beams, grid, factory, cfg.k_occupied, cfg.k_free, renderer=engine)
        report = distributed.render_all()
    assert report.tiles_recomputed == len(grid) == 42
    untiled = GPOccupancyMap(beams, PARAMS, cfg.k_occupied, cfg.k_free).render(bounds, 0.1)
    a, b = serial.layers(), distributed.layers()
    assert a.shape == untiled.shape == (380, 407)
    # The serial renderer maps the whole map in one call and the workers tile by tile: the same query can
    # land in another SIMD block, so "the same map" is asserted to 2 float32 ulps (tests/layer_checks.py).
    assert_same_map(a, b)
    assert_same_map(a, untiled)
    assert 0.05 < np.mean(a.probability < 0.35) and 0.01 < np.mean(a.probability > 0.65)  # a real map


def test_a_cluster_by_address_renders_like_the_serial_path() -> None:
    from distributed import LocalCluster

    beams, bounds = make(*corridor_scans()), (0.0, 0.0, 60.0, 20.0)
    cfg = MappingConfig(mapper="gpfol")
    grid = TileGrid.from_bounds(bounds, 0.2, 32)
    factory = GPMapFactory(MapBuilder.from_config(cfg, "gpfol"), PARAMS)
    serial = IncrementalMap(beams, grid, factory, cfg.k_occupied, cfg.k_free)
    serial.render_all()
    with LocalCluster(n_workers=1, threads_per_worker=2, processes=True, dashboard_address=None) as cluster:
        with tile_engine(ScaleConfig(scheduler=cluster.scheduler_address)) as engine:
            remote = IncrementalMap(beams, grid, factory, cfg.k_occupied, cfg.k_free, renderer=engine)
            remote.render_all()
            moved = beams.subset(np.arange(len(beams)))  # an update through the same engine
            assert remote.update_poses(moved).tiles_recomputed == 0
    assert_same_map(serial.layers(), remote.layers())


def test_unreachable_scheduler_is_one_clear_error() -> None:
    with pytest.raises(PipelineError, match=r"cannot reach the Dask scheduler 'tcp://127\.0\.0\.1:9'"):
        with tile_engine(ScaleConfig(scheduler="tcp://127.0.0.1:9", connect_timeout_s=1)):
            pass


class DyingFactory:
    """A map factory whose worker process dies (as one killed for memory would)."""

    def __call__(self, beams, cov_xytheta):
        import os

        os._exit(3)


def test_a_worker_that_dies_is_one_clear_error() -> None:
    import dask

    beams = make(*corridor_scans())
    cfg = MappingConfig(mapper="gpfol")
    grid = TileGrid.from_bounds((0.0, 0.0, 60.0, 20.0), 0.2, 32)
    with dask.config.set({"distributed.scheduler.allowed-failures": 0}):
        with tile_engine(ScaleConfig(scheduler="local", workers=1, threads_per_worker=1)) as engine:
            doomed = IncrementalMap(beams, grid, DyingFactory(), cfg.k_occupied, cfg.k_free, renderer=engine)
            with pytest.raises(PipelineError, match=r"Dask workers died rendering a map tile \(.*\): give"):
                doomed.render_all()
