"""``evaluate suite [--data DIR] [--only NAME ...]``: every recording of a data folder through SLAM and the
map protocols of ``docs/evaluation.md`` (SPEC section 6), one row per recording; ``--markdown FILE`` writes
the results page (:func:`pipeline.results_markdown.suite_markdown`).

Discovery (:func:`discover`): the recordings in ``DIR``, its sub-folders and theirs (CARMEN logs, ROS1 bags,
ROS2 bags -- folders with ``metadata.yaml``, ``.mcap``, ``.db3`` -- and KITTI folders of ``*.bin`` frames).
In one folder a raw CARMEN log and a corrected one (:func:`datasets.carmen.is_corrected_log`) are a pair when
they are the folder's only raw and corrected logs or share a name (``intel.clf`` / ``intel.gfs.log``): SLAM
runs on the raw log and the corrected log is the reference. Any other recording is its own reference when
it has reference poses (a corrected log, a simulated bag with ground truth, KITTI with its poses file), and
has none otherwise (SLAM only). Then the simulated ``loop`` world, seeds 0, 1, 2 (:data:`SIMULATED_SEEDS`),
each written to a temporary folder, read back and scored against its ground truth.

Names: a sub-folder holding one recording (or one pair) gives it its name (``intel``, ``fr079``,
``fr-clinic``); otherwise the file name without its format suffixes and corrected marker (``seattle`` for
``seattle-corrected.log.gz``); names that would repeat are prefixed with their folder; ``loop-SEED``.

Per recording (:func:`run_entry`):

- SLAM on the input, scored against the reference (:func:`pipeline.evaluate_slam.slam_and_score`: ATE
  before / after loop closure, relations between consecutive reference scans, NEES), with the loop closures,
  the wall time, the real-time factor (null where the reader re-stamped most scans: synthetic stamps say
  nothing of the recording's duration) and the loop-search time with its share of the SLAM wall time.
  Where the benchmark's relations lie beside the recording (``NAME.relations``, :func:`relations_beside`),
  also their errors (``slam.relations``, as ``evaluate slam --relations``).
- Maps, where the reference has at least 100 scans: the hold-out protocol on the reference poses (exactly
  ``evaluate map``) and on our own SLAM's poses after loop closure (SPEC section 6, "Maps from our own
  SLAM", :func:`evaluate_slam_poses`), and once more with the test points from our poses as well
  (``slam_poses_own_test_points``: the protocol the reference-pose map is scored by, applied to our
  trajectory, so that neither trajectory is taken as the truth); blocks of 40 scans or of 10 under 400
  scans (``block_scans``); each with its split by the cells the mapped beams observed (``auc_observed``,
  ``unobserved_share`` and per seed, :func:`pipeline.evaluate_map.observed_split`).
  Simulated worlds with a ground-truth raster (``INPUT.gt.npz``): the ground-truth protocol on the true
  poses and on ours.

A recording whose reading, SLAM or maps raise is a row with its error (``Type: first line``) and the suite
goes on (only ``Exception``: an interrupt stops it); a recording with no laser scans is skipped, with the
reason. The stages never print; progress goes through :class:`pipeline.progress.Progress`, one bar per
recording.
"""

from __future__ import annotations

import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from datasets.carmen import is_corrected_log
from datasets.config import InputConfig
from datasets.errors import TopicError, UnknownFormatError
from datasets.paths import SHARED_DATA_DIR
from datasets.registry import guess_format, open_dataset
from datasets.types import Recording
from mapping.config import MappingConfig
from mapping.evaluation import HOLDOUT_BLOCK, holdout_block_scans
from mapping.exports import UNKNOWN_VARIANCE_FRACTION
from mapping.gppol import RigidGroups
from pipeline.artifacts import mapper_covariances, mapper_rigid_groups, rigid_groups_label
from pipeline.config import Config, load_config
from pipeline.errors import PipelineError
from pipeline.evaluate_map import (
    DEFAULT_SEEDS,
    evaluate_ground_truth,
    evaluate_holdout,
    log_loss_means,
    observed_means,
    reference_base_poses,
)
from pipeline.evaluate_slam import (
    match_reference_counted,
    match_relations,
    scan_points_of,
    score_relations,
    slam_and_score,
)
from pipeline.progress import Progress, StageBar
from pipeline.provenance import provenance
from slam import geometry as se2
from slam.metrics import align_se2
from slam.system import wheel_poses_of

FloatArray = NDArray[np.float64]

