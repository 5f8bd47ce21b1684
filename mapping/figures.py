"""Figures of maps and metrics (matplotlib, Agg backend).

Every ``plot_*`` function takes arrays and writes one PNG; nothing here reads recordings. The figures of a
run folder (``plot_layer``, ``plot_classified``, ``plot_before_after_maps``, ``plot_difference``,
``plot_trajectory_covariances``) are drawn at the map's native resolution: every map cell gets at least one
pixel (small maps an integer number of pixels per cell, see :func:`map_view`), and each has a builder
(``*_figure``) returning the :class:`matplotlib.figure.Figure`, so that its legend and colour bar can be
inspected before it is saved. The documentation figures (``plot_roc``, ``plot_street_panels``,
``plot_method_rows``, ``plot_variance_pair``) stay small overviews.
"""

from __future__ import annotations

import gc
import textwrap
from collections.abc import Iterator, Mapping, Sequence
from concurrent.futures import Executor, Future, wait
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numba as nb
import numpy as np
from matplotlib import patheffects
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import EllipseCollection
from matplotlib.colors import CenteredNorm, ListedColormap
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch
from numpy.typing import NDArray
from PIL import Image

from mapping.exports import MapLayers, finite_range
from mapping.gpmap import FREE, OCCUPIED, UNSURE, classify

CLASS_CMAP = ListedColormap(["0.55", "white", "black"])  # unsure (-1), free (0), occupied (1)
_CLASS_STYLE = {"cmap": CLASS_CMAP, "vmin": -1, "vmax": 1, "interpolation": "nearest"}
_PROB_STYLE = {"cmap": "gray_r", "vmin": 0.0, "vmax": 1.0}

#: Resolution of the run-folder figures (pixels per inch); layouts are computed in whole pixels.
DPI = 100
#: A map whose longer side has fewer cells is drawn with an integer number of pixels per cell so that this
#: side spans at least this many pixels.
MIN_MAP_PX = 800
#: The most map cells one panel shows at one pixel each: 16 million (4,000 x 4,000 cells, 400 m x 400 m at
#: 0.1 m). Matplotlib's Agg renderer holds several float copies of an image while drawing it (tens of bytes
#: per pixel), so this keeps a figure near a gigabyte of memory; a larger map (a 1e8-cell map, say) is shown
#: downsampled by the smallest integer factor that fits (block means, see :func:`map_view`), and its title
#: says so.
MAX_PANEL_CELLS = 16_000_000
#: The longest side of one panel in pixels (Agg refuses images wider than 2**16 pixels in all).
MAX_PANEL_SIDE_PX = 30_000

#: Colours of the classified map (display codes 0..3: free, unknown, unsure, occupied).
FREE_COLOUR = "white"
UNKNOWN_COLOUR = "#8fb8de"
UNSURE_COLOUR = "0.6"
OCCUPIED_COLOUR = "black"
_DISPLAY_CLASS_CMAP = ListedColormap([FREE_COLOUR, UNKNOWN_COLOUR, UNSURE_COLOUR, OCCUPIED_COLOUR])
_D_FREE, _D_UNKNOWN, _D_UNSURE, _D_OCCUPIED = 0, 1, 2, 3

#: Colours of the trajectories and of the loop closures in the run-folder figures.
TRAJECTORY_COLOURS = {"before": "tab:red", "after": "tab:blue"}
CLOSURE_COLOUR = "#00c853"

# Layout of the run-folder figures, in pixels at DPI.
_LEFT_PX = 90  # y tick labels and the y label
_GAP_PX = 90  # between panels (the right panel's y tick labels)
_BOTTOM_PX = 50  # x tick labels and the x label
_LEGEND_ROW_PX = 24
_TITLE_LINE_PX = 19
_PANEL_TITLE_PX = 24
_MIN_PANEL_H_PX = 260  # room for a readable colour bar beside a flat map
_MIN_FIG_W_PX = 720
_COLORBAR_W_PX = 18


