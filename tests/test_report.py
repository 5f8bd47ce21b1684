"""Run-folder figures at native resolution (legends, colour bars, closures, ellipses, difference map) and
``report.html`` (written from a synthetic run folder, rendered by headless Chromium when installed)."""

from __future__ import annotations

import gc
import json
import re
import shutil
import subprocess
import weakref
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import matplotlib.image
import matplotlib.pyplot as plt
import numpy as np
import pytest

from mapping import figures
from mapping.exports import MapLayers, write_layers_npz
from pipeline.report import DIFFERENCE_PNG, REPORT_NAME, TRAJECTORY_PNG, png_size, write_report
from slam.trajectory_io import write_tum

CHROMIUM = Path("/usr/bin/chromium")
PRIOR_VARIANCE = 0.85


def _layers(
    shape_hw: tuple[int, int], seed: int = 0, resolution_m: float = 0.2, shift_cells: int = 0
) -> MapLayers:
    """A room: walls (p 0.95) round a free inside (p 0.05), unobserved outside (p 0.5, prior variance);
    ``shift_cells`` moves the room to the right (a drifted map)."""
    h, w = shape_hw
    rng = np.random.default_rng(seed)
    p = np.full(shape_hw, 0.5, np.float32)
    var = np.full(shape_hw, PRIOR_VARIANCE, np.float32)
    r0, r1, c0, c1 = h // 6, h - h // 6, w // 6 + shift_cells, w - w // 6 + shift_cells
    p[r0:r1, c0:c1] = 0.05
    var[r0:r1, c0:c1] = rng.uniform(0.01, 0.1, (r1 - r0, c1 - c0))
    t = max(1, h // 30)
    for rows, cols in (
        (slice(r0, r0 + t), slice(c0, c1)),
        (slice(r1 - t, r1), slice(c0, c1)),
        (slice(r0, r1), slice(c0, c0 + t)),
        (slice(r0, r1), slice(c1 - t, c1)),
    ):
        p[rows, cols] = 0.95
        var[rows, cols] = 0.02
    mean = (p - 0.5).astype(np.float32)
    return MapLayers(p, mean, var, resolution_m, (-w * resolution_m / 2, -h * resolution_m / 2))


def _loop(n: int, radius_m: float, drift: float = 0.0) -> np.ndarray:
    """(n, 3) poses on a circle (the ``drift`` factor grows the radius along the way)."""
    a = np.linspace(0.0, 2 * np.pi, n)
    r = radius_m * (1.0 + drift * a / (2 * np.pi))
    return np.column_stack([r * np.cos(a), r * np.sin(a), a + np.pi / 2])


def _covariances(n: int, scale: float) -> np.ndarray:
    s = scale * np.linspace(0.1, 1.0, n)
    cov = np.zeros((n, 3, 3))
    cov[:, 0, 0] = s**2
    cov[:, 1, 1] = (0.5 * s) ** 2
    cov[:, 2, 2] = 1e-3
    return cov


def _legend_texts(fig) -> list[str]:
    return [t.get_text() for leg in fig.legends for t in leg.get_texts()]


def _panel_px(fig, k: int = 0) -> tuple[float, float]:
    """Pixel size of the k-th map panel of a built figure."""
    fig.canvas.draw()
    box = next(ax for ax in fig.axes if ax.get_label() == f"panel{k}").get_window_extent()
    return box.width, box.height


# ---- figures ------------------------------------------------------------------------------------------


def test_map_view_native_upscaled_and_capped() -> None:
    native = figures.map_view((521, 1228))
    assert (native.step, native.px_per_cell, native.size_px) == (1, 1, (1228, 521))
    small = figures.map_view((40, 90))
    assert small.step == 1 and small.px_per_cell == 9 and small.size_px == (810, 360)
    huge = figures.map_view((10_000, 10_000))  # 1e8 cells
    assert huge.step > 1 and huge.shown_hw[0] * huge.shown_hw[1] <= figures.MAX_PANEL_CELLS
    assert figures.map_view((10_000, 10_000), max_cells=10**8).step == 1
    assert huge.note() and not native.note()


def test_downsample_means_and_maxima() -> None:
    a = np.arange(20, dtype=np.float32).reshape(4, 5)
    a[0, 0] = np.nan
    m = figures.downsample(a, 2)
    assert m.shape == (2, 3)
    assert m[0, 0] == pytest.approx((1 + 5 + 6) / 3)  # NaN left out
    assert m[0, 2] == pytest.approx((4 + 9) / 2)  # the partial block at the right edge
    codes = np.zeros((4, 5), np.int8)
    codes[3, 4] = 3
    assert figures.downsample(codes, 2, "max")[1, 2] == 3
    assert figures.downsample(a, 1) is a


@pytest.mark.parametrize("which", ["probability", "variance", "mean"])
def test_layer_pngs_have_a_pixel_per_cell(tmp_path, which) -> None:
    layers = _layers((300, 1100))
    path = figures.plot_layer(layers, which, tmp_path / f"{which}.png", which, _loop(50, 30)[:, :2])
    w, h = png_size(path)
    assert w >= 1100 and h >= 300
    fig = figures.layer_figure(layers, which, which)
    assert _panel_px(fig) == pytest.approx((1100, 300), abs=1)


def test_small_maps_are_drawn_larger() -> None:
    layers = _layers((30, 50))
    fig = figures.layer_figure(layers, "probability")
    assert _panel_px(fig) == pytest.approx((800, 480), abs=1)  # 16 pixels per cell


def test_huge_maps_are_downsampled_and_say_so(monkeypatch) -> None:
    monkeypatch.setattr(figures, "MAX_PANEL_CELLS", 10_000)
    layers = _layers((300, 1100))
    fig = figures.layer_figure(layers, "probability", "big map")
    assert any("downsampled" in t.get_text() for t in fig.texts)
    pw, ph = _panel_px(fig)
    assert pw * ph <= 10_000 * 1.05


def test_classified_legend_with_and_without_unknown() -> None:
    layers = _layers((120, 200))
    texts = _legend_texts(figures.classified_figure(layers, 0.65, 0.35))
    assert [t.split(" ")[0] for t in texts] == ["occupied", "free", "unsure"]
    assert "0.65" in texts[0] and "0.35" in texts[1]
    unknown = layers.variance >= 0.99 * PRIOR_VARIANCE
    fig = figures.classified_figure(layers, 0.65, 0.35, unknown=unknown)
    assert any(t.startswith("unknown") for t in _legend_texts(fig))
    image = next(ax for ax in fig.axes if ax.get_label() == "panel0").get_images()[0].get_array()
    assert (np.asarray(image)[unknown] == 1).all()  # unknown overrides the class (display code 1)
    with pytest.raises(ValueError, match="unknown mask"):
        figures.classified_figure(layers, unknown=unknown[:, :-1])


def test_variance_colour_bar_marks_unobserved() -> None:
    layers = _layers((120, 200))
    fig = figures.layer_figure(layers, "variance", prior_variance=0.9)
    cax = next(ax for ax in fig.axes if ax.get_label() == "colorbar")
    fig.canvas.draw()
    labels = [t.get_text() for t in cax.get_yticklabels()]
    assert any("unobserved" in t and "0.9" in t for t in labels)
    assert cax.get_ylim()[1] >= 0.9  # the prior level lies on the bar even above the data
    per_cell = np.full(layers.shape, 0.85) + np.linspace(0, 0.05, layers.shape[1])
    fig = figures.layer_figure(layers, "variance", prior_variance=per_cell)
    cax = next(ax for ax in fig.axes if ax.get_label() == "colorbar")
    assert any("unobserved" in t.get_text() for t in cax.get_yticklabels())
    plain = figures.layer_figure(layers, "variance")
    cax = next(ax for ax in plain.axes if ax.get_label() == "colorbar")
    assert not any("unobserved" in t.get_text() for t in cax.get_yticklabels())


def test_before_after_closures_and_ate() -> None:
    before, after = _layers((200, 300), 0), _layers((200, 300), 1)
    pb, pa = _loop(60, 15, drift=0.05), _loop(60, 15)
    closures = np.stack([pa[[59, 55], :2], pa[[0, 2], :2]], axis=1)
    fig = figures.before_after_figure(
        before, after, pb[:, :2], pa[:, :2], closures, ate_m={"before": 0.31, "after": 0.04}
    )
    texts = _legend_texts(fig)
    assert any("loop closure" in t and "x2" in t for t in texts)
    assert any("trajectory before" in t for t in texts) and any("trajectory after" in t for t in texts)
    right = next(ax for ax in fig.axes if ax.get_label() == "panel1")
    assert "ATE 0.040 m" in right.get_title()
    left = next(ax for ax in fig.axes if ax.get_label() == "panel0")
    assert "ATE 0.310 m" in left.get_title()
    marked = [ln for ln in right.get_lines() if ln.get_marker() in ("o", "s") and len(ln.get_xdata()) == 2]
    assert {ln.get_marker() for ln in marked} == {"o", "s"}  # both ends of the closures
    thick = [ln for ln in right.get_lines() if ln.get_color() == figures.CLOSURE_COLOUR and ln.get_lw() >= 2]
    assert len(thick) >= 2
    assert _panel_px(fig, 1) == pytest.approx(_panel_px(fig, 0)) and _panel_px(fig, 0)[0] >= 300


def test_difference_map_is_centred() -> None:
    before, after = _layers((100, 150), 0), _layers((100, 150), 1)
    p = after.probability.copy()
    p[10:20, 10:20] = 0.9
    after = MapLayers(p, after.mean, after.variance, after.resolution_m, after.origin_xy_m)
    fig = figures.difference_figure(before, after, ate_m={"before": 0.3, "after": None})
    image = next(ax for ax in fig.axes if ax.get_label() == "panel0").get_images()[0]
    np.testing.assert_allclose(image.get_array(), p - before.probability, atol=1e-6)
    norm = image.norm
    assert norm.vmin == pytest.approx(-norm.vmax) and norm(0.0) == pytest.approx(0.5)
    assert "0.300" in fig.texts[0].get_text()
    with pytest.raises(ValueError, match="different grids"):
        figures.difference_figure(before, _layers((100, 151)))


def test_covariance_ellipses_two_sigma() -> None:
    cov = np.zeros((2, 3, 3))
    cov[0, :2, :2] = np.diag([4.0, 1.0])
    cov[1, :2, :2] = np.diag([1.0, 9.0])
    major, minor, angle = figures.covariance_ellipses(np.zeros((2, 2)), cov)
    np.testing.assert_allclose(major, [8.0, 12.0])  # full axis: 2 * 2 sigma
    np.testing.assert_allclose(minor, [4.0, 4.0])
    assert abs(np.cos(np.radians(angle[0]))) == pytest.approx(1.0)
    assert abs(np.sin(np.radians(angle[1]))) == pytest.approx(1.0)


def test_trajectory_figure_draws_every_nth_ellipse() -> None:
    pa = _loop(100, 10)
    fig = figures.trajectory_covariances_figure(
        {"before": _loop(100, 10, 0.1), "after": pa},
        {"after": _covariances(100, 0.5)},
        every=10,
        ate_m={"after": 0.05},
    )
    ax = next(a for a in fig.axes if a.get_label() == "panel0")
    (ellipses,) = ax.collections
    assert len(ellipses.get_offsets()) == 11  # poses 0, 10, ..., 90 and the last
    texts = _legend_texts(fig)
    assert any("2-sigma" in t and "every 10" in t for t in texts)
    assert any("ATE 0.050 m" in t for t in texts)
    with_map = figures.trajectory_covariances_figure({"after": pa}, layers=_layers((300, 1100)))
    assert _panel_px(with_map) == pytest.approx((1100, 300), abs=1)


def _drawn_by_matplotlib(fig, path: Path) -> np.ndarray:
    fig.savefig(path, dpi=fig.dpi)
    return (matplotlib.image.imread(path)[..., :3] * 255).round().astype(np.int16)


def _figure_kinds() -> dict:
    """One of every run-folder figure that shows a map, with paths, closures, NaN cells, an unknown overlay
    and a translucent map under ellipses; a 1:1 map (1100 x 300 cells) and an upscaled one (60 x 40)."""
    layers, small = _layers((300, 1100)), _layers((40, 60), 2)
    p = layers.probability.copy()
    p[5:9, 5:40] = np.nan
    holed = MapLayers(p, layers.mean, layers.variance, layers.resolution_m, layers.origin_xy_m)
    unknown = layers.variance >= 0.99 * PRIOR_VARIANCE
    pa = _loop(60, 15)
    closures = np.stack([pa[[59, 55], :2], pa[[0, 2], :2]], axis=1)
    return {
        "probability": lambda: figures.layer_figure(holed, "probability", "p", pa[:, :2], unknown=unknown),
        "variance": lambda: figures.layer_figure(layers, "variance", "v", prior_variance=PRIOR_VARIANCE),
        "mean": lambda: figures.layer_figure(layers, "mean"),
        "small": lambda: figures.layer_figure(small, "probability", unknown=small.variance > 0.8),
        "classified": lambda: figures.classified_figure(layers, unknown=unknown),
        "before_after": lambda: figures.before_after_figure(
            _layers((300, 1100), 1), layers, pa[:, :2], pa[:, :2], closures
        ),
        "difference": lambda: figures.difference_figure(
            _layers((300, 1100), 1), holed, "d", pa[:, :2], closures
        ),
        "trajectory": lambda: figures.trajectory_covariances_figure(
            {"after": pa}, {"after": _covariances(60, 0.5)}, layers=layers
        ),
    }


@pytest.mark.parametrize("kind", list(_figure_kinds()))
def test_pasted_maps_equal_matplotlib_drawn_ones(tmp_path, kind) -> None:
    """save_figure pastes the map images instead of letting matplotlib resample them: the PNG must be the
    one matplotlib draws, up to rounding of the colours (a few levels on a few pixels; everywhere, by one
    or two levels, under the translucent map of the trajectory figure)."""
    make = _figure_kinds()[kind]
    pasted = figures.save_figure(make(), tmp_path / "pasted.png")
    assert figures._paste_maps(make()) is not None  # the fast path was taken
    mine = (matplotlib.image.imread(pasted)[..., :3] * 255).round().astype(np.int16)
    theirs = _drawn_by_matplotlib(make(), tmp_path / "drawn.png")
    assert mine.shape == theirs.shape
    diff = np.abs(mine - theirs).max(axis=2)
    assert diff.max() <= 3, f"{(diff > 3).sum()} pixels differ by more than 3 levels"
    assert diff.mean() < (1.0 if kind == "trajectory" else 0.01)  # a translucent map: rounding everywhere


@pytest.mark.parametrize("kind", ["probability", "variance", "classified", "difference", "trajectory"])
def test_map_images_coloured_in_bands_equal_one_pass(kind, monkeypatch) -> None:
    """The pasted maps are coloured a band of rows at a time (bounded temporaries on big maps): the bytes
    equal matplotlib's colouring of the whole image, NaN cells, masks, norms and alpha included."""
    monkeypatch.setattr(figures, "COLOUR_BAND_ROWS", 7)
    fig = _figure_kinds()[kind]()
    images = [im for ax in fig.axes for im in ax.get_images()]
    assert images
    for image in images:
        whole = image.to_rgba(image.get_array(), alpha=image.get_alpha(), bytes=True)
        np.testing.assert_array_equal(figures._image_rgba(image), whole)
    plt.close(fig)


def test_a_figure_saved_before_is_freed_when_the_next_is_saved(tmp_path) -> None:
    """Figures are reference cycles: a dropped one (its canvas and images) would wait for the cycle
    collector, which big numpy buffers do not prompt. save_figure collects them before it draws."""
    kinds = _figure_kinds()
    gc_was_enabled = gc.isenabled()
    gc.disable()  # no collection but save_figure's own
    try:
        first = kinds["probability"]()
        first.canvas.draw()
        gone = weakref.ref(first)
        figures.save_figure(first, tmp_path / "first.png")
        del first
        assert gone() is not None  # a cycle: dropping the last reference does not free it
        figures.save_figure(kinds["variance"](), tmp_path / "second.png")
        assert gone() is None
    finally:
        if gc_was_enabled:
            gc.enable()


def test_figures_are_freed_while_older_objects_are_frozen(tmp_path) -> None:
    """Within collecting_new_objects_only the objects alive before are frozen (out of every collection),
    save_figure's collection still frees the figure dropped before (made inside the block), and the block
    thaws what it froze."""
    kinds = _figure_kinds()
    before = gc.get_freeze_count()
    old = [[i] for i in range(50_000)]  # tracked objects alive before the block
    gc_was_enabled = gc.isenabled()
    gc.disable()
    try:
        with figures.collecting_new_objects_only():
            assert gc.get_freeze_count() >= before + len(old)
            first = kinds["probability"]()
            gone = weakref.ref(first)
            figures.save_figure(first, tmp_path / "first.png")
            del first
            figures.save_figure(kinds["variance"](), tmp_path / "second.png")
            assert gone() is None
        assert gc.get_freeze_count() == 0
    finally:
        if gc_was_enabled:
            gc.enable()
    del old


def test_png_encoding_in_a_pool_writes_the_same_files(tmp_path) -> None:
    """Within png_encoding_in, save_figure hands the encoding to the pool: when the block ends, the files
    are those written directly, byte for byte. An error inside the block is the one raised, after the
    pending files are written."""
    kinds = _figure_kinds()
    names = ["probability", "classified", "before_after"]
    direct = [figures.save_figure(kinds[k](), tmp_path / f"direct_{k}.png") for k in names]
    with ThreadPoolExecutor(max_workers=2) as pool:
        with figures.png_encoding_in(pool):
            pooled = [figures.save_figure(kinds[k](), tmp_path / f"pooled_{k}.png") for k in names]
            assert len(figures._PNG_ENCODER.get()[1]) == len(names)  # handed to the pool
        for a, b in zip(direct, pooled, strict=True):
            assert a.read_bytes() == b.read_bytes()
        with pytest.raises(RuntimeError, match="drawing failed"), figures.png_encoding_in(pool):
            late = figures.save_figure(kinds["variance"](), tmp_path / "late.png")
            raise RuntimeError("drawing failed")
        assert png_size(late) is not None


def test_figures_that_cannot_be_pasted_are_drawn(tmp_path) -> None:
    """A figure without a map, or with an image that does not fill its panel one to one, goes through
    matplotlib."""
    assert figures._paste_maps(figures.trajectory_covariances_figure({"after": _loop(50, 10)})) is None
    fig = figures.layer_figure(_layers((300, 1100)), "probability")
    fig.axes[0].set_xlim(-200, 200)  # zoomed out: the image no longer fills its panel
    assert figures._paste_maps(fig) is None
    path = figures.save_figure(fig, tmp_path / "zoomed.png")
    assert png_size(path) == tuple(round(v) for v in fig.get_size_inches() * fig.dpi)


# ---- report -------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    """A small complete run folder: two maps with their PNGs, trajectories, covariances, summary."""
    run = tmp_path_factory.mktemp("report") / "run"
    n = 80
    stamps = np.arange(n, dtype=np.int64) * 500_000_000
    pb, pa = _loop(n, 12, drift=0.08), _loop(n, 12)
    traj = run / "trajectory"
    traj.mkdir(parents=True)
    write_tum(traj / "odometry.tum", stamps, pb)
    write_tum(traj / "optimized.tum", stamps, pa)
    np.savez(
        traj / "covariances.npz",
        scan_stamps_ns=stamps,
        scan_before=_covariances(n, 0.8),
        scan_after=_covariances(n, 0.2),
        stamps_ns=stamps[::10],
        before=_covariances(n, 0.8)[::10],
        after=_covariances(n, 0.2)[::10],
        indices=np.arange(0, n, 10),
    )
    maps = {"before": _layers((140, 220), 0, 0.2, shift_cells=6), "after": _layers((140, 220), 1, 0.2)}
    for name, layers in maps.items():
        folder = run / "maps" / name
        folder.mkdir(parents=True)
        write_layers_npz(folder / "layers.npz", layers)
        path = (pb if name == "before" else pa)[:, :2]
        figures.plot_layer(layers, "probability", folder / "occupancy.png", f"{name}: p", path)
        figures.plot_layer(layers, "variance", folder / "variance.png", name, prior_variance=PRIOR_VARIANCE)
        figures.plot_classified(
            layers, folder / "classified.png", unknown=layers.variance >= 0.99 * PRIOR_VARIANCE
        )
    closures = np.stack([pa[[79], :2], pa[[0], :2]], axis=1)
    figures.plot_before_after_maps(
        maps["before"], maps["after"], run / "maps" / "before_after.png", pb[:, :2], pa[:, :2], closures
    )
    summary = {
        "input": "synthetic <loop> & co",
        "loop_closures": [{"query_scan": 79, "target_scan": 0}],
        "counts": {"scans": n, "loop_closures": 1, "loop_closures_rejected": 2},
        "metrics": {"ate_rmse_m": {"before": 0.5, "after": 0.05}, "auc": None},
        "map": {"resolution_m": 0.2, "shape_hw": [140, 220]},
        "timings_s": {"read": 0.1, "slam": 1.0, "map_after": 2.0, "total": 3.1},
        "table": {"input": "synthetic <loop> & co", "scans": n, "ATE before / after (m)": "0.500 / 0.050"},
    }
    (run / "summary.json").write_text(json.dumps(summary))
    write_report(run)
    return run


def test_report_draws_missing_figures_and_links_every_png(run_dir) -> None:
    text = (run_dir / REPORT_NAME).read_text()
    for name in (DIFFERENCE_PNG, TRAJECTORY_PNG):
        assert png_size(run_dir / "maps" / name) is not None
    pngs = sorted(p.relative_to(run_dir).as_posix() for p in (run_dir / "maps").rglob("*.png"))
    assert len(pngs) == 9
    srcs = re.findall(r'<img src="([^"]+)"', text)
    assert sorted(srcs) == pngs and srcs[0] == "maps/before_after.png"
    assert "&lt;loop&gt; &amp; co" in text and "<loop>" not in text  # escaped
    assert 'id="summary"' in text and "0.500 / 0.050" in text
    assert "<script" not in text and "http" not in text.replace("http-equiv", "")
    for src in srcs:  # every figure at least as large as its map
        w, h = png_size(run_dir / src)
        assert w >= 220 and h >= 140


def test_report_embeds_and_survives_a_bad_file(tmp_path, run_dir) -> None:
    run = tmp_path / "copy"
    shutil.copytree(run_dir, run)
    (run / "maps" / TRAJECTORY_PNG).unlink()
    (run / "trajectory" / "covariances.npz").write_bytes(b"not an archive")
    text = write_report(run, embed=True).read_text()
    assert "maps/trajectory.png could not be drawn" in text
    assert text.count('src="data:image/png;base64,') == 8


def test_report_draws_the_trajectory_over_maps_held_in_memory(tmp_path, run_dir, monkeypatch) -> None:
    """The maps a run holds give the same trajectory figure as its ``layers.npz`` read back, unread."""
    from mapping.exports import read_layers_npz
    from pipeline import report

    run = tmp_path / "copy"
    shutil.copytree(run_dir, run)
    (run / "maps" / TRAJECTORY_PNG).unlink()
    maps = {name: read_layers_npz(run / "maps" / name / "layers.npz") for name in ("before", "after")}

    def unread(path):
        raise AssertionError(f"{path} read back")

    monkeypatch.setattr(report, "_read_layers", unread)
    write_report(run, maps=maps)
    assert matplotlib.image.imread(run / "maps" / TRAJECTORY_PNG).tobytes() == (
        matplotlib.image.imread(run_dir / "maps" / TRAJECTORY_PNG).tobytes()
    )


def _chromium(args: list[str], tmp_path: Path) -> subprocess.CompletedProcess:
    profile = tmp_path / "chromium-profile"
    base = [
        str(CHROMIUM),
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-quic",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        f"--user-data-dir={profile}",
    ]
    return subprocess.run([*base, *args], capture_output=True, text=True, timeout=180)


@pytest.mark.skipif(not CHROMIUM.exists(), reason="/usr/bin/chromium missing (apt-get install -y chromium)")
def test_report_renders_in_chromium(run_dir, tmp_path) -> None:
    url = (run_dir / REPORT_NAME).resolve().as_uri()
    shot = tmp_path / "shot.png"
    done = _chromium([f"--screenshot={shot}", "--window-size=1200,2000", url], tmp_path)
    assert shot.is_file(), done.stderr[-2000:]
    rgb = matplotlib.image.imread(shot)[..., :3]
    assert rgb.shape[:2] == (2000, 1200)
    assert rgb.std() > 0.05  # not blank
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    red = (r - b > 0.3) & (r - g > 0.3)  # the page's own styles have no red: only loaded figures do
    assert red.sum() > 3000  # the before trajectory, the difference map's gains, the ellipses
    dom = _chromium(["--dump-dom", url], tmp_path)
    assert dom.returncode == 0, dom.stderr[-2000:]
    assert dom.stdout.count("<img ") == 9
    assert '<table id="summary">' in dom.stdout and "0.500 / 0.050" in dom.stdout