DEFAULT_DATA_DIR = SHARED_DATA_DIR
MAX_DEPTH = 2  # DIR, its sub-folders and theirs
SIMULATED_WORLD = "loop"
SIMULATED_SEEDS = (0, 1, 2)
SYNTHETIC_STAMPS_FRACTION = 0.5  # more scans re-stamped than this: the log's stamps are synthetic
SCAN_MSGTYPES = ("sensor_msgs/msg/LaserScan", "sensor_msgs/msg/PointCloud2")
_FORMAT_SUFFIXES = (".gz", ".bz2", ".clf", ".log", ".bag", ".mcap", ".db3")
_CORRECTED_MARKERS = (".gfs", "-corrected", "_corrected", ".corrected")


@dataclass(frozen=True)
class SuiteEntry:
    """One recording of the suite. ``reference_path`` None: the input's own reference poses, if it has any;
    ``simulated_seed``: the simulated ``loop`` world of that seed (``input_path`` None until simulated)."""

    name: str
    input_path: Path | None
    reference_path: Path | None = None
    simulated_seed: int | None = None
    relations_path: Path | None = None


class _Skipped(Exception):
    """The recording holds nothing the suite can run (e.g. no laser scans); the message says why."""


# --------------------------------------------------------------------------------------------- discovery


def _recording_format(path: Path) -> str | None:
    """The format of a path that looks like a recording (by its name, or a folder's content), else None."""
    if path.name.startswith("."):
        return None
    if path.is_dir():
        if (path / "metadata.yaml").is_file():
            return "ros2"
        if any(path.glob("*.bin")):
            return "kitti"
        return None
    try:
        fmt = guess_format(path)
    except UnknownFormatError:
        return None
    return None if fmt == "kitti" else fmt  # a lone .bin frame is part of a KITTI folder, not a recording


def recording_name(path: Path) -> str:
    """A recording's file name without its format suffixes and corrected marker (``seattle`` for
    ``seattle-corrected.log.gz``, ``intel`` for ``intel.gfs.log``)."""
    name = path.name
    stripped = True
    while stripped:
        stripped = False
        for suffix in _FORMAT_SUFFIXES:
            if name.lower().endswith(suffix) and len(name) > len(suffix):
                name, stripped = name[: -len(suffix)], True
    for marker in _CORRECTED_MARKERS:
        if name.lower().endswith(marker) and len(name) > len(marker):
            return name[: -len(marker)]
    return name


def _collect(folder: Path, depth: int, groups: list[tuple[Path, list[Path]]]) -> None:
    """Append ``(folder, recordings)`` of ``folder`` and of its sub-folders down to :data:`MAX_DEPTH`."""
    found: list[Path] = []
    subfolders: list[Path] = []
    for path in sorted(folder.iterdir()):
        fmt = _recording_format(path)
        if fmt is not None:
            found.append(path)
        elif path.is_dir() and not path.name.startswith(".") and depth < MAX_DEPTH:
            subfolders.append(path)
    if found:
        groups.append((folder, found))
    for sub in subfolders:
        _collect(sub, depth + 1, groups)


def _pair_carmen(paths: list[Path]) -> list[tuple[Path, Path | None]]:
    """``(input, reference or None)`` of a folder's recordings: a raw CARMEN log paired with its corrected
    twin (the folder's only raw and corrected logs, or the two of the same :func:`recording_name`)."""
    carmen = [p for p in paths if not p.is_dir() and guess_format(p) == "carmen"]
    raw = [p for p in carmen if not is_corrected_log(p)]
    corrected = [p for p in carmen if is_corrected_log(p)]
    pairs: dict[Path, Path] = {}
    if len(raw) == 1 and len(corrected) == 1:
        pairs[raw[0]] = corrected[0]
    else:
        names = [recording_name(c) for c in corrected]
        by_name = {n: c for n, c in zip(names, corrected, strict=True) if names.count(n) == 1}
        for r in raw:
            if recording_name(r) in by_name:
                pairs[r] = by_name.pop(recording_name(r))
    twins = set(pairs.values())
    return [(p, pairs.get(p)) for p in paths if p not in twins]


def discover(data_dir: str | Path) -> list[SuiteEntry]:
    """The recordings of ``data_dir`` (module docstring), in path order; PipelineError if it is not a
    folder or holds none."""
    data_dir = Path(data_dir)
    if not data_dir.is_dir():
        raise PipelineError(f"{data_dir}: no such data folder")
    groups: list[tuple[Path, list[Path]]] = []
    if _recording_format(data_dir) is not None:
        groups.append((data_dir.parent, [data_dir]))
    else:
        _collect(data_dir, 0, groups)
    found: list[tuple[Path, Path, Path | None, str]] = []  # folder, input, reference, name
    for folder, paths in groups:
        items = _pair_carmen(paths)
        own_name = folder != data_dir and len(items) == 1
        for path, ref in items:
            found.append((folder, path, ref, folder.name if own_name else recording_name(path)))
    names = [f[3] for f in found]
    entries = []
    for folder, path, ref, name in found:
        if names.count(name) > 1:
            rel = folder.relative_to(data_dir) if folder.is_relative_to(data_dir) else Path(folder.name)
            name = str(rel / recording_name(path)) if str(rel) != "." else recording_name(path)
        entries.append(SuiteEntry(name, path, ref, relations_path=relations_beside(path, name)))
    return entries


