"""Side-by-side figure of the maps of several run folders: one row per run, before / after loop closure.

``python -m pipeline.compare_figure RUN_DIR [RUN_DIR ...] --out PNG`` draws each run's classified maps
(``maps/{before,after}/layers.npz``: black occupied, white free, grey unknown, as the exports classify them)
on a common scale, with each map's occupied / free / unknown cell shares in its title. Made for comparing
mappers or configurations on one recording (the GPPOL / GPFOL figures of docs/mapping.md); the maps are
reduced by ``--step`` cells per pixel, keeping the most informative class of each block (occupied over free
over unknown), so that thin walls survive the reduction.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from mapping.exports import MapLayers, read_layers_npz
from mapping.figures import downsample

#: Class codes of a reduced panel: the maximum over a block wins, so occupied beats free beats unknown.
UNKNOWN_CODE, FREE_CODE, OCCUPIED_CODE = 0, 1, 2


def class_codes(layers: MapLayers) -> NDArray[np.uint8]:
    """(H, W) class code of every cell (``UNKNOWN_CODE`` / ``FREE_CODE`` / ``OCCUPIED_CODE``) from the
    planners' classification (:meth:`MapLayers.occupancy_values`)."""
    values = layers.occupancy_values()
    codes = np.full(values.shape, UNKNOWN_CODE, np.uint8)
    codes[values == 100] = OCCUPIED_CODE
    codes[values == 0] = FREE_CODE
    return codes


def panel_title(label: str, layers: MapLayers) -> str:
    """``label`` with the map's occupied / free / unknown cell shares (percent)."""
    s = layers.cell_shares()
    shares = " / ".join(f"{100 * s[k]:.1f}" for k in ("occupied", "free", "unknown"))
    return f"{label}: occupied / free / unknown {shares} %"


def run_label(run_dir: Path) -> str:
    """A run's row label: its folder name and its mapper (from ``summary.json`` when present)."""
    summary = run_dir / "summary.json"
    if summary.is_file():
        s = json.loads(summary.read_text())
        mapper = s.get("mapper", "?")
        cov = (s.get("map") or {}).get("pose_covariances")
        return f"{mapper}" + (f" ({cov} pose cov.)" if mapper == "gppol" and cov else "")
    return run_dir.name


def compare_figure(
    run_dirs: list[Path], out: Path, step: int = 4, width_in: float = 12.0, dpi: int = 80
) -> Path:
    """Write the comparison PNG ``out`` of the runs ``run_dirs`` (rows) before / after loop closure
    (columns), each map reduced by ``step`` cells per pixel."""
    import matplotlib.pyplot as plt
    from matplotlib.colors import ListedColormap

    cmap = ListedColormap(["0.6", "white", "black"])
    maps = [
        {w: read_layers_npz(d / "maps" / w / "layers.npz") for w in ("before", "after")} for d in run_dirs
    ]
    h, w = maps[0]["after"].shape
    rows = len(run_dirs)
    fig, axes = plt.subplots(
        rows, 2, figsize=(width_in, rows * (width_in / 2) * h / w + 0.5 * rows), squeeze=False
    )
    for r, (run_dir, pair) in enumerate(zip(run_dirs, maps, strict=True)):
        for c, which in enumerate(("before", "after")):
            layers = pair[which]
            codes = downsample(class_codes(layers), step, how="max")
            x0, y0 = layers.origin_xy_m
            hh, ww = layers.shape
            extent = (x0, x0 + ww * layers.resolution_m, y0, y0 + hh * layers.resolution_m)
            ax = axes[r, c]
            ax.imshow(
                codes, origin="lower", extent=extent, cmap=cmap, vmin=0, vmax=2, interpolation="nearest"
            )
            ax.set_title(panel_title(f"{run_label(run_dir)}, {which}", layers), fontsize=8)
            ax.tick_params(labelsize=6)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=dpi)
    plt.close(fig)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m pipeline.compare_figure", description=__doc__.splitlines()[0]
    )
    ap.add_argument("runs", nargs="+", type=Path, help="run folders (one row each)")
    ap.add_argument("--out", type=Path, required=True, help="PNG to write")
    ap.add_argument("--step", type=int, default=4, help="map cells per pixel (default 4)")
    args = ap.parse_args(argv)
    sys.stdout.write(f"{compare_figure(args.runs, args.out, args.step)}\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
