"""``evaluate map INPUT``: AUC of GPPOL, GPFOL and the occupancy-grid baseline (SPEC section 6).

Ground-truth protocol when ``INPUT.gt.npz`` lies beside the input (simulated worlds: every cell of the
raster scored; a world of several platforms is mapped from all their scan topics unless ``--scan-topic``
says otherwise), the hold-out protocol otherwise (blocks of 40 scans held out, of 10 in recordings under
400 scans, ``block_scans`` in the output; test points along their beams).
Maps are built from the input's reference poses; a recording without them is mapped on the optimised
trajectory of the SLAM stage, whose covariances GPPOL then uses, and the output says so (``poses``).
Every seed also splits its test points by the cells the mapped beams observed (a free segment crosses the
cell or an endpoint lies in it; cells of ``mapping.resolution_m``, the raster's own on the ground-truth
protocol): ``auc_observed_*`` / ``auc_unobserved_*`` (null where a label is missing) and
``unobserved_share``, with their means ``auc_observed`` and ``unobserved_share``; the labels of the unobserved
test points (``unobserved_occupied_test_points`` / ``unobserved_free_test_points``) and the share of them each
map classifies against their label (``wrong_unobserved_*``: confidently wrong where no beam was). The test
points and the other AUCs are those of the protocol, untouched. Each seed also reports ``log_loss_*`` (the
mean negative log-likelihood of the test labels, :func:`mapping.metrics.log_loss`): AUC ranks, the log loss
also asks whether the probabilities are honest.

Input uncertainty given to GPPOL:

- laser noise per source: on a simulated world, the noise the simulator used (the ground truth's ``sources``,
  overriding ``mapping.sources``; the output says so), otherwise ``mapping.sources`` / ``default_source``;
- pose covariance: zero for reference poses (taken as exact), for SLAM poses the covariances
  ``mapping.gppol.pose_covariances`` names (default: relative to the earlier passes over each place), and with
  ``perturb_poses = (sigma_xy_m, sigma_theta_rad)`` (``--perturb-poses``, after the Hilbert-maps reference's
  ``perturb_data``) ``diag(sigma_xy^2, sigma_xy^2, sigma_theta^2)`` for every scan. Perturbation: each scan's
  reference BASE pose gets ``(sigma_xy, sigma_xy, sigma_theta) * z``, ``z`` the (N, 3) standard-normal draw of
  ``numpy.random.default_rng(PERTURB_SEED_BASE + seed)`` (``seed`` the hold-out seed; 0 on the ground-truth
  protocol), in scan order. Every mapper (GPPOL, GPFOL, grid) maps the perturbed poses; test points come from
  the UNPERTURBED poses (the truth).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from datasets.errors import DatasetError
from datasets.types import Recording
from mapping.beams import Beams, compose_laser_poses
from mapping.build import MAPPERS, Bounds, MapBuilder
from mapping.config import MappingConfig, SourceNoiseConfig
from mapping.evaluation import (
    HIT_COUNT_EDGES,
    HIT_RADIUS_M,
    NEAREST_HIT_EDGES_M,
    RANGE_EDGES_M,
    auc_by_bins,
    hits_within,
    holdout_block_scans,
    holdout_split,
    holdout_test_points,
    is_carmen_180,
    nearest_hit_m,
    observed_points,
)
from mapping.exports import UNKNOWN_VARIANCE_FRACTION
from mapping.gppol import RigidGroups
from mapping.metrics import auc_shortfall_per_point, log_loss, roc_auc
from pipeline.artifacts import mapper_covariances, mapper_rigid_groups, rigid_groups_label
from pipeline.config import load_config
from pipeline.errors import PipelineError
from pipeline.map_bounds import parse_numbers
from pipeline.progress import Progress

DEFAULT_SEEDS = [0, 1, 2, 3, 4]
PERTURB_SEED_BASE = 1_000_000
# largest --perturb-poses: beyond 100 m the perturbed data's bounds outgrow any map's memory, and a heading
# error of sigma pi is already near uniform
MAX_PERTURB_XY_M, MAX_PERTURB_THETA_RAD = 100.0, np.pi


def make_beams(rec: Recording, base_poses: np.ndarray, indices: np.ndarray, cfg: MappingConfig) -> Beams:
    """World-frame beams of the scans ``indices`` of ``rec`` at BASE poses ``base_poses`` (N, 3) (composed
    with the recording's laser mounting)."""
    return MapBuilder.from_config(cfg).beams(rec.scans, base_poses, rec.laser_in_base_xytheta, indices)


def reference_base_poses(rec: Recording, input_path: Path) -> np.ndarray:
    """(N, 3) base poses of the scans from the recording's reference poses (PipelineError if it has none)."""
    if rec.scans is None or len(rec.scans) == 0:
        raise DatasetError(f"{input_path}: no laser scans to map")
    if rec.reference is None:
        raise PipelineError(f"{input_path}: no reference poses (ground truth or corrected log)")
    if len(rec.reference) != len(rec.scans):
        raise DatasetError(f"{input_path}: {len(rec.reference)} reference poses for {len(rec.scans)} scans")
    return np.asarray(rec.reference.poses_xytheta, dtype=np.float64)


def reference_laser_poses(rec: Recording, input_path: Path) -> np.ndarray:
    """(N, 3) laser poses from the recording's reference poses (PipelineError if it has none)."""
    return compose_laser_poses(reference_base_poses(rec, input_path), rec.laser_in_base_xytheta)


def mapping_poses(
    rec: Recording,
    input_path: Path,
    slam_config: Any = None,
    progress: Progress | None = None,
    pose_covariances: str = "relative",
    rigid_groups: str = "scan",
) -> tuple[np.ndarray, str, np.ndarray | None, RigidGroups | None]:
    """(N, 3) base poses to map with, where they come from, their (N, 3, 3) world-frame covariances and
    rigid groups: the reference poses when the recording has them (``"reference"``, taken as exact:
    None, None), else the optimised trajectory of the SLAM stage, the covariances ``pose_covariances`` names
    (``mapping.gppol.pose_covariances``, :func:`pipeline.artifacts.mapper_covariances`; ``"slam"``, SPEC
    section 6) and the rigid groups ``rigid_groups`` names (``mapping.gppol.rigid_groups``,
    :func:`pipeline.artifacts.mapper_rigid_groups`)."""
    if rec.scans is None or len(rec.scans) == 0:
        raise DatasetError(f"{input_path}: no laser scans to map")
    if rec.reference is not None:
        return reference_base_poses(rec, input_path), "reference", None, None
    from slam.system import run_slam_recording

    result = run_slam_recording(rec, slam_config, progress)
    cov = mapper_covariances(result, "after", pose_covariances)
    groups = mapper_rigid_groups(result, rigid_groups)
    return np.asarray(result.poses_after_xytheta), "slam", None if cov is None else np.asarray(cov), groups


def mapping_laser_poses(
    rec: Recording, input_path: Path, slam_config: Any = None, progress: Progress | None = None
) -> tuple[np.ndarray, str]:
    """(N, 3) laser poses of :func:`mapping_poses` and where they come from."""
    base, source, _, _ = mapping_poses(rec, input_path, slam_config, progress)
    return compose_laser_poses(base, rec.laser_in_base_xytheta), source


def perturb(
    base_poses: np.ndarray, sigma_xy_m: float, sigma_theta_rad: float, seed: int
) -> tuple[np.ndarray, np.ndarray]:
    """Poses (N, 3) with seeded Gaussian noise (module docstring), the (N, 3, 3) covariance given to GPPOL."""
    n = base_poses.shape[0]
    sigma = np.array([sigma_xy_m, sigma_xy_m, sigma_theta_rad], dtype=np.float64)
    z = np.random.default_rng(PERTURB_SEED_BASE + seed).standard_normal((n, 3))
    return base_poses + z * sigma, np.tile(np.diag(sigma**2), (n, 1, 1))


def parse_perturbation(text: str | None) -> tuple[float, float] | None:
    """``"SIGMA_XY_M,SIGMA_THETA_RAD"`` (None passes through); PipelineError if malformed."""
    if text is None:
        return None
    values = parse_numbers(text, 2)
    if values is None or not (0 <= values[0] <= MAX_PERTURB_XY_M and 0 <= values[1] <= MAX_PERTURB_THETA_RAD):
        raise PipelineError(
            f"--perturb-poses must be SIGMA_XY_M,SIGMA_THETA_RAD with 0 <= SIGMA_XY_M <= "
            f"{MAX_PERTURB_XY_M:g} and 0 <= SIGMA_THETA_RAD <= {MAX_PERTURB_THETA_RAD:.4f} (pi), got {text!r}"
        )
    return values[0], values[1]


def _auc_or_none(scores: np.ndarray, labels: np.ndarray) -> float | None:
    """ROC AUC, None unless both labels occur."""
    return roc_auc(scores, labels) if labels.any() and not labels.all() else None


def observed_split(
    beams: Beams,
    points: np.ndarray,
    resolution_m: float,
    anchor_xy_m: tuple[float, float] | np.ndarray | None = None,
) -> tuple[np.ndarray, dict[str, Any]]:
    """(P,) bool: which of the (P, 2) test points lie in a cell the mapped ``beams`` observed
    (:func:`mapping.evaluation.observed_points`: cells of ``resolution_m``, lattice corner ``anchor_xy_m``),
    and the row entries saying so: ``observed_test_points``, ``unobserved_share``, ``observed_cell_m``,
    ``observed_s``."""
    t0 = time.perf_counter()
    observed = observed_points(beams, points, resolution_m, anchor_xy_m)
    seconds = time.perf_counter() - t0
    n = int(observed.size)
    return observed, {
        "observed_test_points": int(observed.sum()),
        "unobserved_share": float(np.sum(~observed) / n) if n else None,
        "observed_cell_m": float(resolution_m),
        "observed_s": seconds,
    }


def _split_aucs(
    p: np.ndarray, labels: np.ndarray, observed: np.ndarray, name: str, cfg: MappingConfig
) -> dict[str, Any]:
    """``auc_observed_NAME`` and ``auc_unobserved_NAME``: AUC of the (P,) scores ``p`` over the test points
    in observed / unobserved cells (None where one label is missing there); ``wrong_unobserved_NAME``: the
    share of the unobserved ones the map classifies against their label (occupied at p >=
    ``cfg.occupied_threshold`` though free, free at p <= ``cfg.free_threshold`` though occupied): how often
    the map is confidently wrong where no beam was (None without unobserved points). An AUC over a handful
    of one label says little: the row's ``unobserved_occupied_test_points`` / ``unobserved_free_test_points``
    give its sample."""
    pu, lu = p[~observed], labels[~observed].astype(bool)
    wrong = np.sum(np.where(lu, pu <= cfg.free_threshold, pu >= cfg.occupied_threshold))
    return {
        f"auc_observed_{name}": _auc_or_none(p[observed], labels[observed]),
        f"auc_unobserved_{name}": _auc_or_none(pu, lu),
        f"wrong_unobserved_{name}": float(wrong / lu.size) if lu.size else None,
    }


def _map_and_score(
    beams: Beams,
    cov: np.ndarray | None,
    cfg: MappingConfig,
    points: np.ndarray,
    labels: np.ndarray,
    seed_offset: int,
    grid_bounds: Bounds | None,
    sort: bool,
    observed: np.ndarray | None = None,
    breakdown: dict[str, np.ndarray] | None = None,
    rigid_groups: RigidGroups | None = None,
    unknown_variance_fraction: float = UNKNOWN_VARIANCE_FRACTION,
) -> dict[str, Any]:
    """Train and query GPPOL and GPFOL (``cov``, ``rigid_groups``, ``unknown_variance_fraction``:
    :meth:`mapping.build.MapBuilder.from_config`, :meth:`~mapping.build.MapBuilder.gp_map`),
    build the grid, score the three; times and parameters. With
    ``observed`` (P,) bool (:func:`observed_split`), also each AUC over the test points in observed and in
    unobserved cells (:func:`_split_aucs`), after the other keys; with ``breakdown``
    (:func:`breakdown_values`), each AUC by bins of it (:func:`_binned_aucs`)."""
    row: dict[str, Any] = {}
    split: dict[str, Any] = {}
    binned: dict[str, Any] = {}
    for mapper in MAPPERS:
        builder = MapBuilder.from_config(cfg, mapper, unknown_variance_fraction)
        t0 = time.perf_counter()
        params = builder.fit(beams, cov, seed_offset, rigid_groups)
        t1 = time.perf_counter()
        gp = builder.gp_map(beams, params, cov, rigid_groups)
        p = gp.query(points, sort=sort).probability
        t2 = time.perf_counter()
        row[f"auc_{mapper}"] = roc_auc(p, labels)
        row[f"log_loss_{mapper}"] = log_loss(p, labels)
        if observed is not None:
            split.update(_split_aucs(p, labels, observed, mapper, cfg))
        if breakdown is not None:
            binned.update(_binned_aucs(p, labels, breakdown, mapper))
        row[f"{mapper}_train_s"] = t1 - t0
        row[f"{mapper}_map_and_query_s"] = t2 - t1
        row[f"{mapper}_hyperparameters"] = {"kernel": params.kernel.name, **params.kernel.as_dict()}
        # eq. (9) per training point at the learnt hyperparameters: compares kernels on one recording
        row[f"{mapper}_lml_per_point"] = params.info.get("lml_per_point")
        row[f"{mapper}_params"] = params.to_dict()  # save as JSON and set mapping.params_file to reuse
    t0 = time.perf_counter()
    p_grid = MapBuilder.from_config(cfg).grid(beams, grid_bounds).query(points)
    row["auc_grid"] = roc_auc(p_grid, labels)
    row["log_loss_grid"] = log_loss(p_grid, labels)
    row["grid_s"] = time.perf_counter() - t0
    if observed is not None:
        split.update(_split_aucs(p_grid, labels, observed, "grid", cfg))
        unobserved = labels[~observed].astype(bool)
        split["unobserved_occupied_test_points"] = int(unobserved.sum())
        split["unobserved_free_test_points"] = int(unobserved.size - unobserved.sum())
    if breakdown is not None:
        binned.update(_binned_aucs(p_grid, labels, breakdown, "grid"))
    row.update(split)
    row.update(binned)
    return row


#: The breakdowns of ``evaluate map --breakdown``: (key, bin edges) of :func:`breakdown_values`.
BREAKDOWNS = (
    ("range_m", RANGE_EDGES_M),
    ("hits_1m", HIT_COUNT_EDGES),
    ("nearest_hit_m", NEAREST_HIT_EDGES_M),
)


def breakdown_values(beams: Beams, points: np.ndarray, ranges_m: np.ndarray) -> dict[str, np.ndarray]:
    """Per (P, 2) test point what ``--breakdown`` splits the AUCs by: ``range_m`` (P,), its distance from
    its laser (``ranges_m``, from :func:`mapping.evaluation.holdout_test_points`), ``hits_1m`` (P,), the
    mapped beams' endpoints within :data:`mapping.evaluation.HIT_RADIUS_M` of it
    (:func:`mapping.evaluation.hits_within`), and ``nearest_hit_m`` (P,), its distance from the nearest
    of them (:func:`mapping.evaluation.nearest_hit_m`)."""
    hits = beams.ends_xy_m[np.asarray(beams.is_hit, dtype=bool)]
    return {
        "range_m": np.asarray(ranges_m, dtype=np.float64),
        "hits_1m": hits_within(hits, points),
        "nearest_hit_m": nearest_hit_m(hits, points),
    }


def _binned_aucs(
    p: np.ndarray, labels: np.ndarray, breakdown: dict[str, np.ndarray], name: str
) -> dict[str, Any]:
    """``by_KEY_NAME`` for each breakdown KEY: :func:`mapping.evaluation.auc_by_bins` of the scores ``p``
    (the points' shares of the AUC's shortfall ranked once for all the splits)."""
    y = np.asarray(labels, dtype=bool)
    lost = auc_shortfall_per_point(p, y) if (y.any() and not y.all()) else None
    return {
        f"by_{key}_{name}": auc_by_bins(p, y, breakdown[key], edges, shortfall=lost)
        for key, edges in BREAKDOWNS
    }


def log_loss_means(rows: list[dict[str, Any]]) -> dict[str, float | None]:
    """{gppol, gpfol, grid}: the mean over the per-seed ``rows`` of ``log_loss_*`` (None where absent)."""
    out: dict[str, float | None] = {}
    for k in ("gppol", "gpfol", "grid"):
        values = [r[f"log_loss_{k}"] for r in rows if r.get(f"log_loss_{k}") is not None]
        out[k] = float(np.mean(values)) if values else None
    return out


def observed_means(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Means over the per-seed ``rows`` of :func:`observed_split` / :func:`_split_aucs`: ``auc_observed``
    {gppol, gpfol, grid} (over the seeds where it is defined; None where it never is) and
    ``unobserved_share``."""

    def mean(key: str) -> float | None:
        values = [r[key] for r in rows if r.get(key) is not None]
        return float(np.mean(values)) if values else None

    return {
        "auc_observed": {k: mean(f"auc_observed_{k}") for k in ("gppol", "gpfol", "grid")},
        "unobserved_share": mean("unobserved_share"),
    }


def evaluate_holdout(
    rec: Recording,
    base_poses: np.ndarray,
    seeds: list[int],
    cfg: MappingConfig,
    progress: Progress,
    cov: np.ndarray | None = None,
    perturb_poses: tuple[float, float] | None = None,
    test_base_poses: np.ndarray | None = None,
    block_scans: int | None = None,
    mappable: np.ndarray | None = None,
    breakdown: bool = False,
    rigid_groups: RigidGroups | None = None,
    unknown_variance_fraction: float = UNKNOWN_VARIANCE_FRACTION,
) -> dict[str, Any]:
    """The hold-out protocol of SPEC section 6 for GPPOL, GPFOL and the grid, one entry per seed.

    ``base_poses`` (N, 3): the base poses the training scans are mapped at; ``test_base_poses`` (N, 3): the
    base poses the test points are computed from (default ``base_poses``; the reference poses when the map
    is built from our own SLAM's poses). ``cov`` (N, 3, 3): base-pose covariances for GPPOL (None: exact
    poses); ``perturb_poses``: see the module docstring (then the covariance is the perturbation's).
    ``block_scans``: scans per held-out block (default :func:`holdout_block_scans`: 40, 10 under 400
    scans). ``mappable`` (N,) bool: the scans that may be mapped (default all; e.g. those with a SLAM pose),
    the held-out ones never are. ``breakdown``: each AUC also by the test points' distance from their laser
    and by the mapped endpoints near them (:func:`breakdown_values`). ``rigid_groups``: the scans that
    share one pose error under ``cov`` (:meth:`mapping.build.MapBuilder.gp_map`; not with
    ``perturb_poses``, whose errors are drawn per scan). ``unknown_variance_fraction``: the export
    configuration's (the maps read the prior unsolved where they are unknown anyway,
    :meth:`mapping.build.MapBuilder.from_config`). Returns ``per_seed`` and ``block_scans``."""
    scans = rec.scans
    n = len(scans)
    block = block_scans if block_scans is not None else holdout_block_scans(n)
    if block is None:
        raise PipelineError(
            f"{rec.source}: {n} scans are too few for the hold-out protocol (under 100: no block fits)"
        )
    carmen = rec.format == "carmen" and all(is_carmen_180(a) for a in scans.angles_rad[: min(n, 10)])
    test_poses = base_poses if test_base_poses is None else test_base_poses
    truth_laser = compose_laser_poses(test_poses, rec.laser_in_base_xytheta)
    per_seed = []
    with progress.stage("evaluate map", total=len(seeds)) as bar:
        for seed in seeds:
            held = np.asarray(holdout_split(n, seed, block=block), dtype=np.int64)
            if held.size == 0:
                raise PipelineError(
                    f"{rec.source}: {n} scans are too few for the hold-out protocol with {block}-scan blocks"
                )
            train = np.setdiff1d(np.arange(n), held)
            if mappable is not None:
                train = train[np.asarray(mappable, dtype=bool)[train]]
            pts, labels, ranges_m = holdout_test_points(
                scans.ranges_m, scans.angles_rad, truth_laser, held.tolist(), seed, carmen, with_ranges=True
            )
            poses, seed_cov, groups = base_poses, cov, rigid_groups
            if perturb_poses is not None:
                poses, seed_cov = perturb(base_poses, *perturb_poses, seed)
                groups = None
            beams = make_beams(rec, poses, train, cfg)
            row = {
                "seed": seed,
                "held_out_scans": int(held.size),
                "training_scans": int(train.size),
                "test_points": int(labels.size),
                "occupied_test_points": int(labels.sum()),
            }
            observed, split = observed_split(beams, pts, cfg.resolution_m)
            binned = breakdown_values(beams, pts, ranges_m) if breakdown else None
            row.update(
                _map_and_score(
                    beams,
                    seed_cov,
                    cfg,
                    pts,
                    labels,
                    seed,
                    None,
                    True,
                    observed,
                    binned,
                    groups,
                    unknown_variance_fraction,
                )
            )
            row.update(split)
            per_seed.append(row)
            bar.advance()
    return {"per_seed": per_seed, "block_scans": block}


def ground_truth_noise(cfg: MappingConfig, gt: Any) -> MappingConfig:
    """``cfg`` with the laser noise of every source the simulator recorded in the ground truth."""
    if not gt.sources:
        return cfg
    sources = dict(cfg.sources)
    for s in gt.sources:
        sources[s.name] = SourceNoiseConfig(
            range_var_m2=s.range_variance_m2, bearing_var_rad2=s.bearing_variance_rad2
        )
    return cfg.model_copy(update={"sources": sources})


def evaluate_ground_truth(
    rec: Recording,
    base_poses: np.ndarray,
    gt: Any,
    gt_path: Path,
    cfg: MappingConfig,
    progress: Progress,
    cov: np.ndarray | None = None,
    perturb_poses: tuple[float, float] | None = None,
    every: int = 1,
    rigid_groups: RigidGroups | None = None,
    unknown_variance_fraction: float = UNKNOWN_VARIANCE_FRACTION,
) -> dict[str, Any]:
    """Score the cells of the ground-truth raster ``gt`` (read from ``gt_path``; SPEC section 6, simulated
    worlds; ``every`` > 1 scores every ``every``-th row and column only, for quick checks).
    Laser noise from the ground truth; ``cov``, ``rigid_groups`` and ``unknown_variance_fraction`` as
    :func:`evaluate_holdout`."""
    cfg = ground_truth_noise(cfg, gt)
    occ = np.asarray(gt.occupancy).astype(bool)
    bounds = gt.bounds_xy_m
    centres = gt.cell_centers_xy_m()[::every, ::every].reshape(-1, 2)
    labels = occ[::every, ::every].ravel()
    poses = base_poses
    if perturb_poses is not None:
        poses, cov = perturb(base_poses, *perturb_poses, 0)
        rigid_groups = None
    with progress.stage("evaluate map", total=1) as bar:
        beams = make_beams(rec, poses, np.arange(len(rec.scans)), cfg)
        row = {"seed": None, "test_points": int(labels.size), "occupied_test_points": int(labels.sum())}
        observed, split = observed_split(beams, centres, float(gt.resolution_m), gt.origin_xy_m)
        row.update(
            _map_and_score(
                beams,
                cov,
                cfg,
                centres,
                labels,
                0,
                bounds,
                False,
                observed,
                None,
                rigid_groups,
                unknown_variance_fraction,
            )
        )
        row.update(split)
        bar.advance()
    noise = {name: s.model_dump() for name, s in cfg.sources.items()}
    return {"per_seed": [row], "sensor_noise": noise, "sensor_noise_from": str(gt_path)}


def _bin_label(key: str, lo: float, hi: float) -> str:
    """A breakdown bin as a table shows it: a distance ``lo-hi m`` ([lo, hi)), a count by its integers
    (``0``, ``1-4``, ``>= 100``)."""
    if key == "range_m":
        return f"distance from the laser {lo:g}-{hi:g} m"
    if key == "nearest_hit_m":
        what = "nearest mapped endpoint"
        return f"{what} >= {lo:g} m" if not np.isfinite(hi) else f"{what} {lo:g}-{hi:g} m"
    title = f"endpoints within {HIT_RADIUS_M:g} m"
    if not np.isfinite(hi):
        return f"{title} >= {lo:g}"
    return f"{title} {lo:g}" if hi == lo + 1 else f"{title} {lo:g}-{hi - 1:g}"


#: The two labels of a test point, as the per-bin keys name them (``auc_lost_occupied``, ``auc_lost_free``).
LABELS = ("occupied", "free")


def breakdown_table(rows: list[dict[str, Any]]) -> dict[str, str]:
    """Table rows of the per-seed breakdowns (:func:`_binned_aucs`), when the rows have them: per bin, the
    AUC of gppol / gpfol / grid as a mean over the seeds where it is defined ('-' where it never is) with
    the bin's test points (summed over the seeds, occupied in brackets), and the part of the whole AUC's
    shortfall that falls on the bin's occupied and on its free points (means over the seeds)."""
    out: dict[str, str] = {}
    names = (*MAPPERS, "grid")
    for key, edges in BREAKDOWNS:
        if f"by_{key}_gppol" not in (rows[0] if rows else {}):
            continue
        for i in range(len(edges) - 1):
            aucs = " / ".join(_mean_bin(rows, f"by_{key}_{mapper}", i, "auc") for mapper in names)
            n = sum(r[f"by_{key}_gppol"][i]["test_points"] for r in rows)
            occ = sum(r[f"by_{key}_gppol"][i]["occupied"] for r in rows)
            where = _bin_label(key, edges[i], edges[i + 1])
            out[f"AUC gppol / gpfol / grid, {where}"] = f"{aucs} ({n} points, {occ} occupied)"
            lost = " / ".join(
                " + ".join(_mean_bin(rows, f"by_{key}_{mapper}", i, f"auc_lost_{label}") for label in LABELS)
                for mapper in names
            )
            out[f"AUC lost (occupied + free) gppol / gpfol / grid, {where}"] = lost
    return out


def _mean_bin(rows: list[dict[str, Any]], key: str, i: int, field: str) -> str:
    """The mean over the seeds' ``rows`` of ``row[key][i][field]`` as a table shows it ('-' if never set)."""
    values = [r[key][i].get(field) for r in rows]
    values = [v for v in values if v is not None]
    return f"{np.mean(values):.4f}" if values else "-"


def _percent(share: float | None) -> str:
    return "-" if share is None else f"{100 * share:.1f} %"


def evaluate_map(
    input_path: Path,
    seeds: list[int] | None = None,
    config_path: Path | None = None,
    progress: Progress | None = None,
    perturb_poses: tuple[float, float] | str | None = None,
    scan_topic: str | None = None,
    breakdown: bool = False,
) -> dict[str, Any]:
    """Evaluate the mappers on ``input_path``; returns the SPEC section 3 keys (``protocol``, ``seeds``,
    ``auc``: {gppol, gpfol, grid} as means over seeds) plus ``per_seed`` details, the means of
    :func:`observed_means` (``auc_observed``, ``unobserved_share``) and a ``table``. ``breakdown`` (hold-out
    protocol): each seed's AUCs also by bins of distance from the laser and of mapped endpoints nearby
    (``by_range_m_*``, ``by_hits_1m_*``), their means in the table.

    ``perturb_poses``: ``(sigma_xy_m, sigma_theta_rad)`` or its text form (module docstring)."""
    from datasets.registry import open_dataset
    from datasets.simulation import load_ground_truth

    progress = progress or Progress()
    if perturb_poses is not None and not isinstance(perturb_poses, str):
        perturb_poses = ",".join(repr(float(v)) for v in perturb_poses)  # (one check for both forms)
    perturb_poses = parse_perturbation(perturb_poses)
    input_path = Path(input_path)
    gt_path = Path(str(input_path) + ".gt.npz")
    gt = load_ground_truth(gt_path) if gt_path.is_file() else None
    if scan_topic is None and gt is not None and len(gt.sources or ()) > 1:
        scan_topic = "all"  # a simulated world of several platforms is scored on all their scans
    config = load_config(config_path, {"input": {"scan_topic": scan_topic}})
    cfg = config.mapping
    rec = open_dataset(input_path, config.input)
    MapBuilder.from_config(cfg).check_sources(rec.scans.sources, str(input_path))
    base_poses, pose_source, cov, groups = mapping_poses(
        rec, input_path, config.slam, progress, cfg.gppol.pose_covariances, cfg.gppol.rigid_groups
    )
    if gt is not None:
        protocol = "ground_truth"
        used_seeds: list[int] = []
        out = evaluate_ground_truth(
            rec,
            base_poses,
            gt,
            gt_path,
            cfg,
            progress,
            cov,
            perturb_poses,
            rigid_groups=groups,
            unknown_variance_fraction=config.export.unknown_variance_fraction,
        )
    else:
        protocol = "holdout"
        used_seeds = list(seeds) if seeds else list(DEFAULT_SEEDS)
        out = evaluate_holdout(
            rec,
            base_poses,
            used_seeds,
            cfg,
            progress,
            cov,
            perturb_poses,
            breakdown=breakdown,
            rigid_groups=groups,
            unknown_variance_fraction=config.export.unknown_variance_fraction,
        )
    rows = out["per_seed"]
    auc = {k: float(np.mean([r[f"auc_{k}"] for r in rows])) for k in ("gppol", "gpfol", "grid")}
    if perturb_poses is not None:
        pose_cov = f"diag({perturb_poses[0]}^2, {perturb_poses[0]}^2, {perturb_poses[1]}^2) (perturbed poses)"
    elif cov is not None:
        pose_cov = (
            f"SLAM {cfg.gppol.pose_covariances} covariances{rigid_groups_label(cfg.gppol.rigid_groups)}"
        )
    else:
        pose_cov = "none (exact reference poses)"
    table: dict[str, Any] = {
        "protocol": protocol,
        "seeds": ",".join(map(str, used_seeds)) or "-",
        "poses": "the input's reference poses" if pose_source == "reference" else "SLAM (no reference)",
        "perturbation": "-" if perturb_poses is None else f"{perturb_poses[0]} m, {perturb_poses[1]} rad",
        "GPPOL pose covariance": pose_cov,
        "GPPOL laser noise": "simulator's (ground truth)" if "sensor_noise_from" in out else "configuration",
    }
    if "block_scans" in out:
        table["held-out block (scans)"] = out["block_scans"]
    table.update({f"AUC {k}": v for k, v in auc.items()})
    for r in rows:
        tag = "" if r["seed"] is None else f" seed {r['seed']}"
        table[f"AUC gppol / gpfol / grid{tag}"] = (
            f"{r['auc_gppol']:.4f} / {r['auc_gpfol']:.4f} / {r['auc_grid']:.4f}"
        )
    seen = observed_means(rows)
    table["AUC observed cells gppol / gpfol / grid"] = " / ".join(
        "-" if v is None else f"{v:.4f}" for v in seen["auc_observed"].values()
    )
    table["test points in unobserved cells"] = _percent(seen["unobserved_share"])
    table.update(breakdown_table(rows))
    if breakdown and protocol != "holdout":
        table["AUC by distance / endpoints nearby"] = "- (hold-out protocol only)"
    result = {
        "protocol": protocol,
        "seeds": used_seeds,
        "auc": auc,
        "input": str(input_path),
        "poses": pose_source,
        "perturb_poses": None if perturb_poses is None else list(perturb_poses),
        "gppol_pose_covariance": pose_cov,
        "log_loss": log_loss_means(rows),
        **seen,
        "per_seed": rows,
        "table": table,
    }
    if "block_scans" in out:
        result["block_scans"] = out["block_scans"]
    if "sensor_noise" in out:
        result["sensor_noise"] = out["sensor_noise"]
        result["sensor_noise_from"] = out["sensor_noise_from"]
    return result
