"""The covariances the mapper receives (:mod:`slam.consistency`): relative covariances from one sparse
factorisation against GTSAM's joint marginals, gauge invariance (where the graph is anchored changes no
mapping covariance and no map; it changes every world-frame marginal), which keyframes are passes over the
same place, and the covariances before / after loop closure on a corridor driven twice."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from slam import geometry as se2
from slam.config import ConsistencyConfig
from slam.consistency import (
    RelativeCovariance,
    closure_corrections,
    keyframe_cells,
    keyframe_consistency_body,
    map_effect,
    revisit_partners,
)
from slam.graph import Edge, PoseGraph

ODO_COV = np.diag([0.02**2, 0.01**2, 0.004**2])
LOOP_COV = np.diag([0.01**2, 0.01**2, 0.002**2])
PRIOR_COV = np.diag([1e-3**2, 1e-3**2, 1e-4**2])
STEP_M = 0.5
WIDTH_M, HEIGHT_M = 20.0, 10.0


def _centreline(s_m: np.ndarray) -> np.ndarray:
    """(N, 3) poses along a 20 m x 10 m rectangle (counter-clockwise from the origin) at arc lengths s."""
    perimeter = 2 * (WIDTH_M + HEIGHT_M)
    s = np.mod(s_m, perimeter)
    corners = np.array([[0, 0], [WIDTH_M, 0], [WIDTH_M, HEIGHT_M], [0, HEIGHT_M], [0, 0]], dtype=float)
    lengths = np.array([WIDTH_M, HEIGHT_M, WIDTH_M, HEIGHT_M])
    starts = np.concatenate([[0.0], np.cumsum(lengths)])
    side = np.clip(np.searchsorted(starts, s, side="right") - 1, 0, 3)
    t = (s - starts[side]) / lengths[side]
    xy = corners[side] + t[:, None] * (corners[side + 1] - corners[side])
    return np.column_stack([xy, side * np.pi / 2])


def _walls() -> np.ndarray:
    """(P, 2) points on the two walls of the corridor, 1 m either side of the centreline, every 0.1 m."""
    out = []
    for d in (-1.0, 1.0):
        x0, y0, x1, y1 = -d, -d, WIDTH_M + d, HEIGHT_M + d
        for a, b in (((x0, y0), (x1, y0)), ((x1, y0), (x1, y1)), ((x1, y1), (x0, y1)), ((x0, y1), (x0, y0))):
            n = int(np.hypot(b[0] - a[0], b[1] - a[1]) / 0.1)
            t = np.linspace(0, 1, n, endpoint=False)[:, None]
            out.append(np.asarray(a) + t * (np.asarray(b) - np.asarray(a)))
    return np.concatenate(out)


class Corridor:
    """A rectangular corridor driven 1.4 times round: keyframes every 0.5 m, the odometry turning 0.3 deg
    too far per metre, loop closures from the second pass onto the first; points within 5 m of each
    keyframe on its walls."""

    def __init__(self, heading_bias_deg_per_m: float = 0.3) -> None:
        perimeter = 2 * (WIDTH_M + HEIGHT_M)
        self.s_m = np.arange(0.0, 1.4 * perimeter, STEP_M)
        self.truth = _centreline(self.s_m)
        self.truth[:, 2] = np.unwrap(self.truth[:, 2])
        k = len(self.truth)
        inc = se2.between(self.truth[:-1], self.truth[1:])
        inc[:, 2] += np.radians(heading_bias_deg_per_m) * STEP_M  # the second pass drifts off the first
        self.before = se2.chain(self.truth[0], inc)
        self.edges: list[Edge] = [Edge("prior", 0, 0, self.before[0], PRIOR_COV)]
        self.edges += [Edge("odometry", i, i + 1, inc[i], ODO_COV) for i in range(k - 1)]
        self.first_pass = int(np.searchsorted(self.s_m, perimeter))
        for q in range(self.first_pass + 4, k, 6):  # the second pass, closed onto the first
            j = q - self.first_pass
            self.edges.append(Edge("loop", j, q, se2.between(self.truth[j], self.truth[q]), LOOP_COV))
        graph = PoseGraph.from_edges(self.edges, self.before)
        self.after = graph.optimize_batch()
        walls = _walls()
        self.points_base = [
            se2.transform_points(se2.inverse(p), walls[np.hypot(*(walls - p[:2]).T) < 5.0])
            for p in self.truth
        ]

    def reanchored(self, key: int, cov: np.ndarray) -> list[Edge]:
        """The same graph with its prior on keyframe ``key`` (at its optimised pose) instead."""
        return [Edge("prior", key, key, self.after[key], cov)] + [e for e in self.edges if e.kind != "prior"]


@pytest.fixture(scope="module")
def corridor() -> Corridor:
    return Corridor()


def _gtsam_relative(edges: list[Edge], poses: np.ndarray, pairs: list[tuple[int, int]]) -> np.ndarray:
    """Covariance of between(x_j, x_k) in x_k's frame from GTSAM's joint marginal of (x_j, x_k)."""
    graph = PoseGraph.from_edges(edges, poses)
    marginals = gtsam.Marginals(graph.graph, graph._estimate)
    out = []
    for j, k in pairs:
        jm = marginals.jointMarginalCovariance(gtsam.KeyVector([j, k]))
        s_jj, s_jk, s_kk = (np.asarray(jm.at(a, b)) for a, b in ((j, j), (j, k), (k, k)))
        m = -se2.adjoint(se2.inverse(se2.between(poses[j], poses[k])))
        out.append(m @ s_jj @ m.T + m @ s_jk + s_jk.T @ m.T + s_kk)
    return np.stack(out)


@pytest.mark.parametrize("bias_deg_per_m", [0.0, 0.3], ids=["consistent", "drifting"])
def test_relative_covariances_equal_gtsams_joint_marginals(bias_deg_per_m) -> None:
    """Exact where the factors' residuals vanish; to first order where the closures pull against a drifting
    odometry (GTSAM's Jacobians there include the derivative of the residual's Logmap)."""
    world = Corridor(bias_deg_per_m)
    fp = world.first_pass
    pairs = [(0, 5), (3, 100), (10, fp + 10), (fp + 30, 40), (7, 7 + 1)]
    ours = RelativeCovariance(world.after, world.edges).between_body(*np.array(pairs).T)
    theirs = _gtsam_relative(world.edges, world.after, pairs)
    rel_err = np.linalg.norm(ours - theirs, axis=(1, 2)) / np.linalg.norm(theirs, axis=(1, 2))
    assert np.max(rel_err) < (1e-7 if bias_deg_per_m == 0 else 1e-3), rel_err
    # a pair tied by loop closures is known far better than the odometry between them says
    assert np.trace(ours[2]) < 0.1 * np.trace(ours[1])


def test_relative_covariance_along_a_chain_is_the_chain_between_the_two(corridor) -> None:
    chain = [e for e in corridor.edges if e.kind != "loop"]
    j, k = 12, 57
    ours = RelativeCovariance(corridor.before, chain).between_body([j], [k])[0]
    inc = [e.measurement_xytheta for e in chain if e.kind == "odometry"][j:k]
    propagated = se2.propagate_chain_cov_body(
        np.array(inc), np.tile(ODO_COV, (k - j, 1, 1)), np.zeros((3, 3))
    )
    np.testing.assert_allclose(ours, propagated[-1], rtol=1e-8)


def test_no_anchor_changes_a_relative_covariance_every_anchor_changes_the_marginals(corridor) -> None:
    """Gauge invariance: the prior moved to another keyframe (and made 100x looser) changes the world-frame
    marginals by metres-squared but no relative covariance and no mapping covariance."""
    pairs = (np.array([0, 20, 90]), np.array([150, 160, 165]))
    moved = corridor.reanchored(60, PRIOR_COV * 100)
    a = RelativeCovariance(corridor.after, corridor.edges).between_body(*pairs)
    b = RelativeCovariance(corridor.after, moved).between_body(*pairs)
    np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-14)

    cfg = ConsistencyConfig()
    path = corridor.s_m
    first = keyframe_consistency_body(
        corridor.before, corridor.after, corridor.edges, corridor.points_base, path, cfg
    )
    second = keyframe_consistency_body(
        corridor.before, corridor.after, moved, corridor.points_base, path, cfg
    )
    for x, y in zip(first, second, strict=True):
        np.testing.assert_allclose(x, y, rtol=1e-6, atol=1e-14)

    def marginals(edges: list[Edge]) -> np.ndarray:
        graph = PoseGraph.from_edges(edges, corridor.after)
        return graph.marginals_body()

    world_a, world_b = marginals(corridor.edges), marginals(moved)
    assert np.max(np.abs(np.trace(world_a - world_b, axis1=1, axis2=2))) > 1e-3


def test_passes_over_the_same_place_are_partners_one_pass_along_a_corridor_is_not(corridor) -> None:
    cells = keyframe_cells(corridor.after, corridor.points_base, 1.0)
    j, k = revisit_partners(cells, corridor.s_m, 10.0, 0.25, 4)
    assert len(k) > 0
    # a partner is an earlier pass: at least 10 m of travel before, near the same place
    assert np.all(corridor.s_m[k] - corridor.s_m[j] >= 10.0)
    place = np.hypot(*(corridor.truth[j, :2] - corridor.truth[k, :2]).T)
    assert np.all(place < 10.0)
    # the first lap has none until it comes back within sight of where it started
    assert np.all(corridor.s_m[k] > 50.0)
    # every keyframe of the second pass but the few leaving the turn at its start has one
    assert len(np.unique(k)) >= 0.9 * (len(corridor.truth) - corridor.first_pass - 10)
    # one pass down three sides (45 m): a corridor seen along its length is one visit of each of its cells
    first = keyframe_cells(corridor.after[:90], corridor.points_base[:90], 1.0)
    assert len(revisit_partners(first, corridor.s_m[:90], 10.0, 0.25, 4)[0]) == 0
    # ... unless the gap is shorter than the travel along which a wall stays in sight (5 m here)
    assert len(revisit_partners(first, corridor.s_m[:90], 0.4, 0.25, 4)[0]) > 0


def test_closure_corrections_are_the_change_of_the_relative_pose() -> None:
    before = np.array([[0.0, 0.0, 0.0], [5.0, 1.0, 0.3]])
    np.testing.assert_allclose(
        closure_corrections(before, before, np.array([0]), np.array([1])), 0.0, atol=1e-12
    )
    # the closure moves keyframe 1 by (0.4, -0.1) m and 0.05 rad in its own frame relative to keyframe 0
    shift = np.array([0.4, -0.1, 0.05])
    after = before.copy()
    after[1] = se2.compose(before[1], se2.inverse(shift))
    got = closure_corrections(before, after, np.array([0]), np.array([1]))[0]
    np.testing.assert_allclose(got, se2.logmap(shift), atol=1e-12)


def test_second_pass_uncertain_before_loop_closure_sharp_after(corridor) -> None:
    cfg = ConsistencyConfig()
    before, after = keyframe_consistency_body(
        corridor.before, corridor.after, corridor.edges, corridor.points_base, corridor.s_m, cfg
    )
    lever = 3.0
    fp = corridor.first_pass
    first_b, first_a = map_effect(before[:90], lever), map_effect(after[:90], lever)  # 45 m, one pass
    second_b, second_a = map_effect(before[fp + 20 :], lever), map_effect(after[fp + 20 :], lever)
    drift_m = np.hypot(*(corridor.before[fp + 20 :, :2] - corridor.truth[fp + 20 :, :2]).T)
    # the first pass: the local odometry uncertainty (one odometry step), before and after
    step = map_effect(ODO_COV, lever)
    assert np.max(first_b) <= 1.01 * step and np.max(first_a) <= 1.01 * step
    # the second pass before closure: as uncertain as the odometry's disagreement with the first pass
    assert np.median(np.sqrt(second_b)) > 0.5 * np.median(drift_m) > 0.3
    # after closure it is tied to the first pass: centimetres, where its world-frame marginal is not
    assert np.sqrt(np.max(second_a)) < 0.05
    world = se2.rotate_cov_to_world(
        corridor.after, PoseGraph.from_edges(corridor.edges, corridor.after).marginals_body()
    )
    assert np.median(np.sqrt(map_effect(world[fp + 20 :], lever))) > 3 * np.median(np.sqrt(second_a))


def _ray_cast(poses: np.ndarray, angles_rad: np.ndarray, segments: np.ndarray, max_m: float) -> np.ndarray:
    """(N, B) ranges from each pose along each beam angle to the nearest of (S, 4) wall segments."""
    out = np.full((len(poses), len(angles_rad)), np.inf)
    a, b = segments[:, :2], segments[:, 2:] - segments[:, :2]
    for i, p in enumerate(poses):
        d = np.column_stack([np.cos(p[2] + angles_rad), np.sin(p[2] + angles_rad)])  # (B, 2)
        w = a - p[:2]  # (S, 2)
        den = d[:, None, 0] * b[None, :, 1] - d[:, None, 1] * b[None, :, 0]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (w[None, :, 0] * b[None, :, 1] - w[None, :, 1] * b[None, :, 0]) / den
            u = (w[None, :, 0] * d[:, None, 1] - w[None, :, 1] * d[:, None, 0]) / den
        hit = (t > 0) & (u >= 0) & (u <= 1) & np.isfinite(t)
        out[i] = np.min(np.where(hit, t, np.inf), axis=1)
    return np.where(out <= max_m, out, np.inf)


def test_the_map_does_not_change_with_the_graphs_anchor_the_world_marginals_would_move_it(corridor) -> None:
    """GPPOL maps of the second pass over the corridor from the mapping covariances of the graph anchored at
    its first keyframe and at keyframe 60 (prior 100x looser): the same map. With the world-frame marginals
    of the two graphs instead the maps differ."""
    from datasets.types import ScanSequence
    from mapping.build import MapBuilder
    from mapping.config import MappingConfig
    from mapping.kernels import make_kernel
    from mapping.train import GPParams

    walls = []
    for d in (-1.0, 1.0):
        x0, y0, x1, y1 = -d, -d, WIDTH_M + d, HEIGHT_M + d
        walls += [[x0, y0, x1, y0], [x1, y0, x1, y1], [x1, y1, x0, y1], [x0, y1, x0, y0]]
    angles = np.radians(np.arange(-90.0, 90.5, 2.0))
    ranges = _ray_cast(corridor.truth, angles, np.array(walls), 8.0)
    n = len(ranges)
    scans = ScanSequence(list(ranges), [angles] * n, np.arange(n) * 10**8, 0.05, 8.0)
    builder = MapBuilder.from_config(MappingConfig(), "gppol")
    beams = builder.beams(scans, corridor.after, np.zeros(3), np.arange(n)[::2])
    params = GPParams(make_kernel("se", {"sigma_f": 1.0, "length_scale": 0.4}), 0.1, 2.0, 0.0)
    bounds = (-2.0, -2.0, 22.0, 2.0)

    def render(cov_world: np.ndarray) -> np.ndarray:
        return builder.gp_map(beams, params, cov_world).render(bounds, 0.2).probability

    moved = corridor.reanchored(60, PRIOR_COV * 100)
    cfg = ConsistencyConfig()
    maps = []
    for edges in (corridor.edges, moved):
        _, after = keyframe_consistency_body(
            corridor.before, corridor.after, edges, corridor.points_base, corridor.s_m, cfg
        )
        maps.append(render(se2.rotate_cov_to_world(corridor.after, after)))
    np.testing.assert_allclose(maps[0], maps[1], atol=1e-6)
    world = [
        se2.rotate_cov_to_world(corridor.after, PoseGraph.from_edges(e, corridor.after).marginals_body())
        for e in (corridor.edges, moved)
    ]
    assert np.max(np.abs(render(world[0]) - render(world[1]))) > 0.01
