"""Map exports for planners and people: ``map_server`` PGM + YAML and ``layers.npz``.

Raster convention everywhere in this project: arrays are (H, W) with row 0 at the LOWEST y and column 0 at
the lowest x; ``origin_xy_m`` is the world position of the lower-left corner of cell (0, 0); cell (r, c)
covers ``[x0 + c*res, x0 + (c+1)*res) x [y0 + r*res, y0 + (r+1)*res)``.

``map_server`` images are the other way up (row 0 is the TOP), which the writer and reader handle.

One classification for planners (:class:`Classification`): a cell whose latent GP variance exceeds
``unknown_variance_fraction`` of the prior variance ``k(x*, x*)`` is *unknown* (no data constrained it);
a known cell is *occupied* when ``p(occ) >= occupied_threshold``, *free* when ``p(occ) <= free_threshold``
and unknown in between. Its int8 values (100 / 0 / -1, :func:`datasets.ros.maps.trinary_occupancy`) are the
maps bag's ``nav_msgs/OccupancyGrid`` and, as grey levels 0 / 254 / 205, the ``trinary`` PGM, so that the
two load to the same cells.
"""

from __future__ import annotations

import zipfile
from collections.abc import Mapping
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any

import numba as nb
import numpy as np
import yaml
from numpy.typing import NDArray

from datasets.errors import GpomError
from datasets.ros.maps import FREE_VALUE, OCCUPIED_VALUE, UNKNOWN_VALUE, trinary_occupancy

#: Grey levels of a ``trinary`` map_server image (what ``map_saver`` writes: nav2_map_server map_io.cpp
#: ``tryWriteMapToFile``; ROS1 map_server map_saver.cpp).
PGM_OCCUPIED, PGM_FREE, PGM_UNKNOWN = 0, 254, 205
#: The YAML thresholds of a ``trinary`` image. map_server thresholds ``occ = (255 - grey) / 255``: 0 -> 1.0,
#: 205 -> 0.196078, 254 -> 0.0039, so ``free_thresh`` must lie between the free and the unknown levels or
#: the unknown grey loads as free. These are the fixed values ROS1's map_saver and nav2's (since
#: ros-navigation/navigation2 PR #5278) write for trinary maps; the probability thresholds of the
#: classification are the YAML's extra keys ``occupied_threshold_p`` / ``free_threshold_p``.
TRINARY_OCCUPIED_THRESH, TRINARY_FREE_THRESH = 0.65, 0.196
#: Default of ``export.unknown_variance_fraction`` (its choice: the configuration's description).
UNKNOWN_VARIANCE_FRACTION = 0.9


class MapExportError(GpomError):
    """A map file cannot be written or read back."""


def finite_range(values: NDArray) -> tuple[float, float] | None:
    """The smallest and largest finite value of ``values`` (any shape), or None when it has none; reads a
    big float32 layer in place, without the float64 copy and the boolean index of the direct expression."""
    a = np.asarray(values)
    if a.size == 0:
        return None
    with np.errstate(invalid="ignore"):
        lo, hi = np.fmin.reduce(a, axis=None), np.fmax.reduce(a, axis=None)  # NaN only where all are NaN
    if np.isfinite(lo) and np.isfinite(hi):
        return float(lo), float(hi)
    finite = a[np.isfinite(a)]
    return (float(finite.min()), float(finite.max())) if finite.size else None


@nb.njit(cache=True)
def _above_fraction(variance: NDArray, prior: NDArray, fraction: float) -> NDArray[np.bool_]:
    """``~(variance <= fraction * prior)`` in float64 over two C-contiguous arrays of one shape, in one pass
    without the float64 temporaries of the numpy expression."""
    out = np.empty(variance.shape, dtype=np.bool_)
    v, p, o = variance.ravel(), prior.ravel(), out.ravel()
    for i in range(v.size):
        o[i] = not (np.float64(v[i]) <= fraction * np.float64(p[i]))
    return out


