"""``python run.py evaluate slam`` on a simulated bag: JSON keys of SPEC section 3, a relations file derived
from the ground truth, and bad input as one line with exit status 1."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from datasets.registry import open_dataset
from datasets.relations import Relations, write_relations
from slam import geometry as se2
from tests.conftest import REPO


def run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "run.py", *args], cwd=REPO, capture_output=True, text=True, timeout=600
    )


@pytest.fixture(scope="module")
def loop_bag(tmp_path_factory) -> object:
    path = tmp_path_factory.mktemp("loop") / "loop.bag"
    done = run_cli("simulate", "loop", "--out", str(path))
    assert done.returncode == 0, done.stderr
    return path


def test_evaluate_slam_against_the_ground_truth(loop_bag) -> None:
    done = run_cli("evaluate", "slam", str(loop_bag), "--reference", str(loop_bag), "--json")
    assert done.returncode == 0, done.stderr
    out = json.loads(done.stdout)
    assert set(out) >= {"relations", "ate_rmse_m"}
    assert out["relations"] is None
    assert out["ate_rmse_m"]["after"] <= 0.05
    assert out["ate_rmse_m"]["after"] < out["ate_rmse_m"]["before"]
    assert out["reference"]["matched_scans"] == out["slam"]["scans"]


def test_evaluate_slam_with_a_relations_file(loop_bag, tmp_path) -> None:
    rec = open_dataset(loop_bag)
    truth = rec.reference.poses_xytheta  # relations of the robot's base, as the benchmark's
    a = np.arange(0, len(truth) - 20, 7)
    b = a + 20
    rel = se2.between(truth[a], truth[b])
    relations = Relations(
        rec.scans.stamps_ns[a],
        rec.scans.stamps_ns[b],
        np.column_stack([rel[:, :2], np.zeros(len(a))]),
        np.column_stack([np.zeros((len(a), 2)), rel[:, 2]]),
    )
    path = tmp_path / "loop.relations"
    write_relations(path, relations)
    done = run_cli("evaluate", "slam", str(loop_bag), "--relations", str(path), "--json")
    assert done.returncode == 0, done.stderr
    out = json.loads(done.stdout)
    r = out["relations"]
    assert out["ate_rmse_m"] is None
    assert r["count"] == len(a) and r["unmatched"] == 0
    assert 0 < r["trans_mean_m"] < 0.03 and r["rot_mean_deg"] < 0.5
    assert set(r) >= {"count", "trans_mean_m", "trans_std_m", "rot_mean_deg", "rot_std_deg"}


def test_bad_relations_file_is_one_line(loop_bag, tmp_path) -> None:
    missing = tmp_path / "missing.relations"
    done = run_cli("evaluate", "slam", str(loop_bag), "--relations", str(missing), "--json")
    assert done.returncode == 1
    assert done.stderr.strip() == f"error: {missing}: no such file or directory"
    assert done.stdout == ""
    far = tmp_path / "far.relations"
    far.write_text("1.0 2.0 1 0 0 0 0 0\n")
    done = run_cli("evaluate", "slam", str(loop_bag), "--relations", str(far))
    assert done.returncode == 1
    assert "none of its 1 relations has both stamps within 50 ms of a scan" in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1 and "Traceback" not in done.stderr
