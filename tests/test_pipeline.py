"""The full pipeline: run folders, exports read back, remap, interruption, errors.

One simulated ``loop`` run is shared by the module (it takes about a minute); the Intel and scans-only
runs are marked slow.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from datasets.ros.maps import read_map_bag
from mapping.exports import read_layers_npz, read_map_server
from pipeline.config import load_config
from pipeline.run import run_pipeline
from tests.conftest import REPO, data_file
from tests.layer_checks import assert_same_map

FAST_TRAINING = {"mapping": {"train": {"anneal_evaluations": 20, "lbfgs_iterations": 20}}}

SPEC_FILES = [
    "config.yaml",
    "summary.json",
    "scans.npz",
    "trajectory/odometry.tum",
    "trajectory/optimized.tum",
    "trajectory/pose_graph.g2o",
    "trajectory/covariances.npz",
    "maps/before/occupancy.pgm",
    "maps/before/occupancy.yaml",
    "maps/before/layers.npz",
    "maps/before/occupancy.png",
    "maps/before/variance.png",
    "maps/before/classified.png",
    "maps/after/occupancy.pgm",
    "maps/after/occupancy.yaml",
    "maps/after/layers.npz",
    "maps/after/occupancy.png",
    "maps/after/variance.png",
    "maps/after/classified.png",
    "maps/before_after.png",
    "maps/maps.mcap",
]


def run_cli(*args: str, timeout: float = 900) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "run.py", *args], cwd=REPO, capture_output=True, text=True, timeout=timeout
    )


def write_config(path: Path, overrides: dict) -> Path:
    path.write_text(yaml.safe_dump(overrides))
    return path


@pytest.fixture(scope="module")
def loop_bag(tmp_path_factory) -> Path:
    from datasets.simulation import simulate

    bag = tmp_path_factory.mktemp("loop") / "loop.mcap"
    simulate("loop", bag, seed=0)
    return bag


@pytest.fixture(scope="module")
def loop_run(loop_bag, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("runs") / "loop"
    cfg = write_config(out.parent / "fast.yaml", FAST_TRAINING)
    run_pipeline(loop_bag, out, load_config(cfg))  # the default mapper: GPPOL with the SLAM covariances
    return out


def check_run_folder(out: Path) -> dict:
    """Every file of SPEC section 4 is there and the exports agree with the layers."""
    for name in SPEC_FILES:
        assert (out / name).is_file(), name
    summary = json.loads((out / "summary.json").read_text())
    rasters = read_map_bag(out / "maps" / "maps.mcap")
    for which in ("before", "after"):
        layers = read_layers_npz(out / "maps" / which / "layers.npz")
        assert layers.probability.dtype == np.float32 and layers.shape == tuple(summary["map"]["shape_hw"])
        values, meta = read_map_server(out / "maps" / which / "occupancy.yaml")
        assert (out / "maps" / which / meta["image"]).is_file()
        assert values.shape == layers.shape and meta["resolution"] == layers.resolution_m
        assert meta["origin"][:2] == list(layers.origin_xy_m) and meta["mode"] == "trinary"
        np.testing.assert_array_equal(values, layers.occupancy_values())  # as map_server loads it
        for kind in ("occupancy", "variance"):
            grid = rasters[f"/{which}/{kind}"]
            assert grid.shape == layers.shape
            assert grid.resolution_m == pytest.approx(layers.resolution_m)
            assert grid.origin_xy_m == pytest.approx(layers.origin_xy_m)
        occ = rasters[f"/{which}/occupancy"].layers["value"]
        np.testing.assert_array_equal(occ, values)  # the bag's OccupancyGrid is the PGM, cell for cell
        gm = rasters[f"/{which}/grid_map"]
        assert gm.shape == layers.shape and gm.origin_xy_m == pytest.approx(layers.origin_xy_m)
        for name in ("probability", "mean", "variance"):
            np.testing.assert_array_equal(gm.layers[name], getattr(layers, name))
        # the placement uncertainty (m): where a beam observed the cell, from the world marginals
        placement = layers.placement_sigma_m
        assert placement is not None and placement.shape == layers.shape
        np.testing.assert_array_equal(gm.layers["placement_sigma"], placement)
        seen = np.isfinite(placement)
        assert 0.05 < seen.mean() < 1 and np.all(placement[seen] >= 0)
        # the summary's shares of occupied / free / unknown cells are those of the exported classification
        shares = summary["map"]["cell_shares"][which]
        for value, key in ((100, "occupied"), (0, "free"), (-1, "unknown")):
            assert shares[key] == pytest.approx(np.mean(values == value), abs=1e-12)
        assert f"cells occupied / free / unknown, {which} (%)" in summary["table"]
    unmatched = summary["table"]["scans without a scan match (placed by prediction)"]
    assert unmatched == f"{summary['slam']['odometry_fallbacks']} of {summary['counts']['scans']}"
    with np.load(out / "trajectory/covariances.npz") as z:
        n = summary["counts"]["scans"]
        for key in ("scan_before", "scan_after", "scan_relative_before", "scan_relative_after"):
            cov = z[key]
            assert cov.shape == (n, 3, 3) and np.isfinite(cov).all(), key
            np.testing.assert_allclose(cov, np.swapaxes(cov, 1, 2), atol=1e-15)
            assert np.all(np.linalg.eigvalsh(cov) >= -1e-12), key
    return summary


def test_loop_run_folder_is_complete(loop_run) -> None:
    summary = check_run_folder(loop_run)
    assert summary["counts"]["scans"] == 614 and summary["mapper"] == "gppol"
    assert 0 < summary["map"]["unseen_probability"] < 1
    assert summary["map"]["pose_covariances"] == "relative"
    with np.load(loop_run / "trajectory/covariances.npz") as z:
        # after loop closure the mapper's covariances are tied to the earlier passes: centimetres where the
        # world-frame marginals, relative to the first pose, reach decimetres along the far side of the loop
        rel, world = z["scan_relative_after"], z["scan_after"]
        sigma = np.sqrt(rel[:, 0, 0] + rel[:, 1, 1])
        assert np.median(sigma) < 0.02 and np.percentile(sigma, 95) < 0.1
        assert np.median(np.sqrt(world[:, 0, 0] + world[:, 1, 1])) > 5 * np.median(sigma)
    # the world marginals go to the placement layer instead: decimetres after loop closure, and several
    # times that on the odometry chain before it
    placement = {
        w: read_layers_npz(loop_run / "maps" / w / "layers.npz").placement_sigma_m
        for w in ("before", "after")
    }
    assert 0.05 < np.nanmedian(placement["after"]) < 0.5
    assert np.nanmedian(placement["before"]) > 2 * np.nanmedian(placement["after"])
    assert summary["counts"]["loop_closures"] >= 1
    ate = summary["metrics"]["ate_rmse_m"]
    assert ate["after"] < 0.05 and ate["after"] <= ate["before"]
    auc = summary["metrics"]["auc"]
    # the loop world's odometry chain drifts 0.4 m along its gallery: the map before loop closure is worse
    # (`run.py demo`, GPPOL, seed 0: 0.681 before, 0.883 after)
    assert 0.6 < auc["before"] < auc["after"] <= 1 and auc["after"] > 0.75, auc
    # over the cells a beam observed the maps score higher than over the whole raster (55 % of it unseen),
    # and the loop's start is seen by two passes
    by_cells = summary["metrics"]["auc_by_cells"]
    assert by_cells["cells"]["revisited"] > 0.1 * by_cells["cells"]["observed"]
    assert by_cells["cells"]["revisited"] + by_cells["cells"]["seen_once"] == by_cells["cells"]["observed"]
    for which in ("before", "after"):
        assert by_cells[which]["observed"] > auc[which]
    assert set(summary["timings_s"]) >= {
        "read",
        "slam",
        "train",
        "map_before",
        "map_after",
        "export",
        "total",
    }
    # CPU per stage: every timed stage, none negative, together within the run's total
    cpu = summary["cpu_s"]
    assert set(cpu) == set(summary["timings_s"])
    assert all(c["user"] >= 0 and c["system"] >= 0 for c in cpu.values())
    stages = [c for name, c in cpu.items() if name != "total"]
    total = cpu["total"]["user"] + cpu["total"]["system"]
    assert sum(c["user"] + c["system"] for c in stages) <= total + 0.05
    assert cpu["slam"]["user"] > 0 and cpu["total"]["user"] > cpu["slam"]["user"]
    assert not list(loop_run.parent.glob("*.partial-*"))


def test_snap_to_lattice() -> None:
    from pipeline.map_bounds import snap_to_lattice

    b = snap_to_lattice((-20.885, -8.146, 101.846, 43.92), 0.1)
    assert b[0] <= -20.885 and b[1] <= -8.146 and b[2] >= 101.846 and b[3] >= 43.92
    assert [round(v / 0.1) * 0.1 for v in b] == pytest.approx(b, abs=1e-12)
    assert b[2] - b[0] < 122.731 + 0.2 + 1e-9
    assert snap_to_lattice(b, 0.1) == pytest.approx(b, abs=1e-12)
    assert snap_to_lattice((0.0, 0.0, float("inf"), 1.0), 0.1) == (0.0, 0.0, float("inf"), 1.0)


def test_loop_maps_share_the_ground_truth_lattice(loop_bag, loop_run) -> None:
    """The maps lie on the world lattice of their resolution, as the simulated world's ground truth does, so
    the run scores the cells it rendered: its AUC is the AUC of the GP map queried at the ground truth's
    cells and stored as float32, as the layers are."""
    from datasets.simulation import ground_truth_path, load_ground_truth
    from mapping.evaluation import raster_cell_centres
    from mapping.metrics import roc_auc
    from pipeline.api import load_run

    summary = json.loads((loop_run / "summary.json").read_text())
    res = summary["map"]["resolution_m"]
    cells = np.asarray(summary["map"]["origin_xy_m"]) / res
    np.testing.assert_allclose(cells, np.round(cells), atol=1e-9)
    gt = load_ground_truth(ground_truth_path(loop_bag))
    centres = raster_cell_centres(gt.occupancy.shape, np.asarray(gt.origin_xy_m), gt.resolution_m)
    p = load_run(loop_run).query(centres).probability.astype(np.float32)
    assert summary["metrics"]["auc"]["after"] == roc_auc(p, gt.occupancy.astype(bool).ravel())


def test_remap_with_own_trajectory_reproduces_after_map(loop_run) -> None:
    result = run_cli("remap", str(loop_run), "--recompute", "--json")
    assert result.returncode == 0, result.stderr
    assert json.loads(result.stdout)["recomputed"] is True
    a = read_layers_npz(loop_run / "maps/after/layers.npz")
    b = read_layers_npz(loop_run / "remap/maps/remap/layers.npz")
    assert_same_map(a, b)
    np.testing.assert_array_equal(a.placement_sigma_m, b.placement_sigma_m)
    # without --recompute nothing changed, so nothing is recomputed
    result = run_cli("remap", str(loop_run), "--out", str(loop_run.parent / "copy"), "--json")
    assert result.returncode == 0 and json.loads(result.stdout)["recomputed"] is False


def test_remap_with_perturbed_trajectory_differs(loop_run, tmp_path) -> None:
    from slam.trajectory_io import read_tum, write_tum

    stamps, poses = read_tum(loop_run / "trajectory/optimized.tum")
    rng = np.random.default_rng(0)
    poses = poses + rng.normal(0, [0.1, 0.1, 0.02], poses.shape)
    write_tum(tmp_path / "noisy.tum", stamps, poses)
    out = tmp_path / "remap"
    result = run_cli("remap", str(loop_run), "--poses", str(tmp_path / "noisy.tum"), "--out", str(out))
    assert result.returncode == 0, result.stderr
    a = read_layers_npz(loop_run / "maps/after/layers.npz")
    b = read_layers_npz(out / "maps/remap/layers.npz")
    assert a.shape == b.shape
    assert np.mean(np.abs(a.probability - b.probability)) > 0.01


def test_remap_with_a_g2o_written_by_gtsam(loop_run, tmp_path) -> None:
    import gtsam

    graph, values = gtsam.readG2o(str(loop_run / "trajectory/pose_graph.g2o"), False)
    with np.load(loop_run / "trajectory/covariances.npz") as z:
        keyframes = len(z["indices"])
    assert values.size() == keyframes and graph.size() >= keyframes - 1  # GTSAM reads every edge
    shifted = gtsam.Values()
    for k in range(keyframes):
        p = values.atPose2(k)
        shifted.insert(k, gtsam.Pose2(p.x() + 0.5, p.y(), p.theta()))  # the whole map moved 0.5 m in x
    gtsam.writeG2o(graph, shifted, str(tmp_path / "shifted.g2o"))
    out = tmp_path / "remap"
    res = run_cli("remap", str(loop_run), "--poses", str(tmp_path / "shifted.g2o"), "--out", str(out))
    assert res.returncode == 0, res.stderr
    a = read_layers_npz(loop_run / "maps/after/layers.npz")
    b = read_layers_npz(out / "maps/remap/layers.npz")
    # 0.5 m is 5 cells: the remapped map is the run's map moved by 5 columns (GTSAM writes 6 digits)
    inner = (slice(20, -20), slice(20, -20))
    diff = np.abs(b.probability[:, 5:][inner] - a.probability[:, :-5][inner])
    assert np.median(diff) < 1e-3 and np.mean(diff > 0.1) < 0.01

    # a graph optimised by GTSAM itself (plain Gaussian factors, no robust loss) maps too, nearly the same
    graph.add(gtsam.PriorFactorPose2(0, values.atPose2(0), gtsam.noiseModel.Isotropic.Sigma(3, 1e-3)))
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, gtsam.LevenbergMarquardtParams()).optimize()
    gtsam.writeG2o(graph, result, str(tmp_path / "optimised.g2o"))
    out = tmp_path / "remap2"
    res = run_cli("remap", str(loop_run), "--poses", str(tmp_path / "optimised.g2o"), "--out", str(out))
    assert res.returncode == 0, res.stderr
    c = read_layers_npz(out / "maps/remap/layers.npz")
    assert c.shape == a.shape and np.mean(np.abs(c.probability - a.probability)) < 0.05


def test_remap_errors(loop_run, tmp_path) -> None:
    res = run_cli("remap", str(tmp_path))
    assert (
        res.returncode == 1 and res.stderr.startswith("error: ") and "not a complete run folder" in res.stderr
    )
    (tmp_path / "bad.tum").write_text("1.0 2.0\n")
    res = run_cli("remap", str(loop_run), "--poses", str(tmp_path / "bad.tum"), "--out", str(tmp_path / "o"))
    assert res.returncode == 1 and "expected 8 fields" in res.stderr and not (tmp_path / "o").exists()
    res = run_cli("remap", str(loop_run), "--bounds", "1,2,3", "--out", str(tmp_path / "o"))
    assert res.returncode == 1 and "--bounds must be" in res.stderr


def test_run_refuses_existing_folder_and_bad_config(loop_bag, loop_run, tmp_path) -> None:
    res = run_cli("run", str(loop_bag), "--out", str(loop_run), "--mapper", "gpfol")
    assert res.returncode == 1
    assert res.stderr.strip() == f"error: {loop_run}: already exists (use --overwrite to replace it)"
    bad = write_config(tmp_path / "bad.yaml", {"mapping": {"resolutoin_m": 0.2}})
    res = run_cli("run", str(loop_bag), "--out", str(tmp_path / "o"), "--config", str(bad))
    assert res.returncode == 1 and "Traceback" not in res.stderr
    assert res.stderr.strip() == f"error: {bad}: unknown configuration key 'mapping.resolutoin_m'"
    bad = write_config(tmp_path / "bad2.yaml", {"mapping": {"resolution_m": -0.1}})
    res = run_cli("run", str(loop_bag), "--out", str(tmp_path / "o"), "--config", str(bad))
    assert res.returncode == 1 and "invalid value -0.1 for 'mapping.resolution_m'" in res.stderr
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize(
    ("sig", "status", "said"), [(signal.SIGINT, 130, "interrupted"), (signal.SIGTERM, 143, "terminated")]
)
def test_interrupted_run_leaves_no_complete_folder(loop_bag, tmp_path, sig, status, said) -> None:
    """Ctrl-C and SIGTERM (a service manager, a cluster's time limit) both unwind the run: no folder left."""
    out = tmp_path / "run"
    cfg = write_config(tmp_path / "fast.yaml", FAST_TRAINING)
    proc = subprocess.Popen(
        [
            sys.executable,
            "run.py",
            "run",
            str(loop_bag),
            "--out",
            str(out),
            "--config",
            str(cfg),
            "--mapper",
            "gpfol",
        ],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        # a test session started in the background of a non-interactive shell ignores SIGINT, and so would
        # the run it starts: give the run Ctrl-C's default disposition, as a terminal would
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    deadline = time.monotonic() + 300
    while not list(tmp_path.glob("run.partial-*")) and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.05)
    assert list(tmp_path.glob("run.partial-*")), "the run never started writing"
    time.sleep(0.5)
    proc.send_signal(sig)
    _, stderr = proc.communicate(timeout=120)
    assert proc.returncode == status, stderr
    assert said in stderr and "Traceback" not in stderr
    assert not out.exists()
    assert not list(tmp_path.glob("run.partial-*"))


@pytest.mark.slow
def test_run_on_scans_only_bag(tmp_path) -> None:
    """A real bag without odometry or tf: SLAM from the scans alone, then maps."""
    out = tmp_path / "lsm"
    cfg = write_config(tmp_path / "fast.yaml", FAST_TRAINING)
    bag = data_file("lsm-demo/demo_index_fixed.bag")
    res = run_cli("run", str(bag), "--out", str(out), "--config", str(cfg), "--mapper", "gpfol", "--json")
    assert res.returncode == 0, res.stderr
    summary = check_run_folder(out)
    assert summary["counts"]["scans"] == 360
    assert summary["no_return"]["range_m"] > 0 and "range_max" in summary["no_return"]["rule"]
    after = read_layers_npz(out / "maps/after/layers.npz")
    # a real map: confidently free and confidently occupied cells both exist
    assert (after.probability < 0.35).mean() > 0.05 and (after.probability > 0.65).mean() > 0.005


@pytest.mark.slow
def test_run_on_intel(tmp_path) -> None:
    out = tmp_path / "intel"
    cfg = write_config(tmp_path / "fast.yaml", FAST_TRAINING)
    res = run_cli(
        "run",
        str(data_file("intel/intel.clf.bz2")),
        "--out",
        str(out),
        "--config",
        str(cfg),
        "--mapper",
        "gpfol",
    )
    assert res.returncode == 0, res.stderr
    summary = check_run_folder(out)
    assert summary["counts"]["scans"] == 13_631 and summary["counts"]["loop_closures"] > 50
    h, w = summary["map"]["shape_hw"]
    assert 300 < h < 700 and 300 < w < 700  # the lab is about 40 m x 40 m at 0.1 m
    assert os.path.getsize(out / "maps/after/occupancy.pgm") > h * w


def test_run_summary_reports_its_tiles(loop_run) -> None:
    summary = json.loads((loop_run / "summary.json").read_text())
    tiles = summary["tiles"]
    h, w = summary["map"]["shape_hw"]
    t = tiles["tile_cells"]
    assert tiles["count"] == -(-h // t) * -(-w // t) and tiles["engine"] == "serial"
    # in one process each map is rendered at once (no per-tile support); the tiles serve later updates
    assert tiles["rendering"] == "whole map" and tiles["support_beams_mean"] is None


def test_run_summary_reports_the_cells_solved_and_those_beyond_reach(loop_run) -> None:
    """GPPOL's SE kernel decays: each map's cells are either solved or answered with the prior beyond
    every input's reach (mapping.reach); the layers there read exactly the prior."""
    from mapping.exports import read_layers_npz
    from mapping.train import GPParams
    from pipeline.bench.big_building import render_rates

    summary = json.loads((loop_run / "summary.json").read_text())
    h, w = summary["map"]["shape_hw"]
    render = summary["map"]["render"]
    assert set(render) == {"before", "after"}
    for name, stats in render.items():
        assert stats["points"] == h * w == stats["solved"] + stats["prior"]
        assert stats["solved"] > 0 and stats["solved_s"] > 0 and stats["prior_s"] >= 0
        rates = render_rates(stats)
        assert rates["cells_solved"] == stats["solved"] and rates["solved_cells_per_s"] > 0
        layers = read_layers_npz(loop_run / "maps" / name / "layers.npz")
        prior = GPParams.from_dict(summary["params"]).prior_variance
        at_prior = np.sum(layers.variance == np.float32(prior))
        assert at_prior >= stats["prior"]


def test_build_maps_returns_the_tiled_maps_layers_in_memory_of_their_own(loop_run) -> None:
    """build_maps hands back each map's layers as its tiled map holds them, in arrays of their own (a later
    update of a tiled map leaves them as they were), and the run's layers.npz are those layers (GPPOL's
    rigid groups: the keyframes the run folder's covariances.npz names)."""
    from pipeline.api import RunView
    from pipeline.artifacts import read_mapper_covariances
    from pipeline.progress import Progress
    from pipeline.run import StageTimer, build_maps
    from slam.trajectory_io import read_tum

    view = RunView(loop_run, "after")
    trajectories = {}
    for name, tum in (("before", "odometry.tum"), ("after", "optimized.tum")):
        _, poses = read_tum(loop_run / "trajectory" / tum)
        _, cov = read_mapper_covariances(loop_run / "trajectory" / "covariances.npz", name, "relative")
        trajectories[name] = (poses, cov)
    scans = view.scans
    layers, maps, _, _ = build_maps(
        scans.scans, scans.laser_in_base_xytheta, trajectories, view.config, StageTimer(), Progress(),
        params=view.params, rigid_groups=view.rigid_groups,
    )  # fmt: skip
    for name in ("before", "after"):
        held, stored = maps[name].layers(), read_layers_npz(loop_run / "maps" / name / "layers.npz")
        for field in ("probability", "mean", "variance"):
            mine = getattr(layers[name], field)
            np.testing.assert_array_equal(mine, getattr(held, field))
            np.testing.assert_array_equal(mine, getattr(stored, field))
            assert not np.shares_memory(mine, maps[name].sink.arrays[field])
        assert layers[name].origin_xy_m == held.origin_xy_m and layers[name].resolution_m == held.resolution_m


@pytest.mark.slow
def test_remap_after_a_local_correction_recomputes_only_the_tiles_it_reaches(loop_run, tmp_path) -> None:
    """A loop-closure-like correction of part of the trajectory: the incremental remap (on a local Dask
    cluster) equals a full serial recomputation (tests/layer_checks.py) and re-renders a fraction of the
    tiles."""
    from slam.trajectory_io import read_tum, write_tum

    stamps, poses = read_tum(loop_run / "trajectory/optimized.tum")
    first, last = 200, 240  # turn this stretch by 0.02 rad about its first pose
    c, s = np.cos(0.02), np.sin(0.02)
    d = poses[first : last + 1, :2] - poses[first, :2]
    poses[first : last + 1, :2] = poses[first, :2] + d @ np.array([[c, -s], [s, c]]).T
    poses[first : last + 1, 2] += 0.02
    write_tum(tmp_path / "stretch.tum", stamps[first : last + 1], poses[first : last + 1])
    # the other lines stay as they are: reading and writing a TUM file changes the last bits of the yaws
    lines = (loop_run / "trajectory/optimized.tum").read_text().splitlines(keepends=True)
    body = [i for i, line in enumerate(lines) if not line.startswith("#")]
    stretch = (tmp_path / "stretch.tum").read_text().splitlines(keepends=True)
    new = [line for line in stretch if not line.startswith("#")]
    for i, line in zip(body[first : last + 1], new, strict=True):
        lines[i] = line
    (tmp_path / "corrected.tum").write_text("".join(lines))
    runs = {}
    for name, extra in (("incremental", ["--scheduler", "local"]), ("full", ["--recompute"])):
        res = run_cli(
            "remap", str(loop_run), "--poses", str(tmp_path / "corrected.tum"), "--out", str(tmp_path / name),
            "--json", *extra,
        )  # fmt: skip
        assert res.returncode == 0, res.stderr
        runs[name] = json.loads(res.stdout)
    inc, full = runs["incremental"]["tiles"], runs["full"]["tiles"]
    assert inc["incremental"] and inc["engine"] == "dask-local" and not full["incremental"]
    assert full["fraction_recomputed"] == 1.0
    # a 30 m laser sees much of this 120 m x 50 m world from the stretch: a fraction of the tiles
    assert 0 < inc["fraction_recomputed"] < 0.6 and inc["tiles_total"] == full["tiles_total"]
    # the beams of the mapped scans (selected by motion along the odometry) of the stretch moved
    from mapping.build import MapBuilder
    from pipeline.artifacts import ODOMETRY_TUM, SCANS_FILE, read_scans
    from pipeline.config import load_config

    laser = read_scans(loop_run / SCANS_FILE).laser_in_base_xytheta
    odometry = read_tum(loop_run / "trajectory" / ODOMETRY_TUM)[1]
    mapped = MapBuilder.from_config(load_config(loop_run / "config.yaml").mapping).select_scans(
        odometry, laser
    )
    in_stretch = int(np.count_nonzero((mapped >= first) & (mapped <= last)))
    assert 10 < in_stretch <= 41 and inc["changed_beams"] == in_stretch * 360
    a = read_layers_npz(tmp_path / "incremental/maps/remap/layers.npz")
    b = read_layers_npz(tmp_path / "full/maps/remap/layers.npz")
    assert_same_map(a, b)
    after = read_layers_npz(loop_run / "maps/after/layers.npz")
    assert not np.array_equal(a.probability, after.probability)


def test_gppols_rigid_groups_are_the_runs_keyframes_when_configured(loop_run, tmp_path) -> None:
    """``mapping.gppol.rigid_groups: keyframe``: the scans GPPOL treats as sharing one pose error are those
    of one keyframe (read back from the run's covariances.npz); a covariance file that names no keyframes of
    these scans gives none, and so does the default, ``scan`` (each scan alone, as the run mapped)."""
    from pipeline.api import RunView
    from pipeline.artifacts import read_keyframe_indices, read_rigid_groups, rigid_groups_label
    from slam.trajectory_io import TrajectoryFormatError

    view = RunView(loop_run, "after")
    assert view.config.mapping.gppol.rigid_groups == "scan" and view.rigid_groups is None
    assert view.gp_map.inputs.rigid_groups is None
    path = loop_run / "trajectory" / "covariances.npz"
    keyframes = read_keyframe_indices(path)
    n = len(view.scans.scans.stamps_ns)
    read = read_rigid_groups(path, n, "keyframe")
    groups = read.group_of_scan
    assert groups.shape == (n,) and len(keyframes) < n  # several scans per keyframe on this world
    np.testing.assert_array_equal(groups[keyframes], np.arange(len(keyframes)))
    assert np.all(np.diff(groups) >= 0) and np.all(np.diff(groups) <= 1)
    # each scan's offset from its keyframe: none for a keyframe, growing along the odometry after it
    offsets = read.offset_cov_body
    assert offsets.shape == (n, 3, 3) and np.all(offsets[keyframes] == 0)
    spread = np.trace(offsets, axis1=1, axis2=2)
    later = np.flatnonzero(np.diff(groups) == 0) + 1  # scans after their keyframe
    assert np.all(spread[later] > 0)
    no_offsets = tmp_path / "no_offsets.npz"
    with np.load(path) as z:
        np.savez(no_offsets, **{k: z[k] for k in z.files if k != "scan_keyframe_offset_body"})
    assert read_rigid_groups(no_offsets, n, "keyframe").offset_cov_body is None  # exactly rigid
    with np.load(path) as z:
        np.savez(no_offsets, **{**{k: z[k] for k in z.files}, "scan_keyframe_offset_body": offsets[:-1]})
    with pytest.raises(TrajectoryFormatError, match="scan_keyframe_offset_body"):
        read_rigid_groups(no_offsets, n, "keyframe")
    assert read_rigid_groups(path, n, "scan") is None
    other = tmp_path / "other.npz"
    np.savez(other, scan_stamps_ns=np.arange(n), scan_after=np.zeros((n, 3, 3)))
    assert read_rigid_groups(other, n, "keyframe") is None
    np.savez(other, indices=np.array([0, 5, n + 3]))
    assert read_rigid_groups(other, n, "keyframe") is None
    with pytest.raises(ValueError, match="rigid groups"):
        read_rigid_groups(path, n, "pass")
    assert rigid_groups_label("scan") == "" and "keyframes" in rigid_groups_label("keyframe")


@pytest.mark.slow
def test_a_run_with_keyframe_rigid_groups_maps_and_remaps_with_them(loop_bag, loop_run, tmp_path) -> None:
    """``mapping.gppol.rigid_groups: keyframe`` changes the run's GPPOL maps (the scans of one keyframe share
    its pose error), and ``remap`` rebuilds the same map from the run folder, with the groups the Python API
    reads back."""
    from pipeline.api import load_run
    from pipeline.artifacts import read_keyframe_indices

    out = tmp_path / "grouped"
    overrides = {
        **FAST_TRAINING,
        "mapping": {**FAST_TRAINING.get("mapping", {}), "gppol": {"rigid_groups": "keyframe"}},
    }
    run_pipeline(loop_bag, out, load_config(write_config(tmp_path / "grouped.yaml", overrides)))
    grouped = read_layers_npz(out / "maps/after/layers.npz")
    alone = read_layers_npz(loop_run / "maps/after/layers.npz")
    assert grouped.shape == alone.shape
    # the simulated poses are accurate, so the maps differ little, but they differ
    assert np.abs(grouped.probability - alone.probability).max() > 0
    view = load_run(out)
    assert view.gp_map.inputs.rigid_groups is view.rigid_groups.group_of_scan
    assert view.gp_map.inputs.group_moments is not None  # each scan's odometry from its keyframe
    keyframes = read_keyframe_indices(out / "trajectory" / "covariances.npz")
    np.testing.assert_array_equal(view.rigid_groups.group_of_scan[keyframes], np.arange(len(keyframes)))
    result = run_cli("remap", str(out), "--recompute", "--json")
    assert result.returncode == 0, result.stderr
    assert_same_map(grouped, read_layers_npz(out / "remap/maps/remap/layers.npz"))
