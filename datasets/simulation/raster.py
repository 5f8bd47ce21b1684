"""Exact ground-truth occupancy rasters of a world, and their file format ``PATH.gt.npz``.

Raster convention (the same in memory and on disk):

- ``occupancy`` (H, W) uint8: 1 occupied, 0 free. **Row 0 is the lowest y** (south), column 0 the lowest x,
  so cell ``(i, j)`` covers ``x in [ox + j r, ox + (j+1) r)``, ``y in [oy + i r, oy + (i+1) r)``, where
  ``(ox, oy) = origin_xy_m`` are the world coordinates of the lower-left corner of cell (0, 0) and
  ``r = resolution_m``.
  (An image viewer shows it upside down: flip rows to draw north up.)
- A cell is occupied when its **centre** lies inside a polygon of the world (scanline fill; on a boundary the
  rule is closed in x and half-open in y). The occupied area therefore matches the polygons' area to within
  about one cell along their perimeter, at any resolution.

``PATH.gt.npz`` keys (all plain arrays, readable with ``np.load(path)`` without pickle):
``occupancy``, ``resolution_m`` (), ``origin_xy_m`` (2,), ``frame_id`` (), ``world`` (), ``seed`` (),
``source_names`` (S,), ``source_range_variance_m2`` (S,), ``source_bearing_variance_rad2`` (S,) -- the sensor
noise of each scan source (the topics of the bag), ``odometry_noise_names`` / ``odometry_noise_values`` (the
wheel-odometry noise model, empty when odometry is exact) and ``meta_json`` () (everything above plus the
sensor specifications, as JSON).
"""

from __future__ import annotations

import io
import json
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numba
import numpy as np
from numpy.typing import NDArray

from datasets.errors import DatasetError, first_line
from datasets.simulation.geometry import World

GT_SUFFIX = ".gt.npz"
PNG_SUFFIX = ".gt.png"


@numba.njit(cache=True)
def _fill(occ, vertices, starts, ox, oy, res):  # pragma: no cover - compiled
    h, w = occ.shape
    xs = np.empty(vertices.shape[0], dtype=np.float64)
    for p in range(starts.shape[0] - 1):
        a = starts[p]
        b = starts[p + 1]
        ymin = vertices[a:b, 1].min()
        ymax = vertices[a:b, 1].max()
        i0 = max(0, int(np.ceil((ymin - oy) / res - 0.5)))
        i1 = min(h - 1, int(np.floor((ymax - oy) / res - 0.5)))
        for i in range(i0, i1 + 1):
            yc = oy + (i + 0.5) * res
            n = 0
            for k in range(a, b):
                k2 = k + 1 if k + 1 < b else a
                y0 = vertices[k, 1]
                y1 = vertices[k2, 1]
                if (y0 <= yc < y1) or (y1 <= yc < y0):
                    x0 = vertices[k, 0]
                    x1 = vertices[k2, 0]
                    xs[n] = x0 + (yc - y0) * (x1 - x0) / (y1 - y0)
                    n += 1
            cross = np.sort(xs[:n])
            for m in range(0, n - 1, 2):
                j0 = max(0, int(np.ceil((cross[m] - ox) / res - 0.5)))
                j1 = min(w - 1, int(np.floor((cross[m + 1] - ox) / res - 0.5)))
                for j in range(j0, j1 + 1):
                    occ[i, j] = 1


def rasterize(
    world: World, resolution_m: float, bounds_xy_m: tuple[float, float, float, float] | None = None
) -> tuple[NDArray[np.uint8], NDArray[np.float64]]:
    """The (H, W) uint8 occupancy raster of ``world`` and its (2,) origin, at ``resolution_m``.

    The raster covers ``bounds_xy_m`` (default: the world's bounds), rounded up to whole cells from its
    lower-left corner.
    """
    if not resolution_m > 0:
        raise DatasetError(f"raster resolution must be > 0 m, got {resolution_m}")
    xmin, ymin, xmax, ymax = bounds_xy_m or world.bounds_xy_m
    w = int(np.ceil((xmax - xmin) / resolution_m - 1e-9))
    h = int(np.ceil((ymax - ymin) / resolution_m - 1e-9))
    occ = np.zeros((h, w), dtype=np.uint8)
    if world.polygons:
        vertices = np.concatenate(world.polygons).astype(np.float64)
        starts = np.cumsum([0] + [len(p) for p in world.polygons]).astype(np.int64)
        _fill(occ, vertices, starts, float(xmin), float(ymin), float(resolution_m))
    return occ, np.array([xmin, ymin], dtype=np.float64)


