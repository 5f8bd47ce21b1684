"""Maps as ROS messages: OccupancyGrid and GridMap written and read back with the right size, resolution,
origin, orientation and values."""

from __future__ import annotations

import weakref
from pathlib import Path

import numpy as np
import pytest

from datasets.ros.bag import open_bag
from datasets.ros.maps import Raster, percent_int8, read_map_bag, trinary_occupancy, write_map_bag
from datasets.ros.writer import bag_kind_of_path, open_bag_writer

T0 = 1_700_000_000_123_456_789


def _raster() -> Raster:
    rng = np.random.default_rng(1)
    prob = rng.uniform(0, 1, (5, 8)).astype(np.float32)
    prob[0, 0] = 1.0  # the lower-left cell
    var = rng.uniform(0, 2, (5, 8)).astype(np.float32)
    var[0, 1] = np.nan
    mean = rng.normal(size=(5, 8)).astype(np.float32)
    return Raster({"probability": prob, "mean": mean, "variance": var}, 0.2, (-1.0, 3.0), "map")


def test_percent_int8() -> None:
    v = percent_int8(np.array([0.0, 0.004, 0.5, 1.0, 2.0, np.nan]), 1.0)
    assert v.tolist() == [0, 0, 50, 100, 100, -1]


def _edge_values(dtype: type, shape: tuple[int, int]) -> np.ndarray:
    """Random values in [-0.5, 1.5] with NaN, infinities and exact halves of a percent sprinkled in."""
    rng = np.random.default_rng(7)
    v = rng.uniform(-0.5, 1.5, shape)
    flat = v.reshape(-1)
    flat[:40] = np.arange(40) * 0.005  # 0.5 %, 1.5 %, ...: ties rounded half to even
    flat[40:44] = (np.nan, np.inf, -np.inf, 0.35)
    return rng.permuted(v.reshape(-1)).reshape(shape).astype(dtype)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_percent_int8_and_trinary_equal_their_numpy_definitions(dtype: type) -> None:
    v = _edge_values(dtype, (37, 53))
    with np.errstate(invalid="ignore"):
        x = np.asarray(v, np.float64)
        ok = np.isfinite(x)
        want = np.full(x.shape, -1, np.int8)
        want[ok] = np.clip(np.round(x[ok] * 50.0), 0, 100).astype(np.int8)
        np.testing.assert_array_equal(percent_int8(v, 2.0), want)
        unknown = np.random.default_rng(8).uniform(size=v.shape) < 0.2
        for mask in (None, unknown, unknown.astype(np.float32)):
            want = np.full(x.shape, -1, np.int8)
            want[x >= 0.65] = 100
            want[x <= 0.35] = 0
            if mask is not None:
                want[mask.astype(bool)] = -1
            np.testing.assert_array_equal(trinary_occupancy(v, mask, 0.65, 0.35), want)
    # non-contiguous views and integer input take the same path
    np.testing.assert_array_equal(percent_int8(v[::2, ::3], 2.0), percent_int8(v[::2, ::3].copy(), 2.0))
    assert percent_int8(np.array([0, 1, 3]), 2.0).tolist() == [0, 50, 100]


@pytest.mark.parametrize("name", ["maps.bag", "maps.mcap"])
def test_map_bag_round_trip(tmp_path: Path, name: str) -> None:
    raster = _raster()
    counts = write_map_bag(tmp_path / name, {"before": raster, "after": raster}, T0, {"after": 4.0})
    assert counts == {
        f"/{m}/{k}": 1 for m in ("before", "after") for k in ("occupancy", "variance", "grid_map")
    }
    back = read_map_bag(tmp_path / name)
    occ = back["/before/occupancy"]
    assert occ.shape == (5, 8) and occ.resolution_m == pytest.approx(0.2) and occ.origin_xy_m == (-1.0, 3.0)
    np.testing.assert_array_equal(occ.layers["value"], trinary_occupancy(raster.layers["probability"]))
    assert occ.layers["value"][0, 0] == 100
    var = back["/after/variance"].layers["value"]
    assert var[0, 1] == -1  # NaN -> unknown
    np.testing.assert_array_equal(var, percent_int8(raster.layers["variance"], 4.0))
    gm = back["/after/grid_map"]
    assert gm.shape == (5, 8) and gm.origin_xy_m == pytest.approx((-1.0, 3.0)) and gm.resolution_m == 0.2
    for layer in ("probability", "mean", "variance"):
        np.testing.assert_array_equal(gm.layers[layer], raster.layers[layer])