def relations_beside(path: Path, name: str) -> Path | None:
    """The benchmark relations file of a recording (Kuemmerle et al. 2009): ``NAME.relations`` beside it,
    named as the suite's row or as the recording (``intel/intel.relations``, ``fr-clinic/fr-clinic.relations``
    for ``fr-clinic/fr-clinic_robotlaser.clf.bz2``), else None."""
    for stem in dict.fromkeys((Path(name).name, recording_name(path))):
        candidate = path.parent / f"{stem}.relations"
        if candidate.is_file():
            return candidate
    return None


def simulated_entries(seeds: tuple[int, ...] = SIMULATED_SEEDS) -> list[SuiteEntry]:
    """The simulated ``loop`` world of each seed (``loop-SEED``), simulated when run."""
    return [SuiteEntry(f"{SIMULATED_WORLD}-{s}", None, None, s) for s in seeds]


# ------------------------------------------------------------------------------------ maps from our SLAM


def _offset_jacobian(poses_xytheta: FloatArray, offset_xytheta: FloatArray) -> FloatArray:
    """(N, 3, 3) Jacobian of ``pose (+) offset`` with respect to the world-frame (x, y, theta) of ``pose``."""
    theta = poses_xytheta[:, 2]
    c, s = np.cos(theta), np.sin(theta)
    ox, oy = float(offset_xytheta[0]), float(offset_xytheta[1])
    j = np.tile(np.eye(3), (len(theta), 1, 1))
    j[:, 0, 2] = -s * ox - c * oy
    j[:, 1, 2] = c * ox - s * oy
    return j


def slam_poses_on_reference(
    ref: Recording,
    rows: NDArray[np.int64],
    slam_base_xytheta: FloatArray,
    slam_cov_xytheta: FloatArray | None,
    slam_laser_in_base_xytheta: FloatArray,
) -> tuple[FloatArray, FloatArray | None, FloatArray, NDArray[np.bool_]]:
    """Our SLAM poses of the reference's scans, aligned to the reference poses (SE(2) least squares on the
    laser positions, :func:`slam.metrics.align_se2`).

    ``rows`` (M,): the row of ``ref.reference`` (distinct) of each of our (M, 3) base poses
    ``slam_base_xytheta``, with their (M, 3, 3) world-frame covariances (None: exact) and our recording's
    laser mounting. Returns, in the reference's scan order (N scans): the (N, 3) base poses in the
    reference's base frame (its laser mounting), their (N, 3, 3) covariances ``R S R^T`` (R the alignment's
    rotation, with the lever arms of the two mountings) or None, the alignment (3,), and the (N,) mask of
    the reference scans that have a SLAM pose (NaN poses and covariances where they have none)."""
    n = len(ref.scans)
    rows = np.asarray(rows, dtype=np.int64)
    if rows.size < 3 or len(np.unique(rows)) != rows.size or rows.min() < 0 or rows.max() >= n:
        raise PipelineError(
            f"{ref.source}: {rows.size} scans matched to SLAM scans (distinct, of its {n}, at least 3 needed)"
        )
    matched = np.zeros(n, dtype=bool)
    matched[rows] = True
    slam_mount = np.asarray(slam_laser_in_base_xytheta, dtype=np.float64)
    ref_mount = np.asarray(ref.laser_in_base_xytheta, dtype=np.float64)
    truth_laser = se2.compose(np.asarray(ref.reference.poses_xytheta, dtype=np.float64)[rows], ref_mount)
    ours = np.asarray(slam_base_xytheta, dtype=np.float64)
    our_laser = se2.compose(ours, slam_mount)
    align = align_se2(our_laser, truth_laser)
    aligned_laser = se2.compose(align, our_laser)
    to_base = se2.inverse(ref_mount)
    base = np.full((n, 3), np.nan)
    base[rows] = se2.compose(aligned_laser, to_base)
    if slam_cov_xytheta is None:
        return base, None, align, matched
    rot = se2.rot3(float(align[2]))
    j = _offset_jacobian(aligned_laser, to_base) @ rot @ _offset_jacobian(ours, slam_mount)
    cov = np.full((n, 3, 3), np.nan)
    cov[rows] = j @ np.asarray(slam_cov_xytheta, dtype=np.float64) @ np.transpose(j, (0, 2, 1))
    return base, cov, align, matched


