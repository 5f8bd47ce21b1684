"""Map exports: the planners' classification, the trinary map_server PGM + YAML, layers.npz (old files too)
and the maps bag's trajectories, loop closures and TF read back with rosbags' own readers."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from rosbags import rosbag1, rosbag2

from datasets.errors import DatasetError
from datasets.ros.maps import Raster, read_map_bag, trinary_occupancy, write_map_bag
from datasets.ros.typestores import stamp_ns_of, standard_typestore, yaw_of_quaternion
from datasets.types import Trajectory
from mapping.config import MappingConfig
from mapping.exports import (
    Classification,
    MapExportError,
    MapLayers,
    finite_range,
    read_layers_npz,
    read_map_server,
    write_layers_npz,
    write_map_server,
)
from mapping.kernels import make_kernel
from mapping.train import GPParams
from pipeline.config import ExportConfig
from pipeline.map_exports import write_maps

T0 = 1_700_000_000_000_000_000
PRIOR = 0.8


def _layers(classified: bool = True) -> MapLayers:
    rng = np.random.default_rng(0)
    prob = rng.uniform(0, 1, (7, 11)).astype(np.float32)
    prob[0, 0] = 1.0  # lowest-left cell occupied: must stay at row 0 after the round trip
    prob[-1, -1] = 0.0
    var = rng.uniform(0, PRIOR, (7, 11)).astype(np.float32)
    var[0, 0] = var[-1, -1] = 0.01
    var[3, 4] = np.nan
    rule = Classification(np.full((7, 11), PRIOR, np.float32), 0.9, 0.65, 0.35) if classified else None
    return MapLayers(prob, rng.normal(size=(7, 11)).astype(np.float32), var, 0.25, (-3.0, 2.5), "map", rule)


def test_classification_unknown_overrides_probability() -> None:
    rule = Classification(np.full((1, 6), 2.0, np.float32), 0.5, 0.65, 0.35)
    p = np.array([[0.9, 0.9, 0.1, 0.1, 0.5, 0.65]])
    var = np.array([[1.0, 1.01, 1.0, np.nan, 0.0, 0.0]])
    np.testing.assert_array_equal(rule.unknown(var), [[False, True, False, True, False, False]])
    # known: occupied at p >= 0.65, free at p <= 0.35, unknown between; unknown cells are -1 whatever p
    assert rule.values(p, var).tolist() == [[100, -1, 0, -1, -1, 100]]
    assert trinary_occupancy(np.array([0.35, np.nan])).tolist() == [0, -1]
    with pytest.raises(MapExportError):
        Classification(np.ones((1, 1), np.float32), 1.5, 0.65, 0.35)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_unknown_mask_and_finite_range_equal_their_numpy_definitions(dtype: type) -> None:
    rng = np.random.default_rng(3)
    var = rng.uniform(0.0, 1.0, (41, 29)).astype(dtype)
    var.reshape(-1)[:3] = (np.nan, np.inf, -np.inf)
    prior = rng.uniform(0.5, 1.0, var.shape).astype(np.float32)
    var[5, :10] = 0.9 * prior[5, :10].astype(np.float64)  # at the threshold, as float64 rounds it
    rule = Classification(prior, 0.9, 0.65, 0.35)
    with np.errstate(invalid="ignore"):
        want = ~(np.asarray(var, np.float64) <= 0.9 * np.asarray(prior, np.float64))
    np.testing.assert_array_equal(rule.unknown(var), want)
    np.testing.assert_array_equal(rule.unknown(var.T.copy().T), want)  # a Fortran-ordered layer
    finite = var[np.isfinite(var)]
    assert finite_range(var) == (float(finite.min()), float(finite.max()))
    assert finite_range(np.array([np.nan, np.inf])) is None and finite_range(np.zeros(0)) is None
    assert finite_range(np.array([[2.0, np.nan], [-1.0, 3.0]], np.float32)) == (-1.0, 3.0)


def test_map_server_trinary_round_trip(tmp_path: Path) -> None:
    layers = _layers()
    values = layers.occupancy_values()
    assert {-1, 0, 100} <= set(np.unique(values).tolist())
    pgm, yml = write_map_server(tmp_path / "occupancy", values, 0.25, (-3.0, 2.5), {"prior_variance": PRIOR})
    meta = yaml.safe_load(yml.read_text())
    assert meta["image"] == "occupancy.pgm" and meta["mode"] == "trinary" and meta["resolution"] == 0.25
    assert meta["origin"] == [-3.0, 2.5, 0.0] and meta["negate"] == 0
    # the loader's thresholds put grey 205 (occ = 50 / 255) between free and occupied
    assert meta["free_thresh"] < 50 / 255 < meta["occupied_thresh"] and 1 / 255 < meta["free_thresh"]
    assert meta["prior_variance"] == PRIOR
    back, _ = read_map_server(yml)
    np.testing.assert_array_equal(back, values)
    assert back[0, 0] == 100 and back[-1, -1] == 0 and back[3, 4] == -1
    # the image itself is top-down: its last row is the map's row 0; only the three trinary grey levels
    raw = np.frombuffer(pgm.read_bytes()[-77:], np.uint8).reshape(7, 11)
    assert raw[-1, 0] == 0 and raw[0, -1] == 254 and set(np.unique(raw).tolist()) == {0, 205, 254}
    with pytest.raises(MapExportError, match="100 / 0 / -1"):
        write_map_server(tmp_path / "bad", np.full((2, 2), 50, np.int8), 0.25, (0.0, 0.0))
    with pytest.raises(MapExportError, match="clash"):
        write_map_server(tmp_path / "bad", values, 0.25, (0.0, 0.0), {"free_thresh": 0.3})


def test_read_map_server_scale_mode(tmp_path: Path) -> None:
    """Older run folders hold ``mode: scale`` images without alpha: thresholded, scaled in between."""
    grey = np.array([[0, 90, 128, 166, 255]], np.uint8)  # occ = 1, 0.647, 0.498, 0.349, 0
    (tmp_path / "old.pgm").write_bytes(b"P5\n# old\n5 1\n255\n" + grey.tobytes())
    meta = dict(image="old.pgm", mode="scale", resolution=0.1, origin=[0.0, 0.0, 0.0], negate=0)
    (tmp_path / "old.yaml").write_text(yaml.safe_dump({**meta, "occupied_thresh": 0.65, "free_thresh": 0.35}))
    values, _ = read_map_server(tmp_path / "old.yaml")
    assert values.tolist() == [[100, 99, 49, 0, 0]]


def test_layers_round_trip(tmp_path: Path) -> None:
    layers = _layers()
    back = read_layers_npz(write_layers_npz(tmp_path / "layers.npz", layers))
    for name in ("probability", "mean", "variance"):
        assert getattr(back, name).dtype == np.float32
        np.testing.assert_array_equal(getattr(back, name), getattr(layers, name))
    assert back.resolution_m == 0.25 and back.origin_xy_m == (-3.0, 2.5) and back.frame_id == "map"
    assert back.classification is not None and back.classification.unknown_variance_fraction == 0.9
    np.testing.assert_array_equal(back.occupancy_values(), layers.occupancy_values())
    with np.load(tmp_path / "layers.npz") as z:
        np.testing.assert_array_equal(z["unknown"], layers.unknown.astype(np.uint8))
        assert z["prior_variance"].dtype == np.float32 and float(z["free_threshold"]) == 0.35


def test_layers_without_classification_still_read(tmp_path: Path) -> None:
    """A layers.npz written before the classification existed (only the float layers and the placement)."""
    layers = _layers(classified=False)
    np.savez_compressed(
        tmp_path / "old.npz",
        probability=layers.probability,
        mean=layers.mean,
        variance=layers.variance,
        resolution_m=np.float64(0.25),
        origin_xy_m=np.array([-3.0, 2.5]),
        frame_id=np.str_("map"),
        row0="lowest y",
    )
    back = read_layers_npz(tmp_path / "old.npz")
    assert back.classification is None and back.unknown is None
    np.testing.assert_array_equal(back.variance, layers.variance)
    with pytest.raises(MapExportError):
        back.occupancy_values()


def _read_all(path: Path) -> dict[str, list]:
    """Every message of a bag by topic, read and decoded with rosbags' readers and the standard types."""
    out: dict[str, list] = {}
    if path.suffix == ".bag":
        store = standard_typestore("ros1")
        with rosbag1.Reader(path) as reader:
            for conn, _, raw in reader.messages():
                out.setdefault(conn.topic, []).append(store.deserialize_ros1(raw, conn.msgtype))
    else:
        store = standard_typestore("ros2")
        with rosbag2.Reader(path) as reader:
            for conn, _, raw in reader.messages():
                out.setdefault(conn.topic, []).append(store.deserialize_cdr(raw, conn.msgtype))
    return out


