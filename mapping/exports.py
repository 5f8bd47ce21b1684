"""Map exports for planners and people: ``map_server`` PGM + YAML and ``layers.npz``.

Raster convention everywhere in this project: arrays are (H, W) with row 0 at the LOWEST y and column 0 at
the lowest x; ``origin_xy_m`` is the world position of the lower-left corner of cell (0, 0); cell (r, c)
covers ``[x0 + c*res, x0 + (c+1)*res) x [y0 + r*res, y0 + (r+1)*res)``.

``map_server`` images are the other way up (row 0 is the TOP), which the writer and reader handle.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml
from numpy.typing import NDArray

from datasets.errors import GpomError


class MapExportError(GpomError):
    """A map file cannot be written or read back."""


@dataclass(frozen=True)
class MapLayers:
    """A rendered map: float32 (H, W) layers with their placement in the world."""

    probability: NDArray[np.float32]
    mean: NDArray[np.float32]
    variance: NDArray[np.float32]
    resolution_m: float
    origin_xy_m: tuple[float, float]
    frame_id: str = "map"

    @property
    def shape(self) -> tuple[int, int]:
        return tuple(self.probability.shape)  # type: ignore[return-value]


def probability_to_pgm_grey(probability: NDArray) -> NDArray[np.uint8]:
    """map_server grey levels (negate = 0): 255 (white) free, 0 (black) occupied: ``round((1 - p) * 255)``."""
    p = np.clip(np.nan_to_num(np.asarray(probability, dtype=np.float64), nan=0.5), 0.0, 1.0)
    return np.round((1.0 - p) * 255.0).astype(np.uint8)


def write_map_server(
    stem: Path,
    probability: NDArray,
    resolution_m: float,
    origin_xy_m: tuple[float, float],
    occupied_threshold: float = 0.65,
    free_threshold: float = 0.35,
) -> tuple[Path, Path]:
    """Write ``stem.pgm`` (binary P5) and ``stem.yaml`` in the ROS ``map_server`` format.

    ``mode: scale`` keeps the probabilities: map_server maps a grey level back to ``p = (255 - v) / 255`` and
    to occupancy 100 above ``occupied_thresh``, 0 below ``free_thresh``, and linearly in between.
    Returns the two paths.
    """
    stem = Path(stem)
    grey = probability_to_pgm_grey(probability)[::-1]  # row 0 of the image is the top of the map
    height, width = grey.shape
    pgm = stem.with_suffix(".pgm")
    with open(pgm, "wb") as f:
        f.write(f"P5\n# gpom occupancy map, p = (255 - v) / 255\n{width} {height}\n255\n".encode())
        f.write(np.ascontiguousarray(grey).tobytes())
    meta = {
        "image": pgm.name,
        "mode": "scale",
        "resolution": float(resolution_m),
        "origin": [float(origin_xy_m[0]), float(origin_xy_m[1]), 0.0],
        "negate": 0,
        "occupied_thresh": float(occupied_threshold),
        "free_thresh": float(free_threshold),
    }
    yml = stem.with_suffix(".yaml")
    yml.write_text(yaml.safe_dump(meta, sort_keys=False))
    return pgm, yml


def read_map_server(yaml_path: Path) -> tuple[NDArray[np.float64], dict]:
    """Load a map_server map as ROS does: returns p(occ) (H, W) with row 0 at the lowest y, and the YAML."""
    yaml_path = Path(yaml_path)
    try:
        meta = yaml.safe_load(yaml_path.read_text())
        pgm = yaml_path.parent / meta["image"]
        data = pgm.read_bytes()
    except (OSError, KeyError, TypeError, yaml.YAMLError) as exc:
        raise MapExportError(f"{yaml_path}: not a readable map_server map ({exc})") from None
    tokens: list[bytes] = []
    pos = 0
    while len(tokens) < 4:
        while data[pos : pos + 1].isspace():
            pos += 1
        if data[pos : pos + 1] == b"#":
            pos = data.index(b"\n", pos) + 1
            continue
        end = pos
        while not data[end : end + 1].isspace():
            end += 1
        tokens.append(data[pos:end])
        pos = end
    if tokens[0] != b"P5" or int(tokens[3]) != 255:
        raise MapExportError(f"{pgm}: not an 8-bit binary PGM")
    width, height = int(tokens[1]), int(tokens[2])
    pixels = np.frombuffer(data[pos + 1 : pos + 1 + width * height], dtype=np.uint8)
    if pixels.size != width * height:
        raise MapExportError(f"{pgm}: truncated image ({pixels.size} of {width * height} pixels)")
    grey = pixels.reshape(height, width)[::-1]
    p = (255.0 - grey) / 255.0
    if meta.get("negate", 0):
        p = 1.0 - p
    return p, meta


def write_layers_npz(path: Path, layers: MapLayers) -> Path:
    """Write float32 probability, mean, variance with resolution, origin and frame to ``path`` (.npz)."""
    path = Path(path)
    np.savez_compressed(
        path,
        probability=layers.probability.astype(np.float32),
        mean=layers.mean.astype(np.float32),
        variance=layers.variance.astype(np.float32),
        resolution_m=np.float64(layers.resolution_m),
        origin_xy_m=np.asarray(layers.origin_xy_m, dtype=np.float64),
        frame_id=np.str_(layers.frame_id),
        row0="lowest y",
    )
    return path


def read_layers_npz(path: Path) -> MapLayers:
    """Read a ``layers.npz`` written by :func:`write_layers_npz`."""
    try:
        with np.load(Path(path)) as z:
            return MapLayers(
                probability=z["probability"],
                mean=z["mean"],
                variance=z["variance"],
                resolution_m=float(z["resolution_m"]),
                origin_xy_m=(float(z["origin_xy_m"][0]), float(z["origin_xy_m"][1])),
                frame_id=str(z["frame_id"]),
            )
    except (OSError, KeyError, ValueError) as exc:
        raise MapExportError(f"{path}: not a readable layers file ({exc})") from None
