"""Where the maps of a run lie and how large they may be: their bounds, their size in cells, and the check of
that size against ``scale.max_map_cells`` before anything is allocated."""

from __future__ import annotations

import math

import numpy as np

from datasets.types import ScanSequence
from mapping.build import Bounds
from pipeline.errors import PipelineError

__all__ = [
    "Bounds",
    "check_map_cells",
    "map_cells",
    "parse_numbers",
    "scan_reach_m",
    "snap_to_lattice",
    "union_bounds",
]


def parse_numbers(text: str, count: int) -> list[float] | None:
    """``count`` comma-separated finite numbers of a command-line option, or None if ``text`` is not that."""
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        return None
    return values if len(values) == count and all(np.isfinite(values)) else None


def union_bounds(*bounds: Bounds) -> Bounds:
    """The smallest box holding every box of ``bounds``."""
    b = np.asarray(bounds, dtype=np.float64)
    return float(b[:, 0].min()), float(b[:, 1].min()), float(b[:, 2].max()), float(b[:, 3].max())


def snap_to_lattice(bounds: Bounds, resolution_m: float) -> Bounds:
    """``bounds`` grown outward to the world lattice of cells of ``resolution_m`` (corners at integer
    multiples of it): the grids of every run, and a ground-truth raster on the same lattice, then share their
    cells (a map is scored on such a raster from the cells it rendered). Unchanged where the corners are not
    finite or too large for the lattice to be represented (beyond 2^52 cells from the origin)."""
    xmin, ymin, xmax, ymax = bounds
    lo = np.floor(np.array([xmin, ymin]) / resolution_m)
    hi = np.ceil(np.array([xmax, ymax]) / resolution_m)
    corners = np.concatenate([lo, hi])
    if not np.all(np.isfinite(corners)) or np.abs(corners).max() > 2**52:
        return bounds
    return (
        float(lo[0] * resolution_m),
        float(lo[1] * resolution_m),
        float(hi[0] * resolution_m),
        float(hi[1] * resolution_m),
    )


def map_cells(bounds: Bounds, resolution_m: float) -> tuple[int, int]:
    """(width, height) in cells of a map over ``bounds`` at ``resolution_m`` (Python ints: never overflow;
    PipelineError when a side is beyond every float, e.g. at a subnormal resolution)."""
    xmin, ymin, xmax, ymax = bounds
    sides = ((xmax - xmin) / resolution_m, (ymax - ymin) / resolution_m)
    if not all(math.isfinite(v) for v in sides):
        raise PipelineError(f"a map over {bounds} at {resolution_m:g} m has more cells than any float counts")
    return math.ceil(sides[0]), math.ceil(sides[1])


def _count_text(n: int) -> str:
    """``n`` as it is when short, else ``1.23e+07`` (beyond the float range: a power of ten)."""
    if n < 100_000:
        return str(n)
    return f"{n:.3g}" if n < 10**300 else f"~1e+{len(str(n)) - 1}"


def check_map_cells(bounds: Bounds, resolution_m: float, max_cells: int, what: str) -> None:
    """PipelineError, before any allocation, when a map over ``bounds`` at ``resolution_m`` would have more
    than ``max_cells`` cells (``scale.max_map_cells``); ``what`` says which map (and how its bounds were
    found) in the message."""
    try:
        width, height = map_cells(bounds, resolution_m)
    except PipelineError as exc:  # (bounds beyond every float: say which map, and so which option)
        raise PipelineError(f"{what}: {exc}") from None
    if width * height > max_cells:
        size_x, size_y = bounds[2] - bounds[0], bounds[3] - bounds[1]
        raise PipelineError(
            f"{what}: {size_x:.4g} x {size_y:.4g} m at {resolution_m:g} m is {_count_text(width)} x "
            f"{_count_text(height)} = {_count_text(width * height)} cells, above scale.max_map_cells = "
            f"{max_cells:.3g} (choose a coarser resolution or smaller bounds, or raise the limit in the "
            "configuration)"
        )


def scan_reach_m(scans: ScanSequence) -> float:
    """The longest valid return of ``scans`` (m): the smallest map of a run covers one scan's disc of it."""
    reach = 0.0
    for r, lo, hi in zip(scans.ranges_m, scans.range_min_m, scans.range_max_m, strict=True):
        with np.errstate(invalid="ignore"):
            hits = r[(r >= lo) & (r < hi)]
        if hits.size:
            reach = max(reach, float(hits.max()))
    return reach