def evaluate_slam_poses(
    ref: Recording,
    reference_path: str | Path,
    rows: NDArray[np.int64],
    slam_base_xytheta: FloatArray,
    slam_cov_xytheta: FloatArray | None,
    slam_laser_in_base_xytheta: FloatArray,
    seeds: list[int],
    cfg: MappingConfig,
    progress: Progress,
    block_scans: int | None = None,
    test_points_from: Literal["reference", "slam"] = "reference",
    slam_rigid_groups: RigidGroups | None = None,
    breakdown: bool = False,
    unknown_variance_fraction: float = UNKNOWN_VARIANCE_FRACTION,
) -> dict[str, Any]:
    """The hold-out protocol on our SLAM's poses (SPEC section 6, "Maps from our own SLAM"): the training
    scans mapped at our aligned poses (:func:`slam_poses_on_reference`; GPPOL with our rotated marginals;
    training scans without a SLAM pose left out), the test points from the REFERENCE poses of the held-out
    scans. Output of :func:`pipeline.evaluate_map.evaluate_holdout` plus ``alignment_xytheta``,
    ``unmatched_reference_scans`` and ``test_points_from``.

    ``test_points_from="slam"``: the test points from OUR poses of the held-out scans instead (a held-out
    scan without a SLAM pose keeps its reference pose): the map's agreement with scans it was not built
    from, both placed by our SLAM -- the protocol the reference-pose map is scored by, so the two compare
    the trajectories' consistency without taking either as the truth.

    ``slam_rigid_groups``: the rigid groups of our M poses (:meth:`mapping.build.MapBuilder.gp_map`;
    None: each scan alone). ``breakdown``, ``unknown_variance_fraction``: as
    :func:`pipeline.evaluate_map.evaluate_holdout`."""
    if test_points_from not in ("reference", "slam"):
        raise ValueError(f"test_points_from must be 'reference' or 'slam', got {test_points_from!r}")
    base, cov, align, matched = slam_poses_on_reference(
        ref, rows, slam_base_xytheta, slam_cov_xytheta, slam_laser_in_base_xytheta
    )
    truth = reference_base_poses(ref, Path(reference_path))
    test = truth if test_points_from == "reference" else np.where(matched[:, None], base, truth)
    groups = None
    if slam_rigid_groups is not None:
        groups = slam_rigid_groups.placed_on(len(ref.scans), rows)
    out = evaluate_holdout(
        ref,
        base,
        seeds,
        cfg,
        progress,
        cov,
        test_base_poses=test,
        block_scans=block_scans,
        mappable=matched,
        rigid_groups=groups,
        breakdown=breakdown,
        unknown_variance_fraction=unknown_variance_fraction,
    )
    out["alignment_xytheta"] = align.tolist()
    out["unmatched_reference_scans"] = int(np.sum(~matched))
    out["test_points_from"] = test_points_from
    return out


# ------------------------------------------------------------------------------------------- one entry


class _BarProgress(Progress):
    """Every stage of a sub-step advances the recording's bar (one bar per recording on a terminal)."""

    def __init__(self, bar: StageBar) -> None:
        self._bar = bar

    @contextmanager
    def stage(self, name: str, total: int | None = None) -> Iterator[StageBar]:
        yield self._bar


def _one_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return f"{type(exc).__name__}: {text.splitlines()[0]}" if text else type(exc).__name__


def _bag_topics(path: Path, cfg: InputConfig) -> dict[str, dict]:
    """``{topic: {"type": ..., "count": ...}}`` of a bag read without scans ({} if that fails too)."""
    try:
        return dict(open_dataset(path, cfg, scan_topic="none").meta.get("topics", {}))
    except Exception:
        return {}


def _read(path: Path, cfg: InputConfig) -> Recording:
    """The recording at ``path``; _Skipped when it holds no laser scans (a bag of other topics)."""
    try:
        rec = open_dataset(path, cfg)
    except TopicError:
        topics = _bag_topics(path, cfg)
        if topics and not any(t.get("type") in SCAN_MSGTYPES for t in topics.values()):
            raise _Skipped(f"no laser scans (topics: {', '.join(topics)})") from None
        raise
    if (rec.scans is None or len(rec.scans) == 0) and (rec.clouds is None or len(rec.clouds) == 0):
        raise _Skipped("no laser scans")
    return rec


def _trim_seed_rows(out: dict[str, Any]) -> list[dict[str, Any]]:
    """Per-seed rows without the full parameter dumps (the hyperparameters stay)."""
    return [{k: v for k, v in r.items() if not k.endswith("_params")} for r in out["per_seed"]]


