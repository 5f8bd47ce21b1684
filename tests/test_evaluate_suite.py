"""``python run.py evaluate suite``: discovery of a data folder, a failing recording as a row, the JSON of a
small real run, the 10-scan blocks of short recordings, and the map built from SLAM poses."""

from __future__ import annotations

import json
import math
import random
import re
import subprocess
import sys

import numpy as np
import pytest

from datasets.registry import open_dataset
from mapping.config import MappingConfig
from mapping.evaluation import holdout_block_scans, holdout_split
from pipeline.errors import PipelineError
from pipeline.evaluate_map import evaluate_holdout, reference_base_poses
from pipeline.evaluate_suite import (
    discover,
    evaluate_slam_poses,
    evaluate_suite,
    relations_beside,
    slam_poses_on_reference,
    table_row,
)
from pipeline.progress import Progress
from slam import geometry as se2
from tests.conftest import REPO, data_file

FAST = {"train": {"anneal_evaluations": 40, "lbfgs_iterations": 40, "problems": 48}}


def run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "run.py", *args], cwd=REPO, capture_output=True, text=True, timeout=600
    )


@pytest.fixture(scope="module")
def data_folder(tmp_path_factory):
    """A data folder of symlinks to real files (never copies) plus a broken log, a non-recording file, and a
    log three levels down (too deep to be found)."""
    root = tmp_path_factory.mktemp("data")
    links = {
        "intel/intel.clf.bz2": "intel/intel.clf.bz2",
        "intel/intel.gfs.log": "intel/intel.gfs.log",
        "intel/intel.relations": "intel/intel.relations",
        "radish/seattle-corrected.log.gz": "radish-corrected/seattle-corrected.log.gz",
        "radish/orebro-corrected.log.gz": "radish-corrected/orebro-corrected.log.gz",
        "radish/belgioioso-corrected.log.gz": "radish-corrected/belgioioso-corrected.log.gz",
        "jackal/test2.bag": "jackal/test2.bag",
    }
    for rel, target in links.items():
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).symlink_to(data_file(target))
    (root / "broken").mkdir()
    (root / "broken" / "broken.clf").write_text("FLASER 3 1.0 2.0\n")  # truncated record
    (root / "README.md").write_text("not a recording\n")
    deep = root / "a" / "b" / "c"
    deep.mkdir(parents=True)
    (deep / "deep.clf").symlink_to(data_file("radish-corrected/orebro-corrected.log.gz"))
    return root


def test_discovery_pairs_twins_names_folders_and_stops_two_levels_down(data_folder) -> None:
    entries = {e.name: e for e in discover(data_folder)}
    assert set(entries) == {"intel", "seattle", "orebro", "belgioioso", "jackal", "broken"}
    intel = entries["intel"]
    assert intel.input_path.name == "intel.clf.bz2" and intel.reference_path.name == "intel.gfs.log"
    assert intel.relations_path.name == "intel.relations"  # the benchmark's relations beside the log
    assert entries["seattle"].relations_path is None
    # a corrected log without a raw twin is its own reference (decided when read)
    assert entries["seattle"].reference_path is None
    assert entries["seattle"].input_path.name == "seattle-corrected.log.gz"


