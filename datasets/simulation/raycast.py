"""Exact 2D ray casting against polygon edges (numba, parallel over rays).

A ray ``O + t d`` (``t >= 0``, ``d`` a unit vector) meets an edge ``A + u (B - A)`` (``0 <= u <= 1``)
at ``t = (w x e) / (d x e)``, ``u = (w x d) / (d x e)`` with ``w = A - O``, ``e = B - A`` and ``a x b`` the
2D cross product. Polygons are closed sets: a ray that touches a corner or runs along an edge hits at the
first point of contact (a collinear edge gives its nearer end). ``u`` is accepted within ``EDGE_TOLERANCE``
of [0, 1] so that a ray aimed exactly at a vertex is not lost between the two edges sharing it (rounding).
"""

from __future__ import annotations

import numba
import numpy as np
from numpy.typing import NDArray

EDGE_TOLERANCE = 1e-9


@numba.njit(parallel=True, cache=True, fastmath=False)
def _cast(ox, oy, dx, dy, edges, out, hit_edge):  # pragma: no cover - compiled
    n_rays = ox.shape[0]
    n_edges = edges.shape[0]
    lo = -EDGE_TOLERANCE
    hi = 1.0 + EDGE_TOLERANCE
    for r in numba.prange(n_rays):
        px = ox[r]
        py = oy[r]
        vx = dx[r]
        vy = dy[r]
        best = np.inf
        best_k = -1
        for k in range(n_edges):
            ax = edges[k, 0]
            ay = edges[k, 1]
            ex = edges[k, 2] - ax
            ey = edges[k, 3] - ay
            wx = ax - px
            wy = ay - py
            denom = vx * ey - vy * ex
            if denom != 0.0:
                t = (wx * ey - wy * ex) / denom
                if t >= 0.0 and t < best:
                    u = (wx * vy - wy * vx) / denom
                    if lo <= u <= hi:
                        best = t
                        best_k = k
            elif wx * vy - wy * vx == 0.0:
                # collinear: the ray runs along the edge; first contact is the nearer end (or the origin)
                t0 = wx * vx + wy * vy
                t1 = (edges[k, 2] - px) * vx + (edges[k, 3] - py) * vy
                if t0 > t1:
                    t0, t1 = t1, t0
                if t1 >= 0.0:
                    t = max(t0, 0.0)
                    if t < best:
                        best = t
                        best_k = k
        out[r] = best
        hit_edge[r] = best_k


def cast_rays(
    origins_xy_m: NDArray[np.floating], angles_rad: NDArray[np.floating], edges: NDArray[np.floating]
) -> NDArray[np.float64]:
    """Distance (m) from each origin along each world-frame angle to the first edge hit, ``inf`` if none.

    ``origins_xy_m`` (..., 2) and ``angles_rad`` (...) broadcast together; ``edges`` (E, 4) as
    ``x0, y0, x1, y1`` (:meth:`World.edges`). Returns an array of the broadcast shape.
    """
    return cast_rays_hit_edges(origins_xy_m, angles_rad, edges)[0]


def cast_rays_hit_edges(
    origins_xy_m: NDArray[np.floating], angles_rad: NDArray[np.floating], edges: NDArray[np.floating]
) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """:func:`cast_rays` plus the index (into ``edges``) of the edge each ray hits, -1 for none.

    The edge gives the surface orientation at the hit (the angle of incidence of a laser beam).
    """
    origins = np.asarray(origins_xy_m, dtype=np.float64)
    angles = np.asarray(angles_rad, dtype=np.float64)
    shape = np.broadcast_shapes(origins.shape[:-1], angles.shape)
    o = np.broadcast_to(origins, (*shape, 2)).reshape(-1, 2)
    a = np.broadcast_to(angles, shape).reshape(-1)
    e = np.ascontiguousarray(edges, dtype=np.float64).reshape(-1, 4)
    out = np.empty(a.shape[0], dtype=np.float64)
    hit_edge = np.empty(a.shape[0], dtype=np.int64)
    _cast(
        np.ascontiguousarray(o[:, 0]),
        np.ascontiguousarray(o[:, 1]),
        np.cos(a),
        np.sin(a),
        e,
        out,
        hit_edge,
    )
    return out.reshape(shape), hit_edge.reshape(shape)
