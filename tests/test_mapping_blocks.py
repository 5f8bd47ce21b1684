"""The block-shared neighbour search (mapping.blocks): exact on real data, in every path it can take."""

from __future__ import annotations

import numpy as np
import pytest

from datasets.registry import open_dataset
from mapping.blocks import BLOCK_M, MIN_BLOCK, chunk_neighbours
from mapping.config import MappingConfig
from mapping.gpmap import grid_centres, tile_order
from mapping.neighbours import BeamIndex
from pipeline.evaluate_map import make_beams, reference_laser_poses
from tests.conftest import data_file
from tests.test_mapping_core import random_beams

K = 15


@pytest.fixture(scope="module")
def intel_index():
    """Every fifth scan of the Intel lab at its corrected poses: corridors with dense fans of beams, rooms,
    and space outside the building far from every beam."""
    path = data_file("intel/intel.gfs.log")
    rec = open_dataset(path)
    poses = reference_laser_poses(rec, path)
    beams = make_beams(rec, poses, np.arange(0, len(rec.scans), 5), MappingConfig())
    return beams, BeamIndex.build(beams)


def brute(beams, queries: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """(Q, k) sorted distances to the k nearest endpoints and to the k nearest free segments."""
    hits = beams.hit_xy_m
    p = beams.origins_xy_m
    d = beams.free_ends_xy_m - p
    l2 = np.einsum("ij,ij->i", d, d)
    occ, free = [], []
    for q in queries:
        occ.append(np.sort(np.hypot(*(hits - q).T))[:k])
        t = np.clip(np.einsum("ij,ij->i", q - p, d) / np.where(l2 > 0, l2, 1.0), 0, 1)
        free.append(np.sort(np.hypot(*(p + t[:, None] * d - q).T))[:k])
    return np.array(occ), np.array(free)


def search(index: BeamIndex, queries: np.ndarray, k: int, chunk: int = 256, **options):
    """chunk_neighbours over ``queries`` in chunks, as the map's prediction runs it; the distances of what
    it found (endpoints, segments' closest points) and the segment ids."""
    n = queries.shape[0]
    ido = np.full((n, k), -1, np.int64)
    idf = np.full((n, k), -1, np.int64)
    tf = np.zeros((n, k))
    no = np.zeros(n, np.int64)
    nf = np.zeros(n, np.int64)
    for lo in range(0, n, chunk):
        hi = min(lo + chunk, n)
        chunk_neighbours(
            queries, lo, hi, index.points, index.segments, k, k, ido[lo:hi], no[lo:hi], idf[lo:hi], tf[lo:hi],
            nf[lo:hi], **options,
        )  # fmt: skip
    assert (no == min(k, index.hit_xy.shape[0])).all() and (nf == min(k, index.seg.shape[0])).all()
    d_occ = np.hypot(*(index.hit_xy[ido] - queries[:, None]).transpose(2, 0, 1))
    seg = index.seg[idf]
    closest = seg[..., :2] + tf[..., None] * seg[..., 2:4]
    d_free = np.hypot(*(closest - queries[:, None]).transpose(2, 0, 1))
    return d_occ, d_free, idf


def test_blocks_find_the_exact_neighbours_on_real_data(intel_index) -> None:
    """Map cells in render order over corridors, rooms and empty space outside the lab: the k nearest
    endpoints and segments, at the brute-force distances, each segment once (a segment is listed by every
    index cell it crosses); the same as each query searched alone (blocks of one query)."""
    beams, index = intel_index
    pts, _, (h, w) = grid_centres((-22.0, -22.0, 22.0, 22.0), 0.1)
    order = tile_order(int(h), int(w), 64)
    rng = np.random.default_rng(0)
    starts = rng.choice(order.size // 256, 16, replace=False) * 256
    queries = np.ascontiguousarray(np.concatenate([pts[order[s : s + 256]] for s in starts]))
    b_occ, b_free = brute(beams, queries, K)
    # by default blocks in dense data search query by query; an infinite entry ratio searches every block
    # as one
    for options in ({}, {"entry_ratio": np.inf}):
        d_occ, d_free, idf = search(index, queries, K, **options)
        np.testing.assert_allclose(d_occ, b_occ, rtol=0, atol=1e-12)
        np.testing.assert_allclose(d_free, b_free, rtol=0, atol=1e-12)
        assert all(len(set(row)) == K for row in idf.tolist())
    # far from the data as well as inside: k-th free segments from centimetres to metres away
    assert b_free[:, -1].min() < 0.05 and b_free[:, -1].max() > 3.0
    a_occ, a_free, _ = search(index, queries, K, block_m=1e-9)  # every query alone
    np.testing.assert_array_equal(d_occ, a_occ)
    np.testing.assert_array_equal(d_free, a_free)


def test_blocks_over_scattered_points_and_capped_candidates(intel_index) -> None:
    """Test points scattered over the map (blocks of any size, some of one point) and blocks whose range
    search is capped to a few candidates (so they are searched query by query): still exact."""
    beams, index = intel_index
    rng = np.random.default_rng(1)
    queries = rng.uniform(-20.0, 20.0, (600, 2))
    queries = np.ascontiguousarray(queries[np.lexsort(np.floor(queries.T / 2.0))])  # some locality
    b_occ, b_free = brute(beams, queries, K)
    for options in (
        {"block_m": 2.0, "entry_ratio": np.inf},
        {"block_m": BLOCK_M},
        {"block_m": 2.0, "max_candidates": 3 * K, "entry_ratio": np.inf},
    ):
        d_occ, d_free, _ = search(index, queries, K, **options)
        np.testing.assert_allclose(d_occ, b_occ, rtol=0, atol=1e-12)
        np.testing.assert_allclose(d_free, b_free, rtol=0, atol=1e-12)


def test_blocks_with_fewer_items_than_k() -> None:
    """Five beams (four returns): a block's centre finds fewer than k items, and its queries get all of
    them, searched alone."""
    beams = random_beams(2, n_scans=1, n_beams=5, no_return_every=100)
    index = BeamIndex.build(beams)
    queries = np.ascontiguousarray(
        np.stack(np.meshgrid(np.arange(4) * 0.1, np.arange(4) * 0.1), -1).reshape(-1, 2)
    )
    assert queries.shape[0] >= MIN_BLOCK
    n = queries.shape[0]
    ido = np.full((n, K), -1, np.int64)
    idf = np.full((n, K), -1, np.int64)
    no = np.zeros(n, np.int64)
    nf = np.zeros(n, np.int64)
    chunk_neighbours(queries, 0, n, index.points, index.segments, K, K, ido, no, idf, np.zeros((n, K)), nf)
    assert (no == 4).all() and (nf == 5).all()
    assert all(sorted(row[:5]) == list(range(5)) for row in idf.tolist())
