"""Figures of maps and metrics (matplotlib, Agg backend; small PNGs).

Every function takes arrays and writes one PNG; nothing here reads recordings.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.colors import ListedColormap
from numpy.typing import NDArray

from mapping.exports import MapLayers
from mapping.gpmap import classify

CLASS_CMAP = ListedColormap(["0.55", "white", "black"])  # unsure (-1), free (0), occupied (1)
_CLASS_STYLE = {"cmap": CLASS_CMAP, "vmin": -1, "vmax": 1, "interpolation": "nearest"}
_PROB_STYLE = {"cmap": "gray_r", "vmin": 0.0, "vmax": 1.0}


def _extent(layers: MapLayers) -> tuple[float, float, float, float]:
    h, w = layers.shape
    x0, y0 = layers.origin_xy_m
    r = layers.resolution_m
    return x0, x0 + w * r, y0, y0 + h * r


def _finish(fig, path: Path, dpi: int) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi, bbox_inches="tight")
    plt.close(fig)
    return path


def _size(layers: MapLayers, width_in: float) -> tuple[float, float]:
    h, w = layers.shape
    return width_in, max(2.5, width_in * h / w * 0.9)


def plot_layer(
    layers: MapLayers,
    which: str,
    path: Path,
    title: str = "",
    path_xy_m: NDArray | None = None,
    width_in: float = 7.0,
    dpi: int = 110,
) -> Path:
    """One layer (``probability``, ``variance`` or ``mean``) with a colour bar and, optionally, the robot's
    path (N, 2)."""
    data = getattr(layers, which)
    fig, ax = plt.subplots(figsize=_size(layers, width_in))
    if which == "probability":
        im = ax.imshow(data, origin="lower", extent=_extent(layers), cmap="gray_r", vmin=0.0, vmax=1.0)
        label = "p(occupied)"
    elif which == "variance":
        im = ax.imshow(data, origin="lower", extent=_extent(layers), cmap="viridis")
        label = "GP variance"
    else:
        im = ax.imshow(data, origin="lower", extent=_extent(layers), cmap="RdBu_r")
        label = "GP mean"
    if path_xy_m is not None:
        ax.plot(path_xy_m[:, 0], path_xy_m[:, 1], "r-", lw=0.6, alpha=0.8)
    fig.colorbar(im, ax=ax, label=label, fraction=0.046, pad=0.02)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title)
    return _finish(fig, path, dpi)


def plot_classified(
    layers: MapLayers,
    path: Path,
    occupied_threshold: float = 0.65,
    free_threshold: float = 0.35,
    title: str = "",
    width_in: float = 7.0,
    dpi: int = 110,
) -> Path:
    """Occupied (black, p >= occupied_threshold), free (white, p <= free_threshold), unsure (grey)."""
    cls = classify(layers.probability, occupied_threshold, free_threshold)
    fig, ax = plt.subplots(figsize=_size(layers, width_in))
    ax.imshow(cls, origin="lower", extent=_extent(layers), **_CLASS_STYLE)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title or f"occupied p >= {occupied_threshold}, free p <= {free_threshold}, grey unsure")
    return _finish(fig, path, dpi)


def plot_roc(
    curves: Mapping[str, tuple[NDArray, NDArray, float]], path: Path, title: str = "", dpi: int = 110
) -> Path:
    """ROC curves: ``{name: (fpr, tpr, auc)}``, with the chance diagonal."""
    fig, ax = plt.subplots(figsize=(4.6, 4.4))
    ax.plot([0, 1], [0, 1], "--", color="0.6", lw=1, label="random guess (0.5)")
    for name, (fpr, tpr, auc) in curves.items():
        ax.plot(fpr, tpr, lw=1.6, label=f"{name} (AUC {auc:.4f})")
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1.005)
    ax.set_xlabel("false-positive rate")
    ax.set_ylabel("true-positive rate")
    ax.set_title(title)
    ax.legend(loc="lower right", fontsize=8)
    ax.grid(alpha=0.3)
    return _finish(fig, path, dpi)


def plot_street_panels(
    ground_truth: NDArray,
    gt_origin_xy_m: tuple[float, float],
    gt_resolution_m: float,
    hits_xy_m: NDArray,
    poses_xy_m: NDArray,
    grid_probability: MapLayers,
    gp: MapLayers,
    path: Path,
    occupied_threshold: float = 0.65,
    free_threshold: float = 0.35,
    dpi: int = 90,
) -> Path:
    """The six panels of the paper's Figure 6: (a) ground truth, (b) laser returns and robot poses,
    (c) occupancy grid, (d) GP variance, (e) GP p(occupied), (f) classified GP map."""
    h, w = ground_truth.shape
    ox, oy = gt_origin_xy_m
    ext = (ox, ox + w * gt_resolution_m, oy, oy + h * gt_resolution_m)
    fig, axes = plt.subplots(3, 2, figsize=(11, 3 * 11 / 2 * h / w + 1.5))
    a = axes.ravel()
    a[0].imshow(ground_truth, origin="lower", extent=ext, interpolation="nearest", **_PROB_STYLE)
    a[0].plot(poses_xy_m[:, 0], poses_xy_m[:, 1], "r.", ms=3)
    a[0].set_title("(a) ground truth and robot poses")
    a[1].plot(hits_xy_m[:, 0], hits_xy_m[:, 1], "k.", ms=1.5)
    a[1].plot(poses_xy_m[:, 0], poses_xy_m[:, 1], "r.", ms=3)
    a[1].set_xlim(ext[0], ext[1])
    a[1].set_ylim(ext[2], ext[3])
    a[1].set_aspect("equal")
    a[1].set_title("(b) laser returns and robot poses")
    a[2].imshow(grid_probability.probability, origin="lower", extent=_extent(grid_probability), **_PROB_STYLE)
    a[2].set_title("(c) occupancy grid p(occupied)")
    im = a[3].imshow(gp.variance, origin="lower", extent=_extent(gp), cmap="viridis")
    fig.colorbar(im, ax=a[3], fraction=0.03, pad=0.02)
    a[3].set_title("(d) GP predictive variance")
    im = a[4].imshow(gp.probability, origin="lower", extent=_extent(gp), cmap="gray_r", vmin=0, vmax=1)
    fig.colorbar(im, ax=a[4], fraction=0.03, pad=0.02)
    a[4].set_title("(e) GP p(occupied)")
    cls = classify(gp.probability, occupied_threshold, free_threshold)
    a[5].imshow(cls, origin="lower", extent=_extent(gp), **_CLASS_STYLE)
    a[5].set_title(f"(f) classified: black p >= {occupied_threshold}, white p <= {free_threshold}")
    for ax in a:
        ax.tick_params(labelsize=7)
    fig.tight_layout()
    return _finish(fig, path, dpi)


def plot_before_after_maps(
    before: MapLayers,
    after: MapLayers,
    path: Path,
    path_before_xy_m: NDArray | None = None,
    path_after_xy_m: NDArray | None = None,
    closures_xy_m: NDArray | None = None,
    titles: tuple[str, str] = ("before loop closure", "after loop closure"),
    width_in: float = 12.0,
    dpi: int = 100,
) -> Path:
    """Two probability maps side by side with one colour bar, each with its trajectory (N, 2); loop
    closures ``closures_xy_m`` (C, 2, 2) (query and target positions on the ``after`` trajectory) are drawn
    on the right panel."""
    h, w = after.shape
    fig, axes = plt.subplots(1, 2, figsize=(width_in, max(3.0, width_in / 2 * h / w * 0.95 + 0.6)))
    im = None
    for ax, layers, traj, title in zip(
        axes, (before, after), (path_before_xy_m, path_after_xy_m), titles, strict=True
    ):
        im = ax.imshow(layers.probability, origin="lower", extent=_extent(layers), **_PROB_STYLE)
        if traj is not None and len(traj):
            ax.plot(traj[:, 0], traj[:, 1], "-", color="tab:red", lw=0.7, alpha=0.85, label="trajectory")
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        ax.set_title(title, fontsize=10)
    if closures_xy_m is not None and len(closures_xy_m):
        for k, seg in enumerate(np.asarray(closures_xy_m)):
            axes[1].plot(
                seg[:, 0], seg[:, 1], "-", color="tab:green", lw=0.6, label="loop closure" if k == 0 else None
            )
    for ax in axes:
        if ax.get_legend_handles_labels()[0]:
            ax.legend(loc="lower right", fontsize=7)
    fig.colorbar(im, ax=axes, label="p(occupied)", fraction=0.025, pad=0.02)
    return _finish(fig, path, dpi)


def plot_method_rows(
    rows: Mapping[str, MapLayers],
    path: Path,
    occupied_threshold: float = 0.65,
    free_threshold: float = 0.35,
    tracks_xy_m: Mapping[str, NDArray] | None = None,
    width_in: float = 9.0,
    dpi: int = 60,
) -> Path:
    """The paper's Figure 9: one row per method ``{name: layers}``, p(occupied) on the left and the
    classified map on the right; ``tracks_xy_m`` ``{label: (N, 2)}`` drawn on the first probability panel."""
    first = next(iter(rows.values()))
    h, w = first.shape
    n = len(rows)
    fig, axes = plt.subplots(n, 2, figsize=(width_in, n * width_in / 2 * h / w + 0.6 * n), squeeze=False)
    for k, (name, layers) in enumerate(rows.items()):
        a0, a1 = axes[k]
        a0.imshow(layers.probability, origin="lower", extent=_extent(layers), cmap="jet", vmin=0, vmax=1)
        a0.set_title(f"({'abcdefgh'[k]}) {name}: p(occupied)", fontsize=9)
        cls = classify(layers.probability, occupied_threshold, free_threshold)
        a1.imshow(cls, origin="lower", extent=_extent(layers), **_CLASS_STYLE)
        a1.set_title(f"{name}: classified (black occ., white free, grey unsure)", fontsize=9)
        for ax in (a0, a1):
            ax.tick_params(labelsize=7)
    for (label, xy), colour in zip((tracks_xy_m or {}).items(), ("w", "m", "c"), strict=False):
        axes[0, 0].plot(xy[:, 0], xy[:, 1], ".", color=colour, ms=1.5, label=label)
    if tracks_xy_m:
        axes[0, 0].legend(loc="lower right", fontsize=6, markerscale=4)
    fig.tight_layout()
    return _finish(fig, path, dpi)


def plot_variance_pair(
    layers: Mapping[str, MapLayers], path: Path, width_in: float = 10.0, dpi: int = 70
) -> Path:
    """The paper's Figure 10: the predictive variance of each method ``{name: layers}`` side by side, each
    with its own colour bar (logarithmic, so that low variances of well-observed areas stay apart)."""
    from matplotlib.colors import LogNorm

    first = next(iter(layers.values()))
    h, w = first.shape
    n = len(layers)
    fig, axes = plt.subplots(1, n, figsize=(width_in, width_in / n * h / w + 0.8), squeeze=False)
    for k, (name, lay) in enumerate(layers.items()):
        ax = axes[0, k]
        v = np.asarray(lay.variance, dtype=np.float64)
        norm = LogNorm(vmin=max(float(np.percentile(v, 0.5)), 1e-4), vmax=max(float(v.max()), 2e-4))
        im = ax.imshow(
            np.maximum(v, norm.vmin), origin="lower", extent=_extent(lay), cmap="viridis", norm=norm
        )
        fig.colorbar(im, ax=ax, fraction=0.03, pad=0.02)
        ax.set_title(f"({'abcdefgh'[k]}) {name}: predictive variance (log scale)", fontsize=9)
        ax.tick_params(labelsize=7)
    fig.tight_layout()
    return _finish(fig, path, dpi)
