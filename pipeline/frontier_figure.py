"""The exploration figure of ``docs/figures/frontier_loop.png``: a run folder's map with its frontier cells,
the expected variance reduction of the next-best views and the views themselves (:mod:`mapping.frontier`).

``python -m pipeline.frontier_figure [RUN_DIR [OUT_PNG]]`` (default: ``out/demo/run``, the ``loop`` world of
``run.py demo``, and ``docs/figures/frontier_loop.png``).
"""

from __future__ import annotations

import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import yaml
from matplotlib import patheffects
from matplotlib.colors import ListedColormap

from mapping.exports import UNKNOWN_VARIANCE_FRACTION, MapLayers, read_layers_npz
from mapping.frontier import ExplorationPlan, ExplorationSettings, plan_exploration
from mapping.train import GPParams

REPO = Path(__file__).resolve().parent.parent
DEFAULT_RUN = REPO / "out" / "demo" / "run"
DEFAULT_OUT = REPO / "docs" / "figures" / "frontier_loop.png"


def run_settings(run_dir: Path, n_views: int = 5) -> ExplorationSettings:
    """Exploration settings with the thresholds of the run's ``config.yaml`` (``mapping.free_threshold``,
    ``mapping.occupied_threshold``, ``export.unknown_variance_fraction``; defaults where absent). The file is
    read as plain YAML, not validated, so that folders written by older versions still load."""
    cfg_path = Path(run_dir) / "config.yaml"
    raw = yaml.safe_load(cfg_path.read_text()) if cfg_path.exists() else {}
    mapping = (raw or {}).get("mapping") or {}
    export = (raw or {}).get("export") or {}
    return ExplorationSettings(
        free_threshold=float(mapping.get("free_threshold", 0.35)),
        occupied_threshold=float(mapping.get("occupied_threshold", 0.65)),
        unknown_variance_fraction=float(export.get("unknown_variance_fraction", UNKNOWN_VARIANCE_FRACTION)),
        n_views=n_views,
    )


def plot_exploration(
    layers: MapLayers,
    plan: ExplorationPlan,
    path: Path,
    title: str = "",
    width_in: float = 11.0,
    dpi: int = 110,
) -> Path:
    """p(occupied) in grey, unknown cells tinted blue, frontier cells red, the expected variance reduction
    of the next-best views as a heat map and the views as numbered arrows (best first)."""
    h, w = layers.shape
    x0, y0 = layers.origin_xy_m
    r = layers.resolution_m
    ext = (x0, x0 + w * r, y0, y0 + h * r)
    fig, ax = plt.subplots(figsize=(width_in, max(3.0, width_in * h / w * 0.95 + 0.8)))
    ax.imshow(layers.probability, origin="lower", extent=ext, cmap="gray_r", vmin=0.0, vmax=1.0)
    tint = np.ma.masked_where(~plan.knowledge.unknown, np.ones(layers.shape))
    ax.imshow(tint, origin="lower", extent=ext, cmap=ListedColormap(["#6a8fd0"]), alpha=0.35)
    info = np.ma.masked_where(plan.information <= 1e-6, plan.information)
    if info.count():
        im = ax.imshow(info, origin="lower", extent=ext, cmap="YlOrBr", alpha=0.75, vmin=0.0)
        fig.colorbar(im, ax=ax, label="expected variance reduction per cell", fraction=0.03, pad=0.01)
    front = np.ma.masked_where(~plan.frontier, np.ones(layers.shape))
    ax.imshow(front, origin="lower", extent=ext, cmap=ListedColormap(["red"]), interpolation="nearest")
    cand = plan.candidates_xytheta
    if cand.size:
        ax.plot(cand[:, 0], cand[:, 1], ".", color="tab:green", ms=2.5, label="candidate positions")
    views = plan.views_xytheta
    arrow = 0.05 * (ext[1] - ext[0])
    for i, (x, y, th) in enumerate(views):
        ax.annotate(
            "",
            xy=(x + arrow * np.cos(th), y + arrow * np.sin(th)),
            xytext=(x, y),
            annotation_clip=False,
            arrowprops={
                "arrowstyle": "-|>,head_length=0.5,head_width=0.3",
                "color": "tab:blue",
                "lw": 2.0,
                "path_effects": [patheffects.withStroke(linewidth=3.5, foreground="white")],
            },
        )
        ax.annotate(
            str(i + 1),
            xy=(x, y),
            xytext=(-9 * np.cos(th), -9 * np.sin(th)),
            textcoords="offset points",
            ha="center",
            va="center",
            fontsize=8,
            fontweight="bold",
            color="tab:blue",
            bbox={"boxstyle": "circle,pad=0.15", "fc": "white", "ec": "tab:blue", "lw": 0.8},
        )
    ax.plot([], [], "s", color="red", ms=5, label="frontier cells")
    ax.plot([], [], "s", color="#6a8fd0", alpha=0.5, ms=5, label="unknown (variance)")
    ax.plot([], [], "-", color="tab:blue", lw=1.8, label="next-best views (rank)")
    ax.legend(loc="upper left", fontsize=7, framealpha=0.85)
    ax.set_xlim(ext[0], ext[1])
    ax.set_ylim(ext[2], ext[3])
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi, bbox_inches="tight")
    plt.close(fig)
    return path


def write_frontier_figure(
    run_dir: Path = DEFAULT_RUN, out_png: Path = DEFAULT_OUT, which: str = "after", n_views: int = 5
) -> tuple[Path, ExplorationPlan]:
    """Plan on ``run_dir/maps/{which}/layers.npz`` with ``run_dir/maps/params.json`` and write the figure;
    returns its path and the plan."""
    run_dir = Path(run_dir)
    layers = read_layers_npz(run_dir / "maps" / which / "layers.npz")
    params = GPParams.load(run_dir / "maps" / "params.json")
    settings = run_settings(run_dir, n_views)
    plan = plan_exploration(layers, params, settings)
    laser = settings.laser
    title = (
        f"{which} loop closure: {int(plan.frontier.sum())} frontier cells in {len(plan.clusters)} clusters, "
        f"{len(plan.views_xytheta)} next-best views ({np.degrees(laser.fov_rad):.0f} deg, "
        f"{laser.range_max_m:g} m laser)"
    )
    return plot_exploration(layers, plan, out_png, title), plan


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    run_dir = Path(args[0]) if args else DEFAULT_RUN
    out = Path(args[1]) if len(args) > 1 else DEFAULT_OUT
    path, plan = write_frontier_figure(run_dir, out)
    gains = ", ".join(f"{g:.0f}" for g in plan.view_gains)
    sys.stdout.write(f"{path}: views {plan.views_xytheta.round(2).tolist()}, gains {gains}\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
