"""TUM, g2o and covariance files: writer paired with reader, exact round trips, one-line errors."""

from __future__ import annotations

import numpy as np
import pytest

from slam.graph import Edge
from slam.trajectory_io import (
    TrajectoryFormatError,
    load_covariances,
    read_g2o,
    read_tum,
    save_covariances,
    write_g2o,
    write_tum,
)


def _poses(n: int = 50) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(2)
    stamps = 976052857_337284000 + np.cumsum(rng.integers(1, 300_000_000, n))
    poses = np.column_stack([rng.normal(0, 10, n), rng.normal(0, 10, n), rng.uniform(-np.pi, np.pi, n)])
    return stamps.astype(np.int64), poses


def test_tum_round_trip_is_exact_in_stamps(tmp_path) -> None:
    stamps, poses = _poses()
    path = tmp_path / "odometry.tum"
    write_tum(path, stamps, poses)
    first = path.read_text().splitlines()[1].split()
    assert len(first) == 8 and first[3] == "0.0"  # t x y z qx qy qz qw, planar
    s2, p2 = read_tum(path)
    np.testing.assert_array_equal(s2, stamps)
    np.testing.assert_allclose(p2[:, :2], poses[:, :2], rtol=0, atol=0)
    np.testing.assert_allclose(np.angle(np.exp(1j * (p2[:, 2] - poses[:, 2]))), 0.0, atol=1e-12)


def test_tum_bad_lines_are_one_line_errors(tmp_path) -> None:
    path = tmp_path / "bad.tum"
    path.write_text("# t x y z qx qy qz qw\n1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 1\n")
    with pytest.raises(TrajectoryFormatError, match=r"bad.tum: line 3: expected 8 fields"):
        read_tum(path)
    path.write_text("1.0 0 0 0 0 0 nan 1\n")
    with pytest.raises(TrajectoryFormatError, match=r"line 1: NaN or infinite"):
        read_tum(path)
    with pytest.raises(TrajectoryFormatError, match=r"no such file"):
        read_tum(tmp_path / "missing.tum")


def test_g2o_round_trip_keeps_vertices_edges_and_information(tmp_path) -> None:
    _, poses = _poses(6)
    edges = [Edge("prior", 0, 0, poses[0], np.eye(3) * 1e-6)]
    cov = np.array([[0.01, 0.002, 0.001], [0.002, 0.02, 0.0005], [0.001, 0.0005, 0.003]])
    for i in range(5):
        edges.append(Edge("odometry", i, i + 1, np.array([1.0, 0.1 * i, 0.05]), cov * (i + 1)))
    edges.append(Edge("loop", 1, 5, np.array([-0.5, 2.0, 3.0]), cov * 0.5, robust="cauchy"))
    path = tmp_path / "pose_graph.g2o"
    write_g2o(path, poses, edges)
    text = path.read_text()
    assert text.count("VERTEX_SE2") == 6 and text.count("EDGE_SE2") == 6 and "FIX 0" in text
    g = read_g2o(path)
    np.testing.assert_array_equal(g.vertices_xytheta, poses)
    assert g.fixed == (0,)
    assert [e.kind for e in g.edges] == ["odometry"] * 5 + ["loop"]
    for ours, theirs in zip(edges[1:], g.edges, strict=True):
        assert (ours.key_from, ours.key_to) == (theirs.key_from, theirs.key_to)
        np.testing.assert_array_equal(ours.measurement_xytheta, theirs.measurement_xytheta)
        np.testing.assert_allclose(theirs.information, ours.information, rtol=1e-12)


def test_g2o_bad_input(tmp_path) -> None:
    path = tmp_path / "bad.g2o"
    path.write_text("VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 7 1 0 0 1 0 0 1 0 1\n")
    with pytest.raises(TrajectoryFormatError, match=r"line 2: edge between unknown vertices 0 and 7"):
        read_g2o(path)
    path.write_text("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\n")
    with pytest.raises(TrajectoryFormatError, match=r"line 1: unsupported g2o record 'VERTEX_SE3:QUAT'"):
        read_g2o(path)


def test_covariance_archive_round_trip(tmp_path) -> None:
    rng = np.random.default_rng(0)
    a = rng.normal(size=(7, 3, 3))
    before = a @ np.swapaxes(a, 1, 2)
    after = 0.5 * before
    stamps = np.arange(7, dtype=np.int64) * 10**9
    path = tmp_path / "covariances.npz"
    save_covariances(path, stamps, before, after, indices=np.arange(7) * 3)
    data = load_covariances(path)
    np.testing.assert_array_equal(data["before"], before)
    np.testing.assert_array_equal(data["after"], after)
    np.testing.assert_array_equal(data["stamps_ns"], stamps)
    np.testing.assert_array_equal(data["indices"], np.arange(7) * 3)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["covariances.npz"]  # no temporary left behind
    with pytest.raises(TrajectoryFormatError, match="no such file"):
        load_covariances(tmp_path / "none.npz")


def test_g2o_round_trip_is_bit_exact_for_random_poses(tmp_path) -> None:
    """Every bit of every vertex and measurement survives the text: remap's 1 um pose tolerance is never
    spent on our own files. Values span magnitudes from 1e-300 to 1e300, signs, -0.0 and subnormals."""
    rng = np.random.default_rng(7)
    n = 2000
    scale = 10.0 ** rng.uniform(-300, 300, (n, 3))
    poses = rng.choice([-1.0, 1.0], (n, 3)) * rng.random((n, 3)) * scale
    poses[:, 2] = rng.uniform(-np.pi, np.pi, n)
    poses[0] = [-0.0, 5e-324, np.nextafter(np.pi, 0.0)]
    poses[1] = [np.finfo(float).max, -np.finfo(float).tiny, -np.pi]
    cov = np.diag([0.01, 0.02, 0.003])
    edges = [Edge("odometry", i, i + 1, poses[i + 1] - poses[i] * 0.5, cov) for i in range(50)]
    path = tmp_path / "random.g2o"
    write_g2o(path, poses, edges)
    g = read_g2o(path)
    assert g.vertices_xytheta.view(np.uint64).tolist() == poses.view(np.uint64).tolist()
    for ours, theirs in zip(edges, g.edges, strict=True):
        assert (
            theirs.measurement_xytheta.view(np.uint64).tolist()
            == ours.measurement_xytheta.view(np.uint64).tolist()
        )
    # 6 significant digits (GTSAM's writeG2o) would not do: the same poses differ after such a round trip
    path.write_text("".join(f"VERTEX_SE2 {k} {x:.6g} {y:.6g} {t:.6g}\n" for k, (x, y, t) in enumerate(poses)))
    assert not np.array_equal(read_g2o(path).vertices_xytheta, poses)


def test_tum_positions_are_bit_exact_and_yaw_within_two_ulps(tmp_path) -> None:
    rng = np.random.default_rng(8)
    n = 2000
    stamps = np.cumsum(rng.integers(1, 10**9, n)).astype(np.int64)
    poses = np.column_stack([rng.normal(0, 1e3, n), rng.normal(0, 1e-3, n), rng.uniform(-np.pi, np.pi, n)])
    write_tum(tmp_path / "t.tum", stamps, poses)
    s2, p2 = read_tum(tmp_path / "t.tum")
    np.testing.assert_array_equal(s2, stamps)
    assert p2[:, :2].view(np.uint64).tolist() == poses[:, :2].view(np.uint64).tolist()
    np.testing.assert_allclose(np.angle(np.exp(1j * (p2[:, 2] - poses[:, 2]))), 0.0, rtol=0, atol=2 * 4.5e-16)