def test_grid_map_uses_grid_map_index_convention(tmp_path: Path) -> None:
    """GridMap cell (0, 0) is the (max x, max y) corner and storage is column-major."""
    raster = _raster()
    write_map_bag(tmp_path / "m.bag", {"m": raster}, T0)
    with open_bag(tmp_path / "m.bag", "ros1") as bag:
        (_, _, msg), *_ = list(bag.messages(["/m/grid_map"]))
    prob = msg.data[list(msg.layers).index("probability")]
    assert [d.label for d in prob.layout.dim] == ["column_index", "row_index"]
    rows_x = prob.layout.dim[1].size  # grid_map rows run along x
    cols_y = prob.layout.dim[0].size
    assert (rows_x, cols_y) == (8, 5)
    data = np.asarray(prob.data)
    # M(i=0, j=0) is raster[H-1, W-1] (max y, max x); M(rows-1, cols-1) is raster[0, 0] (min x, min y)
    assert data[0] == raster.layers["probability"][-1, -1]
    assert data[(cols_y - 1) * rows_x + (rows_x - 1)] == raster.layers["probability"][0, 0] == 1.0
    # the pose is the map centre
    assert msg.info.pose.position.x == pytest.approx(-1.0 + 8 * 0.2 / 2)
    assert msg.info.pose.position.y == pytest.approx(3.0 + 5 * 0.2 / 2)


@pytest.mark.parametrize("name", ["maps.bag", "maps.mcap", "maps", "maps.db3"])
def test_map_bag_chunks_are_compressed(tmp_path: Path, name: str) -> None:
    """A big map's float layers are mostly unknown space (one value): the maps bag compresses its chunks
    (lz4 in ROS1, zstd in MCAP) and reads back bit for bit; SQLite3 has no chunks to compress."""
    rng = np.random.default_rng(0)
    prob = np.full((400, 500), 0.5, np.float32)
    prob[100:300, 100:400] = rng.uniform(0, 1, (200, 300))
    var = np.where(prob == 0.5, 0.8, 0.1).astype(np.float32)
    raster = Raster({"probability": prob, "mean": prob - 0.5, "variance": var}, 0.1, (0.0, 0.0), "map")
    write_map_bag(tmp_path / name, {"after": raster}, T0)
    back = read_map_bag(tmp_path / name)["/after/grid_map"]
    for layer in ("probability", "mean", "variance"):
        np.testing.assert_array_equal(back.layers[layer], raster.layers[layer])
    path = tmp_path / name
    size = sum(f.stat().st_size for f in path.rglob("*")) if path.is_dir() else path.stat().st_size
    payload = 3 * prob.nbytes
    if name == "maps.db3":
        assert size > payload
    else:
        assert size < 0.6 * payload  # the random block alone is 0.3 of it


@pytest.mark.parametrize("name", ["built.bag", "built.mcap"])
def test_a_built_message_is_dropped_before_the_bag_copies_its_bytes(tmp_path: Path, name: str) -> None:
    arrays: list[weakref.ref] = []
    alive_at_write: list[bool] = []
    with open_bag_writer(tmp_path / name) as w:
        raw_write = w._raw.write

        def spy(conn: object, stamp_ns: int, data: bytes) -> None:
            alive_at_write.append(arrays[-1]() is not None)
            raw_write(conn, stamp_ns, data)

        w._raw.write = spy

        def build() -> object:
            values = np.arange(6, dtype=np.float32)
            arrays.append(weakref.ref(values))
            return w.types["std_msgs/msg/Float32MultiArray"](
                layout=w.types["std_msgs/msg/MultiArrayLayout"](dim=[], data_offset=0), data=values
            )

        w.write_built("/built", "std_msgs/msg/Float32MultiArray", T0, build, latching=True)
        w.write("/kept", "std_msgs/msg/Float32MultiArray", T0, build())
    assert alive_at_write == [False, True]  # write() keeps the caller's message, write_built() does not
    with open_bag(tmp_path / name, bag_kind_of_path(tmp_path / name)[0]) as bag:
        data = {topic: np.asarray(msg.data).tolist() for topic, _, msg in bag.messages(["/built", "/kept"])}
    assert data == {"/built": [0, 1, 2, 3, 4, 5], "/kept": [0, 1, 2, 3, 4, 5]}
