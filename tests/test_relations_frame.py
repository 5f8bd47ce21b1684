"""The benchmark's relations are scored on the robot's base poses, not the laser's (SPEC section 6)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from datasets.registry import open_dataset
from datasets.relations import Relations, read_relations
from pipeline.evaluate_slam import judged_closures_text, match_reference, match_relations, score_relations
from slam import geometry as se2
from slam import metrics
from tests.conftest import data_file


def _turning_base_trajectory(n: int = 40) -> np.ndarray:
    """(n, 3) base poses of a robot driving and turning 0.2 rad per step."""
    poses = np.zeros((n, 3))
    for i in range(1, n):
        poses[i] = se2.compose(poses[i - 1], np.array([0.3, 0.0, 0.2]))
    return poses


def _relations(poses_xytheta: np.ndarray, stamps_ns: np.ndarray, a: np.ndarray, b: np.ndarray) -> Relations:
    rel = se2.between(poses_xytheta[a], poses_xytheta[b])
    return Relations(
        stamps_ns[a],
        stamps_ns[b],
        np.column_stack([rel[:, :2], np.zeros(len(a))]),
        np.column_stack([np.zeros((len(a), 2)), rel[:, 2]]),
    )


def test_relations_of_the_base_score_zero_with_a_mounting_off_the_base() -> None:
    base = _turning_base_trajectory()
    mount = np.array([0.22, 0.0, 0.0])  # fr-clinic's laser, 0.22 m ahead of the base
    stamps = np.arange(len(base), dtype=np.int64) * 1_000_000_000
    rec = SimpleNamespace(laser_in_base_xytheta=mount, scans=SimpleNamespace(stamps_ns=stamps), meta={})
    result = SimpleNamespace(
        poses_after_xytheta=base, poses_before_xytheta=base, keyframe_scans=np.zeros(1, int), loop_closures=()
    )
    a = np.arange(0, len(base) - 5, 3)
    b = a + 5
    of_base = _relations(base, stamps, a, b)
    out = score_relations(result, of_base, match_relations(rec, of_base, "base.relations"))
    assert out["count"] == len(a) and out["trans_mean_m"] < 1e-9 and out["rot_mean_deg"] < 1e-9
    # the same motion described by the laser's poses differs by the mounting turned through each relation
    of_laser = _relations(se2.compose(base, mount), stamps, a, b)
    out = score_relations(result, of_laser, match_relations(rec, of_laser, "laser.relations"))
    assert out["trans_mean_m"] > 0.1 and out["rot_mean_deg"] < 1e-9


def test_relations_split_into_local_and_revisits_with_the_wheels_alone_on_the_local_ones() -> None:
    """Relations a few metres of travel apart score the front end, those across passes the loop closures;
    the wheel odometry alone is scored on the local ones. The loop closures a relation joins are judged by
    it: one right, one 0.5 m off; one that no relation reaches is not judged."""
    base = _turning_base_trajectory(200)  # 0.3 m per step: 60 m of travel
    stamps = np.arange(len(base), dtype=np.int64) * 1_000_000_000
    rec = SimpleNamespace(laser_in_base_xytheta=np.zeros(3), scans=SimpleNamespace(stamps_ns=stamps), meta={})
    after = base.copy()
    after[150:] = se2.compose(after[150:], np.array([0.5, 0.0, 0.0]))  # a jump 45 m of travel in
    keyframes = np.arange(0, len(base), 10)

    def closure(q: int, t: int, off) -> SimpleNamespace:  # keyframe q seen from keyframe t, plus an error
        rel = se2.between(base[10 * t], base[10 * q]) + off
        return SimpleNamespace(query_keyframe=q, target_keyframe=t, relative_xytheta=rel)

    closures = (closure(16, 0, 0.0), closure(19, 3, [0.5, 0.0, 0.0]), closure(12, 5, 0.0))
    result = SimpleNamespace(
        poses_after_xytheta=after, poses_before_xytheta=base, keyframe_scans=keyframes, loop_closures=closures
    )
    a = np.array([0, 10, 20, 140, 0, 30, 100])
    b = np.array([5, 15, 30, 145, 160, 190, 180])  # local: 1.5, 1.5, 3, 1.5 m; 3 revisits across the jump
    relations = _relations(base, stamps, a, b)
    wheels = base + np.array([0.0, 0.1, 0.0])  # off by a constant: no error on relative poses
    wheels[12] += np.array([0.2, 0.0, 0.0])  # one wheel pose 0.2 m off: the relation 10 -> 15 is not
    out = score_relations(result, relations, match_relations(rec, relations, "r.relations"), wheels)
    assert out["count"] == 7
    assert out["local"]["count"] == 4 and out["local"]["trans_mean_m"] < 1e-9
    assert out["revisit"]["count"] == 3 and out["revisit"]["trans_mean_m"] > 0.1
    assert out["wheels_local"]["count"] == 4 and out["wheels_local"]["trans_mean_m"] < 1e-9
    judged = out["closures"]  # 0 -> 160 and 30 -> 190 join keyframes 0 / 16 and 3 / 19; none reaches 5 / 12
    assert judged["judged"] == 2 and judged["correct"] == 1
    assert [(w["query_keyframe"], round(w["error_m"], 9)) for w in judged["wrong"]] == [(19, 0.5)]
    assert judged["disputed"] is None and judged_closures_text(judged) == "1 / 2 (worst 0.50 m / 0.0 deg)"
    # scattered landmarks seen from every pose: the scans side with the (exact) relation, not the closure
    world = np.random.default_rng(0).uniform(-80.0, 80.0, (4000, 2))
    scans = score_relations(
        result,
        relations,
        match_relations(rec, relations, "r.relations"),
        wheels,
        lambda i: se2.transform_points(se2.inverse(base[i]), world),
    )["closures"]
    assert scans["disputed"] == 0 and scans["wrong"][0]["overlap_at_relation"] == 1.0
    assert judged_closures_text(scans) == "1 / 2 (worst 0.50 m / 0.0 deg; the scans dispute 0 of 1)"
    wheels[15] += np.array([0.2, 0.0, 0.0])  # now the relation 10 -> 15 is off by 0.2 m
    out = score_relations(result, relations, match_relations(rec, relations, "r.relations"), wheels)
    assert abs(out["wheels_local"]["trans_mean_m"] - 0.2 / 4) < 1e-9
    without_wheels = score_relations(result, relations, match_relations(rec, relations, "r.relations"))
    assert without_wheels["wheels_local"] is None


def test_fr079_relations_fit_gmappings_trajectory_in_the_base_frame() -> None:
    """Independent of our SLAM: GMapping's corrected fr079 poses (the laser's; the raw log mounts it 0.04 m
    behind the base) agree with the benchmark's relations better once moved to the base."""
    raw = open_dataset(data_file("fr079/fr079.clf.bz2"))
    ref = open_dataset(data_file("fr079/freiburg-079-corrected.log.gz"))
    relations = read_relations(data_file("fr079/fr079.relations"))
    _, ok, i1, i2 = match_relations(raw, relations, "fr079.relations")
    scans, rows = match_reference(raw, ref)
    row_of = np.full(len(raw.scans), -1)
    row_of[scans] = rows
    r1, r2 = row_of[np.maximum(i1, 0)], row_of[np.maximum(i2, 0)]
    ok &= (r1 >= 0) & (r2 >= 0)
    assert ok.sum() > 1600
    target = np.column_stack([relations.xyz_m[ok, :2], relations.rpy_rad[ok, 2]])
    laser = ref.reference.poses_xytheta
    base = se2.compose(laser, se2.inverse(raw.laser_in_base_xytheta))
    err_laser = metrics.relation_errors(laser[r1[ok]], laser[r2[ok]], target).as_dict()["trans_mean_m"]
    err_base = metrics.relation_errors(base[r1[ok]], base[r2[ok]], target).as_dict()["trans_mean_m"]
    assert raw.laser_in_base_xytheta[0] < -0.03
    assert err_base < 0.85 * err_laser