def _map_result(out: dict[str, Any], protocol: str, seeds: list[int], poses: str, pose_cov: str) -> dict:
    """An ``evaluate map``-shaped result (SPEC section 3 keys) of a protocol's output."""
    rows = out["per_seed"]
    result: dict[str, Any] = {
        "protocol": protocol,
        "seeds": list(seeds) if protocol == "holdout" else [],
        "auc": {k: float(np.mean([r[f"auc_{k}"] for r in rows])) for k in ("gppol", "gpfol", "grid")},
        "log_loss": log_loss_means(rows),
        **observed_means(rows),
        "poses": poses,
        "gppol_pose_covariance": pose_cov,
    }
    for key in (
        "block_scans",
        "alignment_xytheta",
        "unmatched_reference_scans",
        "sensor_noise_from",
        "test_points_from",
    ):
        if key in out:
            result[key] = out[key]
    result["per_seed"] = _trim_seed_rows(out)
    return result


def _maps_skipped(reason: str) -> dict[str, Any]:
    return {
        "reference_poses": None,
        "slam_poses": None,
        "slam_poses_own_test_points": None,
        "skipped": reason,
    }


def run_entry(
    entry: SuiteEntry,
    config: Config,
    seeds: list[int],
    slam_only: bool = False,
    progress: Progress | None = None,
    breakdown: bool = False,
) -> dict[str, Any]:
    """One row of the suite (module docstring); never raises an ``Exception`` (it becomes ``error``).
    ``breakdown``: the hold-out protocols' per-seed rows also split the AUCs (``evaluate map
    --breakdown``)."""
    progress = progress or Progress()
    row: dict[str, Any] = {
        "name": entry.name,
        "input": None if entry.input_path is None else str(entry.input_path),
        "reference": None if entry.reference_path is None else str(entry.reference_path),
        "reference_kind": None,
        "error": None,
        "skipped": None,
        "notes": [],
        "slam": None,
        "maps": None,
        "timings_s": {},
    }
    if entry.simulated_seed is not None:
        row["simulated"] = {"world": SIMULATED_WORLD, "seed": entry.simulated_seed}
    steps = 2 + (0 if slam_only else 2 * (1 if entry.simulated_seed is not None else len(seeds)))
    t0 = time.perf_counter()
    with progress.stage(entry.name, total=steps) as bar:
        try:
            if entry.simulated_seed is None:
                _evaluate(
                    row,
                    entry.input_path,
                    entry.reference_path,
                    config,
                    seeds,
                    slam_only,
                    bar,
                    entry.relations_path,
                    breakdown,
                )
            else:
                from datasets.simulation import simulate

                with tempfile.TemporaryDirectory(prefix="gpom-suite-") as tmp:
                    t1 = time.perf_counter()
                    bag = Path(tmp) / f"{SIMULATED_WORLD}-seed{entry.simulated_seed}.bag"
                    simulate(SIMULATED_WORLD, bag, seed=entry.simulated_seed)
                    row["input"] = str(bag)
                    row["timings_s"]["simulate_s"] = time.perf_counter() - t1
                    _evaluate(row, bag, None, config, seeds, slam_only, bar, breakdown=breakdown)
        except _Skipped as why:
            row["skipped"] = str(why)
        except Exception as exc:  # the dataset boundary: one row with its error, the suite goes on
            row["error"] = _one_line(exc)
    row["timings_s"]["total_s"] = time.perf_counter() - t0
    return row


