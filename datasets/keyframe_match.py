"""Find the scans of a corrected keyframe log in its raw log (e.g. ``intel.gfs.log`` in ``intel.clf``).

A SLAM-corrected CARMEN log keeps a subset of the raw log's scans, in the raw log's order, with their ranges
and new poses. Two things identify a keyframe scan in the raw log:

- **its logger stamp**, when the corrected log kept it: corrected logs round stamps to 6 significant digits
  (10 ms at 2683.77 s) and ``intel.clf`` logs scans in bursts 1 ms apart, so the nearest stamp is the wrong
  scan for 19% of ``intel.gfs.log``; among the raw scans whose logger stamp lies within ``window_s``, the one
  with the same ranges is taken ("stamp").
- **its ranges and its place in line order**, when the stamps are missing, relative, synthetic or wrong
  (three of ``radish-corrected/*.log.gz`` stamp every scan alike; ``fr079``'s corrected log has unreliable
  stamps): the keyframes left without a stamp match are given raw scans with the same ranges, in increasing
  line order between the stamp matches around them ("content_order").

Ranges agree when their largest difference is at most ``tolerance_m``. Measured: corrected logs print
ranges with 6 significant digits (``%g``), raw logs with 2 decimals, so every one of the 910 scans of
``intel.gfs.log`` and of the 4,791 of ``freiburg-079-corrected.log.gz`` has exactly the ranges of its raw
scan (difference 0.0); no two raw scans of ``intel.clf`` or ``fr079.clf`` have the same ranges, and any two
differ by at least 1 cm in some beam, so a tolerance under 5 mm cannot confuse them.

Keyframes that match nothing are reported ("unmatched", index -1), never dropped silently.
"""

from __future__ import annotations

from bisect import bisect_left
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from datasets.errors import DatasetError
from datasets.stamps import NS_PER_S, ns_to_decimal
from datasets.types import Recording

MATCH_METHODS: tuple[str, ...] = ("stamp", "content_order", "unmatched")
_MAX_WINDOW_SCANS = 64  # a stamp window holding more raw scans says the stamps do not separate scans
_MAX_WINDOW_NS = 1 << 62  # a wider stamp window (window_s beyond 146 years) is clipped to this
_MEAN_SLACK_M = 1e-6  # float64 rounding of the mean ranges in the content prefilter


@dataclass(frozen=True, eq=False)
class ScanMatch:
    """How each scan of a keyframe log was found in its raw log (:func:`match_keyframe_scans`).

    ``indices`` (K,) int64: index into the raw log's scans, -1 where unmatched (strictly increasing over the
    matched ones); ``methods`` (K,) str: one of :data:`MATCH_METHODS` per keyframe; ``range_error_m`` (K,)
    float64: the largest absolute range difference of each match (NaN where unmatched).
    """

    indices: NDArray[np.int64]
    methods: NDArray[np.str_]
    range_error_m: NDArray[np.float64]

    @property
    def matched(self) -> NDArray[np.bool_]:
        """(K,) True for the keyframes found in the raw log."""
        return self.indices >= 0

    @property
    def unmatched(self) -> NDArray[np.int64]:
        """Indices of the keyframes found nowhere in the raw log."""
        return np.flatnonzero(self.indices < 0)

    @property
    def counts(self) -> dict[str, int]:
        """``{"stamp": n, "content_order": m, "unmatched": u}`` (JSON-ready)."""
        return {m: int(np.sum(self.methods == m)) for m in MATCH_METHODS}


