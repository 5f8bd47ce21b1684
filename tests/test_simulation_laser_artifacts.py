"""The realistic-laser effects of :class:`LaserArtifacts`: losses at grazing incidence, mixed pixels at depth
edges, outliers, dropouts; and the hit-edge ray cast they rely on."""

from __future__ import annotations

import numpy as np

from datasets.simulation.geometry import World, box
from datasets.simulation.raycast import cast_rays, cast_rays_hit_edges
from datasets.simulation.sensors import LaserArtifacts, LaserSpec, simulate_ranges


def corridor() -> World:
    """A 3 m wide, 200 m long corridor along x (walls at y = -1.5 and y = 1.5), and a box at x = 5."""
    return World(
        "corridor",
        (box(-100.0, -1.7, 100.0, -1.5), box(-100.0, 1.5, 100.0, 1.7), box(5.0, 0.5, 5.5, 1.0)),
        ("wall", "wall", "box"),
        (-100.0, -2.0, 100.0, 2.0),
    )


def test_hit_edges_name_the_surface_and_agree_with_cast_rays() -> None:
    edges = corridor().edges()
    angles = np.linspace(-np.pi, np.pi, 721)
    d, k = cast_rays_hit_edges(np.zeros(2), angles, edges)
    np.testing.assert_array_equal(d, cast_rays(np.zeros(2), angles, edges))
    assert np.all((k >= 0) == np.isfinite(d))
    assert np.mean(k >= 0) > 0.99  # only rays exactly along the open corridor miss
    up = np.abs(angles - np.pi / 2) < 0.3
    hit_y = edges[k[up], 1]
    np.testing.assert_allclose(hit_y, 1.5)  # the inner face of the north wall
    _, none = cast_rays_hit_edges(np.array([0.0, 50.0]), np.array([np.pi / 2]), edges)
    assert none[0] == -1


def test_grazing_incidence_loses_the_far_wall_returns() -> None:
    spec = LaserSpec.sweep(
        "/scan",
        1081,
        270.0,
        range_min_m=0.1,
        range_max_m=30.0,
        artifacts=LaserArtifacts(max_incidence_rad=np.deg2rad(80.0), incidence_fade_rad=0.0),
    )
    pose = np.array([[-50.0, 0.0, 0.0]])  # far from the box
    r = simulate_ranges(corridor().edges(), pose, spec, np.random.default_rng(0))[0]
    a = spec.angles_rad().astype(np.float64)
    ok = np.isfinite(r)
    # a wall 1.5 m to the side is seen up to 1.5 / cos(80 deg) = 8.6 m away, no farther
    assert ok.any() and r[ok].max() <= 1.5 / np.cos(np.deg2rad(80.0)) + 1e-6
    steep = np.abs(np.abs(a) - np.pi / 2) < np.deg2rad(60.0)
    assert np.all(ok[steep])
    plain = LaserSpec.sweep("/scan", 1081, 270.0, range_min_m=0.1, range_max_m=30.0)
    r0 = simulate_ranges(corridor().edges(), pose, plain, np.random.default_rng(0))[0]
    assert np.sum(np.isfinite(r0) & (r0 > 9.0)) > 20  # without the effect the far wall returns


def test_mixed_pixels_only_at_depth_edges_and_outliers_are_short() -> None:
    spec = LaserSpec.sweep(
        "/scan",
        1081,
        270.0,
        range_min_m=0.1,
        range_max_m=30.0,
        artifacts=LaserArtifacts(mixed_pixel_probability=1.0, outlier_probability=0.0),
    )
    world = corridor()
    pose = np.array([[0.0, 0.0, 0.0]])
    true = cast_rays(pose[:, :2], spec.angles_rad().astype(np.float64), world.edges())
    r = simulate_ranges(world.edges(), pose, spec, np.random.default_rng(1))[0].astype(np.float64)
    with np.errstate(invalid="ignore"):
        changed = np.isfinite(r) & (np.abs(r - true) > 1e-4)
        jump = np.isfinite(true[:-1]) & np.isfinite(true[1:]) & (np.abs(np.diff(true)) > 0.3)
    at_edge = np.zeros_like(changed)
    at_edge[:-1] |= jump
    at_edge[1:] |= jump
    assert changed.any() and np.all(at_edge[changed])
    lo = np.minimum(true[:-1], true[1:])
    hi = np.maximum(true[:-1], true[1:])
    idx = np.flatnonzero(changed)
    for i in idx:  # a veil point lies between the two surfaces of its edge
        pair = [j for j in (i - 1, i) if 0 <= j < len(jump) and jump[j]]
        assert any(lo[j] - 1e-4 <= r[i] <= hi[j] + 1e-4 for j in pair)
    out = LaserSpec.sweep(
        "/scan",
        1081,
        270.0,
        range_min_m=0.1,
        range_max_m=30.0,
        artifacts=LaserArtifacts(outlier_probability=0.2, dropout_probability=0.1),
    )
    ro = simulate_ranges(world.edges(), np.repeat(pose, 20, axis=0), out, np.random.default_rng(2))
    t = np.broadcast_to(true, ro.shape)
    fin = np.isfinite(ro)
    assert 0.05 < np.mean(~fin) < 0.15  # dropouts (no return)
    short = fin & (ro < t - 0.01)
    assert 0.15 < short.sum() / fin.sum() < 0.25 and np.all(ro[fin] <= t[fin] + 1e-6)


def test_a_spec_without_artifacts_is_unchanged() -> None:
    spec = LaserSpec.sweep("/scan", 17, 180.0, range_min_m=0.1, range_max_m=34.0, range_variance_m2=1e-4)
    assert "artifacts" not in spec.as_dict()
    with_art = LaserSpec.sweep(
        "/scan", 17, 180.0, range_min_m=0.1, range_max_m=34.0, artifacts=LaserArtifacts()
    )
    assert with_art.as_dict()["artifacts"]["max_incidence_rad"] == np.pi / 2