@dataclass(frozen=True)
class NoiseSource:
    """The noise of one scan source (a topic of the bag): range and bearing variances."""

    name: str
    range_variance_m2: float
    bearing_variance_rad2: float


@dataclass(frozen=True)
class GroundTruth:
    """An occupancy raster with its geometry (see the module docstring for the convention)."""

    occupancy: NDArray[np.uint8]
    resolution_m: float
    origin_xy_m: NDArray[np.float64]
    world: str
    frame_id: str = "map"
    seed: int = 0
    sources: tuple[NoiseSource, ...] = ()
    odometry_noise: dict[str, float] = field(default_factory=dict)
    meta: dict = field(default_factory=dict)

    @property
    def shape(self) -> tuple[int, int]:
        return self.occupancy.shape  # type: ignore[return-value]

    @property
    def bounds_xy_m(self) -> tuple[float, float, float, float]:
        """(xmin, ymin, xmax, ymax) covered by the raster."""
        h, w = self.occupancy.shape
        x0, y0 = (float(v) for v in self.origin_xy_m)
        return (x0, y0, x0 + w * self.resolution_m, y0 + h * self.resolution_m)

    def cell_centers_xy_m(self) -> NDArray[np.float64]:
        """(H, W, 2) world coordinates of every cell centre."""
        h, w = self.occupancy.shape
        xs = self.origin_xy_m[0] + (np.arange(w) + 0.5) * self.resolution_m
        ys = self.origin_xy_m[1] + (np.arange(h) + 0.5) * self.resolution_m
        gx, gy = np.meshgrid(xs, ys)
        return np.stack([gx, gy], axis=-1)

    def cell_of(self, points_xy_m: NDArray[np.floating]) -> NDArray[np.int64]:
        """(N, 2) (row, col) cell indices of (N, 2) finite world points (may fall outside the raster)."""
        p = np.asarray(points_xy_m, dtype=np.float64)
        rc = np.floor((p - self.origin_xy_m) / self.resolution_m).astype(np.int64)
        return rc[:, ::-1]

    def occupied_at(self, points_xy_m: NDArray[np.floating]) -> NDArray[np.bool_]:
        """(N,) True where the points fall in an occupied cell (False outside the raster or not finite)."""
        p = np.asarray(points_xy_m, dtype=np.float64)
        finite = np.isfinite(p).all(axis=1)
        rc = self.cell_of(np.where(finite[:, None], p, self.origin_xy_m - 1.0))
        h, w = self.occupancy.shape
        inside = (rc[:, 0] >= 0) & (rc[:, 0] < h) & (rc[:, 1] >= 0) & (rc[:, 1] < w)
        out = np.zeros(rc.shape[0], dtype=bool)
        out[inside] = self.occupancy[rc[inside, 0], rc[inside, 1]] == 1
        return out


def ground_truth_path(bag_path: str | Path) -> Path:
    """``PATH.gt.npz`` beside the bag ``PATH`` (a ``.bag``, a ``.mcap`` or a ROS 2 bag folder)."""
    p = Path(bag_path)
    return p.with_name(p.name + GT_SUFFIX)