def match_keyframe_scans(
    keyframes: Recording, full: Recording, window_s: float = 0.05, tolerance_m: float = 0.005
) -> ScanMatch:
    """Find every scan of ``keyframes`` in ``full`` by logger stamp, else by content and line order.

    1. Stamp: a keyframe whose logger stamp no other keyframe shares takes, among the raw scans whose
       logger stamp lies within ``window_s`` (at most 64 of them), the one with the closest ranges if they
       agree within ``tolerance_m``. Of these matches the longest run increasing in both logs is kept.
    2. Content and order: each remaining keyframe may take a raw scan with ranges within ``tolerance_m``
       lying strictly between the raw scans of the stamp matches before and after it; of these candidates
       the largest set increasing in both logs is chosen.

    Both recordings need scans; the stamps are ``meta["logger_stamps_ns"]`` (CARMEN logs), and without
    them only step 2 runs. DatasetError when a recording has no scans.
    """
    if keyframes.scans is None or full.scans is None:
        raise DatasetError("match_scans: both recordings need scans")
    k_ranges, f_ranges = keyframes.scans.ranges_m, full.scans.ranges_m
    n_k = len(k_ranges)
    indices = np.full(n_k, -1, dtype=np.int64)
    errors = np.full(n_k, np.nan)
    methods = np.full(n_k, "unmatched", dtype="<U13")

    by_stamp, stamp_err = _match_by_stamp(keyframes, full, k_ranges, f_ranges, window_s, tolerance_m)
    found = np.flatnonzero(by_stamp >= 0)
    anchors = found[_longest_increasing(by_stamp[found])]
    indices[anchors] = by_stamp[anchors]
    errors[anchors] = stamp_err[anchors]
    methods[anchors] = "stamp"

    pairs_j, pairs_i, pairs_err = _content_candidates(k_ranges, f_ranges, indices, tolerance_m)
    order = np.lexsort((-pairs_i, pairs_j))  # by keyframe, then raw index descending: one pick per keyframe
    chosen = order[_longest_increasing(pairs_i[order])]
    indices[pairs_j[chosen]] = pairs_i[chosen]
    errors[pairs_j[chosen]] = pairs_err[chosen]
    methods[pairs_j[chosen]] = "content_order"
    return ScanMatch(indices, methods, errors)


def match_scans(
    keyframes: Recording, full: Recording, window_s: float = 0.05, tolerance_m: float = 0.005
) -> NDArray[np.int64]:
    """(K,) index into ``full.scans`` of each scan of ``keyframes`` (:func:`match_keyframe_scans`).

    DatasetError naming the first unmatched keyframe when some scan is found nowhere in ``full``; use
    :func:`match_keyframe_scans` to keep the others and learn how each was matched.
    """
    result = match_keyframe_scans(keyframes, full, window_s, tolerance_m)
    missing = result.unmatched
    if missing.size:
        j = int(missing[0])
        stamps = keyframes.meta.get("logger_stamps_ns") if isinstance(keyframes.meta, dict) else None
        stamp = f" (logger stamp {ns_to_decimal(int(stamps[j]))} s)" if stamps is not None else ""
        raise DatasetError(
            f"{keyframes.source}: {missing.size} of {len(result.indices)} scans have no scan with the same "
            f"ranges in {full.source}, in line order, the first is scan {j}{stamp}"
        )
    return result.indices


def _match_by_stamp(
    keyframes: Recording,
    full: Recording,
    k_ranges: list[NDArray],
    f_ranges: list[NDArray],
    window_s: float,
    tolerance_m: float,
) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """(K,) raw index (-1: none) and range error of each keyframe's match within the logger-stamp window."""
    n_k = len(k_ranges)
    out = np.full(n_k, -1, dtype=np.int64)
    err_out = np.full(n_k, np.nan)
    k_meta = keyframes.meta if isinstance(keyframes.meta, dict) else {}
    f_meta = full.meta if isinstance(full.meta, dict) else {}
    k_stamps, f_stamps = k_meta.get("logger_stamps_ns"), f_meta.get("logger_stamps_ns")
    if k_stamps is None or f_stamps is None or len(k_stamps) != n_k or len(f_stamps) != len(f_ranges):
        return out, err_out
    k_stamps = np.asarray(k_stamps, dtype=np.int64)
    _, inverse, shared = np.unique(k_stamps, return_inverse=True, return_counts=True)
    unique = shared[inverse] == 1  # a stamp several keyframes carry identifies none of them
    order = np.argsort(f_stamps, kind="stable")
    ordered = np.asarray(f_stamps, dtype=np.int64)[order]
    window_ns = min(round(window_s * NS_PER_S), _MAX_WINDOW_NS)
    # stamps near the int64 limits would wrap around in the window arithmetic: saturate the window ends
    info = np.iinfo(np.int64)
    lo = np.searchsorted(ordered, np.maximum(k_stamps, info.min + window_ns) - window_ns, side="left")
    hi = np.searchsorted(ordered, np.minimum(k_stamps, info.max - window_ns) + window_ns, side="right")
    for j in np.flatnonzero(unique & (hi - lo <= _MAX_WINDOW_SCANS)).tolist():
        ranges = k_ranges[j]
        best, best_err = -1, np.inf
        for i in order[lo[j] : hi[j]].tolist():
            other = f_ranges[i]
            if other.shape != ranges.shape:
                continue
            err = float(np.max(np.abs(other - ranges)))
            if err < best_err:
                best, best_err = i, err
        if best >= 0 and best_err <= tolerance_m:
            out[j], err_out[j] = best, best_err
    return out, err_out