@dataclass(frozen=True)
class Classification:
    """How a map's cells are classified for planners (module docstring).

    ``prior_variance`` (H, W) float32 is the latent prior variance ``k(x*, x*)`` at every cell (what the map
    reads where no data reach); the thresholds are dimensionless.
    """

    prior_variance: NDArray[np.float32]
    unknown_variance_fraction: float
    occupied_threshold: float
    free_threshold: float

    def __post_init__(self) -> None:
        if not 0.0 < self.unknown_variance_fraction <= 1.0:
            raise MapExportError(
                f"unknown_variance_fraction must be in (0, 1], got {self.unknown_variance_fraction}"
            )
        if not 0.0 < self.free_threshold < self.occupied_threshold < 1.0:
            raise MapExportError(
                f"need 0 < free ({self.free_threshold}) < occupied ({self.occupied_threshold}) < 1"
            )

    def unknown(self, variance: NDArray) -> NDArray[np.bool_]:
        """(H, W) bool: cells whose variance exceeds the fraction of their prior (NaN variance: unknown)."""
        var = np.ascontiguousarray(variance)
        prior = np.ascontiguousarray(self.prior_variance)
        if var.shape != prior.shape or var.dtype.kind != "f" or prior.dtype.kind != "f":
            var, prior = np.broadcast_arrays(np.asarray(var, np.float64), np.asarray(prior, np.float64))
            var, prior = np.ascontiguousarray(var), np.ascontiguousarray(prior)
        return _above_fraction(var, prior, float(self.unknown_variance_fraction))

    def values(self, probability: NDArray, variance: NDArray) -> NDArray[np.int8]:
        """(H, W) int8 OccupancyGrid values: 100 occupied, 0 free, -1 unknown."""
        return self.values_with(probability, self.unknown(variance))

    def values_with(self, probability: NDArray, unknown: NDArray[np.bool_]) -> NDArray[np.int8]:
        """:meth:`values` with the (H, W) mask :meth:`unknown` already computed."""
        return trinary_occupancy(probability, unknown, self.occupied_threshold, self.free_threshold)

    def yaml_keys(self) -> dict[str, Any]:
        """The thresholds and the prior as extra map_server YAML keys: ``prior_variance`` is a number when
        it is the same at every cell, else its ``[min, max]`` (the layer is in ``layers.npz``)."""
        lo, hi = finite_range(self.prior_variance) or (float("nan"), float("nan"))
        return {
            "occupied_threshold_p": float(self.occupied_threshold),
            "free_threshold_p": float(self.free_threshold),
            "unknown_variance_fraction": float(self.unknown_variance_fraction),
            "prior_variance": lo if lo == hi else [lo, hi],
        }


@dataclass(frozen=True)
class MapLayers:
    """A rendered map: float32 (H, W) layers with their placement in the world, and optionally how its
    cells are classified for planners (None for maps read from files that predate it)."""

    probability: NDArray[np.float32]
    mean: NDArray[np.float32]
    variance: NDArray[np.float32]
    resolution_m: float
    origin_xy_m: tuple[float, float]
    frame_id: str = "map"
    classification: Classification | None = None
    #: (H, W) float32 world-frame placement uncertainty (m; NaN where no beam observed the cell), see
    #: :mod:`mapping.placement`; None when the map's poses came without world covariances
    placement_sigma_m: NDArray[np.float32] | None = None

    @property
    def shape(self) -> tuple[int, int]:
        return tuple(self.probability.shape)  # type: ignore[return-value]

    @cached_property
    def unknown(self) -> NDArray[np.bool_] | None:
        """(H, W) bool: cells no data constrained (GP variance above the fraction of the prior), or None
        (computed once: the exports ask for it many times)."""
        return None if self.classification is None else self.classification.unknown(self.variance)

    def occupancy_values(self) -> NDArray[np.int8]:
        """(H, W) int8 values 100 / 0 / -1 of the planners' classification (computed once; read-only)."""
        if self.classification is None:
            raise MapExportError("the map has no classification (no prior variance / thresholds)")
        return self._occupancy_values

    @cached_property
    def _occupancy_values(self) -> NDArray[np.int8]:
        values = self.classification.values_with(self.probability, self.unknown)
        values.flags.writeable = False
        return values

    def cell_shares(self) -> dict[str, float]:
        """The shares of the map's cells the planners' classification calls ``occupied``, ``free`` (of an
        unknown cell's probability nothing is said) and ``unknown``; they sum to 1."""
        values = self.occupancy_values()
        n = max(values.size, 1)
        return {
            "occupied": float(np.count_nonzero(values == 100)) / n,
            "free": float(np.count_nonzero(values == 0)) / n,
            "unknown": float(np.count_nonzero(values == -1)) / n,
        }


