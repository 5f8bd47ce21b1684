"""Figures of simulated worlds: ground truth, true trajectories, beams and returns, drifting odometry.

``write_docs_figures(out_dir)`` regenerates the PNGs under ``docs/figures/simulation/`` (seed 0):

    python -c "from datasets.simulation.figures import write_docs_figures; write_docs_figures()"
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from datasets.se2 import compose
from datasets.simulation.recording import SimulatedRun

DOCS_DIR = Path(__file__).resolve().parents[2] / "docs" / "figures" / "simulation"
# (poses, returns) per platform, as in the paper's Figure 8
COLORS = (("tab:orange", "tab:green"), ("tab:red", "tab:blue"))


def plot_run(run: SimulatedRun, path: str | Path, beams_every: int = 1, dpi: int = 110) -> None:
    """Draw ``run`` into a PNG: ground truth (grey), per platform its poses, beams and returns; for drifting
    odometry also the odometry trajectory (aligned at the start) against the truth."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection

    gt = run.ground_truth
    xmin, ymin, xmax, ymax = gt.bounds_xy_m
    width = 7.5
    fig, ax = plt.subplots(figsize=(width, width * (ymax - ymin) / (xmax - xmin) + 0.9))
    ax.imshow(
        np.where(gt.occupancy == 1, 0.35, 1.0),
        cmap="gray",
        vmin=0,
        vmax=1,
        origin="lower",
        extent=(xmin, xmax, ymin, ymax),
        interpolation="nearest",
    )
    scans = run.recording.scans
    assert scans is not None
    truth = run.true_poses.poses_xytheta
    for i, platform in enumerate(run.platforms):
        pose_color, hit_color = COLORS[i % 2]
        idx = np.flatnonzero(scans.source_index == i)
        sel = idx[::beams_every]
        lasers = compose(truth[sel], platform.laser_in_base_xytheta[None, :])
        segs, hits = [], []
        for k, lp in zip(sel, lasers, strict=True):
            r = scans.ranges_m[k].astype(np.float64)
            a = scans.angles_rad[k].astype(np.float64) + lp[2]
            ok = np.isfinite(r) & (r >= scans.range_min_m[k])
            length = np.where(ok, r, scans.range_max_m[k])
            ends = lp[:2] + np.stack([np.cos(a), np.sin(a)], axis=1) * length[:, None]
            segs.append(np.stack([np.broadcast_to(lp[:2], ends.shape), ends], axis=1))
            hits.append(ends[ok])
        if segs:
            ax.add_collection(
                LineCollection(np.concatenate(segs), colors=hit_color, linewidths=0.3, alpha=0.25)
            )
            h = np.concatenate(hits)
            ax.plot(h[:, 0], h[:, 1], ".", color=hit_color, ms=1.5, label=f"{platform.laser.topic} returns")
        dense = platform.truth_dense.poses_xytheta
        ax.plot(dense[:, 0], dense[:, 1], "-", color=pose_color, lw=0.8)
        ax.plot(
            truth[idx, 0],
            truth[idx, 1],
            "o",
            color=pose_color,
            ms=2.5,
            label=f"{platform.name} poses",
            zorder=4 + len(run.platforms) - i,  # the first (slowest) platform on top
        )
        if platform.odometry_noise is not None:
            odo = platform.odometry.poses_xytheta
            ax.plot(odo[:, 0], odo[:, 1], "--", color="magenta", lw=1.0, label="wheel odometry")
            end_err = float(np.hypot(*(odo[-1, :2] - dense[-1, :2])))
            ax.annotate(
                f"odometry error at the end: {end_err:.1f} m",
                xy=(odo[-1, 0], odo[-1, 1]),
                xytext=(0.02, 0.02),
                textcoords="axes fraction",
                color="magenta",
                fontsize=8,
            )
    ax.set_xlim(xmin, xmax)
    ax.set_ylim(ymin, ymax)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(
        f"{run.name} (seed {run.seed}): {len(scans)} scans, {run.world.area_m2:,.0f} m$^2$", fontsize=10
    )
    ax.legend(loc="upper right", fontsize=7, markerscale=3, framealpha=0.85)
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, dpi=dpi, format="png", metadata={"Software": None})
    plt.close(fig)
    _save_small_png(buffer, path)


def _save_small_png(buffer: io.BytesIO, path: str | Path, colors: int = 96) -> None:
    """Re-encode a PNG with a palette of ``colors`` (figures stay well under 200 KB)."""
    from PIL import Image

    buffer.seek(0)
    with Image.open(buffer) as img:
        img.convert("RGB").quantize(colors=colors, dither=Image.Dither.NONE).save(path, optimize=True)


def write_docs_figures(out_dir: str | Path = DOCS_DIR, seed: int = 0) -> list[Path]:
    """Write ``{street,two-platform,loop}.png`` into ``out_dir``; returns their paths."""
    from datasets.simulation.scenarios import make_world

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, every in (("street", 1), ("two-platform", 1), ("loop", 25)):
        p = out / f"{name}.png"
        plot_run(make_world(name, seed), p, beams_every=every)
        paths.append(p)
    return paths
