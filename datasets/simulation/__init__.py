"""Simulated worlds with exact ground truth, written as ROS bags.

- :func:`make_world` ``(name, seed) -> SimulatedRun``: in memory, without a bag -- the
  :class:`~datasets.types.Recording` a reader would return, the world's polygons, the ground-truth raster
  (:class:`GroundTruth`), the true poses and each platform's laser and odometry noise;
- :func:`simulate` ``(world, out, seed) -> dict``: writes the bag ``out`` plus ``out.gt.npz`` / ``out.gt.png``
  (``python run.py simulate {street,two-platform,loop} --out PATH [--seed N]``);
- :func:`load_ground_truth` reads ``PATH.gt.npz`` (convention in :mod:`datasets.simulation.raster`).

Worlds: ``street`` and ``two-platform`` are the paper's simulated datasets I and II (section 4.1, Figures 6
and 8, Table 2); ``loop`` is an indoor loop with drifting wheel odometry for SLAM. Modules: ``geometry``
(polygons, :class:`World`), ``raycast`` (exact ray casting), ``raster`` (ground truth), ``sensors`` (laser,
odometry, paths), ``scenarios`` (the worlds), ``recording`` (assembly), ``output``, ``figures``;
``city`` (a generated city of any size, the scale benchmark's world: edges, path and ranges only).
"""

from datasets.simulation.geometry import World
from datasets.simulation.output import simulate
from datasets.simulation.raster import (
    GroundTruth,
    NoiseSource,
    ground_truth_path,
    load_ground_truth,
    rasterize,
    save_ground_truth,
)
from datasets.simulation.raycast import cast_rays
from datasets.simulation.recording import Platform, SimulatedRun
from datasets.simulation.scenarios import SCENARIOS, make_world
from datasets.simulation.sensors import LaserSpec, OdometryNoise

__all__ = [
    "SCENARIOS",
    "GroundTruth",
    "LaserSpec",
    "NoiseSource",
    "OdometryNoise",
    "Platform",
    "SimulatedRun",
    "World",
    "cast_rays",
    "ground_truth_path",
    "load_ground_truth",
    "make_world",
    "rasterize",
    "save_ground_truth",
    "simulate",
]