def write_map_server(
    stem: Path,
    occupancy: NDArray,
    resolution_m: float,
    origin_xy_m: tuple[float, float],
    extra: Mapping[str, Any] | None = None,
) -> tuple[Path, Path]:
    """Write ``stem.pgm`` (binary P5) and ``stem.yaml``: a ``trinary`` map_server map of the (H, W) int8
    OccupancyGrid values ``occupancy`` (100 occupied -> grey 0, 0 free -> 254, -1 unknown -> 205).

    map_server loads it back to exactly these values (:func:`read_map_server`). ``extra`` keys are added
    to the YAML; map_server reads only the keys it knows (nav2 map_io.cpp ``loadMapYaml``). Returns the two
    paths.
    """
    stem = Path(stem)
    values = np.asarray(occupancy)
    bad = ~np.isin(values, (OCCUPIED_VALUE, FREE_VALUE, UNKNOWN_VALUE))
    if values.ndim != 2 or bad.any():
        raise MapExportError(f"{stem}: a trinary map needs (H, W) values 100 / 0 / -1")
    grey = np.full(values.shape, PGM_UNKNOWN, dtype=np.uint8)
    grey[values == OCCUPIED_VALUE] = PGM_OCCUPIED
    grey[values == FREE_VALUE] = PGM_FREE
    grey = grey[::-1]  # row 0 of the image is the top of the map
    height, width = grey.shape
    pgm = stem.with_suffix(".pgm")
    with open(pgm, "wb") as f:
        f.write(
            f"P5\n# gpom trinary map: 0 occupied, 254 free, 205 unknown\n{width} {height}\n255\n".encode()
        )
        f.write(np.ascontiguousarray(grey).tobytes())
    meta = {
        "image": pgm.name,
        "mode": "trinary",
        "resolution": float(resolution_m),
        "origin": [float(origin_xy_m[0]), float(origin_xy_m[1]), 0.0],
        "negate": 0,
        "occupied_thresh": TRINARY_OCCUPIED_THRESH,
        "free_thresh": TRINARY_FREE_THRESH,
    }
    clash = set(meta) & set(extra or {})
    if clash:
        raise MapExportError(f"{stem}: extra YAML keys clash with map_server's: {', '.join(sorted(clash))}")
    meta.update(dict(extra or {}))
    yml = stem.with_suffix(".yaml")
    yml.write_text(yaml.safe_dump(meta, sort_keys=False))
    return pgm, yml


def _read_pgm(pgm: Path) -> NDArray[np.uint8]:
    """The (H, W) grey levels of a binary 8-bit PGM, image row 0 first (the top)."""
    data = pgm.read_bytes()
    tokens: list[bytes] = []
    pos = 0
    try:
        while len(tokens) < 4:
            while data[pos : pos + 1].isspace():
                pos += 1
            if data[pos : pos + 1] == b"#":
                pos = data.index(b"\n", pos) + 1
                continue
            end = pos
            while end < len(data) and not data[end : end + 1].isspace():
                end += 1
            if end == pos:
                raise ValueError("header ends early")
            tokens.append(data[pos:end])
            pos = end
        width, height, depth = int(tokens[1]), int(tokens[2]), int(tokens[3])
    except ValueError as exc:
        raise MapExportError(f"{pgm}: not a binary PGM ({exc})") from None
    if tokens[0] != b"P5" or depth != 255:
        raise MapExportError(f"{pgm}: not an 8-bit binary PGM")
    pixels = np.frombuffer(data[pos + 1 : pos + 1 + width * height], dtype=np.uint8)
    if pixels.size != width * height:
        raise MapExportError(f"{pgm}: truncated image ({pixels.size} of {width * height} pixels)")
    return pixels.reshape(height, width)


