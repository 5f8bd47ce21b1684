"""Comparing two renderings of the same map computed along different code paths.

The compiled GP core runs with ``fastmath`` and solves LANES (:data:`mapping.core.LANES`) queries per SIMD
block, so on some CPUs (e.g. with AVX-512's approximate reciprocals, or where a query lands in another lane of
its block) the same query can come out a few float64 ulps apart, and that, rounded to the float32 layers, is
at most a float32 ulp or two in a handful of cells. "The same map" is therefore asserted as:
every cell within 2 float32 ulps, and at least 99.99 % of the cells bit for bit identical. A real difference
(another neighbour set, another pose) changes far more cells by far more than that.

One exception: a cell that one rendering answered with the prior unsolved (mean exactly 0: beyond the reach
of every input that rendering saw, :mod:`mapping.reach`; a tile sees only its support) may read otherwise in
the other's solve, but the reach guarantees that the solve is unknown too: its variance is at least
``unknown_fraction`` of the prior's (the classification's fraction, 0.9 by default). Where both read the
prior, they are equal.
"""

from __future__ import annotations

import numpy as np

LAYER_NAMES = ("probability", "mean", "variance")


def assert_same_map(
    a, b, max_ulp: int = 2, min_identical: float = 0.9999, unknown_fraction: float = 0.9
) -> None:
    """``a`` and ``b`` (MapLayers or anything with the three float32 layers) are the same map."""
    prior_a, prior_b = np.asarray(a.mean) == 0, np.asarray(b.mean) == 0
    at_prior = prior_a | prior_b
    va, vb = np.asarray(a.variance, np.float64), np.asarray(b.variance, np.float64)
    one = (prior_a ^ prior_b) & ~np.isnan(va)
    solved_share = np.where(prior_a, vb, va)[one] / np.where(prior_a, va, vb)[one]
    assert solved_share.min(initial=1.0) >= unknown_fraction, (
        f"a cell at the prior on one side is known on the other ({solved_share.min():.3f} of its variance)"
    )
    for name in LAYER_NAMES:
        x, y = np.asarray(getattr(a, name)), np.asarray(getattr(b, name))
        assert x.shape == y.shape, (name, x.shape, y.shape)
        assert np.array_equal(np.isnan(x), np.isnan(y)), name
        both = prior_a & prior_b & ~np.isnan(x)
        assert np.array_equal(x[both], y[both]), f"{name}: cells at the prior on both sides differ"
        ok = ~np.isnan(x) & ~at_prior
        np.testing.assert_array_max_ulp(x[ok], y[ok], maxulp=max_ulp)
        identical = float(np.mean(x[ok].view(np.uint32) == y[ok].view(np.uint32))) if ok.any() else 1.0
        assert identical >= min_identical, f"{name}: only {identical:.6%} of the cells are bit-identical"
