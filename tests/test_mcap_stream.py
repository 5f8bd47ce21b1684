"""Big messages written into an MCAP bag piece by piece (:mod:`datasets.ros.mcap_stream`): the bytes a reader
gets are those of rosbags' own serialisation of the whole message, Foxglove's independent MCAP reader accepts
the file with its CRCs checked, and the writer never holds the whole message."""

from __future__ import annotations

import re
import tracemalloc
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import yaml
from mcap.reader import make_reader

import datasets.ros.writer as writer_module
from datasets.ros.maps import (
    GRID_MAP,
    OCCUPANCY_GRID,
    Raster,
    grid_map_msg,
    occupancy_grid_msg,
    read_map_bag,
    trinary_occupancy,
    write_map_bag,
)
from datasets.ros.writer import StreamedArray, open_bag_writer
from datasets.types import Trajectory

T0 = 1_700_000_000_123_456_789


def _raster(shape: tuple[int, int] = (123, 217), seed: int = 0) -> Raster:
    rng = np.random.default_rng(seed)
    layers = {k: rng.normal(size=shape).astype(np.float32) for k in ("probability", "mean", "variance", "x")}
    layers["variance"][::7, ::5] = np.nan
    return Raster(layers, 0.1, (-3.0, 2.5), "map")


def _mcap_file(path: Path) -> Path:
    return path / f"{path.name}.mcap" if path.is_dir() else path


def _raw_messages(path: Path) -> tuple[dict[str, bytes], object]:
    """Topic -> message bytes, and the summary, read by the ``mcap`` package with CRCs checked."""
    with _mcap_file(path).open("rb") as f:
        reader = make_reader(f, validate_crcs=True)
        raw = {channel.topic: bytes(msg.data) for _, channel, msg in reader.iter_messages()}
        return raw, reader.get_summary()