@dataclass(frozen=True)
class MapView:
    """How a (H, W) layer is drawn: blocks of ``step`` x ``step`` cells become one displayed cell (1: every
    cell shown), and each displayed cell is ``px_per_cell`` x ``px_per_cell`` pixels."""

    shape_hw: tuple[int, int]
    step: int
    px_per_cell: int

    @property
    def shown_hw(self) -> tuple[int, int]:
        """Displayed cells (rows, columns)."""
        h, w = self.shape_hw
        return -(-h // self.step), -(-w // self.step)

    @property
    def size_px(self) -> tuple[int, int]:
        """The panel's size in pixels (width, height)."""
        h, w = self.shown_hw
        return w * self.px_per_cell, h * self.px_per_cell

    @property
    def downsampled(self) -> bool:
        return self.step > 1

    def note(self) -> str:
        """The title's note on a downsampled map ("" at native resolution)."""
        if not self.downsampled:
            return ""
        h, w = self.shape_hw
        return f" [downsampled for display: {w} x {h} cells, {self.step} x {self.step} cells per pixel]"


def map_view(
    shape_hw: tuple[int, int], max_cells: int | None = None, max_side_px: int | None = None
) -> MapView:
    """At least one pixel per cell, up to ``max_cells`` cells (default :data:`MAX_PANEL_CELLS`) and
    ``max_side_px`` pixels a side (default :data:`MAX_PANEL_SIDE_PX`) per panel; beyond, the smallest
    integer downsampling factor that fits. A small map gets an integer number of pixels per cell so that its
    longer side spans at least :data:`MIN_MAP_PX` pixels."""
    max_cells = MAX_PANEL_CELLS if max_cells is None else max_cells
    max_side_px = MAX_PANEL_SIDE_PX if max_side_px is None else max_side_px
    h, w = (max(1, int(v)) for v in shape_hw)
    step = 1
    while -(-h // step) * -(-w // step) > max_cells or max(-(-h // step), -(-w // step)) > max_side_px:
        step += 1
    px = max(1, -(-MIN_MAP_PX // max(h, w))) if step == 1 else 1
    return MapView((h, w), step, px)


def downsample(array: NDArray, step: int, how: str = "mean") -> NDArray:
    """(H, W) -> (ceil(H/step), ceil(W/step)): the finite mean (``"mean"``, float32, NaN where a block has
    no finite value) or the maximum (``"max"``, same dtype) of each ``step`` x ``step`` block. Works one row
    of blocks at a time, so that a huge map is never copied whole."""
    a = np.asarray(array)
    if step == 1:
        return a
    if how not in ("mean", "max"):
        raise ValueError(f"downsample: how must be 'mean' or 'max', not {how!r}")
    h, w = a.shape
    hh, ww = -(-h // step), -(-w // step)
    mean = how == "mean"
    dtype = np.float32 if mean else a.dtype
    fill = np.nan if mean else (False if a.dtype == bool else np.iinfo(a.dtype).min)
    out = np.empty((hh, ww), dtype=dtype)
    for i in range(hh):
        band = np.full((step, ww * step), fill, dtype=dtype)
        rows = a[i * step : (i + 1) * step]
        band[: rows.shape[0], :w] = rows
        blocks = band.reshape(step, ww, step)
        if mean:
            finite = np.isfinite(blocks)
            total = np.where(finite, blocks, 0.0).sum(axis=(0, 2), dtype=np.float64)
            count = finite.sum(axis=(0, 2))
            with np.errstate(invalid="ignore", divide="ignore"):
                out[i] = np.where(count > 0, total / np.maximum(count, 1), np.nan)
        else:
            out[i] = blocks.max(axis=(0, 2))
    return out


def _extent(layers: MapLayers) -> tuple[float, float, float, float]:
    h, w = layers.shape
    x0, y0 = layers.origin_xy_m
    r = layers.resolution_m
    return x0, x0 + w * r, y0, y0 + h * r


def _view_extent(layers: MapLayers, view: MapView) -> tuple[float, float, float, float]:
    """The world extent of the displayed cells (a downsampled map's last blocks may reach past the map)."""
    h, w = view.shown_hw
    x0, y0 = layers.origin_xy_m
    r = layers.resolution_m * view.step
    return x0, x0 + w * r, y0, y0 + h * r


def _finish(fig, path: Path, dpi: int) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi, bbox_inches="tight")
    plt.close(fig)
    return path


#: Where :func:`save_figure` hands its PNG encoding (an executor and the futures it has handed over), within
#: :func:`png_encoding_in`.
_PNG_ENCODER: ContextVar[tuple[Executor, list[Future]] | None] = ContextVar("png_encoder", default=None)


@contextmanager
def png_encoding_in(pool: Executor) -> Iterator[None]:
    """Within the block, :func:`save_figure` encodes and writes its pasted PNGs in ``pool`` (the encoder
    releases the GIL, so the next figure is drawn meanwhile); the block ends when they are written, and
    re-raises the first error of one."""
    pending: list[Future] = []
    token = _PNG_ENCODER.set((pool, pending))
    try:
        yield
    except BaseException:
        wait(pending)  # the block's own error is the one to see
        raise
    finally:
        _PNG_ENCODER.reset(token)
    for future in pending:
        future.result()


@contextmanager
def collecting_new_objects_only() -> Iterator[None]:
    """Within the block, a collection (:func:`save_figure`'s, or the interpreter's own) walks only the
    objects made inside it: those alive before (a run's scans, beams and graph) are frozen
    (:func:`gc.freeze`) and thawed when it ends, so that collecting each dropped figure costs what the
    figures hold, not what the whole process holds. Garbage among the frozen objects waits for a collection
    after the block; an enclosing freeze is thawed too."""
    gc.freeze()
    try:
        yield
    finally:
        gc.unfreeze()


def _write_png(rgb: NDArray[np.uint8], path: Path) -> None:
    Image.fromarray(rgb).save(path, format="png", compress_level=PNG_COMPRESS_LEVEL)


def save_figure(fig: Figure, path: Path) -> Path:
    """Write a run-folder figure (built by a ``*_figure`` function) as a PNG at its own size; returns the
    path (within :func:`png_encoding_in`, the file is written when that block ends).

    The maps are pasted rather than drawn: matplotlib would resample each (H, W) map image to the pixels
    it already covers one to one, through masked float copies of the whole map, which is most of the
    time a big building's figures take. Here every panel's images are coloured once by their own colour
    map and norm (:meth:`~matplotlib.image.AxesImage.to_rgba`), the figure is drawn without them on a
    transparent panel, and the two are composited in uint8 (:func:`_paste_maps`). A figure whose images
    do not fill their panel at an integer number of pixels per cell is drawn by matplotlib as before."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # A figure is a web of reference cycles, so the figures drawn before this one (their canvases and
    # images: hundreds of megabytes for a big building) are freed only when the cycle collector runs, which
    # big numpy buffers do not prompt; collected here, their memory serves this figure.
    gc.collect()
    rgb = _paste_maps(fig)
    encoder = _PNG_ENCODER.get()
    if rgb is None:
        fig.savefig(path, dpi=fig.dpi, metadata={"Software": None})
    elif encoder is None:
        _write_png(rgb, path)
    else:
        pool, pending = encoder
        pending.append(pool.submit(_write_png, rgb, path))
    return path


#: zlib level of the pasted-map PNGs: the fastest, as encoding is most of a big map's figure time and the
#: files grow only a little.
PNG_COMPRESS_LEVEL = 1


def _panel_box_px(ax: Axes, image: Any, height_px: int) -> tuple[slice, slice, int] | None:
    """Where ``image`` lies in the figure's pixel rows and columns (top row first), and its pixels per
    cell, if it fills ``ax`` exactly at an integer number of pixels per cell with the cells drawn as
    squares of one colour; None otherwise."""
    if image.get_interpolation() != "nearest" or image.origin != "lower" or image.get_clip_path() is not None:
        return None
    data = image.get_array()
    if data is None or data.ndim not in (2, 3):
        return None
    h, w = data.shape[:2]
    x0, x1, y0, y1 = image.get_extent()
    if not (np.allclose((x0, x1), ax.get_xlim()) and np.allclose((y0, y1), ax.get_ylim())):
        return None
    box = ax.get_window_extent()
    bx0, by0, bx1, by1 = (round(v) for v in (box.x0, box.y0, box.x1, box.y1))
    if not np.allclose((box.x0, box.y0, box.x1, box.y1), (bx0, by0, bx1, by1), atol=1e-3):
        return None
    px = (bx1 - bx0) // w
    if px < 1 or px * w != bx1 - bx0 or px * h != by1 - by0:
        return None
    return slice(height_px - by1, height_px - by0), slice(bx0, bx1), px


@nb.njit(cache=True)
def _over(dst: NDArray[np.uint8], src: NDArray[np.uint8]) -> None:
    """Composite the straight-alpha (H, W, 4) uint8 ``src`` over the opaque (H, W, 3) uint8 ``dst`` in
    place (a compiled loop: numpy's masked blends of a 15-million-pixel figure take longer than its
    PNG encoding)."""
    h, w = src.shape[0], src.shape[1]
    for i in range(h):
        for j in range(w):
            a = np.uint16(src[i, j, 3])
            if a == 255:
                for c in range(3):
                    dst[i, j, c] = src[i, j, c]
            elif a > 0:
                for c in range(3):
                    dst[i, j, c] = np.uint8((src[i, j, c] * a + dst[i, j, c] * (255 - a) + 127) // 255)


#: Rows of a map image coloured at a time by :func:`_image_rgba`.
COLOUR_BAND_ROWS = 256


def _image_rgba(image: Any) -> NDArray[np.uint8]:
    """(H, W, 4) uint8: :meth:`~matplotlib.image.AxesImage.to_rgba` of the image's array, ``COLOUR_BAND_ROWS``
    rows at a time. Colouring by a scaled norm is cell by cell, so the bands give the same bytes; a big map's
    float temporaries (matplotlib's masked copies, the look-up indices) then stay a band's size."""
    values = image.get_array()
    alpha = image.get_alpha()
    if values.ndim != 2 or not image.norm.scaled() or np.ndim(alpha) != 0:
        return image.to_rgba(values, alpha=alpha, bytes=True)
    out = np.empty((*values.shape, 4), dtype=np.uint8)
    for r0 in range(0, values.shape[0], COLOUR_BAND_ROWS):
        band = slice(r0, r0 + COLOUR_BAND_ROWS)
        out[band] = image.to_rgba(values[band], alpha=alpha, bytes=True)
    return out


def _paste_maps(fig: Figure) -> NDArray[np.uint8] | None:
    """The (H, W, 3) uint8 pixels of ``fig`` with its map images pasted one to one (see
    :func:`save_figure`), or None when it has no image or one that does not fill its panel exactly."""
    width_px, height_px = (round(v) for v in fig.get_size_inches() * fig.dpi)
    panels = []
    for ax in fig.axes:
        images = sorted((im for im in ax.get_images() if im.get_visible()), key=lambda im: im.get_zorder())
        for image in images:
            where = _panel_box_px(ax, image, height_px)
            if where is None:
                return None
            panels.append((ax, image, where))
    if not panels:
        return None
    colours = [_image_rgba(image) for _, image, _ in panels]
    axes = {id(ax): ax for ax, _, _ in panels}.values()
    saved = [(ax, ax.patch.get_alpha()) for ax in axes]
    fig_alpha = fig.patch.get_alpha()
    try:
        for _, image, _ in panels:
            image.set_visible(False)
        for ax in axes:
            ax.patch.set_alpha(0.0)
        fig.patch.set_alpha(0.0)
        fig.canvas.draw()
        drawn = np.asarray(fig.canvas.buffer_rgba())
        if drawn.shape[:2] != (height_px, width_px):
            return None
        out = np.empty((height_px, width_px, 3), dtype=np.uint8)
        out[:] = np.round(np.asarray(matplotlib.colors.to_rgb(fig.get_facecolor())) * 255)
        for ax in axes:
            box = next(w for a, _, w in panels if a is ax)
            out[box[0], box[1]] = np.round(np.asarray(matplotlib.colors.to_rgb(ax.get_facecolor())) * 255)
        for (_, _, (rows, cols, px)), rgba in zip(panels, colours, strict=True):
            cells = rgba[::-1]  # origin "lower": the first row is the bottom one
            if px > 1:
                cells = np.repeat(np.repeat(cells, px, axis=0), px, axis=1)
            _over(out[rows, cols], cells)
        _over(out, drawn)
    finally:
        for _, image, _ in panels:
            image.set_visible(True)
        for ax, alpha in saved:
            ax.patch.set_alpha(alpha)
        fig.patch.set_alpha(fig_alpha)
    return out


def _ate_text(ate_m: float | None) -> str:
    return "" if ate_m is None or not np.isfinite(ate_m) else f" (ATE {ate_m:.3f} m)"


@dataclass
class _Canvas:
    """A figure laid out in whole pixels: ``panels`` map axes of ``w_px`` x ``h_px`` side by side, a right
    column ``right_px`` wide (colour bar), rows for a legend below and a wrapped title above."""

    fig: Figure
    axes: list[Axes]
    left_px: int
    bottom_px: int
    right_x_px: int
    w_px: int
    h_px: int

    def _frac(self, x_px: float, y_px: float, w_px: float, h_px: float) -> list[float]:
        fw, fh = self.fig.get_size_inches() * DPI
        return [x_px / fw, y_px / fh, w_px / fw, h_px / fh]

    def colorbar_axes(self) -> Axes:
        """An axes for a vertical colour bar in the right column, labelled ``"colorbar"``."""
        h = max(self.h_px, 200)
        return self.fig.add_axes(
            self._frac(self.right_x_px + 15, self.bottom_px, _COLORBAR_W_PX, h), label="colorbar"
        )

    def legend_below(self, handles: Sequence, ncol: int) -> None:
        """A legend under the panels (never over the map)."""
        fw, fh = self.fig.get_size_inches() * DPI
        self.fig.legend(
            handles=list(handles),
            loc="upper left",
            bbox_to_anchor=(self.left_px / fw, (self.bottom_px - _BOTTOM_PX + 4) / fh),
            ncol=ncol,
            frameon=False,
            fontsize=9,
            handlelength=2.2,
        )


def _canvas(
    w_px: int,
    h_px: int,
    title: str,
    panels: int = 1,
    right_px: int = 130,
    legend_entries: int = 0,
    panel_titles: bool = False,
) -> tuple[_Canvas, int]:
    """Lay out a figure around ``panels`` axes of exactly ``w_px`` x ``h_px`` pixels; returns the canvas and
    the number of legend columns to use."""
    width = max(_LEFT_PX + panels * w_px + (panels - 1) * _GAP_PX + right_px, _MIN_FIG_W_PX)
    ncol = legend_entries if width >= 1100 else min(legend_entries, 2)
    legend_rows = -(-legend_entries // ncol) if legend_entries else 0
    lines = textwrap.wrap(title, max(40, (width - _LEFT_PX) // 7)) if title else []
    bottom = _BOTTOM_PX + legend_rows * _LEGEND_ROW_PX + (8 if legend_rows else 0)
    content = max(h_px, _MIN_PANEL_H_PX)
    top = 14 + _TITLE_LINE_PX * len(lines) + (_PANEL_TITLE_PX if panel_titles else 0)
    height = bottom + content + top
    fig = Figure(figsize=(width / DPI, height / DPI), dpi=DPI)
    FigureCanvasAgg(fig)
    axes = [
        fig.add_axes(
            [(_LEFT_PX + k * (w_px + _GAP_PX)) / width, bottom / height, w_px / width, h_px / height],
            label=f"panel{k}",
        )
        for k in range(panels)
    ]
    if lines:
        fig.text(_LEFT_PX / width, 1 - 8 / height, "\n".join(lines), ha="left", va="top", fontsize=11)
    right_x = _LEFT_PX + panels * w_px + (panels - 1) * _GAP_PX
    return _Canvas(fig, axes, _LEFT_PX, bottom, right_x, w_px, h_px), max(ncol, 1)


def _map_axes(ax: Axes, extent: tuple[float, float, float, float]) -> None:
    ax.set_xlim(extent[0], extent[1])
    ax.set_ylim(extent[2], extent[3])
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.tick_params(labelsize=8)


def _show(ax: Axes, image: NDArray, extent, **style):
    return ax.imshow(image, origin="lower", extent=extent, interpolation="nearest", aspect="auto", **style)


def _unknown_overlay(ax: Axes, unknown: NDArray, view: MapView, extent) -> None:
    """Paint the cells of the (H, W) bool mask ``unknown`` in :data:`UNKNOWN_COLOUR` (others transparent)."""
    mask = downsample(np.asarray(unknown, dtype=bool), view.step, "max")
    # 8-bit RGBA (a quarter of float32's resampling work): the colour where True, transparent black
    # elsewhere, as the mask times the colour's four bytes read as one uint32 (a lookup by the mask's
    # bytes, an (H, W, 4) gather, is several times slower)
    colour = (matplotlib.colors.to_rgba_array(UNKNOWN_COLOUR)[0] * 255 + 0.5).astype(np.uint8)
    rgba = np.multiply(mask, colour.view(np.uint32)[0], dtype=np.uint32).view(np.uint8)
    _show(ax, rgba.reshape(*mask.shape, 4), extent)


def _check_mask(unknown: NDArray | None, shape_hw: tuple[int, int]) -> None:
    if unknown is not None and np.shape(unknown) != tuple(shape_hw):
        raise ValueError(f"unknown mask of shape {np.shape(unknown)} for a map of shape {tuple(shape_hw)}")


def _mark_prior(cax: Axes, cbar, prior_variance: float | NDArray) -> None:
    """Mark the prior variance (the level of unobserved cells) on a variance colour bar: a line and a tick
    labelled "unobserved" for one level, a hatched band over the range of a per-cell (H, W) prior."""
    prior_range = finite_range(prior_variance)
    if prior_range is None:
        return
    lo, hi = prior_range
    vmin, vmax = cbar.mappable.norm.vmin, cbar.mappable.norm.vmax
    span = max(vmax - vmin, 1e-12)
    if hi - lo <= 1e-6 * span:
        level = 0.5 * (lo + hi)
        cax.axhline(level, color="red", lw=2.5)
        label = f"{level:.3g} unobserved\n(prior variance)"
    else:
        cax.axhspan(lo, hi, facecolor="none", edgecolor="red", hatch="///", lw=1.5)
        level = 0.5 * (lo + hi)
        label = f"{lo:.3g}-{hi:.3g} unobserved\n(prior variance)"
    ticks = [t for t in cbar.get_ticks() if vmin <= t <= vmax and abs(t - level) > 0.08 * span]
    cbar.set_ticks([*ticks, level], labels=[f"{t:.3g}" for t in ticks] + [label])
    for text in cax.get_yticklabels()[-1:]:
        text.set_color("red")
        text.set_fontweight("bold")


def _finish_map(canvas: Any, ax: Any, extent: Any, im: Any, label: str, legend: list, ncol: int) -> tuple:
    """Axes in metres, the colour bar of ``im`` labelled ``label`` and the legend below (if any entries) of
    a one-panel map figure; returns the colour bar's axes and the colour bar."""
    _map_axes(ax, extent)
    cax = canvas.colorbar_axes()
    cbar = canvas.fig.colorbar(im, cax=cax, label=label)
    cax.tick_params(labelsize=8)
    if legend:
        canvas.legend_below(legend, ncol)
    return cax, cbar


def layer_figure(
    layers: MapLayers,
    which: str,
    title: str = "",
    path_xy_m: NDArray | None = None,
    prior_variance: float | NDArray | None = None,
    unknown: NDArray | None = None,
    ate_m: float | None = None,
) -> Figure:
    """One layer (``probability``, ``variance`` or ``mean``) at native resolution with its colour bar and,
    optionally, the robot's path (N, 2) in metres. ``prior_variance`` (a level, or (H, W) per cell) marks on
    the variance colour bar what unobserved cells read; ``unknown`` (H, W) bool paints never-observed cells
    (probability and mean layers); ``ate_m`` goes into the title."""
    if which not in ("probability", "variance", "mean"):
        raise ValueError(f"layer_figure: unknown layer {which!r} (probability, variance or mean)")
    _check_mask(unknown, layers.shape)
    view = map_view(layers.shape)
    data = downsample(getattr(layers, which), view.step)
    extent = _view_extent(layers, view)
    legend: list = []
    if path_xy_m is not None and len(path_xy_m):
        legend.append(Line2D([], [], color="tab:red", lw=1.2, label="trajectory"))
    show_unknown = unknown is not None and which != "variance"
    if show_unknown:
        legend.append(Patch(facecolor=UNKNOWN_COLOUR, edgecolor="0.3", label="unknown (never observed)"))
    right = 210 if which == "variance" and prior_variance is not None else 130
    full_title = f"{title}{_ate_text(ate_m)}{view.note()}"
    canvas, ncol = _canvas(*view.size_px, full_title, right_px=right, legend_entries=len(legend))
    ax = canvas.axes[0]
    if which == "probability":
        im = _show(ax, data, extent, cmap="gray_r", vmin=0.0, vmax=1.0)
        label = "p(occupied)"
    elif which == "variance":
        data_range = finite_range(data)
        vmax = data_range[1] if data_range is not None else 1.0
        if prior_variance is not None:
            prior_shape = np.shape(prior_variance)
            if prior_shape and prior_shape != tuple(layers.shape):
                raise ValueError(f"prior_variance of shape {prior_shape} for a map of shape {layers.shape}")
            prior_range = finite_range(prior_variance)
            if prior_range is not None:
                vmax = max(vmax, prior_range[1])
        vmin = min(0.0, data_range[0]) if data_range is not None else 0.0
        im = _show(ax, data, extent, cmap="viridis", vmin=vmin, vmax=max(vmax, vmin + 1e-12))
        label = "GP predictive variance"
    else:
        data_range = finite_range(data)
        lim = max(abs(data_range[0]), abs(data_range[1])) if data_range is not None else 1.0
        im = _show(ax, data, extent, cmap="RdBu_r", norm=CenteredNorm(0.0, max(lim, 1e-9)))
        label = "GP mean (latent)"
    if show_unknown:
        _unknown_overlay(ax, unknown, view, extent)
    if path_xy_m is not None and len(path_xy_m):
        ax.plot(path_xy_m[:, 0], path_xy_m[:, 1], "-", color="tab:red", lw=1.0, alpha=0.85)
    cax, cbar = _finish_map(canvas, ax, extent, im, label, legend, ncol)
    if which == "variance" and prior_variance is not None:
        _mark_prior(cax, cbar, prior_variance)
    return canvas.fig


def plot_layer(
    layers: MapLayers,
    which: str,
    path: Path,
    title: str = "",
    path_xy_m: NDArray | None = None,
    prior_variance: float | NDArray | None = None,
    unknown: NDArray | None = None,
    ate_m: float | None = None,
) -> Path:
    """Write :func:`layer_figure` as a PNG at ``path``; returns the path."""
    return save_figure(layer_figure(layers, which, title, path_xy_m, prior_variance, unknown, ate_m), path)


def classified_figure(
    layers: MapLayers,
    occupied_threshold: float = 0.65,
    free_threshold: float = 0.35,
    title: str = "",
    unknown: NDArray | None = None,
    ate_m: float | None = None,
) -> Figure:
    """Occupied (black, p >= occupied_threshold), free (white, p <= free_threshold), unsure (grey) and, when
    the (H, W) bool mask ``unknown`` is given, unknown (blue; it overrides the class), with a legend."""
    _check_mask(unknown, layers.shape)
    cls = classify(layers.probability, occupied_threshold, free_threshold)
    codes = np.full(cls.shape, _D_UNSURE, dtype=np.int8)
    codes[cls == FREE] = _D_FREE
    codes[cls == OCCUPIED] = _D_OCCUPIED
    codes[cls == UNSURE] = _D_UNSURE
    if unknown is not None:
        codes[np.asarray(unknown, dtype=bool)] = _D_UNKNOWN
    view = map_view(layers.shape)
    shown = downsample(codes, view.step, "max")  # a block shows its most significant class
    extent = _view_extent(layers, view)
    legend = [
        Patch(facecolor=OCCUPIED_COLOUR, edgecolor="0.3", label=f"occupied (p >= {occupied_threshold:g})"),
        Patch(facecolor=FREE_COLOUR, edgecolor="0.3", label=f"free (p <= {free_threshold:g})"),
        Patch(facecolor=UNSURE_COLOUR, edgecolor="0.3", label="unsure (in between)"),
    ]
    if unknown is not None:
        legend.append(Patch(facecolor=UNKNOWN_COLOUR, edgecolor="0.3", label="unknown (never observed)"))
    default = f"classified: occupied p >= {occupied_threshold:g}, free p <= {free_threshold:g}"
    full_title = f"{title or default}{_ate_text(ate_m)}{view.note()}"
    canvas, ncol = _canvas(*view.size_px, full_title, right_px=40, legend_entries=len(legend))
    ax = canvas.axes[0]
    _show(ax, shown, extent, cmap=_DISPLAY_CLASS_CMAP, vmin=-0.5, vmax=3.5)
    _map_axes(ax, extent)
    canvas.legend_below(legend, ncol)
    return canvas.fig


def plot_classified(
    layers: MapLayers,
    path: Path,
    occupied_threshold: float = 0.65,
    free_threshold: float = 0.35,
    title: str = "",
    unknown: NDArray | None = None,
    ate_m: float | None = None,
) -> Path:
    """Write :func:`classified_figure` as a PNG at ``path``; returns the path."""
    return save_figure(
        classified_figure(layers, occupied_threshold, free_threshold, title, unknown, ate_m), path
    )


def _draw_closures(ax: Axes, closures_xy_m: NDArray) -> None:
    """Loop closures (C, 2, 2): a thick outlined line from the query position (circle) to the matched
    earlier position (square)."""
    outline = [patheffects.Stroke(linewidth=4.5, foreground="black"), patheffects.Normal()]
    for seg in np.asarray(closures_xy_m, dtype=np.float64):
        ax.plot(seg[:, 0], seg[:, 1], "-", color=CLOSURE_COLOUR, lw=2.5, path_effects=outline, zorder=5)
    seg = np.asarray(closures_xy_m, dtype=np.float64)
    style = {"color": CLOSURE_COLOUR, "mec": "black", "mew": 1.2, "ms": 8, "ls": "none", "zorder": 6}
    ax.plot(seg[:, 0, 0], seg[:, 0, 1], marker="o", **style)
    ax.plot(seg[:, 1, 0], seg[:, 1, 1], marker="s", **style)


def _closure_handle(count: int) -> Line2D:
    return Line2D(
        [],
        [],
        color=CLOSURE_COLOUR,
        lw=2.5,
        marker="o",
        mec="black",
        ms=7,
        label=f"loop closure x{count} (circle: query, square: matched scan)",
    )


def _check_closures(closures_xy_m: NDArray | None) -> NDArray | None:
    if closures_xy_m is None or len(closures_xy_m) == 0:
        return None
    seg = np.asarray(closures_xy_m, dtype=np.float64)
    if seg.ndim != 3 or seg.shape[1:] != (2, 2):
        raise ValueError(f"closures_xy_m must be (C, 2, 2), not {seg.shape}")
    return seg


def before_after_figure(
    before: MapLayers,
    after: MapLayers,
    path_before_xy_m: NDArray | None = None,
    path_after_xy_m: NDArray | None = None,
    closures_xy_m: NDArray | None = None,
    titles: tuple[str, str] = ("before loop closure", "after loop closure"),
    ate_m: Mapping[str, float | None] | None = None,
    title: str = "",
) -> Figure:
    """Two probability maps side by side at native resolution with one colour bar, each with its trajectory
    (N, 2); loop closures ``closures_xy_m`` (C, 2, 2) (query and matched positions on the ``after``
    trajectory) drawn on the right panel, thick, with markers on both ends. ``ate_m`` ``{"before": m,
    "after": m}`` (either may be None) goes into the panel titles."""
    views = [map_view(before.shape), map_view(after.shape)]
    view = max(views, key=lambda v: v.step)
    w_px = max(v.size_px[0] for v in views)
    h_px = max(v.size_px[1] for v in views)
    closures = _check_closures(closures_xy_m)
    legend: list = []
    for name, traj in (("before", path_before_xy_m), ("after", path_after_xy_m)):
        if traj is not None and len(traj):
            legend.append(Line2D([], [], color=TRAJECTORY_COLOURS[name], lw=1.5, label=f"trajectory {name}"))
    if closures is not None:
        legend.append(_closure_handle(len(closures)))
    canvas, ncol = _canvas(
        w_px, h_px, f"{title}{view.note()}", panels=2, legend_entries=len(legend), panel_titles=True
    )
    ate_m = ate_m or {}
    im = None
    for ax, layers, traj, name, panel_title in zip(
        canvas.axes,
        (before, after),
        (path_before_xy_m, path_after_xy_m),
        ("before", "after"),
        titles,
        strict=True,
    ):
        v = map_view(layers.shape)
        extent = _view_extent(layers, v)
        im = _show(ax, downsample(layers.probability, v.step), extent, **_PROB_STYLE)
        if traj is not None and len(traj):
            ax.plot(traj[:, 0], traj[:, 1], "-", color=TRAJECTORY_COLOURS[name], lw=1.2, alpha=0.9)
        if name == "after" and closures is not None:
            _draw_closures(ax, closures)
        _map_axes(ax, extent)
        ax.set_title(f"{panel_title}{_ate_text(ate_m.get(name))}", fontsize=10)
    canvas.fig.colorbar(im, cax=canvas.colorbar_axes(), label="p(occupied)")
    if legend:
        canvas.legend_below(legend, ncol)
    return canvas.fig


def plot_before_after_maps(
    before: MapLayers,
    after: MapLayers,
    path: Path,
    path_before_xy_m: NDArray | None = None,
    path_after_xy_m: NDArray | None = None,
    closures_xy_m: NDArray | None = None,
    titles: tuple[str, str] = ("before loop closure", "after loop closure"),
    ate_m: Mapping[str, float | None] | None = None,
    title: str = "",
) -> Path:
    """Write :func:`before_after_figure` as a PNG at ``path``; returns the path."""
    fig = before_after_figure(
        before, after, path_before_xy_m, path_after_xy_m, closures_xy_m, titles, ate_m, title
    )
    return save_figure(fig, path)


def difference_figure(
    before: MapLayers,
    after: MapLayers,
    title: str = "",
    path_after_xy_m: NDArray | None = None,
    closures_xy_m: NDArray | None = None,
    ate_m: Mapping[str, float | None] | None = None,
) -> Figure:
    """``p_after - p_before`` per cell (maps of the same shape and origin) on a diverging colour map centred
    at 0 (red: more occupied after loop closure, blue: more free), symmetric about 0 up to the largest
    change; optionally the ``after`` trajectory (N, 2) and the loop closures (C, 2, 2)."""
    if before.shape != after.shape or not np.allclose(before.origin_xy_m, after.origin_xy_m):
        raise ValueError(
            f"difference of maps on different grids: {before.shape} at {before.origin_xy_m} and "
            f"{after.shape} at {after.origin_xy_m}"
        )
    view = map_view(after.shape)
    diff = downsample(
        np.asarray(after.probability, np.float32) - np.asarray(before.probability, np.float32), view.step
    )
    extent = _view_extent(after, view)
    diff_range = finite_range(diff)
    lim = max(max(abs(diff_range[0]), abs(diff_range[1])) if diff_range is not None else 0.0, 0.05)
    closures = _check_closures(closures_xy_m)
    legend: list = []
    if path_after_xy_m is not None and len(path_after_xy_m):
        legend.append(Line2D([], [], color="0.2", lw=1.2, label="trajectory after"))
    if closures is not None:
        legend.append(_closure_handle(len(closures)))
    ate_m = ate_m or {}
    ate = ""
    if ate_m.get("before") is not None or ate_m.get("after") is not None:
        b, a = ate_m.get("before"), ate_m.get("after")
        ate = f" (ATE {'?' if b is None else f'{b:.3f}'} -> {'?' if a is None else f'{a:.3f}'} m)"
    default = "change of p(occupied) with loop closure: after - before"
    canvas, ncol = _canvas(
        *view.size_px, f"{title or default}{ate}{view.note()}", right_px=170, legend_entries=len(legend)
    )
    ax = canvas.axes[0]
    im = _show(ax, diff, extent, cmap="RdBu_r", norm=CenteredNorm(0.0, lim))
    if path_after_xy_m is not None and len(path_after_xy_m):
        ax.plot(path_after_xy_m[:, 0], path_after_xy_m[:, 1], "-", color="0.2", lw=0.9, alpha=0.7)
    if closures is not None:
        _draw_closures(ax, closures)
    _finish_map(canvas, ax, extent, im, "p_after - p_before\n(red: more occupied after)", legend, ncol)
    return canvas.fig


def plot_difference(
    before: MapLayers,
    after: MapLayers,
    path: Path,
    title: str = "",
    path_after_xy_m: NDArray | None = None,
    closures_xy_m: NDArray | None = None,
    ate_m: Mapping[str, float | None] | None = None,
) -> Path:
    """Write :func:`difference_figure` as a PNG at ``path``; returns the path."""
    return save_figure(difference_figure(before, after, title, path_after_xy_m, closures_xy_m, ate_m), path)


def covariance_ellipses(
    xy_m: NDArray, cov_xytheta: NDArray, n_sigma: float = 2.0
) -> tuple[NDArray, NDArray, NDArray]:
    """Ellipses of the (N, 3, 3) (x, y, theta) covariances' position blocks at ``n_sigma``: full axis
    lengths (N,) and (N,) in metres (major, minor: ``2 * n_sigma * sqrt(eigenvalue)``) and the major axis'
    angle (N,) in degrees from +x. NaN entries give zero-size ellipses."""
    cov = np.asarray(cov_xytheta, dtype=np.float64)
    if cov.ndim != 3 or cov.shape[1:] != (3, 3) or len(cov) != len(xy_m):
        raise ValueError(f"covariances of shape {cov.shape} for {len(xy_m)} poses (need (N, 3, 3))")
    block = np.nan_to_num(cov[:, :2, :2])
    block = 0.5 * (block + np.swapaxes(block, 1, 2))
    values, vectors = np.linalg.eigh(block)  # ascending
    values = np.clip(values, 0.0, None)
    major = 2.0 * n_sigma * np.sqrt(values[:, 1])
    minor = 2.0 * n_sigma * np.sqrt(values[:, 0])
    angle_deg = np.degrees(np.arctan2(vectors[:, 1, 1], vectors[:, 0, 1]))
    return major, minor, angle_deg


def trajectory_covariances_figure(
    trajectories_xy_m: Mapping[str, NDArray],
    covariances: Mapping[str, NDArray] | None = None,
    every: int = 10,
    closures_xy_m: NDArray | None = None,
    ate_m: Mapping[str, float | None] | None = None,
    layers: MapLayers | None = None,
    title: str = "",
    n_sigma: float = 2.0,
) -> Figure:
    """Trajectories ``{name: (N, 2) or (N, 3)}`` (metres) with the ``n_sigma`` position ellipses of their
    world-frame (N, 3, 3) covariances ``{name: cov}`` at every ``every``-th pose (and the last), to scale;
    loop closures (C, 2, 2) with markers on both ends; ``ate_m`` ``{name: m}`` in the legend; over the map
    ``layers`` (faint, at native resolution) when given, else on a plain equal-aspect plot."""
    if every < 1:
        raise ValueError(f"every must be >= 1, not {every}")
    covariances = covariances or {}
    ate_m = ate_m or {}
    closures = _check_closures(closures_xy_m)
    trajs = {k: np.asarray(v, dtype=np.float64)[:, :2] for k, v in trajectories_xy_m.items() if len(v)}
    if layers is not None:
        view = map_view(layers.shape)
        extent = _view_extent(layers, view)
        w_px, h_px = view.size_px
        note = view.note()
    else:
        pts = np.concatenate([*trajs.values(), *([closures.reshape(-1, 2)] if closures is not None else [])])
        pts = pts[np.isfinite(pts).all(axis=1)] if len(pts) else np.zeros((1, 2))
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        size = np.maximum(hi - lo, 1.0) * 1.08
        centre = 0.5 * (lo + hi)
        long_px = 900
        if size[0] >= size[1]:
            w_px, h_px = long_px, max(int(long_px * size[1] / size[0] + 0.5), 1)
        else:
            w_px, h_px = max(int(long_px * size[0] / size[1] + 0.5), 1), long_px
        scale = max(size[0] / w_px, size[1] / h_px)  # metres per pixel, equal in x and y
        half = 0.5 * scale * np.array([w_px, h_px])
        extent = (centre[0] - half[0], centre[0] + half[0], centre[1] - half[1], centre[1] + half[1])
        note = ""
    legend: list = []
    colours = {}
    for k, name in enumerate(trajs):
        colours[name] = TRAJECTORY_COLOURS.get(name, f"C{k + 2}")
        label = f"{name}{_ate_text(ate_m.get(name))}"
        legend.append(Line2D([], [], color=colours[name], lw=1.5, label=label))
    drawn = [name for name in trajs if name in covariances]
    if drawn:
        legend.append(
            Patch(facecolor="none", edgecolor="0.2", label=f"{n_sigma:g}-sigma position, every {every} poses")
        )
    if closures is not None:
        legend.append(_closure_handle(len(closures)))
    default = f"trajectories with {n_sigma:g}-sigma position covariance ellipses (to scale)"
    canvas, ncol = _canvas(w_px, h_px, f"{title or default}{note}", right_px=40, legend_entries=len(legend))
    ax = canvas.axes[0]
    if layers is not None:
        _show(
            ax, downsample(layers.probability, view.step), extent, cmap="gray_r", vmin=0, vmax=1, alpha=0.45
        )
    for name, xy in trajs.items():
        ax.plot(xy[:, 0], xy[:, 1], "-", color=colours[name], lw=1.2, alpha=0.9)
        if name in covariances:
            idx = np.unique(np.r_[np.arange(0, len(xy), every), len(xy) - 1])
            major, minor, angle = covariance_ellipses(xy, covariances[name], n_sigma)
            ax.add_collection(
                EllipseCollection(
                    major[idx],
                    minor[idx],
                    angle[idx],
                    units="xy",
                    offsets=xy[idx],
                    offset_transform=ax.transData,
                    facecolors=matplotlib.colors.to_rgba(colours[name], 0.12),
                    edgecolors=colours[name],
                    linewidths=1.0,
                    zorder=4,
                )
            )
    if closures is not None:
        _draw_closures(ax, closures)
    _map_axes(ax, extent)
    canvas.legend_below(legend, ncol)
    return canvas.fig


def plot_trajectory_covariances(
    path: Path,
    trajectories_xy_m: Mapping[str, NDArray],
    covariances: Mapping[str, NDArray] | None = None,
    every: int = 10,
    closures_xy_m: NDArray | None = None,
    ate_m: Mapping[str, float | None] | None = None,
    layers: MapLayers | None = None,
    title: str = "",
) -> Path:
    """Write :func:`trajectory_covariances_figure` as a PNG at ``path``; returns the path."""
    fig = trajectory_covariances_figure(
        trajectories_xy_m, covariances, every, closures_xy_m, ate_m, layers, title
    )
    return save_figure(fig, path)


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