def _evaluate(
    row: dict[str, Any],
    input_path: Path,
    reference_path: Path | None,
    config: Config,
    seeds: list[int],
    slam_only: bool,
    bar: StageBar,
    relations_path: Path | None = None,
    breakdown: bool = False,
) -> None:
    """Fill ``row`` with the SLAM metrics (and the benchmark relations' errors where ``relations_path``
    is given) and the maps of one recording (raises on failure)."""
    from datasets.relations import read_relations
    from datasets.simulation import load_ground_truth

    timings = row["timings_s"]
    notes: list[str] = row["notes"]
    t0 = time.perf_counter()
    gt_path = Path(str(input_path) + ".gt.npz")
    gt = load_ground_truth(gt_path) if gt_path.is_file() else None
    input_cfg = config.input
    if gt is not None and len(gt.sources or ()) > 1 and input_cfg.scan_topic is None:
        input_cfg = input_cfg.model_copy(update={"scan_topic": "all"})  # as evaluate map does
    rec = _read(input_path, input_cfg)
    if reference_path is not None:
        ref = open_dataset(reference_path, input_cfg)
        row["reference_kind"] = "corrected twin"
    elif rec.reference is not None:
        ref, reference_path = rec, input_path
        row["reference"] = str(input_path)
        row["reference_kind"] = "ground truth" if gt is not None else "its own reference poses"
        notes.append("ground-truth protocol" if gt is not None else "input = reference")
    else:
        ref = None
        notes.append("no reference")
    scans = rows = None
    if ref is not None:
        scans, rows, scan_matching = match_reference_counted(rec, ref)
    relations = rel_match = None
    if relations_path is not None:
        relations = read_relations(relations_path)
        rel_match = match_relations(rec, relations, relations_path)
        row["relations"] = str(relations_path)
    timings["read_s"] = time.perf_counter() - t0
    bar.advance()

    restamped = rec.meta.get("restamped", {}).get("laser", 0) if isinstance(rec.meta, dict) else 0
    n_scans = len(rec.scans) if rec.scans is not None else 0
    synthetic = bool(n_scans) and restamped > SYNTHETIC_STAMPS_FRACTION * n_scans
    if synthetic:
        notes.append(f"no real-time factor: synthetic stamps ({restamped} of {n_scans} scans re-stamped)")

    out, result = slam_and_score(rec, ref, scans, rows, reference_path, config.slam, Progress())
    if ref is not None:
        out["reference"]["scan_matching"] = scan_matching  # as evaluate slam
    if relations is not None:
        out["relations"] = score_relations(
            result, relations, rel_match, wheel_poses_of(rec), scan_points_of(rec, config.slam)
        )
    slam = out["slam"]
    timings["slam_s"] = slam["wall_s"]
    if synthetic:
        slam["realtime_factor"] = None
        slam["realtime_factor_note"] = (
            f"synthetic stamps: the reader re-stamped {restamped} of {n_scans} scans (all equal or zero)"
        )
    loop_s = result.timings_s.get("loop_search_s")
    slam["loop_search_s"] = loop_s
    slam["loop_search_share"] = loop_s / slam["wall_s"] if loop_s is not None and slam["wall_s"] > 0 else None
    if "wheel_odometry" in slam:
        notes.append(f"wheel odometry: {slam['wheel_odometry']}")
    row["slam"] = out
    bar.advance()

    if slam_only:
        row["maps"] = _maps_skipped("--slam-only")
        return
    cfg = config.mapping
    fraction = config.export.unknown_variance_fraction
    progress = _BarProgress(bar)
    mode = cfg.gppol.pose_covariances
    slam_cov = mapper_covariances(result, "after", mode)
    shared = rigid_groups_label(cfg.gppol.rigid_groups)
    pose_cov = (
        f"SLAM {mode} covariances{shared} (aligned)" if slam_cov is not None else "none (laser noise only)"
    )
    if ref is None:
        _own_maps_only(row, rec, result, slam_cov, cfg, seeds, progress, breakdown, fraction)
        return
    truth = reference_base_poses(ref, Path(reference_path))
    ours = np.asarray(result.poses_after_xytheta)[scans]
    our_cov = None if slam_cov is None else np.asarray(slam_cov)[scans]
    slam_groups = mapper_rigid_groups(result, cfg.gppol.rigid_groups)
    our_groups = None if slam_groups is None else slam_groups.take(scans)
    maps: dict[str, Any] = {"reference_poses": None, "slam_poses": None, "slam_poses_own_test_points": None}
    row["maps"] = maps
    if gt is not None:
        t0 = time.perf_counter()
        by_ref = evaluate_ground_truth(
            ref, truth, gt, gt_path, cfg, progress, unknown_variance_fraction=fraction
        )
        maps["reference_poses"] = _map_result(by_ref, "ground_truth", [], "reference", "none (exact poses)")
        timings["maps_reference_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        base, cov, align, matched = slam_poses_on_reference(
            ref, rows, ours, our_cov, rec.laser_in_base_xytheta
        )
        if not np.all(matched):
            raise PipelineError(f"{ref.source}: {int(np.sum(~matched))} scans have no SLAM pose to map")
        groups = None if our_groups is None else our_groups.placed_on(len(ref.scans), rows)
        by_slam = evaluate_ground_truth(
            ref,
            base,
            gt,
            gt_path,
            cfg,
            progress,
            cov=cov,
            rigid_groups=groups,
            unknown_variance_fraction=fraction,
        )
        by_slam["alignment_xytheta"] = align.tolist()
        maps["slam_poses"] = _map_result(by_slam, "ground_truth", [], "slam", pose_cov)
        timings["maps_slam_s"] = time.perf_counter() - t0
        return
    n_ref = len(ref.scans)
    block = holdout_block_scans(n_ref)
    if block is None:
        maps["skipped"] = f"{n_ref} reference scans: too few for the hold-out protocol (under 100)"
        notes.append(f"no maps: {n_ref} reference scans")
        return
    if block != HOLDOUT_BLOCK:
        notes.append(f"maps: blocks of {block} scans")
    t0 = time.perf_counter()
    by_ref = evaluate_holdout(
        ref,
        truth,
        seeds,
        cfg,
        progress,
        block_scans=block,
        breakdown=breakdown,
        unknown_variance_fraction=fraction,
    )
    exact = "none (exact reference poses)"
    maps["reference_poses"] = _map_result(by_ref, "holdout", seeds, "reference", exact)
    timings["maps_reference_s"] = time.perf_counter() - t0
    protocols = (
        ("slam_poses", "maps_slam_s", "reference"),
        ("slam_poses_own_test_points", "maps_slam_own_s", "slam"),
    )
    for key, timing, test_points_from in protocols:
        t0 = time.perf_counter()
        by_slam = evaluate_slam_poses(
            ref,
            reference_path,
            rows,
            ours,
            our_cov,
            rec.laser_in_base_xytheta,
            seeds,
            cfg,
            progress,
            block,
            test_points_from,
            our_groups,
            breakdown,
            fraction,
        )
        maps[key] = _map_result(by_slam, "holdout", seeds, "slam", pose_cov)
        timings[timing] = time.perf_counter() - t0