@pytest.fixture
def streamed(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """The sizes of the messages written by :func:`datasets.ros.mcap_stream.write_streamed`."""
    sizes: list[int] = []
    original = writer_module.write_streamed

    def spy(raw: object, conn: object, stamp_ns: int, pieces: Iterator[bytes], size: int) -> None:
        sizes.append(size)
        original(raw, conn, stamp_ns, pieces, size)

    monkeypatch.setattr(writer_module, "write_streamed", spy)
    return sizes


@pytest.mark.parametrize("name", ["maps.mcap", "maps"])
def test_streamed_grid_maps_read_back_byte_for_byte(tmp_path: Path, name: str, streamed: list[int]) -> None:
    before, after = _raster(seed=1), _raster(seed=2)
    path = tmp_path / name
    path_xy = Trajectory(np.array([T0, T0 + 10]), np.array([[0.0, 0.0, 0.0], [1.0, 0.5, 0.2]]), "map")
    counts = write_map_bag(
        path, {"before": before, "after": after}, T0, paths={"after": path_xy}, tf_trajectory=path_xy
    )
    assert len(streamed) == 6  # each map's two OccupancyGrids and GridMap, nothing else
    raw, summary = _raw_messages(path)
    with open_bag_writer(tmp_path / "whole.mcap") as w:
        for map_name, raster in (("before", before), ("after", after)):
            whole = bytes(w.typestore.serialize_cdr(grid_map_msg(w, raster, T0), GRID_MAP))
            assert raw[f"/{map_name}/grid_map"] == whole
            assert len(whole) in streamed
            occupancy = trinary_occupancy(raster.layers["probability"])
            whole = bytes(
                w.typestore.serialize_cdr(occupancy_grid_msg(w, occupancy, raster, T0), OCCUPANCY_GRID)
            )
            assert raw[f"/{map_name}/occupancy"] == whole
    # the summary counts every message once, the streamed ones included
    assert summary.statistics.message_count == sum(counts.values()) == 9  # /tf twice
    by_topic = {summary.channels[c].topic: n for c, n in summary.statistics.channel_message_counts.items()}
    assert by_topic == counts
    if path.is_dir():
        meta = yaml.safe_load((path / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
        assert meta["message_count"] == 9
        topics = meta["topics_with_message_count"]
        assert {t["topic_metadata"]["name"]: t["message_count"] for t in topics} == counts
    back = read_map_bag(path)  # and through rosbags' reader
    for layer, values in after.layers.items():
        np.testing.assert_array_equal(back["/after/grid_map"].layers[layer], values)


@pytest.mark.parametrize("name", ["maps.bag", "maps.db3"])
def test_other_bags_get_the_whole_message(tmp_path: Path, name: str, streamed: list[int]) -> None:
    raster = _raster()
    write_map_bag(tmp_path / name, {"after": raster}, T0)
    assert streamed == []
    back = read_map_bag(tmp_path / name)["/after/grid_map"]
    for layer, values in raster.layers.items():
        np.testing.assert_array_equal(back.layers[layer], values)


def _pieces(values: np.ndarray, cuts: list[int]) -> StreamedArray:
    return StreamedArray(values.dtype, values.size, lambda: iter(np.split(values, cuts)))


def test_arrays_in_uneven_pieces_serialise_as_the_whole_message(tmp_path: Path, streamed: list[int]) -> None:
    """Two arrays of different element types, cut into uneven pieces (some empty), and an empty array."""
    axes = np.linspace(-1, 1, 11, dtype=np.float32)
    buttons = np.arange(-3, 4, dtype=np.int32)
    cases = [(axes, buttons, [0, 3, 3, 10]), (axes[:0], buttons, [0])]
    with open_bag_writer(tmp_path / "joy.mcap") as w:
        joy = w.types["sensor_msgs/msg/Joy"]

        def build(data: list[np.ndarray]) -> object:
            return joy(header=w.header(T0, "pad"), axes=data[0], buttons=data[1])

        wants = []
        for i, (a, b, cuts) in enumerate(cases):
            w.write_arrays_streamed(
                f"/joy{i}", "sensor_msgs/msg/Joy", T0, build, [_pieces(a, cuts), _pieces(b, [2, 2])]
            )
            wants.append(bytes(w.typestore.serialize_cdr(build([a, b]), "sensor_msgs/msg/Joy")))
    assert len(streamed) == 2
    raw, _ = _raw_messages(tmp_path / "joy.mcap")
    assert [raw["/joy0"], raw["/joy1"]] == wants


@pytest.mark.parametrize(
    "pieces", [[np.zeros(4, np.float32)], [np.zeros(5, np.float32), np.ones(1, np.float32)]]
)
def test_pieces_that_do_not_add_up_leave_no_bag(tmp_path: Path, pieces: list[np.ndarray]) -> None:
    """Fewer or more elements than announced (5): an error, before the compressor is flushed or fed more
    than it was promised, and no bag."""
    wrong = StreamedArray(np.dtype(np.float32), 5, lambda: iter(pieces))
    with pytest.raises(ValueError, match=r"pieces hold (at least )?\d+ bytes, not the \d+ announced") as err:
        with open_bag_writer(tmp_path / "bad.mcap") as w:
            msgtype = "std_msgs/msg/Float32MultiArray"
            layout = w.types["std_msgs/msg/MultiArrayLayout"](dim=[], data_offset=0)
            w.write_arrays_streamed(
                "/a", msgtype, T0, lambda d: w.types[msgtype](layout=layout, data=d[0]), [wrong]
            )
    held, announced = (int(n) for n in re.findall(r"\d+", str(err.value)))
    assert held - announced == (4 if len(pieces) == 2 else -4)  # one float32 too many or too few
    assert list(tmp_path.iterdir()) == []


def test_a_streamed_grid_map_is_never_held_whole(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Python-tracked memory (numpy arrays, bytes, rosbags' buffers) at its peak while a 32 MB GridMap is
    written: a part of the message when streamed; several copies when written whole."""
    raster = _raster((1000, 2000))
    message_bytes = 4 * raster.layers["mean"].nbytes
    occupancy = np.zeros(raster.shape, np.int8)  # given, as the pipeline does, not derived in the bag writer

    def peak(name: str) -> int:
        small = _raster((3, 4))  # imports and compiled functions loaded first, not counted
        write_map_bag(tmp_path / f"small-{name}", {"after": small}, T0, {"after": 2.0})
        tracemalloc.start()
        try:
            write_map_bag(tmp_path / name, {"after": raster}, T0, {"after": 2.0}, {"after": occupancy})
            return tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()

    streamed = peak("streamed.mcap")
    monkeypatch.setattr(writer_module, "streaming_storage", lambda raw: None)
    whole = peak("whole.mcap")
    assert streamed < 0.5 * message_bytes  # bands of rows, the int8 grids and the compressor's output
    assert whole > 2 * message_bytes
