"""Comparing two renderings of the same map computed along different code paths.

The compiled GP core runs with ``fastmath`` and solves LANES (:data:`mapping.core.LANES`) queries per SIMD
block, so on some CPUs (e.g. with AVX-512's approximate reciprocals, or where a query lands in another lane of
its block) the same query can come out a few float64 ulps apart, and that, rounded to the float32 layers, is
at most a float32 ulp or two in a handful of cells. "The same map" is therefore asserted as:
every cell within 2 float32 ulps, and at least 99.99 % of the cells bit for bit identical. A real difference
(another neighbour set, another pose) changes far more cells by far more than that.

One exception: a cell that one rendering answered with the prior unsolved (mean exactly 0: beyond the reach
of every input that rendering saw, :mod:`mapping.reach`; a tile sees only its support) may read up to 1e-5
apart from the other's solve, which the reach test's tolerance (1e-4 of k(0)) bounds.
"""

from __future__ import annotations

import numpy as np

LAYER_NAMES = ("probability", "mean", "variance")


def assert_same_map(
    a, b, max_ulp: int = 2, min_identical: float = 0.9999, prior_tolerance: float = 1e-5
) -> None:
    """``a`` and ``b`` (MapLayers or anything with the three float32 layers) are the same map."""
    at_prior = (np.asarray(a.mean) == 0) | (np.asarray(b.mean) == 0)
    for name in LAYER_NAMES:
        x, y = np.asarray(getattr(a, name)), np.asarray(getattr(b, name))
        assert x.shape == y.shape, (name, x.shape, y.shape)
        assert np.array_equal(np.isnan(x), np.isnan(y)), name
        prior = at_prior & ~np.isnan(x)
        gap = np.abs(x[prior].astype(np.float64) - y[prior]).max(initial=0.0)
        assert gap <= prior_tolerance, f"{name}: cells at the prior on one side differ by {gap:.2e}"
        ok = ~np.isnan(x) & ~at_prior
        np.testing.assert_array_max_ulp(x[ok], y[ok], maxulp=max_ulp)
        identical = float(np.mean(x[ok].view(np.uint32) == y[ok].view(np.uint32))) if ok.any() else 1.0
        assert identical >= min_identical, f"{name}: only {identical:.6%} of the cells are bit-identical"