def _own_maps_only(
    row: dict[str, Any],
    rec: Recording,
    result: Any,
    slam_cov: FloatArray | None,
    cfg: MappingConfig,
    seeds: list[int],
    progress: Progress,
    breakdown: bool = False,
    unknown_variance_fraction: float = UNKNOWN_VARIANCE_FRACTION,
) -> None:
    """The map score of a recording without any reference (SPEC section 6, "own test points"): the
    hold-out protocol with our SLAM's poses after loop closure for the training scans and the test points
    alike, where it has at least 100 scans (``unknown_variance_fraction``: as
    :func:`pipeline.evaluate_map.evaluate_holdout`)."""
    n = len(rec.scans)
    block = holdout_block_scans(n)
    maps: dict[str, Any] = {"reference_poses": None, "slam_poses": None, "slam_poses_own_test_points": None}
    row["maps"] = maps
    if block is None:
        maps["skipped"] = f"{n} scans: too few for the hold-out protocol (under 100)"
        row["notes"].append(f"no maps: {n} scans")
        return
    if block != HOLDOUT_BLOCK:
        row["notes"].append(f"maps: blocks of {block} scans")
    t0 = time.perf_counter()
    ours = np.asarray(result.poses_after_xytheta)
    cov = None if slam_cov is None else np.asarray(slam_cov)
    groups = mapper_rigid_groups(result, cfg.gppol.rigid_groups)
    by_self = evaluate_holdout(
        rec,
        ours,
        seeds,
        cfg,
        progress,
        cov,
        block_scans=block,
        rigid_groups=groups,
        breakdown=breakdown,
        unknown_variance_fraction=unknown_variance_fraction,
    )
    mode = cfg.gppol.pose_covariances
    shared = rigid_groups_label(cfg.gppol.rigid_groups)
    pose_cov = f"SLAM {mode} covariances{shared}" if cov is not None else "none (laser noise only)"
    maps["slam_poses_own_test_points"] = _map_result(by_self, "holdout", seeds, "slam", pose_cov)
    row["timings_s"]["maps_slam_own_s"] = time.perf_counter() - t0


# ------------------------------------------------------------------------------------------- the suite


def evaluate_suite(
    data_dir: str | Path | None = None,
    only: list[str] | None = None,
    seeds: list[int] | None = None,
    config_path: str | Path | None = None,
    slam_only: bool = False,
    simulated: bool = True,
    progress: Progress | None = None,
    command: str | None = None,
    breakdown: bool = False,
) -> dict[str, Any]:
    """Run every recording of ``data_dir`` (default :data:`DEFAULT_DATA_DIR`) and, with ``simulated``, the
    ``loop`` world of seeds 0-2. Returns ``datasets`` (one row per recording, SPEC section 3), ``data``,
    ``seeds``, ``slam_only``, ``wall_s``, ``provenance`` (date, commit, version, machine and the command
    line ``command`` when the suite started, :func:`pipeline.provenance.provenance`) and ``table`` (one
    dict of printable cells per row).

    ``only``: names to run (PipelineError naming the known ones when a name is unknown). ``breakdown``: the
    hold-out protocols' per-seed rows also hold ``evaluate map --breakdown``'s splits (``by_*`` keys)."""
    progress = progress or Progress()
    origin = provenance(command)
    config = load_config(config_path)
    data = Path(data_dir) if data_dir is not None else DEFAULT_DATA_DIR
    entries = discover(data) + (simulated_entries() if simulated else [])
    if only:
        known = [e.name for e in entries]
        unknown = [n for n in only if n not in known]
        if unknown:
            raise PipelineError(
                f"--only: no dataset named {', '.join(unknown)} in {data} (names: {', '.join(known)})"
            )
        entries = [e for e in entries if e.name in only]
    if not entries:
        raise PipelineError(f"{data}: no recordings found (CARMEN logs, ROS bags, KITTI folders)")
    used_seeds = list(seeds) if seeds else list(DEFAULT_SEEDS)
    t0 = time.perf_counter()
    rows = [run_entry(e, config, used_seeds, slam_only, progress, breakdown) for e in entries]
    return {
        "data": str(data),
        "seeds": used_seeds,
        "slam_only": slam_only,
        "datasets": rows,
        "wall_s": time.perf_counter() - t0,
        "provenance": origin,
        "table": [table_row(r) for r in rows],
    }