def read_map_server(yaml_path: Path) -> tuple[NDArray[np.int8], dict]:
    """Load a map_server map as nav2 does (map_io.cpp ``loadMapFromFile``, grey images without alpha):
    returns the (H, W) int8 OccupancyGrid values with row 0 at the lowest y, and the YAML.

    ``occ = (255 - grey) / 255`` (``grey / 255`` with ``negate``); ``trinary``: 100 if ``occ >
    occupied_thresh``, 0 if ``occ < free_thresh``, else -1; ``scale``: the same, linearly 0..100 in between
    (``rint``); ``raw``: the grey level itself when 0..100, else -1.
    """
    yaml_path = Path(yaml_path)
    try:
        meta = yaml.safe_load(yaml_path.read_text())
        pgm = yaml_path.parent / meta["image"]
        occ_th, free_th = float(meta["occupied_thresh"]), float(meta["free_thresh"])
        mode = str(meta.get("mode", "trinary"))
        negate = bool(meta.get("negate", 0))
        grey = _read_pgm(pgm)[::-1].astype(np.float64)
    except (OSError, KeyError, TypeError, ValueError, yaml.YAMLError) as exc:
        raise MapExportError(f"{yaml_path}: not a readable map_server map ({exc})") from None
    if mode == "raw":
        out = np.where(grey <= 100, grey, UNKNOWN_VALUE).astype(np.int8)
        return out, meta
    if mode not in ("trinary", "scale"):
        raise MapExportError(f"{yaml_path}: unknown map_server mode '{mode}'")
    shade = grey / 255.0
    occ = shade if negate else 1.0 - shade
    out = np.full(grey.shape, UNKNOWN_VALUE, dtype=np.int8)
    if mode == "scale":
        between = np.rint((occ - free_th) / (occ_th - free_th) * 100.0)
        out = np.clip(between, 0, 100).astype(np.int8)
    out[occ > occ_th] = OCCUPIED_VALUE
    out[occ < free_th] = FREE_VALUE
    return out, meta


def write_layers_npz(path: Path, layers: MapLayers) -> Path:
    """Write float32 probability, mean, variance with resolution, origin and frame to ``path`` (.npz); with
    a classification also the float32 ``prior_variance`` layer, the ``unknown`` mask (uint8 0 / 1) and the
    scalars ``unknown_variance_fraction``, ``occupied_threshold``, ``free_threshold``; with a placement
    uncertainty its float32 ``placement_sigma_m`` layer."""
    path = Path(path)
    extra: dict[str, Any] = {}
    c = layers.classification
    if c is not None:
        extra = dict(
            prior_variance=np.asarray(c.prior_variance, dtype=np.float32),
            unknown=np.asarray(layers.unknown, dtype=np.uint8),
            unknown_variance_fraction=np.float64(c.unknown_variance_fraction),
            occupied_threshold=np.float64(c.occupied_threshold),
            free_threshold=np.float64(c.free_threshold),
        )
    if layers.placement_sigma_m is not None:
        extra["placement_sigma_m"] = np.asarray(layers.placement_sigma_m, dtype=np.float32)
    arrays = dict(
        probability=np.asarray(layers.probability, dtype=np.float32),  # no copy of float32 layers
        mean=np.asarray(layers.mean, dtype=np.float32),
        variance=np.asarray(layers.variance, dtype=np.float32),
        resolution_m=np.float64(layers.resolution_m),
        origin_xy_m=np.asarray(layers.origin_xy_m, dtype=np.float64),
        frame_id=np.str_(layers.frame_id),
        row0=np.str_("lowest y"),
        **extra,
    )
    # np.savez_compressed's layout (one .npy per array in a deflated zip) at zlib level 1 instead of 6:
    # a big building's layers are written in 60 % of the time for a file 2 % larger
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=1) as zf:
        for name, value in arrays.items():
            with zf.open(f"{name}.npy", "w", force_zip64=True) as f:
                np.lib.format.write_array(f, np.asanyarray(value), allow_pickle=False)
    return path


def read_layers_npz(path: Path) -> MapLayers:
    """Read a ``layers.npz`` written by :func:`write_layers_npz` (files without a classification too)."""
    try:
        with np.load(Path(path)) as z:
            classification = None
            if "prior_variance" in z.files:
                classification = Classification(
                    prior_variance=z["prior_variance"],
                    unknown_variance_fraction=float(z["unknown_variance_fraction"]),
                    occupied_threshold=float(z["occupied_threshold"]),
                    free_threshold=float(z["free_threshold"]),
                )
            return MapLayers(
                probability=z["probability"],
                mean=z["mean"],
                variance=z["variance"],
                resolution_m=float(z["resolution_m"]),
                origin_xy_m=(float(z["origin_xy_m"][0]), float(z["origin_xy_m"][1])),
                frame_id=str(z["frame_id"]),
                classification=classification,
                placement_sigma_m=z["placement_sigma_m"] if "placement_sigma_m" in z.files else None,
            )
    except (OSError, KeyError, ValueError) as exc:
        raise MapExportError(f"{path}: not a readable layers file ({exc})") from None