def _arrays_of(gt: GroundTruth) -> dict[str, np.ndarray]:
    names = [s.name for s in gt.sources]
    meta = {
        "world": gt.world,
        "seed": gt.seed,
        "frame_id": gt.frame_id,
        "resolution_m": gt.resolution_m,
        "origin_xy_m": [float(v) for v in gt.origin_xy_m],
        "shape": list(gt.occupancy.shape),
        "row_0": "lowest y",
        "sources": [
            {
                "name": s.name,
                "range_variance_m2": s.range_variance_m2,
                "bearing_variance_rad2": s.bearing_variance_rad2,
            }
            for s in gt.sources
        ],
        "odometry_noise": gt.odometry_noise,
        **gt.meta,
    }
    return {
        "occupancy": np.ascontiguousarray(gt.occupancy, dtype=np.uint8),
        "resolution_m": np.array(gt.resolution_m, dtype=np.float64),
        "origin_xy_m": np.asarray(gt.origin_xy_m, dtype=np.float64),
        "frame_id": np.array(gt.frame_id),
        "world": np.array(gt.world),
        "seed": np.array(gt.seed, dtype=np.int64),
        "source_names": np.array(names, dtype=str) if names else np.zeros(0, dtype="<U1"),
        "source_range_variance_m2": np.array([s.range_variance_m2 for s in gt.sources], dtype=np.float64),
        "source_bearing_variance_rad2": np.array(
            [s.bearing_variance_rad2 for s in gt.sources], dtype=np.float64
        ),
        "odometry_noise_names": np.array(list(gt.odometry_noise), dtype=str)
        if gt.odometry_noise
        else np.zeros(0, dtype="<U1"),
        "odometry_noise_values": np.array(list(gt.odometry_noise.values()), dtype=np.float64),
        "meta_json": np.array(json.dumps(meta, sort_keys=True)),
    }


def save_ground_truth(gt: GroundTruth, path: str | Path) -> None:
    """Write ``gt`` as a compressed ``.npz``, byte for byte the same for the same content.

    ``np.savez_compressed`` stamps each member with the wall-clock time; this writer uses a fixed date.
    """
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for key, array in _arrays_of(gt).items():
            info = zipfile.ZipInfo(key + ".npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            member = io.BytesIO()
            np.lib.format.write_array(member, np.asanyarray(array), allow_pickle=False)
            zf.writestr(info, member.getvalue())
    Path(path).write_bytes(buffer.getvalue())


def load_ground_truth(path: str | Path) -> GroundTruth:
    """Read a ``PATH.gt.npz`` written by :func:`save_ground_truth` (DatasetError naming the file if not)."""
    p = Path(path)
    if not p.is_file():
        raise DatasetError(f"{p}: no such ground-truth file")
    try:
        with np.load(p, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise DatasetError(f"{p}: not a readable ground-truth .npz ({first_line(exc)})") from None
    missing = [k for k in ("occupancy", "resolution_m", "origin_xy_m") if k not in data]
    if missing:
        raise DatasetError(f"{p}: ground-truth file lacks {', '.join(missing)}")
    occ = data["occupancy"]
    if occ.ndim != 2 or occ.dtype != np.uint8:
        raise DatasetError(f"{p}: occupancy must be a (H, W) uint8 array, got {occ.dtype} {occ.shape}")
    names = [str(s) for s in data.get("source_names", np.zeros(0))]
    rvar = data.get("source_range_variance_m2", np.zeros(len(names)))
    bvar = data.get("source_bearing_variance_rad2", np.zeros(len(names)))
    sources = tuple(NoiseSource(n, float(r), float(b)) for n, r, b in zip(names, rvar, bvar, strict=True))
    odo = dict(
        zip(
            (str(s) for s in data.get("odometry_noise_names", np.zeros(0))),
            (float(v) for v in data.get("odometry_noise_values", np.zeros(0))),
            strict=True,
        )
    )
    meta = json.loads(str(data["meta_json"])) if "meta_json" in data else {}
    known = {"world", "seed", "frame_id", "resolution_m", "origin_xy_m", "shape", "row_0", "sources"}
    return GroundTruth(
        occupancy=occ,
        resolution_m=float(data["resolution_m"]),
        origin_xy_m=np.asarray(data["origin_xy_m"], dtype=np.float64).reshape(2),
        world=str(data.get("world", "")),
        frame_id=str(data.get("frame_id", "map")),
        seed=int(data.get("seed", 0)),
        sources=sources,
        odometry_noise=odo,
        meta={k: v for k, v in meta.items() if k not in known and k != "odometry_noise"},
    )


def save_ground_truth_png(gt: GroundTruth, path: str | Path) -> None:
    """The raster as a greyscale PNG, one pixel per cell, north up (occupied black, free white)."""
    from PIL import Image

    img = np.where(gt.occupancy[::-1] == 1, 0, 255).astype(np.uint8)
    Image.fromarray(img).save(path, format="PNG", optimize=True)