# ------------------------------------------------------------------------------------------- the table


def _pair(a: Any, b: Any, fmt: str) -> str:
    if a is None and b is None:
        return "-"
    return " / ".join("-" if v is None else format(v, fmt) for v in (a, b))


def _aucs(result: dict[str, Any] | None) -> str:
    if not result:
        return "-"
    auc = result["auc"]
    return " / ".join(f"{auc[k]:.4f}" for k in ("gppol", "gpfol", "grid"))


def _observed(result: dict[str, Any] | None) -> str:
    """GPPOL's AUC over the test points in observed cells / the share of test points in unobserved ones."""
    if not result or result.get("unobserved_share") is None:
        return "-"
    auc = result["auc_observed"]["gppol"]
    return f"{'-' if auc is None else format(auc, '.4f')} / {100 * result['unobserved_share']:.1f} %"


TABLE_LEGEND = (
    "scans: of the input (matched to the reference); ATE (m), NEES (3 if consistent): before / after loop "
    "closure; consecutive: error between consecutive reference scans after loop closure, m / deg; "
    "relations: mean error against the benchmark's relations (NAME.relations beside the log) after loop "
    "closure, m / deg; closures: accepted / rejected; x RT: real-time factor of the SLAM stage; loop "
    "search: its time and share of the SLAM time; AUC (mean over the seeds): GPPOL / GPFOL / grid, maps on "
    "the reference poses and on ours (test points from the reference poses), and on ours with the test "
    "points from our poses too; observed: maps on the reference poses, GPPOL's AUC over the test points in "
    "cells the mapped beams observed / the share of test points in cells they did not"
)


def table_row(row: dict[str, Any]) -> dict[str, str]:
    """The printable cells of one suite row (column name -> text; ``-`` where there is nothing; the columns
    are explained by :data:`TABLE_LEGEND`)."""
    out = row.get("slam") or {}
    s = out.get("slam")
    ref = out.get("reference")
    ate = out.get("ate_rmse_m")
    rel = ref["relations_consecutive"]["after"] if ref else None
    nees = ref["nees_mean"] if ref else None
    cells: dict[str, str] = {"dataset": row["name"]}
    cells["scans"] = "-" if s is None else f"{s['scans']}" + (f" ({ref['matched_scans']})" if ref else "")
    cells["ATE m"] = _pair(ate["before"], ate["after"], ".3f") if ate else "-"
    cells["consecutive"] = "-" if rel is None else _pair(rel["trans_mean_m"], rel["rot_mean_deg"], ".3f")
    cells["NEES"] = _pair(nees["before"], nees["after"], ".3g") if nees else "-"
    bench = out.get("relations")
    cells["relations m / deg"] = (
        "-" if not bench else _pair(bench["trans_mean_m"], bench["rot_mean_deg"], ".4f")
    )
    cells["closures"] = "-" if s is None else f"{s['loop_closures_accepted']} / {s['loop_closures_rejected']}"
    cells["SLAM s"] = "-" if s is None else f"{s['wall_s']:.1f}"
    rtf = None if s is None else s.get("realtime_factor")
    cells["x RT"] = "-" if rtf is None else f"{rtf:.0f}" if rtf >= 10 else f"{rtf:.2g}"
    loop_s = None if s is None else s.get("loop_search_s")
    share = 0.0 if s is None else s.get("loop_search_share") or 0.0
    cells["loop search s"] = "-" if loop_s is None else f"{loop_s:.1f} ({100 * share:.0f} %)"
    maps = row.get("maps") or {}
    cells["AUC ref. poses"] = _aucs(maps.get("reference_poses"))
    cells["AUC SLAM poses"] = _aucs(maps.get("slam_poses"))
    cells["AUC SLAM poses, own test points"] = _aucs(maps.get("slam_poses_own_test_points"))
    cells["AUC observed GPPOL / unobserved"] = _observed(maps.get("reference_poses"))
    notes = list(row.get("notes") or [])
    if row.get("skipped"):
        notes.insert(0, f"skipped: {row['skipped']}")
    if row.get("error"):
        notes.insert(0, f"error: {row['error']}")
    cells["notes"] = "; ".join(notes)
    return cells
