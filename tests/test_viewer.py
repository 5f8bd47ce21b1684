"""The Rerun viewer export: a run folder written as an .rrd, read back with rerun's own reader.

The run folder is small and synthetic but written with the pipeline's own writers (scans, trajectories and
covariances, layers, summary), so its layout is the one ``run`` writes; every value is known, so the test
checks the recording's contents, not just its entity paths.
"""

from __future__ import annotations

import math
from collections import defaultdict
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest

from datasets.types import ScanSequence
from mapping.exports import MapLayers, write_layers_npz
from pipeline.artifacts import write_scans, write_trajectories
from pipeline.errors import PipelineError
from pipeline.run_folder import write_summary
from pipeline.viewer import (
    MAP_Z_M,
    MAX_STATIC_ELLIPSES,
    check_rerun_path,
    covariance_ellipses_xy,
    occupancy_u8,
    write_rerun,
)
from slam import geometry
from slam.odometry import scan_points_base
from slam.result import SlamResult
from slam.trajectory_io import write_tum

rerun_chunk = pytest.importorskip("rerun.chunk")

N_SCANS = 40
N_BEAMS = 90
LASER_IN_BASE = np.array([0.2, 0.05, 0.1])
STAMP0_NS = 1_325_376_000_013_000_000
CLOSURES = [(38, 1), (39, 2)]
MAP_SHAPES = {"before": (30, 50), "after": (32, 48)}


def _scans(rng: np.random.Generator) -> ScanSequence:
    ranges, angles = [], []
    for i in range(N_SCANS):
        r = rng.uniform(0.5, 12.0, N_BEAMS).astype(np.float32)
        r[i % 7 :: 11] = np.inf  # no return
        r[3] = np.nan
        r[5] = 0.05  # below range_min
        r[7] = 30.0  # at range_max: no return
        ranges.append(r)
        angles.append(np.linspace(-np.pi, np.pi, N_BEAMS, endpoint=False).astype(np.float32))
    stamps = STAMP0_NS + np.arange(N_SCANS, dtype=np.int64) * 500_000_000
    return ScanSequence(ranges, angles, stamps, 0.1, 30.0)


def _layers(shape: tuple[int, int], origin: tuple[float, float], rng: np.random.Generator) -> MapLayers:
    p = rng.uniform(0, 1, shape).astype(np.float32)
    p[0, :5] = np.nan  # unknown cells
    var = rng.uniform(0.01, 0.9, shape).astype(np.float32)
    return MapLayers(p, rng.normal(size=shape).astype(np.float32), var, 0.25, origin)


def _slam(stamps: np.ndarray) -> SlamResult:
    t = np.linspace(0, 2 * np.pi, N_SCANS)
    after = np.stack([8 * np.cos(t), 4 * np.sin(t), t + np.pi / 2], axis=1)
    before = after + np.stack([0.02 * np.arange(N_SCANS), -0.01 * np.arange(N_SCANS), 0 * t], axis=1)
    k = np.arange(N_SCANS)
    cov_after = np.zeros((N_SCANS, 3, 3))
    cov_after[:, 0, 0] = 0.01 + 0.001 * k
    cov_after[:, 1, 1] = 0.02 + 0.0005 * k
    cov_after[:, 0, 1] = cov_after[:, 1, 0] = 0.005
    cov_after[:, 2, 2] = 0.001
    keyframes = np.arange(0, N_SCANS, 4)
    return SlamResult(
        stamps_ns=stamps,
        poses_before_xytheta=before,
        poses_after_xytheta=after,
        cov_before_xytheta=2 * cov_after,
        cov_after_xytheta=cov_after,
        relative_cov_before_xytheta=0.5 * cov_after,
        relative_cov_after_xytheta=0.25 * cov_after,
        odometry_status=np.zeros(N_SCANS, np.int8),
        keyframe_scans=keyframes,
        keyframe_stamps_ns=stamps[keyframes],
        keyframe_cov_before=2 * cov_after[keyframes],
        keyframe_cov_after=cov_after[keyframes],
        loop_closures=(),
        rejected_loop_closures=(),
        graph_vertices_xytheta=after[keyframes],
        graph_edges=(),
    )


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    rng = np.random.default_rng(3)
    out = tmp_path_factory.mktemp("viewer") / "run"
    out.mkdir()
    scans = _scans(rng)
    write_scans(out / "scans.npz", scans, LASER_IN_BASE)
    write_trajectories(out / "trajectory", _slam(scans.stamps_ns))
    for name, shape in MAP_SHAPES.items():
        (out / "maps" / name).mkdir(parents=True)
        write_layers_npz(out / "maps" / name / "layers.npz", _layers(shape, (-11.0, -6.5), rng))
    summary = {
        "counts": {"scans": N_SCANS, "loop_closures": len(CLOSURES)},
        "loop_closures": [{"query_scan": q, "target_scan": t} for q, t in CLOSURES],
        "table": {"scans": N_SCANS, "loop closures (accepted / rejected)": "2 / 0"},
    }
    write_summary(out, summary)
    return out


