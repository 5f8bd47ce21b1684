"""A simulated run in memory: the Recording a reader would return, plus everything only a simulator knows."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from datasets.se2 import compose
from datasets.simulation.geometry import World
from datasets.simulation.raster import GroundTruth, NoiseSource, rasterize
from datasets.simulation.sensors import LaserSpec, OdometryNoise, simulate_ranges
from datasets.types import Recording, ScanSequence, Trajectory

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Platform:
    """One simulated robot: its laser, where it was when it scanned, and its wheel odometry.

    ``scan_stamps_ns`` (N,) and ``scan_poses_xytheta`` (N, 3): true base poses in the world at each scan;
    ``odometry`` the wheel odometry as published (for exact odometry, the true poses); ``truth_dense`` the
    true base trajectory at the odometry rate (for figures and metrics).
    """

    name: str
    laser: LaserSpec
    scan_stamps_ns: NDArray[np.int64]
    scan_poses_xytheta: FloatArray
    odometry: Trajectory
    truth_dense: Trajectory
    laser_in_base_xytheta: FloatArray = field(default_factory=lambda: np.zeros(3))
    odometry_noise: OdometryNoise | None = None


@dataclass(frozen=True)
class SimulatedRun:
    """A world, its exact ground truth and the recording of the robots that drove through it.

    - ``recording``: what ``open_dataset`` returns for the written bag (scans of every platform merged in
      stamp order, ``ScanSequence.sources`` = scan topics; ``reference`` = true base pose at each scan;
      ``odometry`` = the wheel odometry of a single platform, None with several (see ``platforms``));
    - ``world``: the polygons; ``ground_truth``: the occupancy raster with the sensor and odometry noise;
    - ``platforms``: per robot, its laser, true poses, odometry and noise models;
    - ``true_poses``: (N, 3) true base pose at each scan of ``recording.scans`` (= ``recording.reference``).
    """

    name: str
    seed: int
    world: World
    recording: Recording
    ground_truth: GroundTruth
    platforms: tuple[Platform, ...]

    @property
    def true_poses(self) -> Trajectory:
        assert self.recording.reference is not None
        return self.recording.reference

    def odometry_messages(self) -> int:
        return sum(len(p.odometry) for p in self.platforms)


def scan_platforms(world: World, platforms: list[Platform], rng_streams: list[np.random.Generator]):
    """(ranges per platform) simulated scans of every platform, one random stream each."""
    edges = world.edges()
    out = []
    for p, rng in zip(platforms, rng_streams, strict=True):
        laser_poses = compose(p.scan_poses_xytheta, p.laser_in_base_xytheta[None, :])
        out.append(simulate_ranges(edges, laser_poses, p.laser, rng))
    return out


def assemble(
    name: str,
    seed: int,
    world: World,
    platforms: list[Platform],
    ranges: list[NDArray[np.float32]],
    resolution_m: float,
    frame_id: str = "map",
) -> SimulatedRun:
    """Merge the platforms' scans in stamp order into a Recording and rasterize the ground truth."""
    stamps = np.concatenate([p.scan_stamps_ns for p in platforms])
    source = np.concatenate([np.full(len(p.scan_stamps_ns), i, np.int32) for i, p in enumerate(platforms)])
    local = np.concatenate([np.arange(len(p.scan_stamps_ns)) for p in platforms])
    order = np.lexsort((source, stamps))
    angles = [p.laser.angles_rad() for p in platforms]
    scans = ScanSequence(
        ranges_m=[ranges[source[k]][local[k]] for k in order],
        angles_rad=[angles[source[k]] for k in order],
        stamps_ns=stamps[order],
        range_min_m=np.array([platforms[source[k]].laser.range_min_m for k in order]),
        range_max_m=np.array([platforms[source[k]].laser.range_max_m for k in order]),
        frame_ids=[platforms[source[k]].laser.frame_id for k in order],
        source_index=source[order],
        sources=[p.laser.topic for p in platforms],
    )
    truth = np.concatenate([p.scan_poses_xytheta for p in platforms])[order]
    reference = Trajectory(stamps[order], truth, frame_id=frame_id)
    single = len(platforms) == 1
    occ, origin = rasterize(world, resolution_m)
    odo_noise = platforms[0].odometry_noise if single and platforms[0].odometry_noise else None
    gt = GroundTruth(
        occupancy=occ,
        resolution_m=float(resolution_m),
        origin_xy_m=origin,
        world=name,
        frame_id=frame_id,
        seed=seed,
        sources=tuple(
            NoiseSource(p.laser.topic, p.laser.range_variance_m2, p.laser.bearing_variance_rad2)
            for p in platforms
        ),
        odometry_noise=odo_noise.as_dict() if odo_noise else {},
        meta={
            "lasers": [p.laser.as_dict() for p in platforms],
            "laser_in_base_xytheta": {p.name: [float(v) for v in p.laser_in_base_xytheta] for p in platforms},
            "odometry_topics": {p.name: _odom_topic(p) for p in platforms},
            "odometry_exact": {p.name: p.odometry_noise is None for p in platforms},
            "no_return": "+inf (REP 117); ranges below range_min are written as 0.0",
            "scene_area_m2": world.area_m2,
        },
    )
    recording = Recording(
        source=Path(f"simulation:{name}"),
        format="simulation",
        scans=scans,
        odometry=platforms[0].odometry if single else None,
        scan_poses=None,
        reference=reference,
        laser_in_base_xytheta=platforms[0].laser_in_base_xytheta.copy(),
        meta=_recording_meta(name, seed, platforms),
    )
    return SimulatedRun(name, seed, world, recording, gt, tuple(platforms))


def _odom_topic(p: Platform) -> str:
    ns = p.laser.topic.rsplit("/", 1)[0]
    return f"{ns}/odom"


def _recording_meta(name: str, seed: int, platforms: list[Platform]) -> dict:
    """Recording.meta; with several platforms, per-source odometry and laser mountings for the bag writer
    (``<ns>/odom`` and one ``/tf_static`` entry per laser)."""
    meta: dict = {"world": name, "seed": seed, "platforms": [p.name for p in platforms]}
    if len(platforms) > 1:
        meta["odometry_by_source"] = {p.laser.topic: p.odometry for p in platforms}
        meta["laser_in_base_by_source"] = {p.laser.topic: p.laser_in_base_xytheta.copy() for p in platforms}
    return meta
