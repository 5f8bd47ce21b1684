"""Map exports: map_server PGM + YAML and layers.npz round trips, orientation included."""

from __future__ import annotations

import numpy as np
import yaml

from mapping.exports import MapLayers, read_layers_npz, read_map_server, write_layers_npz, write_map_server


def _layers() -> MapLayers:
    rng = np.random.default_rng(0)
    prob = rng.uniform(0, 1, (7, 11)).astype(np.float32)
    prob[0, 0] = 1.0  # lowest-left cell occupied: must stay at row 0 after the round trip
    prob[-1, -1] = 0.0
    return MapLayers(prob, rng.normal(size=(7, 11)).astype(np.float32), prob * 0.1, 0.25, (-3.0, 2.5))


def test_map_server_round_trip(tmp_path) -> None:
    layers = _layers()
    pgm, yml = write_map_server(tmp_path / "occupancy", layers.probability, 0.25, (-3.0, 2.5), 0.65, 0.35)
    meta = yaml.safe_load(yml.read_text())
    assert meta["image"] == "occupancy.pgm" and meta["resolution"] == 0.25
    assert meta["origin"] == [-3.0, 2.5, 0.0]
    assert meta["occupied_thresh"] == 0.65 and meta["free_thresh"] == 0.35
    header = pgm.read_bytes()[:2]
    assert header == b"P5"
    p, _ = read_map_server(yml)
    assert p.shape == (7, 11)
    np.testing.assert_allclose(p, layers.probability, atol=0.5 / 255 + 1e-9)
    assert p[0, 0] == 1.0 and p[-1, -1] == 0.0
    # the image itself is top-down: its last row is the map's row 0
    raw = np.frombuffer(pgm.read_bytes()[-77:], np.uint8).reshape(7, 11)
    assert raw[-1, 0] == 0 and raw[0, -1] == 255


def test_layers_round_trip(tmp_path) -> None:
    layers = _layers()
    back = read_layers_npz(write_layers_npz(tmp_path / "layers.npz", layers))
    for name in ("probability", "mean", "variance"):
        assert getattr(back, name).dtype == np.float32
        np.testing.assert_array_equal(getattr(back, name), getattr(layers, name))
    assert back.resolution_m == 0.25 and back.origin_xy_m == (-3.0, 2.5) and back.frame_id == "map"