def _content_candidates(
    k_ranges: list[NDArray], f_ranges: list[NDArray], indices: NDArray[np.int64], tolerance_m: float
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.float64]]:
    """Candidate pairs (keyframe j, raw i, range error) for the keyframes still unmatched in ``indices``.

    Raw scans of the keyframe's beam count whose mean range is within ``tolerance_m`` of its own (a bound
    that every match satisfies), lying strictly between the raw scans of the matched keyframes around it,
    with ranges within ``tolerance_m``."""
    n_k, n_f = len(k_ranges), len(f_ranges)
    matched = np.flatnonzero(indices >= 0)
    # raw index bounds of each keyframe: the matches before and after it (exclusive)
    low = np.concatenate([[-1], indices[matched]])[np.searchsorted(matched, np.arange(n_k), side="left")]
    high = np.concatenate([indices[matched], [n_f]])[np.searchsorted(matched, np.arange(n_k), side="right")]

    groups: dict[int, tuple[NDArray, NDArray, NDArray]] = {}  # beams -> (rows sorted by mean, means, raw idx)
    beams = np.array([r.shape[0] for r in f_ranges], dtype=np.int64)
    for b in np.unique(beams).tolist():
        raw = np.flatnonzero(beams == b)
        rows = np.stack([f_ranges[i] for i in raw.tolist()])
        means = rows.astype(np.float64).mean(axis=1)
        sort = np.argsort(means, kind="stable")
        groups[b] = (rows[sort], means[sort], raw[sort])

    pj: list[NDArray] = []
    pi: list[NDArray] = []
    pe: list[NDArray] = []
    for j in np.flatnonzero(indices < 0).tolist():
        ranges = k_ranges[j]
        group = groups.get(ranges.shape[0])
        if group is None or low[j] + 1 >= high[j]:
            continue
        rows, means, raw = group
        mean = float(ranges.astype(np.float64).mean())
        a = np.searchsorted(means, mean - tolerance_m - _MEAN_SLACK_M, side="left")
        z = np.searchsorted(means, mean + tolerance_m + _MEAN_SLACK_M, side="right")
        inside = (raw[a:z] > low[j]) & (raw[a:z] < high[j])
        if not np.any(inside):
            continue
        err = np.abs(rows[a:z][inside] - ranges).max(axis=1).astype(np.float64)
        ok = err <= tolerance_m
        pj.append(np.full(int(ok.sum()), j, dtype=np.int64))
        pi.append(raw[a:z][inside][ok])
        pe.append(err[ok])
    if not pj:
        return np.empty(0, np.int64), np.empty(0, np.int64), np.empty(0)
    return np.concatenate(pj), np.concatenate(pi).astype(np.int64), np.concatenate(pe)


def _longest_increasing(values: NDArray[np.int64]) -> NDArray[np.int64]:
    """Positions (increasing) of a longest strictly increasing subsequence of ``values`` (patience sort)."""
    tails: list[int] = []  # tails[k]: smallest last value of an increasing run of length k + 1
    tail_pos: list[int] = []
    parent = np.full(len(values), -1, dtype=np.int64)
    for p, v in enumerate(np.asarray(values).tolist()):
        k = bisect_left(tails, v)
        if k > 0:
            parent[p] = tail_pos[k - 1]
        if k == len(tails):
            tails.append(v)
            tail_pos.append(p)
        else:
            tails[k], tail_pos[k] = v, p
    out: list[int] = []
    p = tail_pos[-1] if tail_pos else -1
    while p >= 0:
        out.append(p)
        p = int(parent[p])
    return np.asarray(out[::-1], dtype=np.int64)