def read_rrd(path: Path) -> dict[tuple[str, bool], list[pa.RecordBatch]]:
    """Record batches of the recording store by (entity path, static)."""
    reader = rerun_chunk.RrdReader(path)
    assert len(reader.recordings()) == 1 and len(reader.blueprints()) == 1
    out: dict[tuple[str, bool], list[pa.RecordBatch]] = defaultdict(list)
    for chunk in reader.stream().to_chunks():
        out[(chunk.entity_path, chunk.is_static)].append(chunk.to_record_batch())
    return out


def temporal_rows(
    batches: list[pa.RecordBatch], column: str
) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    """(stamps_ns, scan indices, per-row flattened values) of a temporal entity, in scan order."""
    stamps, seq, rows = [], [], []
    for rb in batches:
        stamps.append(rb.column("stamp").cast(pa.int64()).to_numpy())
        seq.append(rb.column("scan").to_numpy())
        col = rb.column(column)
        for i in range(len(col)):
            rows.append(_values(col[i].values))
    order = np.argsort(np.concatenate(seq), kind="stable")
    return np.concatenate(stamps)[order], np.concatenate(seq)[order], [rows[i] for i in order]


def _values(arr: pa.Array) -> np.ndarray:
    """Flatten nested list / fixed-size-list arrays down to a numpy array of their leaves."""
    while pa.types.is_list(arr.type) or pa.types.is_fixed_size_list(arr.type):
        arr = arr.flatten()
    return arr.to_numpy(zero_copy_only=False)


def static_value(recording, entity: str, column: str) -> list:
    (rb,) = recording[(entity, True)]
    return rb.column(column).to_pylist()[0]


@pytest.fixture(scope="module")
def recording(run_dir, tmp_path_factory) -> dict:
    rrd = tmp_path_factory.mktemp("rrd") / "run.rrd"
    assert write_rerun(run_dir, rrd) == rrd
    assert rrd.stat().st_size > 0 and not list(rrd.parent.glob(".run.rrd*"))  # no temporary left
    return read_rrd(rrd)


def test_recording_holds_every_entity(recording) -> None:
    entities = {path for path, _ in recording}
    expected = {
        "/world/scan",
        "/world/pose",
        "/world/pose/covariance",
        "/world/covariances",
        "/world/loop_closures",
        "/world/trajectories/odometry",
        "/world/trajectories/optimized",
        "/summary",
    } | {f"/world/maps/{m}/{layer}" for m in MAP_SHAPES for layer in ("occupancy", "variance")}
    assert expected <= entities


def test_one_scan_frame_per_scan_in_the_world_frame(run_dir, recording) -> None:
    from pipeline.artifacts import read_scans
    from slam.trajectory_io import read_tum

    stored = read_scans(run_dir / "scans.npz")
    _, poses = read_tum(run_dir / "trajectory/optimized.tum")
    got_stamps, seq, rows = temporal_rows(recording[("/world/scan", False)], "Points3D:positions")
    assert len(rows) == N_SCANS
    assert np.array_equal(got_stamps, stored.scans.stamps_ns) and np.array_equal(seq, np.arange(N_SCANS))
    for i, row in enumerate(rows):
        # independently: the odometry's base-frame end points, then the base pose after loop closure
        s = stored.scans
        base = scan_points_base(
            s.ranges_m[i], s.angles_rad[i], s.range_min_m[i], s.range_max_m[i], LASER_IN_BASE, 0.0, np.inf
        )
        expected = geometry.transform_points(poses[i], base)
        got = row.reshape(-1, 3)
        assert got.shape == (len(expected), 3) and 0 < len(expected) < N_BEAMS - 3
        np.testing.assert_allclose(got[:, :2], expected, atol=1e-4)
        assert (got[:, 2] == 0).all()


