"""A real run's map_server map loaded by nav2's rules, written out here independently of the project's
reader, classifies every cell as ``layers.npz`` does, and the maps bag's OccupancyGrid is the same map.

nav2's loading rules (ros-navigation/navigation2, nav2_map_server/src/map_io.cpp):

- ``loadMapYaml`` reads only the keys ``image``, ``resolution``, ``origin``, ``free_thresh``,
  ``occupied_thresh``, ``mode`` (absent: trinary) and ``negate``; other keys are never looked at, so our
  extra keys (thresholds on p, prior variance, variance scale) are ignored;
- ``loadMapFromFile``: per pixel, ``shade`` = the mean of its colour channels on 0..1 (a grey PGM: value /
  255), ``occ = negate ? shade : 1 - shade``; in ``trinary`` mode ``occupied_thresh < occ`` -> 100,
  ``occ < free_thresh`` -> 0, else -1 (unknown); image row y goes to map row ``height - y - 1``.

So the unknown grey 205 (occ = 50 / 255 = 0.196) loads as unknown only if ``free_thresh`` <= 0.196: with
the probability threshold 0.35 as ``free_thresh`` it would load as FREE (nav2 PR #5278 fixed its own
map_saver for this: trinary YAMLs get 0.65 / 0.196).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from datasets.ros.bag import open_bag
from datasets.ros.maps import read_map_bag
from mapping.train import GPParams
from pipeline.config import load_config
from pipeline.run import run_pipeline
from slam.trajectory_io import read_tum
from tests.conftest import data_file

FAST = {"mapping": {"train": {"anneal_evaluations": 20, "lbfgs_iterations": 20}, "mapper": "gpfol"}}
NAV2_KEYS = {"image", "resolution", "origin", "free_thresh", "occupied_thresh", "mode", "negate"}


def read_pgm(path: Path) -> np.ndarray:
    """(height, width) uint8 pixels of a binary PGM, image row 0 (the top) first."""
    data = path.read_bytes()
    fields: list[bytes] = []
    lines = iter(data.split(b"\n"))
    while len(fields) < 4:
        line = next(lines).split(b"#")[0]
        fields += line.split()
    assert fields[0] == b"P5" and fields[3] == b"255"
    width, height = int(fields[1]), int(fields[2])
    return np.frombuffer(data[-width * height :], np.uint8).reshape(height, width)


def nav2_load(yaml_path: Path) -> tuple[np.ndarray, dict]:
    """nav2's ``loadMapYaml`` + ``loadMapFromFile`` for grey images: the OccupancyGrid data as (H, W) int8,
    row 0 = the map's origin row (lowest y)."""
    doc = yaml.safe_load(yaml_path.read_text())
    params = {key: doc[key] for key in NAV2_KEYS if key in doc}
    assert params.get("mode", "trinary") == "trinary"
    pixels = read_pgm(yaml_path.parent / params["image"]).astype(np.float64)
    shade = pixels / 255.0
    occ = shade if params["negate"] else 1.0 - shade
    cell = np.full(occ.shape, -1, np.int8)
    cell[params["occupied_thresh"] < occ] = 100
    cell[(occ < params["free_thresh"]) & ~(params["occupied_thresh"] < occ)] = 0
    height = cell.shape[0]
    data = np.empty_like(cell)
    for y in range(height):  # msg.data[width * (height - y - 1) + x] = cell(x, y)
        data[height - y - 1] = cell[y]
    return data, params


@pytest.fixture(scope="module")
def lsm_run(tmp_path_factory) -> Path:
    """A small real run: the 360 scans of lsm-demo (no odometry), GPFOL, fast training."""
    out = tmp_path_factory.mktemp("nav2") / "lsm"
    cfg = out.parent / "fast.yaml"
    cfg.write_text(yaml.safe_dump(FAST))
    run_pipeline(data_file("lsm-demo/demo_index_fixed.bag"), out, load_config(cfg))
    return out


def expected_classes(run: Path, which: str) -> np.ndarray:
    """The classification recomputed from ``layers.npz``'s float layers, config.yaml and params.json:
    unknown where variance > fraction * prior, else 100 at p >= occupied, 0 at p <= free, -1 between."""
    config = yaml.safe_load((run / "config.yaml").read_text())
    occ_t, free_t = config["mapping"]["occupied_threshold"], config["mapping"]["free_threshold"]
    fraction = config["export"]["unknown_variance_fraction"]
    params = GPParams.load(run / "maps" / "params.json")
    prior = float(np.float32(params.kernel.diag(np.zeros((1, 2)))[0]))  # stored as a float32 layer
    with np.load(run / "maps" / which / "layers.npz") as z:
        p, var = z["probability"].astype(np.float64), z["variance"].astype(np.float64)
        np.testing.assert_array_equal(z["unknown"], (var > fraction * prior).astype(np.uint8))
    out = np.full(p.shape, -1, np.int8)
    out[p >= occ_t] = 100
    out[p <= free_t] = 0
    out[var > fraction * prior] = -1
    return out


