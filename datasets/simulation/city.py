"""A synthetic city: a large world for the scale benchmark, not a realistic one.

Blocks on a square street grid, each split into one to four rectangular buildings with random setbacks; a
robot drives every east-west street in a lawnmower pattern and scans all around with a long-range laser.
The world is generated rather than stored so that its size can be chosen (``bench`` renders it at 1 km x
1 km, the tests at 100 m). Unlike the worlds of :mod:`datasets.simulation.scenarios` it has no ground-truth
raster or bag: only the building edges, the scan poses and the ranges, which the mapping stage takes as is.
"""

from __future__ import annotations

import itertools
import math

import numpy as np

from datasets.simulation.geometry import World, box
from datasets.simulation.raycast import cast_rays

CITY_SIZE_M = 1000.0
CITY_STREET_PITCH_M = 50.0
CITY_STREET_WIDTH_M = 10.0
CITY_SCAN_STEP_M = 2.0
CITY_BEAMS = 181
CITY_RANGE_MAX_M = 30.0
CITY_RANGE_SIGMA_M = 0.01
# poses ray cast together, against the edges within reach of the batch
_BATCH = 32


def city_world(size_m: float = CITY_SIZE_M, seed: int = 0) -> World:
    """The buildings of a city of ``size_m`` x ``size_m`` on a street grid of pitch ``CITY_STREET_PITCH_M``:
    every block holds one to four buildings with random setbacks."""
    rng = np.random.default_rng(seed)
    pitch, street = CITY_STREET_PITCH_M, CITY_STREET_WIDTH_M
    n = int(size_m // pitch)
    boxes = []
    for i in range(n):
        for j in range(n):
            x0, y0 = i * pitch + street, j * pitch + street
            x1, y1 = (i + 1) * pitch, (j + 1) * pitch
            if x1 > size_m or y1 > size_m:
                continue
            nx, ny = rng.integers(1, 3, 2)  # buildings per block along x and y
            xs = np.linspace(x0, x1, nx + 1)
            ys = np.linspace(y0, y1, ny + 1)
            for a in range(nx):
                for b in range(ny):
                    sb = rng.uniform(0.5, 3.0, 4)  # set-backs of the four sides
                    boxes.append(box(xs[a] + sb[0], ys[b] + sb[1], xs[a + 1] - sb[2], ys[b + 1] - sb[3]))
    return World(
        f"city-{size_m:g}", tuple(boxes), ("building",) * len(boxes), (0.0, 0.0, float(size_m), float(size_m))
    )


def city_edges(size_m: float = CITY_SIZE_M, seed: int = 0) -> np.ndarray:
    """(E, 4) building outlines (``x0, y0, x1, y1`` edges) of :func:`city_world`."""
    return city_world(size_m, seed).edges()


def city_path(size_m: float = CITY_SIZE_M, step_m: float = CITY_SCAN_STEP_M) -> np.ndarray:
    """(N, 3) scan poses: every east-west street driven in turn (lawnmower), joined along the west and east
    north-south streets, a pose every ``step_m``."""
    pitch, half = CITY_STREET_PITCH_M, CITY_STREET_WIDTH_M / 2
    rows = np.arange(half, size_m, pitch)
    west, east = half, math.floor((size_m - half) / pitch) * pitch + half
    corners = []
    for k, y in enumerate(rows):
        corners += [(west, y), (east, y)] if k % 2 == 0 else [(east, y), (west, y)]
    pts = []
    for (xa, ya), (xb, yb) in itertools.pairwise(corners):
        n = max(int(math.hypot(xb - xa, yb - ya) // step_m), 1)
        t = np.arange(n) / n
        heading = math.atan2(yb - ya, xb - xa)
        pts.append(np.c_[xa + t * (xb - xa), ya + t * (yb - ya), np.full(n, heading)])
    return np.concatenate(pts)


def city_ranges(poses: np.ndarray, edges: np.ndarray, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(N, B) float32 ranges (inf: no return within ``CITY_RANGE_MAX_M``) and (B,) beam angles of a 360-degree
    laser at ``poses``, with Gaussian range noise of ``CITY_RANGE_SIGMA_M``.

    Ray cast in batches of poses, each against only the edges within reach of the batch: casting every beam
    against every edge of a large city would cost (beams x edges)."""
    rng = np.random.default_rng(seed)
    angles = np.linspace(-np.pi, np.pi, CITY_BEAMS, endpoint=False)
    out = np.empty((len(poses), CITY_BEAMS), np.float32)
    lo = np.minimum(edges[:, :2], edges[:, 2:])
    hi = np.maximum(edges[:, :2], edges[:, 2:])
    reach = CITY_RANGE_MAX_M + 1.0
    for start in range(0, len(poses), _BATCH):
        p = poses[start : start + _BATCH]
        a, b = p[:, :2].min(axis=0) - reach, p[:, :2].max(axis=0) + reach
        near = edges[np.all(hi >= a, axis=1) & np.all(lo <= b, axis=1)]
        r = cast_rays(p[:, None, :2], p[:, 2:3] + angles[None, :], near)
        r = r + rng.normal(0.0, CITY_RANGE_SIGMA_M, r.shape)
        out[start : start + _BATCH] = np.where(r < CITY_RANGE_MAX_M, r, np.inf)
    return out, angles