def test_trajectories_closures_and_ellipses(run_dir, recording) -> None:
    from slam.trajectory_io import read_tum

    for name in ("odometry", "optimized"):
        _, poses = read_tum(run_dir / f"trajectory/{name}.tum")
        (strip,) = static_value(recording, f"/world/trajectories/{name}", "LineStrips3D:strips")
        assert len(strip) == N_SCANS
        np.testing.assert_allclose(np.asarray(strip)[:, :2], poses[:, :2], atol=1e-5)
    _, after = read_tum(run_dir / "trajectory/optimized.tum")
    segments = np.asarray(static_value(recording, "/world/loop_closures", "LineStrips3D:strips"))
    assert segments.shape == (len(CLOSURES), 2, 3)
    for seg, (q, t) in zip(segments, CLOSURES, strict=True):
        np.testing.assert_allclose(seg[:, :2], after[[q, t], :2], atol=1e-5)
    ellipses = static_value(recording, "/world/covariances", "LineStrips3D:strips")
    assert len(ellipses) == math.ceil(N_SCANS / max(1, math.ceil(N_SCANS / MAX_STATIC_ELLIPSES)))
    _, _, moving = temporal_rows(recording[("/world/pose/covariance", False)], "LineStrips3D:strips")
    assert len(moving) == N_SCANS


def test_maps_are_grid_maps_of_the_layers(run_dir, recording) -> None:
    from mapping.exports import read_layers_npz

    for name, (h, w) in MAP_SHAPES.items():
        layers = read_layers_npz(run_dir / f"maps/{name}/layers.npz")
        for layer, dtype in (("occupancy", np.uint8), ("variance", np.float32)):
            entity = f"/world/maps/{name}/{layer}"
            (fmt,) = static_value(recording, entity, "GridMap:format")
            assert (fmt["height"], fmt["width"]) == (h, w)
            assert static_value(recording, entity, "GridMap:cell_size") == [0.25]
            np.testing.assert_allclose(
                static_value(recording, entity, "GridMap:translation")[0], [-11.0, -6.5, MAP_Z_M], atol=1e-6
            )
            data = np.frombuffer(bytes(static_value(recording, entity, "GridMap:data")[0]), dtype).reshape(
                h, w
            )
            # a GridMap's row 0 is its top edge (highest y); the layers' row 0 is the lowest y
            source = occupancy_u8(layers.probability) if layer == "occupancy" else layers.variance
            np.testing.assert_array_equal(data[::-1], source)
            if layer == "occupancy":
                assert (data == 255).sum() == 5  # the NaN cells: unknown


def test_occupancy_values_follow_the_occupancy_grid_convention() -> None:
    p = np.array([[0.0, 0.004, 0.5, 0.996, 1.0, np.nan, np.inf]])
    assert occupancy_u8(p).tolist() == [[0, 0, 50, 100, 100, 255, 255]]


def test_covariance_ellipse_is_the_two_sigma_contour() -> None:
    angle = 0.5
    rot = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    cov_xy = rot @ np.diag([0.09, 0.01]) @ rot.T
    cov = np.zeros((1, 3, 3))
    cov[0, :2, :2] = cov_xy
    (outline,) = covariance_ellipses_xy(np.array([[3.0, -1.0]]), cov, sigma=2.0, vertices=64)
    assert np.array_equal(outline[0], outline[-1])  # closed
    d = outline - [3.0, -1.0]
    np.testing.assert_allclose(np.einsum("vi,ij,vj->v", d, np.linalg.inv(cov_xy), d), 4.0, rtol=1e-9)
    radius = np.linalg.norm(d, axis=1)
    assert radius.max() == pytest.approx(2 * 0.3, rel=1e-3) and radius.min() == pytest.approx(
        2 * 0.1, rel=2e-2
    )
    major = d[np.argmax(radius)]
    assert abs(abs(np.dot(major / np.linalg.norm(major), rot[:, 0])) - 1) < 1e-3  # along the rotated axis