@pytest.mark.parametrize("name", ["maps.bag", "maps.mcap"])
def test_map_bag_carries_paths_loop_closures_and_tf(tmp_path: Path, name: str) -> None:
    layers = _layers()
    stamps = T0 + np.arange(5, dtype=np.int64) * 500_000_000
    poses = np.column_stack([np.arange(5.0), 0.5 * np.arange(5.0), np.linspace(-3.0, 3.0, 5)])
    after = Trajectory(stamps, poses, "map")
    before = Trajectory(stamps, poses + np.array([0.2, 0.0, 0.0]), "map")
    closures = np.array([[[0.0, 0.0], [4.0, 2.0]], [[1.0, 0.5], [3.0, 1.5]]])
    params = GPParams(
        make_kernel("se", {"sigma_f": float(np.sqrt(PRIOR)), "length_scale": 1.0}), 0.1, 50.0, 0.0
    )
    fmt = "bag" if name.endswith(".bag") else "mcap"
    maps = {"before": layers, "after": layers}
    write_maps(
        tmp_path,
        maps,
        {"before": before, "after": after},
        closures,
        MappingConfig(),
        ExportConfig(bag_format=fmt, png=False),
        int(stamps[-1]),
        params,
    )
    msgs = _read_all(tmp_path / name)
    assert len(msgs["/tf"]) == 5 and len(msgs["/after/path"]) == 1 and len(msgs["/loop_closures"]) == 1
    # TF map -> base_link per scan: the after trajectory, each at its scan's stamp
    tf = msgs["/tf"][3].transforms[0]
    assert tf.header.frame_id == "map" and tf.child_frame_id == "base_link"
    assert stamp_ns_of(tf.header.stamp) == stamps[3]
    r = tf.transform.rotation
    assert (tf.transform.translation.x, tf.transform.translation.y) == pytest.approx((3.0, 1.5))
    assert yaw_of_quaternion(r.x, r.y, r.z, r.w) == pytest.approx(1.5)
    for which, traj in (("before", before), ("after", after)):
        path = msgs[f"/{which}/path"][0]
        assert path.header.frame_id == "map" and len(path.poses) == 5
        p = path.poses[4]
        assert stamp_ns_of(p.header.stamp) == stamps[4]
        assert (p.pose.position.x, p.pose.position.y) == pytest.approx(tuple(traj.poses_xytheta[4, :2]))
    (marker,) = msgs["/loop_closures"][0].markers
    assert marker.type == 5 and marker.header.frame_id == "map" and len(marker.points) == 4
    assert (marker.points[1].x, marker.points[1].y) == (4.0, 2.0)
    # the OccupancyGrid is the PGM's classification; the GridMap keeps the floats and the unknown mask
    grids = read_map_bag(tmp_path / name)
    pgm_values, meta = read_map_server(tmp_path / "after" / "occupancy.yaml")
    np.testing.assert_array_equal(grids["/after/occupancy"].layers["value"], pgm_values)
    np.testing.assert_array_equal(
        grids["/after/grid_map"].layers["unknown"], layers.unknown.astype(np.float32)
    )
    info = yaml.safe_load(msgs["/after/metadata"][0].data)
    assert info["prior_variance"] == pytest.approx(PRIOR) and info["variance_full_scale"] == pytest.approx(
        PRIOR
    )
    assert meta["unknown_variance_fraction"] == info["unknown_variance_fraction"] == 0.9


def test_write_map_bag_refuses_misshapen_occupancy(tmp_path: Path) -> None:
    layers = _layers()
    raster_layers = {"probability": layers.probability, "mean": layers.mean, "variance": layers.variance}
    raster = Raster(raster_layers, 0.25, (0.0, 0.0))
    with pytest.raises(DatasetError, match="occupancy of shape"):
        write_map_bag(tmp_path / "m.mcap", {"m": raster}, T0, occupancy={"m": np.zeros((2, 2), np.int8)})
