"""Fault injection for the back end: wrong loop closures, as a false positive of the closure search looks.

``evaluate slam --inject-false-closures FRACTION`` hands the pose graph, before its final optimisation,
``round(FRACTION x accepted closures)`` closures between random keyframe pairs whose relative pose is off
by 2-20 m and up to 90 deg, each carrying the information (and robust loss) of a real accepted closure: the
back end cannot tell them from true ones by their covariance. What it keeps of them measures how robust it
is (SLAM's result reports ``fault_injection``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from slam import geometry as se2
from slam.loop_closure import LoopClosure

FloatArray = NDArray[np.float64]

#: The ``reason`` of an injected closure (kept in the result so that reports can tell them apart).
INJECTED = "injected (fault)"


@dataclass(frozen=True)
class FalseClosures:
    """What to inject: ``fraction`` of the accepted closures' count (rounded, at least one when > 0), from
    the random generator seeded with ``seed``; translation errors ``error_m`` (min, max), rotation errors up
    to ``max_error_rad`` either way; pairs at least ``min_separation`` keyframes apart."""

    fraction: float
    seed: int = 0
    error_m: tuple[float, float] = (2.0, 20.0)
    max_error_rad: float = math.pi / 2
    min_separation: int = 10

    def __post_init__(self) -> None:
        if not (0.0 <= self.fraction <= 10.0 and math.isfinite(self.fraction)):
            raise ValueError(f"the fraction of false closures must be in [0, 10], not {self.fraction}")


def false_closures(
    poses_xytheta: FloatArray,
    keyframe_scans: NDArray[np.int64],
    accepted: list[LoopClosure],
    spec: FalseClosures,
) -> list[LoopClosure]:
    """Wrong closures between keyframes of the graph whose current estimate is ``poses_xytheta`` (K, 3)
    (``keyframe_scans`` (K,): their scans). Each measures ``between(x_target, x_query)`` composed with an
    error ``(t cos a, t sin a, r)``: ``t`` uniform in ``spec.error_m``, ``a`` uniform, ``r`` uniform in
    +-``spec.max_error_rad``; its information and robust loss are those of a random accepted closure."""
    count = round(spec.fraction * len(accepted))
    if spec.fraction > 0 and accepted:
        count = max(count, 1)
    k_count = len(poses_xytheta)
    if count == 0 or k_count <= spec.min_separation:
        return []
    rng = np.random.default_rng(spec.seed)
    out: list[LoopClosure] = []
    while len(out) < count:
        query = int(rng.integers(spec.min_separation, k_count))
        target = int(rng.integers(0, query - spec.min_separation + 1))
        t = rng.uniform(*spec.error_m)
        a = rng.uniform(-math.pi, math.pi)
        r = rng.uniform(-spec.max_error_rad, spec.max_error_rad)
        truth = se2.between(poses_xytheta[target], poses_xytheta[query])
        wrong = se2.compose(truth, np.array([t * math.cos(a), t * math.sin(a), r]))
        model = accepted[int(rng.integers(len(accepted)))]
        out.append(
            replace(
                model,
                query_keyframe=query,
                target_keyframe=target,
                query_scan=int(keyframe_scans[query]),
                target_scan=int(keyframe_scans[target]),
                relative_xytheta=np.asarray(wrong, dtype=np.float64),
                reason=INJECTED,
                consistent=True,
            )
        )
    return out
