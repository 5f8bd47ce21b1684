"""The Intel lab map that the mapping figures show and the mapping benchmark times.

Both use the same input (``intel.gfs.log``: the Intel log with corrected poses, in the shared data folder)
and the same map extent (:func:`robust_bounds` of its returns), so that the benchmark's rates are those of
the map in ``docs/figures/mapping/intel_*.png``.
"""

from __future__ import annotations

import numpy as np

from datasets.paths import SHARED_DATA_DIR

#: The Intel log with corrected poses, relative to the shared data folder.
INTEL_GFS_LOG = "intel/intel.gfs.log"
#: Its path in the shared data folder.
INTEL_GFS_PATH = SHARED_DATA_DIR / INTEL_GFS_LOG


def robust_bounds(points_xy_m: np.ndarray, margin_m: float = 1.0, q: float = 0.2) -> tuple[float, ...]:
    """Bounds of the central (100 - 2q)% of the points in x and y, grown by ``margin_m`` (drops the few
    returns seen far away through windows)."""
    lo = np.percentile(points_xy_m, q, axis=0) - margin_m
    hi = np.percentile(points_xy_m, 100 - q, axis=0) + margin_m
    return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])