def test_suite_json_rows_error_skip_and_synthetic_stamps(data_folder) -> None:
    """A small real run through the CLI: seattle and belgioioso (SLAM only), a broken log (a row with its
    error), a bag without scans (skipped); exit status 0 and nothing but JSON on stdout."""
    done = run_cli(
        "evaluate", "suite", "--data", str(data_folder), "--only", "seattle", "broken", "jackal",
        "belgioioso", "--slam-only", "--json",
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    out = json.loads(done.stdout)
    rows = {r["name"]: r for r in out["datasets"]}
    assert list(rows) == ["broken", "jackal", "belgioioso", "seattle"]  # path order, no simulated world

    seattle = rows["seattle"]
    assert set(seattle) >= {"name", "error", "slam", "maps", "input", "reference"}
    assert seattle["error"] is None and seattle["skipped"] is None
    assert seattle["input"] == seattle["reference"] == str(data_folder / "radish/seattle-corrected.log.gz")
    slam = seattle["slam"]
    assert set(slam) >= {"relations", "ate_rmse_m"}
    assert math.isfinite(slam["ate_rmse_m"]["before"]) and math.isfinite(slam["ate_rmse_m"]["after"])
    assert slam["reference"]["matched_scans"] == 241
    assert slam["reference"]["relations_consecutive"]["after"]["count"] == 240
    s = slam["slam"]
    assert s["scans"] == 241 and s["loop_closures_accepted"] >= 0
    assert s["realtime_factor"] > 1  # 1,165 s of data
    assert 0 <= s["loop_search_share"] <= 1 and s["loop_search_s"] >= 0
    assert seattle["maps"] == {
        "reference_poses": None,
        "slam_poses": None,
        "slam_poses_own_test_points": None,
        "skipped": "--slam-only",
    }

    # belgioioso's stamps are synthetic (all equal): no real-time factor, and the row says why
    assert any("synthetic stamps" in n for n in rows["belgioioso"]["notes"])
    belgioioso = rows["belgioioso"]["slam"]["slam"]
    assert belgioioso["realtime_factor"] is None and "synthetic stamps" in belgioioso["realtime_factor_note"]

    broken = rows["broken"]
    assert broken["slam"] is None and broken["skipped"] is None
    assert broken["error"].startswith("CarmenError: ") and "broken.clf" in broken["error"]
    assert "\n" not in broken["error"]

    jackal = rows["jackal"]
    assert jackal["error"] is None and jackal["skipped"].startswith("no laser scans")


def test_relations_found_by_row_or_recording_name_and_shown_in_the_table(tmp_path) -> None:
    clinic = tmp_path / "fr-clinic"
    clinic.mkdir()
    log = clinic / "fr-clinic_robotlaser.clf"
    log.write_text("")
    assert relations_beside(log, "fr-clinic") is None
    (clinic / "fr-clinic.relations").write_text("")
    assert relations_beside(log, "fr-clinic") == clinic / "fr-clinic.relations"
    (clinic / "fr-clinic.relations").unlink()
    (clinic / "fr-clinic_robotlaser.relations").write_text("")
    assert relations_beside(log, "fr-clinic") == clinic / "fr-clinic_robotlaser.relations"
    bench = {"count": 10, "trans_mean_m": 0.01994, "rot_mean_deg": 0.4019}
    row = {"name": "intel", "slam": {"relations": bench, "slam": None}, "maps": None}
    assert table_row(row)["relations m / deg"] == "0.0199 / 0.4019"
    assert table_row({"name": "x", "slam": None, "maps": None})["relations m / deg"] == "-"


def test_suite_table_and_unknown_name(data_folder) -> None:
    done = run_cli("-q", "evaluate", "suite", "--data", str(data_folder), "--only", "broken", "--slam-only")
    assert done.returncode == 0, done.stderr
    # the notes cell wraps within the table's width: read it with the cell borders and line breaks removed
    text = re.sub(r"[\s│]+", " ", done.stdout)
    assert "broken" in text and "error: CarmenError" in text
    done = run_cli("evaluate", "suite", "--data", str(data_folder), "--only", "nowhere", "--no-simulated")
    assert done.returncode == 1
    assert done.stderr.startswith("error: --only: no dataset named nowhere") and "seattle" in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1


def test_holdout_blocks_of_10_for_short_recordings() -> None:
    """Under 400 scans the split is the SPEC's rule with blocks of 10 (and stays 40 from 400 on)."""
    assert holdout_block_scans(400) == 40 and holdout_block_scans(4791) == 40
    assert holdout_block_scans(399) == 10 and holdout_block_scans(100) == 10
    assert holdout_block_scans(99) is None
    for n, seed in [(241, 0), (241, 3), (399, 1), (237, 4)]:
        rng = random.Random(seed)
        blocks = int(n * 0.1 / 10)
        held: list[int] = []
        while len(held) < blocks * 10:
            start = rng.randint(0, n - 10)
            if start in held or start + 10 in held:
                continue
            held.extend(range(start, start + 10))
        split = holdout_split(n, seed, block=10)
        assert split == sorted(held) and len(split) == blocks * 10
        runs = np.split(np.asarray(split), np.flatnonzero(np.diff(split) != 1) + 1)
        assert all(len(r) % 10 == 0 for r in runs)
    assert holdout_split(910, 2) == holdout_split(910, 2, block=40)  # the default is unchanged


def test_slam_poses_are_aligned_and_covariances_rotated() -> None:
    """Our poses = the reference moved rigidly: aligned back exactly, covariance R S R^T."""
    path = data_file("radish-corrected/seattle-corrected.log.gz")
    ref = open_dataset(path)
    truth = reference_base_poses(ref, path)
    move = np.array([3.0, -2.0, 0.7])
    ours = se2.compose(move, truth)
    cov = np.tile(np.diag([0.04, 0.01, 0.001]), (len(truth), 1, 1))
    base, rotated, align, matched = slam_poses_on_reference(
        ref, np.arange(len(truth)), ours, cov, np.zeros(3)
    )
    assert matched.all()
    np.testing.assert_allclose(se2.compose(align, move), 0.0, atol=1e-9)
    np.testing.assert_allclose(se2.between(truth, base), 0.0, atol=1e-9)
    r = se2.rot3(-0.7)
    np.testing.assert_allclose(rotated, r @ cov @ r.T, atol=1e-12)
    # reference scans without a SLAM pose: NaN there, flagged in the mask
    rows = np.arange(5, len(truth))
    base, rotated, _, matched = slam_poses_on_reference(ref, rows, ours[rows], cov[rows], np.zeros(3))
    assert matched.sum() == len(truth) - 5 and not matched[:5].any()
    assert np.isnan(base[:5]).all() and np.isfinite(base[5:]).all() and np.isfinite(rotated[5:]).all()
    with pytest.raises(PipelineError, match="distinct"):
        slam_poses_on_reference(ref, np.zeros(4, dtype=np.int64), ours[:4], cov[:4], np.zeros(3))


def test_map_from_slam_poses_equals_the_reference_map_when_they_are_the_reference() -> None:
    """With the reference poses as 'our SLAM poses' (as given; and moved rigidly, with no SLAM pose for the
    held-out scans: the alignment undoes the move, the test points come from the reference poses), the
    SLAM-pose map path scores the same test points as the reference-pose path, and the same AUCs."""
    path = data_file("radish-corrected/seattle-corrected.log.gz")
    ref = open_dataset(path)
    truth = reference_base_poses(ref, path)
    mount = ref.laser_in_base_xytheta
    cfg = MappingConfig(**FAST)
    expected = evaluate_holdout(ref, truth, [1], cfg, Progress())
    assert expected["block_scans"] == 10 and expected["per_seed"][0]["held_out_scans"] == 20
    all_rows = np.arange(len(truth))
    moved = se2.compose(np.array([-5.0, 8.0, 2.0]), truth)
    not_held = np.setdiff1d(all_rows, holdout_split(len(truth), 1, block=10))
    for rows, ours in ((all_rows, truth), (not_held, moved[not_held])):
        got = evaluate_slam_poses(ref, path, rows, ours, None, mount, [1], cfg, Progress())
        assert got["unmatched_reference_scans"] == len(truth) - len(rows)
        a, b = expected["per_seed"][0], got["per_seed"][0]
        assert a["test_points"] == b["test_points"] and a["occupied_test_points"] == b["occupied_test_points"]
        assert a["training_scans"] == b["training_scans"] == len(truth) - 20
        for mapper in ("gppol", "gpfol", "grid"):
            assert b[f"auc_{mapper}"] == pytest.approx(a[f"auc_{mapper}"], abs=1e-6), mapper
    # a training scan without a SLAM pose is left out of the map (and only of it)
    rows = np.setdiff1d(all_rows, not_held[:3])
    got = evaluate_slam_poses(ref, path, rows, truth[rows], None, mount, [1], cfg, Progress())
    assert got["per_seed"][0]["training_scans"] == len(truth) - 23
    assert got["per_seed"][0]["test_points"] == expected["per_seed"][0]["test_points"]


def test_own_test_points_come_from_the_slam_poses() -> None:
    """The map is built from the training scans only, so moving the held-out scans' SLAM poses changes the
    map only through the alignment (a hair): scored on the reference's test points it stays the
    reference-pose map, scored on test points from those moved poses it loses AUC; with unmoved poses the
    own-test-point protocol gives the reference-pose map's AUC exactly."""
    path = data_file("radish-corrected/seattle-corrected.log.gz")
    ref = open_dataset(path)
    truth = reference_base_poses(ref, path)
    mount = ref.laser_in_base_xytheta
    cfg = MappingConfig(**FAST)
    rows = np.arange(len(truth))
    held = holdout_split(len(truth), 1, block=10)
    moved = truth.copy()
    moved[held] = se2.compose(moved[held], np.array([0.15, -0.1, 0.03]))
    on_ref = evaluate_slam_poses(ref, path, rows, moved, None, mount, [1], cfg, Progress())
    own = evaluate_slam_poses(ref, path, rows, moved, None, mount, [1], cfg, Progress(), None, "slam")
    same = evaluate_slam_poses(ref, path, rows, truth, None, mount, [1], cfg, Progress(), None, "slam")
    expected = evaluate_holdout(ref, truth, [1], cfg, Progress())["per_seed"][0]
    assert own["test_points_from"] == "slam" and on_ref["test_points_from"] == "reference"
    for mapper in ("gppol", "gpfol"):
        key = f"auc_{mapper}"
        # the alignment moves everything by a hair (20 of 241 poses moved), so not bit for bit
        assert on_ref["per_seed"][0][key] == pytest.approx(expected[key], abs=2e-3), mapper
        assert same["per_seed"][0][key] == pytest.approx(expected[key], abs=1e-6), mapper
        assert own["per_seed"][0][key] < expected[key] - 0.01, mapper
    with pytest.raises(ValueError, match="test_points_from"):
        evaluate_slam_poses(ref, path, rows, truth, None, mount, [1], cfg, Progress(), None, "truth")


def test_rigid_groups_follow_our_scans_onto_the_reference_rows() -> None:
    """Each reference row takes the rigid group (and the offset from it) of our scan matched to it; a row
    no scan of ours matches is a group of its own, apart from every group of ours, and exactly rigid."""
    from mapping.gppol import RigidGroups

    rows = np.array([0, 2, 3, 5])
    offsets = np.arange(1, 5)[:, None, None] * np.eye(3)
    placed = RigidGroups(np.array([0, 0, 1, 1]), offsets).placed_on(7, rows)
    got = placed.group_of_scan
    np.testing.assert_array_equal(got[rows], [0, 0, 1, 1])
    alone = np.delete(got, rows)
    assert len(np.unique(alone)) == 3 and not np.isin(alone, [0, 1]).any()
    np.testing.assert_array_equal(placed.offset_cov_body[rows], offsets)
    assert not np.delete(placed.offset_cov_body, rows, axis=0).any()
    assert RigidGroups(np.array([0, 0, 1, 1])).placed_on(7, rows).offset_cov_body is None


def test_breakdown_splits_every_holdout_protocols_seed_rows(data_folder, tmp_path) -> None:
    """``--breakdown``: the per-seed rows of the three hold-out protocols (reference poses, ours on the
    reference's test points, ours on our own) hold evaluate map's splits, whose shares of each AUC's
    shortfall add up to 1 - AUC; without it the rows have none."""
    cfg = tmp_path / "fast.yaml"
    cfg.write_text(json.dumps({"mapping": FAST}))  # JSON is YAML
    out = evaluate_suite(
        data_folder, only=["seattle"], seeds=[0], config_path=cfg, simulated=False, breakdown=True
    )
    maps = out["datasets"][0]["maps"]
    for protocol in ("reference_poses", "slam_poses", "slam_poses_own_test_points"):
        row = maps[protocol]["per_seed"][0]
        for key in ("range_m", "hits_1m", "nearest_hit_m"):
            for mapper in ("gppol", "gpfol", "grid"):
                bins = row[f"by_{key}_{mapper}"]
                assert sum(b["test_points"] for b in bins) == row["test_points"]
                lost = sum(b["auc_lost_occupied"] for b in bins)
                assert lost == pytest.approx(1 - row[f"auc_{mapper}"], abs=1e-9)
    plain = evaluate_suite(data_folder, only=["seattle"], seeds=[0], config_path=cfg, simulated=False)
    row = plain["datasets"][0]["maps"]["slam_poses"]["per_seed"][0]
    assert not any(k.startswith("by_") for k in row)
    assert row["auc_gppol"] == maps["slam_poses"]["per_seed"][0]["auc_gppol"]  # the same maps
