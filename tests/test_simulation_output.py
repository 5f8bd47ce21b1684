"""``simulate`` and ``run.py simulate``: bags that read back through open_dataset, ground truth beside them,
byte-identical output for a seed."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from datasets import open_dataset
from datasets.errors import DatasetError
from datasets.simulation import load_ground_truth, make_world, simulate
from tests.conftest import REPO

WORLDS = ["street", "two-platform", "loop"]
LAYOUTS = {"ros1": "{}.bag", "mcap": "{}.mcap", "folder": "{}"}


def files_of(path: Path) -> dict[str, bytes]:
    """Every file of a bag (a file or a ROS 2 folder) with its bytes."""
    if path.is_dir():
        return {p.name: p.read_bytes() for p in sorted(path.iterdir())}
    return {path.name: path.read_bytes()}


@pytest.mark.parametrize("layout", LAYOUTS)
@pytest.mark.parametrize("world", WORLDS)
def test_bags_read_back_with_the_right_counts(tmp_path: Path, world: str, layout: str) -> None:
    out = tmp_path / LAYOUTS[layout].format(world)
    report = simulate(world, out, seed=0)
    run = make_world(world, 0)
    scans = run.recording.scans
    rec = open_dataset(out, scan_topic="all" if world == "two-platform" else None)
    assert report["scans"] == len(scans) == len(rec.scans)
    assert report["ground_truth_poses"] == len(rec.reference) == len(scans)
    assert report["odometry"] == run.odometry_messages()
    assert rec.scans.sources == scans.sources
    np.testing.assert_array_equal(rec.scans.stamps_ns, scans.stamps_ns)
    np.testing.assert_array_equal(rec.scans.source_index, scans.source_index)
    for got, want in zip(rec.scans.ranges_m, scans.ranges_m, strict=True):
        np.testing.assert_array_equal(got, want)  # bit for bit, inf included
    for got, want in zip(rec.scans.angles_rad, scans.angles_rad, strict=True):
        np.testing.assert_array_equal(got, want)
    np.testing.assert_allclose(rec.reference.poses_xytheta, run.true_poses.poses_xytheta, atol=1e-9)
    if world == "two-platform":
        by_source = rec.meta["odometry_by_source"]
        assert sorted(by_source) == sorted(scans.sources)
        assert sum(len(t) for t in by_source.values()) == report["odometry"]
    else:
        assert len(rec.odometry) == report["odometry"]
        np.testing.assert_allclose(
            rec.odometry.poses_xytheta, run.recording.odometry.poses_xytheta, atol=1e-9
        )
        np.testing.assert_allclose(rec.laser_in_base_xytheta, run.recording.laser_in_base_xytheta, atol=1e-12)
    # the ground truth beside the bag
    gt = load_ground_truth(out.with_name(out.name + ".gt.npz"))
    np.testing.assert_array_equal(gt.occupancy, run.ground_truth.occupancy)
    assert gt.resolution_m == run.ground_truth.resolution_m
    np.testing.assert_array_equal(gt.origin_xy_m, run.ground_truth.origin_xy_m)
    assert [s.name for s in gt.sources] == scans.sources
    assert out.with_name(out.name + ".gt.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize("layout", LAYOUTS)
def test_same_seed_is_byte_identical_and_another_seed_differs(tmp_path: Path, layout: str) -> None:
    outs = {}
    for name, seed in (("a", 1), ("b", 1), ("c", 2)):
        folder = tmp_path / name
        folder.mkdir()
        out = folder / LAYOUTS[layout].format("loop")
        simulate("loop", out, seed=seed)
        outs[name] = out
    for suffix in (".gt.npz", ".gt.png"):
        a, b, c = (p.with_name(p.name + suffix).read_bytes() for p in outs.values())
        assert a == b and a != c
    a, b, c = (files_of(p) for p in outs.values())
    assert a == b
    assert a.keys() == c.keys() and a != c


def test_simulate_refuses_to_overwrite_and_leaves_the_existing_files(tmp_path: Path) -> None:
    out = tmp_path / "street.bag"
    simulate("street", out)
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    with pytest.raises(DatasetError, match=re.escape(f"{out}: already exists")):
        simulate("street", out, seed=5)
    gt_only = tmp_path / "other.bag.gt.npz"
    gt_only.write_bytes(b"x")
    with pytest.raises(DatasetError, match=re.escape("other.bag.gt.npz: already exists")):
        simulate("street", tmp_path / "other.bag")
    assert not (tmp_path / "other.bag").exists()
    gt_only.unlink()
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before
    with pytest.raises(DatasetError, match="no such output directory"):
        simulate("street", tmp_path / "missing" / "x.bag")


def run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "run.py", *args], cwd=REPO, capture_output=True, text=True, timeout=600
    )


def test_cli_simulate_writes_the_bag_and_its_ground_truth(tmp_path: Path) -> None:
    out = tmp_path / "two.mcap"
    result = run_cli("simulate", "two-platform", "--out", str(out), "--seed", "3")
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith(f"wrote {out}: world two-platform, seed 3, scans ")
    assert len(result.stdout.strip().splitlines()) == 1
    assert out.is_file()
    assert (tmp_path / "two.mcap.gt.npz").is_file() and (tmp_path / "two.mcap.gt.png").is_file()
    assert load_ground_truth(tmp_path / "two.mcap.gt.npz").seed == 3
    again = run_cli("simulate", "two-platform", "--out", str(out))
    assert again.returncode == 1
    assert again.stderr.strip() == f"error: {out}: already exists; will not overwrite it"
    bad = run_cli("simulate", "moon", "--out", str(tmp_path / "m.bag"))
    assert bad.returncode == 2
