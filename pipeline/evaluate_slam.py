"""``evaluate slam INPUT (--relations FILE | --reference LOG)``: the SLAM metrics of SPEC section 6.

Runs the SLAM stage on INPUT (its scans, its per-scan wheel odometry and laser mounting) and scores the
trajectories before and after loop closure:

- ``--reference LOG``: a recording whose ``reference`` poses are the (pseudo) ground truth -- a
  GMapping-corrected CARMEN log (``*.gfs.log``, ``*-corrected.log*``) or a simulated bag with ground truth
  (the input itself may be given), or a KITTI folder with its poses file (give the same folder: its own
  poses, moved to the Velodyne frame by the reader, are the reference; SLAM runs on its clouds). Scans are
  matched by content within the logger-stamp window, else by content and line order, for two CARMEN logs
  (:func:`datasets.keyframe_match.match_keyframe_scans`), else by scan stamp; reference scans matched
  nowhere are left out, and ``reference["scan_matching"]`` counts the scans of each way. ATE RMSE (m)
  after SE(2) alignment, the relations error between consecutive reference scans, and the NEES of the
  covariances.
- ``--relations FILE``: Kuemmerle et al. relations ``t1 t2 x y z roll pitch yaw``; the estimated poses at
  ``t1`` / ``t2`` are those of the scans with these stamps (the scan stamps, or the CARMEN logger stamps when
  they fit more relations), within ``STAMP_TOLERANCE_NS``.

Against a reference, poses are compared in the laser frame (the base poses composed with each recording's
laser mounting), the frame of corrected CARMEN logs. Against relations they are compared in the robot's base
frame: the benchmark's relations are between poses of the robot (Kuemmerle et al. 2009 compute everything
"based on the corrected trajectory of the robot"), and on the logs whose laser sits off the base they fit the
base poses, not the laser's (docs/evaluation.md). The returned dict has the SPEC keys ``relations`` and
``ate_rmse_m`` (null when their input is absent) plus ``table`` (what the CLI prints) and details.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from datasets.errors import DatasetError
from datasets.registry import open_dataset
from datasets.types import Recording
from pipeline.config import load_config
from pipeline.errors import PipelineError
from pipeline.progress import Progress
from slam import geometry as se2
from slam import metrics
from slam.config import SlamConfig
from slam.odometry import scan_points_at
from slam.result import SlamResult
from slam.system import run_slam_recording, wheel_poses_of

STAMP_TOLERANCE_NS = 50_000_000  # 50 ms: a relation stamp farther from every scan stamp is not matched


def evaluate_slam(
    input_path: str | Path,
    relations_path: str | Path | None = None,
    reference_path: str | Path | None = None,
    config_path: str | Path | None = None,
    progress: Progress | None = None,
    inject_false_closures: float | None = None,
    seed: int = 0,
) -> dict[str, Any]:
    """Run SLAM on ``input_path`` and score it against a relations file or a reference recording.

    ``inject_false_closures``: fault injection, that share of the accepted closures' count added as wrong
    closures before the final optimisation (:mod:`slam.faults`, seeded with ``seed``);
    ``slam.fault_injection`` in the result says how many the back end kept."""
    from datasets.relations import read_relations
    from slam.faults import FalseClosures

    faults = None
    if inject_false_closures is not None:
        try:
            faults = FalseClosures(float(inject_false_closures), int(seed))
        except ValueError as exc:
            raise PipelineError(f"--inject-false-closures: {exc}") from None

    progress = progress or Progress()
    config = load_config(config_path)
    rec = open_dataset(input_path, config.input)
    if rec.scans is None or len(rec.scans) == 0:
        raise PipelineError(f"{input_path}: no laser scans to run SLAM on")
    # read every input before the (long) SLAM run, so that bad input fails at once
    relations = read_relations(relations_path) if relations_path is not None else None
    ref = None
    if reference_path is not None:
        same = Path(reference_path).resolve() == Path(rec.source).resolve()
        ref = rec if same else open_dataset(reference_path, config.input)
        scans, rows, scan_matching = match_reference_counted(rec, ref)
    else:
        scans = rows = None
    if relations is not None:
        rel_match = match_relations(rec, relations, relations_path)
    if faults is not None and rec.clouds is not None and len(rec.clouds) > 0:
        raise PipelineError(f"{input_path}: false-closure injection needs planar scans, not 3D clouds")
    out, result = slam_and_score(rec, ref, scans, rows, reference_path, config.slam, progress, faults)
    if ref is not None:
        out["reference"]["scan_matching"] = scan_matching
    if relations is not None:
        out["relations"] = score_relations(
            result, relations, rel_match, wheel_poses_of(rec), scan_points_of(rec, config.slam)
        )
    out["table"] = _table(out)
    return out


def slam_and_score(
    rec: Recording,
    ref: Recording | None,
    scans: np.ndarray | None,
    rows: np.ndarray | None,
    reference_path: str | Path | None,
    slam_config: Any = None,
    progress: Progress | None = None,
    faults: Any = None,
) -> tuple[dict[str, Any], SlamResult]:
    """Run the SLAM stage on ``rec`` and score it against ``ref`` (None: no reference) on the ``scans`` of
    ``rec`` matched to the ``rows`` of ``ref.reference`` (:func:`match_reference`).

    Returns the dict of :func:`evaluate_slam` without ``table`` (``relations`` null, ``ate_rmse_m`` null
    without a reference; ``slam``: counts, timings, ``wall_s`` and ``realtime_factor``) and the result."""
    t0 = time.perf_counter()
    result = run_slam_recording(rec, slam_config, progress, faults)
    wall_s = time.perf_counter() - t0
    out: dict[str, Any] = {"relations": None, "ate_rmse_m": None}
    if ref is not None:
        out.update(score_reference(rec, ref, scans, rows, result, reference_path))
    out["slam"] = result.summary()
    out["slam"]["wall_s"] = wall_s
    out["slam"]["realtime_factor"] = _duration_s(rec) / wall_s if wall_s > 0 else None
    return out, result


def _duration_s(rec: Recording) -> float:
    s = rec.scans.stamps_ns
    return float(s[-1] - s[0]) / 1e9 if len(s) > 1 else 0.0


def _laser_poses(base_xytheta: np.ndarray, mount: np.ndarray) -> np.ndarray:
    return se2.compose(base_xytheta, np.asarray(mount, dtype=np.float64))


def match_reference(rec: Recording, ref: Recording) -> tuple[np.ndarray, np.ndarray]:
    """``(scan indices in rec, row indices in ref.reference)`` (M,) each, of the scans both recordings
    share (:func:`match_reference_counted` without the counts)."""
    scans, rows, _ = match_reference_counted(rec, ref)
    return scans, rows


def match_reference_counted(rec: Recording, ref: Recording) -> tuple[np.ndarray, np.ndarray, dict[str, int]]:
    """``(scan indices in rec, row indices in ref.reference, counts)``: the (M,) scans both recordings
    share and how the reference's were matched: ``{"stamp": n, "content_order": m, "unmatched": u}`` for
    two CARMEN logs (:func:`datasets.keyframe_match.match_keyframe_scans`), ``{"same_scans": n,
    "unmatched": 0}`` when the reference is the input or has its scan stamps, else ``{"scan_stamp": n,
    "unmatched": u}`` (a scan stamp within 50 ms). Unmatched reference scans are left out."""
    if ref.reference is None:
        raise PipelineError(
            f"{ref.source}: no reference poses (expected a corrected log such as *.gfs.log or "
            "*-corrected.log*, or a simulated bag with ground truth)"
        )
    same = Path(rec.source).resolve() == Path(ref.source).resolve()
    if same or (ref.scans is not None and np.array_equal(ref.reference.stamps_ns, rec.scans.stamps_ns)):
        n = len(rec.scans)
        return np.arange(n), np.arange(n), {"same_scans": n, "unmatched": 0}
    if rec.format == "carmen" and ref.format == "carmen" and "logger_stamps_ns" in ref.meta:
        from datasets.keyframe_match import match_keyframe_scans

        found = match_keyframe_scans(ref, rec)
        ok = found.matched
        if not np.any(ok):
            raise PipelineError(
                f"{ref.source}: none of its {len(ok)} scans has the ranges of a scan of {rec.source}"
            )
        return found.indices[ok], np.flatnonzero(ok), found.counts
    rows = metrics.index_at_stamps(rec.scans.stamps_ns, ref.reference.stamps_ns, STAMP_TOLERANCE_NS)
    ok = rows >= 0
    if not np.any(ok):
        raise PipelineError(f"{ref.source}: no reference pose within 50 ms of a scan of {rec.source}")
    return rows[ok], np.nonzero(ok)[0], {"scan_stamp": int(ok.sum()), "unmatched": int(np.sum(~ok))}


def score_reference(
    rec: Recording,
    ref: Recording,
    scans: np.ndarray,
    rows: np.ndarray,
    result: SlamResult,
    reference_path: str | Path,
) -> dict[str, Any]:
    """ATE before / after, relations between consecutive reference scans, NEES before / after of the
    ``scans`` of ``rec`` matched to the ``rows`` of ``ref.reference``."""
    if len(scans) < 3:
        raise PipelineError(f"{reference_path}: only {len(scans)} scans matched to {rec.source}")
    mount = rec.laser_in_base_xytheta
    truth = _laser_poses(ref.reference.poses_xytheta[rows], ref.laser_in_base_xytheta)
    before = _laser_poses(result.poses_before_xytheta[scans], mount)
    after = _laser_poses(result.poses_after_xytheta[scans], mount)
    rel_truth = se2.between(truth[:-1], truth[1:])
    rel_after = metrics.relation_errors(after[:-1], after[1:], rel_truth).as_dict()
    rel_before = metrics.relation_errors(before[:-1], before[1:], rel_truth).as_dict()
    # NEES of the base poses (the covariances are the base's), reference moved to the base frame
    truth_base = se2.compose(truth, se2.inverse(mount))
    nees_b = metrics.nees(result.poses_before_xytheta[scans], result.cov_before_xytheta[scans], truth_base)
    nees_a = metrics.nees(result.poses_after_xytheta[scans], result.cov_after_xytheta[scans], truth_base)
    closures = score_loop_closures(result, scans, truth_base)
    # the reference's own noise: consecutive reference poses against our odometry over the same short step
    ref_sigma = metrics.reference_noise_sigma(truth_base, result.poses_before_xytheta[scans])
    ref_cov = np.diag([ref_sigma[0] ** 2, ref_sigma[0] ** 2, ref_sigma[1] ** 2])
    cov_ar = result.cov_after_xytheta[scans] + ref_cov
    nees_ar = metrics.nees(result.poses_after_xytheta[scans], cov_ar, truth_base)
    return {
        "ate_rmse_m": {"before": metrics.ate_rmse(before, truth), "after": metrics.ate_rmse(after, truth)},
        "reference": {
            "path": str(reference_path),
            "matched_scans": len(scans),
            "relations_consecutive": {"before": rel_before, "after": rel_after},
            "nees_mean": {"before": float(np.mean(nees_b[1:])), "after": float(np.mean(nees_a[1:]))},
            "nees_median": {"before": float(np.median(nees_b[1:])), "after": float(np.median(nees_a[1:]))},
            "loop_closures": closures,
            "reference_noise_sigma": {"xy_m": ref_sigma[0], "theta_deg": float(np.degrees(ref_sigma[1]))},
            "nees_mean_with_reference_noise": {"after": float(np.mean(nees_ar[1:]))},
        },
    }


def score_loop_closures(
    result: SlamResult, scans: np.ndarray, truth_base: np.ndarray, min_separation_m: float | None = None
) -> dict[str, Any]:
    """Precision and recall of the accepted loop closures (:func:`slam.metrics.loop_closure_scores`).

    The reference pose of a keyframe is that of the nearest matched scan (``scans``, with base poses
    ``truth_base``) composed with our odometry from it to the keyframe (a corrected keyframe log holds
    a pose for one scan in fifteen of intel.clf; the odometry over a few scans is accurate)."""
    from slam.config import LoopClosureConfig

    sep = LoopClosureConfig().min_separation_m if min_separation_m is None else min_separation_m
    order = np.argsort(scans)
    sorted_scans = np.asarray(scans)[order]
    kf = result.keyframe_scans
    i = np.clip(np.searchsorted(sorted_scans, kf), 1, len(sorted_scans) - 1)
    j = np.where(np.abs(sorted_scans[i - 1] - kf) <= np.abs(sorted_scans[i] - kf), i - 1, i)
    nearest_scan = sorted_scans[j]
    odo = result.poses_before_xytheta
    ref_kf = se2.compose(truth_base[order][j], se2.between(odo[nearest_scan], odo[kf]))
    steps = np.hypot(*np.diff(odo[:, :2], axis=0).T) if len(odo) > 1 else np.zeros(0)
    path = np.concatenate([[0.0], np.cumsum(steps)])[kf]
    lc = result.loop_closures
    return metrics.loop_closure_scores(
        ref_kf,
        path,
        np.array([c.query_keyframe for c in lc], dtype=np.int64),
        np.array([c.target_keyframe for c in lc], dtype=np.int64),
        np.array([c.relative_xytheta for c in lc]).reshape(-1, 3),
        sep,
    )


def match_relations(rec: Recording, relations: Any, relations_path: str | Path) -> tuple:
    """``(stamps used, ok mask, scan index of t1, scan index of t2)`` of each relation: the scan stamps, or
    the CARMEN logger stamps when these fit more relations; DatasetError when none fits."""
    candidates = [("scan", rec.scans.stamps_ns)]
    logger = rec.meta.get("logger_stamps_ns") if isinstance(rec.meta, dict) else None
    if logger is not None and len(logger) == len(rec.scans):
        candidates.append(("logger", np.asarray(logger, dtype=np.int64)))
    best = None
    for name, stamps in candidates:
        order = np.argsort(stamps, kind="stable")
        i1 = metrics.index_at_stamps(stamps[order], relations.stamps1_ns, STAMP_TOLERANCE_NS)
        i2 = metrics.index_at_stamps(stamps[order], relations.stamps2_ns, STAMP_TOLERANCE_NS)
        ok = (i1 >= 0) & (i2 >= 0)
        if best is None or ok.sum() > best[1].sum():
            best = (name, ok, np.where(ok, order[i1], -1), np.where(ok, order[i2], -1))
    if not np.any(best[1]):
        raise DatasetError(
            f"{relations_path}: none of its {len(relations)} relations has both stamps within 50 ms of a "
            f"scan of {rec.source}"
        )
    return best


def score_relations(
    result: SlamResult,
    relations: Any,
    matched: tuple,
    wheel_xytheta: np.ndarray | None = None,
    scan_points: Callable[[int], np.ndarray] | None = None,
) -> dict[str, Any]:
    """The relations metric (SPEC keys) of the trajectory after loop closure, plus ``before`` and counts.

    The relations are of the robot's base poses (module docstring), so the base poses are scored as they are.
    ``local`` and ``revisit`` split the relations after loop closure by the travel between their scans
    (:data:`slam.metrics.LOCAL_TRAVEL_M`): the front end's share of the error and the loop closures'.
    ``wheels_local``, with the (N, 3) wheel poses at the scans ``wheel_xytheta``: the wheel odometry alone
    on the local relations, what scan matching has to beat. ``closures``: the accepted loop closures that a
    relation joins, judged by it (:func:`slam.metrics.closures_against_relations`): the benchmark's truth,
    where a corrected log's poses may err by degrees; with ``scan_points`` (:func:`scan_points_of`) each
    wrong one also says whether its scans overlap more at its pose than at the relation's (``disputed``).
    """
    name, ok, i1, i2 = matched
    a, b = i1[ok], i2[ok]
    target = np.column_stack([relations.xyz_m[ok, :2], relations.rpy_rad[ok, 2]])
    out: dict[str, Any] = {}
    for which, base in (("after", result.poses_after_xytheta), ("before", result.poses_before_xytheta)):
        errs = metrics.relation_errors(base[a], base[b], target).as_dict()
        if which == "after":
            out.update(errs)
        else:
            out["before"] = errs
    travel_m = se2.path_length_m(result.poses_before_xytheta[:, :2])
    local = np.abs(travel_m[b] - travel_m[a]) <= metrics.LOCAL_TRAVEL_M
    after = result.poses_after_xytheta
    for key, mask in (("local", local), ("revisit", ~local)):
        out[key] = metrics.relation_errors(after[a[mask]], after[b[mask]], target[mask]).as_dict()
    out["wheels_local"] = None
    if wheel_xytheta is not None:
        w = np.asarray(wheel_xytheta, dtype=np.float64)
        out["wheels_local"] = metrics.relation_errors(w[a[local]], w[b[local]], target[local]).as_dict()
    lc = result.loop_closures
    out["closures"] = metrics.closures_against_relations(
        result.keyframe_scans,
        result.poses_before_xytheta,
        np.array([c.query_keyframe for c in lc], dtype=np.int64),
        np.array([c.target_keyframe for c in lc], dtype=np.int64),
        np.array([c.relative_xytheta for c in lc]).reshape(-1, 3),
        (a, b),
        target,
        scan_points=scan_points,
    )
    out["unmatched"] = int(np.sum(~ok))
    out["matched_by"] = name
    return out


def scan_points_of(rec: Recording, slam_config: SlamConfig) -> Callable[[int], np.ndarray]:
    """Scan index -> its (P, 2) base-frame end points, as SLAM registers them (the odometry's range
    limits), computed on demand: the relations' arbiter needs a few scans, not all."""
    scans, cfg = rec.scans, slam_config.odometry
    mount = np.asarray(rec.laser_in_base_xytheta, dtype=np.float64)

    def points(i: int) -> np.ndarray:
        return scan_points_at(scans, i, mount, cfg)

    return points