def test_remap_folder_takes_its_scans_from_the_source_run(run_dir, tmp_path) -> None:
    from pipeline.artifacts import read_scans

    remap = tmp_path / "remap"
    (remap / "trajectory").mkdir(parents=True)
    stamps = read_scans(run_dir / "scans.npz").scans.stamps_ns
    poses = np.zeros((N_SCANS, 3))
    poses[:, 0] = np.arange(N_SCANS) * 0.5
    write_tum(remap / "trajectory/remap.tum", stamps, poses)
    (remap / "maps/remap").mkdir(parents=True)
    write_layers_npz(remap / "maps/remap/layers.npz", _layers((10, 12), (0.0, 0.0), np.random.default_rng(0)))
    write_summary(
        remap, {"run_dir": str(run_dir), "covariances": str(run_dir / "trajectory/covariances.npz")}
    )
    rec = read_rrd(write_rerun(remap, tmp_path / "remap.rrd"))
    assert {"/world/trajectories/remap", "/world/maps/remap/occupancy", "/world/maps/remap/variance"} <= {
        p for p, _ in rec
    }
    _, _, rows = temporal_rows(rec[("/world/scan", False)], "Points3D:positions")
    assert len(rows) == N_SCANS
    _, _, arrows = temporal_rows(rec[("/world/pose", False)], "Arrows3D:origins")
    np.testing.assert_allclose(np.stack(arrows)[:, :2], poses[:, :2], atol=1e-6)  # at the remapped poses
    assert ("/world/loop_closures", True) not in rec  # a remap has no loop closures of its own


def test_bad_run_folders_and_outputs(run_dir, tmp_path) -> None:
    with pytest.raises(PipelineError, match="no such run folder"):
        write_rerun(tmp_path / "nothing", tmp_path / "a.rrd")
    half = tmp_path / "half"
    (half / "trajectory").mkdir(parents=True)
    with pytest.raises(PipelineError, match="not a complete run folder"):
        write_rerun(half, tmp_path / "a.rrd")
    with pytest.raises(PipelineError, match=r"must end in \.rrd"):
        write_rerun(run_dir, tmp_path / "a.txt")
    with pytest.raises(PipelineError, match="no such folder"):
        write_rerun(run_dir, tmp_path / "missing" / "a.rrd")
    assert not list(tmp_path.glob("*.rrd")) and not list(tmp_path.glob(".a.rrd*"))


