"""Figures of a SLAM run: trajectories before / after loop closure against a reference, with the scan end
points placed by each (a quick look at the consistency of the poses, not an occupancy map).

``python -m slam.figures OUT_DIR`` regenerates ``docs/figures/slam/`` (intel.clf and the loop world).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from datasets.paths import SHARED_DATA_DIR
from slam import geometry as se2
from slam import metrics
from slam.result import SlamResult


def plot_before_after(
    path: str | Path,
    result: SlamResult,
    points_base: list[NDArray] | None,
    reference_xytheta: NDArray | None = None,
    reference_scans: NDArray | None = None,
    title: str = "",
    every: int = 5,
) -> None:
    """Two panels (before, after loop closure): scan end points of every ``every``-th scan placed by the
    trajectory, the trajectory, and the reference (aligned to it by SE(2)) when given; a small PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 5), dpi=90)
    for ax, name, poses in (
        (axes[0], "before loop closure", result.poses_before_xytheta),
        (axes[1], "after loop closure", result.poses_after_xytheta),
    ):
        if points_base is not None:
            cloud = np.concatenate(
                [se2.transform_points(poses[i], points_base[i]) for i in range(0, len(points_base), every)]
            )
            ax.plot(cloud[:, 0], cloud[:, 1], ",", color="0.45", alpha=0.5)
        label = name
        if reference_xytheta is not None and reference_scans is not None:
            est = poses[reference_scans]
            ate = metrics.ate_rmse(est, reference_xytheta)
            t = se2.inverse(metrics.align_se2(est, reference_xytheta))
            ref_here = se2.compose(t, reference_xytheta)
            ax.plot(ref_here[:, 0], ref_here[:, 1], "-", color="k", lw=0.6, label="reference")
            label = f"{name} (ATE {ate:.3f} m)"
        ax.plot(
            poses[:, 0],
            poses[:, 1],
            "-",
            color="tab:red" if "before" in name else "tab:blue",
            lw=0.6,
            label="estimate",
        )
        if "after" in name:
            for c in result.loop_closures:
                q, t_ = poses[c.query_scan], poses[c.target_scan]
                ax.plot([q[0], t_[0]], [q[1], t_[1]], "-", color="tab:green", lw=0.4)
        ax.set_title(label, fontsize=9)
        ax.set_aspect("equal")
        ax.tick_params(labelsize=7)
        ax.legend(fontsize=7, loc="lower right")
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _main(out_dir: Path) -> None:  # pragma: no cover - figure regeneration
    from datasets.carmen import match_scans
    from datasets.registry import open_dataset
    from datasets.simulation import make_world
    from slam.config import SlamConfig
    from slam.odometry import scans_points_base
    from slam.system import run_slam

    out_dir.mkdir(parents=True, exist_ok=True)
    cfg = SlamConfig()
    oc = cfg.odometry
    data = SHARED_DATA_DIR
    raw = open_dataset(data / "intel" / "intel.clf.bz2")
    gfs = open_dataset(data / "intel" / "intel.gfs.log")
    idx = match_scans(gfs, raw)
    res = run_slam(raw.scans, raw.scan_poses, raw.laser_in_base_xytheta, cfg)
    sc = raw.scans
    pts = scans_points_base(sc, raw.laser_in_base_xytheta, oc)
    plot_before_after(
        out_dir / "intel_before_after.png",
        res,
        pts,
        gfs.reference.poses_xytheta,
        idx,
        "intel.clf: scan-to-submap odometry, then loop closure (green); black: intel.gfs.log",
    )
    rec = make_world("loop", 0).recording
    res = run_slam(rec.scans, rec.odometry, rec.laser_in_base_xytheta, cfg)
    sc = rec.scans
    pts = scans_points_base(sc, rec.laser_in_base_xytheta, oc)
    plot_before_after(
        out_dir / "loop_before_after.png",
        res,
        pts,
        rec.reference.poses_xytheta,
        np.arange(len(sc)),
        "simulated loop world, seed 0; black: ground truth",
        every=3,
    )


if __name__ == "__main__":  # pragma: no cover
    _main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path("docs/figures/slam"))