def judged_closures_text(judged: dict[str, Any] | None) -> str:
    """``correct / judged`` of the loop closures a relation judges (:func:`score_relations`), with the
    wrong one furthest beyond the tolerance and how many wrong ones the scans dispute; ``-`` when none is
    judged (or a JSON from before the judgement)."""
    if not judged or not judged.get("judged"):
        return "-"

    def beyond(w: dict[str, float]) -> float:  # how many tolerances off
        return max(w["error_m"] / metrics.CLOSURE_TOLERANCE_M, w["error_deg"] / metrics.CLOSURE_TOLERANCE_DEG)

    counts = f"{judged['correct']} / {judged['judged']}"
    worst = max(judged["wrong"], key=beyond, default=None)
    if worst is None:
        return counts
    note = f"worst {worst['error_m']:.2f} m / {worst['error_deg']:.1f} deg"
    if judged.get("disputed") is not None:
        note += f"; the scans dispute {judged['disputed']} of {len(judged['wrong'])}"
    return f"{counts} ({note})"


def _table(out: dict[str, Any]) -> dict[str, Any]:
    rows: dict[str, Any] = {}
    ate = out.get("ate_rmse_m")
    if ate:
        rows["ATE RMSE before loop closure (m)"] = ate["before"]
        rows["ATE RMSE after loop closure (m)"] = ate["after"]
    ref = out.get("reference")
    if ref:
        rows["reference scans matched"] = ref["matched_scans"]
        if "scan_matching" in ref:
            rows["reference scans matched by"] = ", ".join(
                f"{k} {v}" for k, v in ref["scan_matching"].items()
            )
        rows["NEES mean after (3 if consistent)"] = ref["nees_mean"]["after"]
        lc = ref.get("loop_closures")
        if lc and lc["precision"] is not None:
            recall = "-" if lc["recall"] is None else f"{lc['recall']:.3f}"
            rows["loop closures precision / recall"] = f"{lc['precision']:.3f} / {recall}"
    rel = out.get("relations")
    if rel:
        rows["relations"] = rel["count"]
        rows["relations translation mean / std (m)"] = f"{rel['trans_mean_m']:.4f} / {rel['trans_std_m']:.4f}"
        rows["relations rotation mean / std (deg)"] = f"{rel['rot_mean_deg']:.3f} / {rel['rot_std_deg']:.3f}"
        for key, label in (
            ("local", f"relations local (<= {metrics.LOCAL_TRAVEL_M:g} m of travel apart): count, m / deg"),
            ("revisit", "relations across passes: count, m / deg"),
            ("wheels_local", "wheel odometry alone, local relations: m / deg"),
        ):
            part = rel.get(key)
            if part and part["count"]:
                count = "" if key == "wheels_local" else f"{part['count']}, "
                rows[label] = f"{count}{part['trans_mean_m']:.4f} / {part['rot_mean_deg']:.3f}"
        if (rel.get("closures") or {}).get("judged"):
            rows["loop closures a relation judges: correct / judged"] = judged_closures_text(rel["closures"])
    s = out["slam"]
    rows["scans / keyframes"] = f"{s['scans']} / {s['keyframes']}"
    closures = f"{s['loop_closures_accepted']} / {s['loop_closures_rejected']}"
    rows["loop closures accepted / rejected"] = closures
    rows["loop closures dropped by the back end"] = s.get("loop_closures_dropped_by_back_end", 0)
    fi = s.get("fault_injection")
    if fi:
        rows["injected false closures: kept / injected"] = f"{fi['kept']} / {fi['injected']}"
    rows["SLAM wall time (s)"] = s["wall_s"]
    return rows