def test_rerun_path_is_checked_before_any_work(tmp_path) -> None:
    """``--rerun FILE.rrd`` is checked before the run: an existing recording is replaced only with
    --overwrite (and never the command's input), and a bad name or place fails at once, not after the run."""
    import subprocess
    import sys

    existing = tmp_path / "mine.rrd"
    existing.write_bytes(b"user data")
    with pytest.raises(PipelineError, match=r"mine\.rrd: already exists \(use --overwrite"):
        check_rerun_path(existing)
    check_rerun_path(existing, overwrite=True)
    with pytest.raises(PipelineError, match="is what this command reads"):
        check_rerun_path(existing, overwrite=True, reads=(tmp_path / "in.clf", existing))
    with pytest.raises(PipelineError, match=r"must end in \.rrd"):
        check_rerun_path(tmp_path / "in.clf")
    (tmp_path / "d.rrd").mkdir()
    with pytest.raises(PipelineError, match="is a folder"):
        check_rerun_path(tmp_path / "d.rrd")
    (tmp_path / "f").write_text("x")
    with pytest.raises(PipelineError, match=r"cannot be created \(.*f is not a folder\)"):
        check_rerun_path(tmp_path / "f" / "sub" / "a.rrd")
    check_rerun_path(tmp_path / "new" / "run" / "a.rrd")  # (inside the run folder about to be made)

    repo = Path(__file__).resolve().parents[1]
    log = tmp_path / "in.clf"
    log.write_text("FLASER 3 1.0 1.0 1.0 0 0 0 0 0 0 1.0 host 1.0\n")
    proc = subprocess.run(
        [sys.executable, "run.py", "run", str(log), "--out", str(tmp_path / "o"), "--rerun", str(existing)],
        cwd=repo, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert proc.returncode == 1 and proc.stderr.count("\n") == 1, proc.stderr
    assert "mine.rrd: already exists" in proc.stderr
    assert existing.read_bytes() == b"user data" and not (tmp_path / "o").exists()


def test_a_recording_the_disk_cannot_hold_is_one_error_and_no_file(run_dir, tmp_path) -> None:
    """The SDK's file writer stopped by the file-size limit (as by a full disk): a PipelineError naming the
    .rrd within the flush timeout, not a hang or the SDK's RuntimeError, and no partial file left."""
    import subprocess
    import sys

    pytest.importorskip("resource")
    full = write_rerun(run_dir, tmp_path / "full.rrd")
    limit = full.stat().st_size // 2
    out = tmp_path / "half" / "a.rrd"
    out.parent.mkdir()
    script = (
        "import resource, sys\n"
        f"resource.setrlimit(resource.RLIMIT_FSIZE, ({limit}, {limit}))\n"
        "import pipeline.viewer as viewer\n"
        "from pipeline.errors import PipelineError\n"
        "viewer.RERUN_FLUSH_TIMEOUT_S = 20.0\n"
        "try:\n"
        "    viewer.write_rerun(sys.argv[1], sys.argv[2])\n"
        "except PipelineError as err:\n"
        "    print('PipelineError:', err)\n"
    )
    repo = Path(__file__).resolve().parents[1]
    proc = subprocess.run(
        [sys.executable, "-c", script, str(run_dir), str(out)],
        cwd=repo,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.startswith(f"PipelineError: {out}: cannot write ("), proc.stdout
    assert list(out.parent.iterdir()) == []


def test_a_recording_that_stalls_on_a_full_disk_is_given_up(tmp_path, monkeypatch) -> None:
    """A child whose file stops growing on a disk without room is given up after ``STALL_S``, not after the
    SDK's flush timeout; on a disk with room the same silence is waited out."""
    import subprocess
    import sys
    import time
    from collections import namedtuple

    import pipeline.viewer as viewer

    usage = namedtuple("usage", "total used free")
    tmp = tmp_path / "a.rrd"
    tmp.write_bytes(b"x" * 100)
    monkeypatch.setattr(viewer, "STALL_S", 1.0)
    monkeypatch.setattr(viewer.shutil, "disk_usage", lambda _p: usage(10**9, 10**9, 0))
    child = subprocess.Popen(
        [sys.executable, "-c", "import time; time.sleep(60)"], stdout=subprocess.PIPE, text=True
    )
    try:
        t0 = time.monotonic()
        assert viewer._await_report(child, tmp) == "no space left on its disk"
        assert time.monotonic() - t0 < 10
    finally:
        child.kill()
        child.wait()
    monkeypatch.setattr(viewer.shutil, "disk_usage", lambda _p: usage(10**9, 0, 10**9))
    script = "import time; time.sleep(3); print('recorded', flush=True)"
    child = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    try:
        assert viewer._await_report(child, tmp) == viewer.RECORDED
    finally:
        child.kill()
        child.wait()


def test_a_damaged_file_of_the_run_folder_is_named_as_such(run_dir, tmp_path) -> None:
    """The parent checks the folder's shape only; a damaged file the recording process meets is reported
    with its own message, not as a failure to write the .rrd."""
    import shutil

    copy = tmp_path / "run"
    shutil.copytree(run_dir, copy)
    layers = next((copy / "maps").glob("*/layers.npz"))
    layers.write_bytes(b"not a zip")
    with pytest.raises(PipelineError) as err:
        write_rerun(copy, tmp_path / "a.rrd")
    assert str(layers) in str(err.value) and "cannot write" not in str(err.value)
    assert not list(tmp_path.glob("*.rrd")) and not list(tmp_path.glob(".a.rrd*"))