@pytest.mark.parametrize("which", ["before", "after"])
def test_nav2_loads_the_classification_of_layers_npz(lsm_run: Path, which: str) -> None:
    loaded, params = nav2_load(lsm_run / "maps" / which / "occupancy.yaml")
    expected = expected_classes(lsm_run, which)
    assert loaded.shape == expected.shape
    counts = {v: int((loaded == v).sum()) for v in (100, 0, -1)}
    assert counts == {v: int((expected == v).sum()) for v in (100, 0, -1)}
    np.testing.assert_array_equal(loaded, expected)
    # a real map: occupied, free and unknown cells all exist, and no unknown cell loads as free
    assert min(counts.values()) > 0.01 * loaded.size, counts
    assert params["free_thresh"] < 50 / 255 < params["occupied_thresh"]


def test_bag_occupancy_grid_is_the_pgm(lsm_run: Path) -> None:
    rasters = read_map_bag(lsm_run / "maps" / "maps.mcap")
    for which in ("before", "after"):
        loaded, params = nav2_load(lsm_run / "maps" / which / "occupancy.yaml")
        grid = rasters[f"/{which}/occupancy"]
        assert grid.origin_xy_m == pytest.approx(tuple(params["origin"][:2]))
        assert grid.resolution_m == pytest.approx(params["resolution"])
        np.testing.assert_array_equal(grid.layers["value"].astype(np.int8), loaded)
        gm = rasters[f"/{which}/grid_map"]
        # the map's layers, its placement uncertainty and the exploration plan's (export.next_best_views > 0)
        map_layers = {"probability", "mean", "variance", "unknown", "placement_sigma"}
        assert set(gm.layers) == map_layers | {"frontier", "information"}
        frontier = gm.layers["frontier"] == 1
        assert frontier.any() and np.all(loaded[frontier] == 0)  # frontier cells are free cells
        with np.load(lsm_run / "maps" / which / "layers.npz") as z:
            np.testing.assert_array_equal(gm.layers["unknown"], z["unknown"].astype(np.float32))
            np.testing.assert_array_equal(gm.layers["placement_sigma"], z["placement_sigma_m"])
        assert np.all(loaded[gm.layers["unknown"] == 1] == -1)  # never observed: never free nor occupied


def test_bag_has_the_run_trajectories_and_tf(lsm_run: Path) -> None:
    stamps, poses = read_tum(lsm_run / "trajectory" / "optimized.tum")
    with open_bag(lsm_run / "maps" / "maps.mcap", "ros2") as bag:
        msgs = {}
        for topic, _, msg in bag.messages(["/tf", "/after/path", "/before/path", "/loop_closures"]):
            msgs.setdefault(topic, []).append(msg)
    assert len(msgs["/tf"]) == len(stamps) == 360
    last = msgs["/tf"][-1].transforms[0].transform.translation
    assert (last.x, last.y) == pytest.approx(tuple(poses[-1, :2]))
    path = msgs["/after/path"][0]
    assert len(path.poses) == 360 and path.poses[100].pose.position.x == pytest.approx(poses[100, 0])
    summary = yaml.safe_load((lsm_run / "summary.json").read_text())
    (marker,) = msgs["/loop_closures"][0].markers
    assert len(marker.points) == 2 * summary["counts"]["loop_closures"]


def test_bag_has_the_next_best_views_in_free_space(lsm_run: Path) -> None:
    """The exploration plan's views (geometry_msgs/PoseArray, one per map) stand in cells the PGM loads
    as free."""
    with open_bag(lsm_run / "maps" / "maps.mcap", "ros2") as bag:
        (views,) = [msg for _, _, msg in bag.messages(["/after/next_best_views"])]
    loaded, params = nav2_load(lsm_run / "maps" / "after" / "occupancy.yaml")
    assert views.header.frame_id == "map" and 0 < len(views.poses) <= 5
    res, (x0, y0) = params["resolution"], params["origin"][:2]
    for pose in views.poses:
        row = int((pose.position.y - y0) / res)
        col = int((pose.position.x - x0) / res)
        assert loaded[row, col] == 0, (pose.position.x, pose.position.y)
