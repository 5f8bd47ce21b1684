"""``report.html``: one page to open after a run, written from the run folder alone.

The page holds the summary table (``summary.json``: input, counts, ATE, AUC, loop closures, map geometry,
durations), the stage times, the loop closures, and every PNG of ``maps/`` with a caption, referenced by
relative path (the page works wherever the folder is moved; ``embed=True`` inlines the images as base64 so
the file stands alone). It is plain HTML and CSS: no script, no network.

Two figures that a run folder may lack are drawn first (from its files, into ``maps/``):
``maps/difference.png`` (p after - p before, when both maps exist) and ``maps/trajectory.png`` (the
trajectories with 2-sigma covariance ellipses over the map). A figure that cannot be drawn (a missing or
unreadable file) is left out and the page says why; the page itself is always written.
"""

from __future__ import annotations

import base64
import html
import json
import struct
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from datasets.errors import GpomError
from datasets.files import write_text_atomic
from mapping.exports import MapLayers, read_layers_npz
from mapping.figures import plot_difference, plot_trajectory_covariances
from pipeline.artifacts import (
    COVARIANCES_NPZ,
    ODOMETRY_TUM,
    OPTIMIZED_TUM,
    TRAJECTORY_DIR,
    covariances_at,
    read_scan_covariances,
)
from pipeline.run_folder import read_summary
from slam.trajectory_io import read_tum

REPORT_NAME = "report.html"
DIFFERENCE_PNG = "difference.png"
TRAJECTORY_PNG = "trajectory.png"
#: About this many covariance ellipses per trajectory on ``trajectory.png``.
ELLIPSES_PER_TRAJECTORY = 60

#: Trajectory files of a run folder by the name the figures give them (``remap.tum``: a remap folder).
_TRAJECTORIES = {"before": ODOMETRY_TUM, "after": OPTIMIZED_TUM, "remap": "remap.tum"}
_COVARIANCE_KEYS = {"before": "before", "after": "after"}

#: Captions of the figures by path under ``maps/`` (``{name}``: the map's folder).
_CAPTIONS = {
    "before_after.png": "Occupancy probability before (left) and after (right) loop closure, each with its "
    "trajectory. Loop closures are drawn in green on the right: a circle at the query scan, a square at the "
    "earlier scan it was matched to.",
    DIFFERENCE_PNG: "Change of the occupancy probability with loop closure, p(after) - p(before), on a "
    "diverging scale centred at 0: red cells became more occupied, blue cells more free.",
    TRAJECTORY_PNG: "Trajectories over the final map (before and after loop closure; in a remap folder, the "
    "remap's poses), with the 2-sigma ellipse of the marginal position covariance (world frame) at regularly "
    "spaced poses, to scale.",
    "occupancy.png": "Map '{name}': GP probability of occupancy p(occupied) at native resolution (at least "
    "one pixel per cell), with the trajectory.",
    "variance.png": "Map '{name}': GP predictive variance. The marked level on the colour bar is the prior "
    "variance: what cells that no beam constrained (unobserved space) read.",
    "classified.png": "Map '{name}': cells classified with the run's thresholds as occupied, free or unsure "
    "(and unknown, never observed, when the run marks them).",
}
_ORDER = ["before_after.png", DIFFERENCE_PNG, TRAJECTORY_PNG]
_MAP_ORDER = ["after", "before", "remap"]
_LAYER_ORDER = ["occupancy.png", "variance.png", "classified.png"]

_CSS = """
body { font-family: sans-serif; margin: 1.5em auto; max-width: 1400px; padding: 0 1em; color: #222; }
h1 { font-size: 1.5em; } h2 { font-size: 1.2em; border-bottom: 1px solid #ccc; padding-bottom: 0.2em; }
table { border-collapse: collapse; margin: 0.5em 0 1em; font-size: 0.92em; }
th, td { border: 1px solid #ccc; padding: 0.25em 0.6em; text-align: left; vertical-align: top; }
th { background: #f2f2f2; font-weight: normal; }
td.num { text-align: right; font-variant-numeric: tabular-nums; }
.bar { display: inline-block; height: 0.8em; background: #4a7ebb; }
figure { margin: 1.5em 0; }
figure img { max-width: 100%; height: auto; border: 1px solid #ddd; }
figcaption { font-size: 0.92em; color: #444; margin-top: 0.3em; }
.note { color: #a33; }
.small { font-size: 0.85em; color: #666; }
"""


def png_size(path: Path) -> tuple[int, int] | None:
    """(width, height) in pixels from a PNG's header, or None if the file is not a PNG."""
    try:
        with open(path, "rb") as f:
            head = f.read(24)
    except OSError:
        return None
    if len(head) < 24 or head[:8] != b"\x89PNG\r\n\x1a\n" or head[12:16] != b"IHDR":
        return None
    width, height = struct.unpack(">II", head[16:24])
    return int(width), int(height)


def _read_layers(path: Path) -> MapLayers | None:
    return read_layers_npz(path) if path.is_file() else None


def _closure_segments(summary: dict[str, Any], poses_xytheta: NDArray) -> NDArray | None:
    """(C, 2, 2) query and target positions of ``summary["loop_closures"]`` on the poses (N, 3)."""
    pairs = [
        (int(c["query_scan"]), int(c["target_scan"]))
        for c in summary.get("loop_closures") or []
        if isinstance(c, dict) and "query_scan" in c and "target_scan" in c
    ]
    pairs = [(q, t) for q, t in pairs if 0 <= q < len(poses_xytheta) and 0 <= t < len(poses_xytheta)]
    if not pairs:
        return None
    idx = np.asarray(pairs, dtype=np.int64)
    return np.stack([poses_xytheta[idx[:, 0], :2], poses_xytheta[idx[:, 1], :2]], axis=1)


def _ate(summary: dict[str, Any]) -> dict[str, float | None]:
    ate = (summary.get("metrics") or {}).get("ate_rmse_m") or {}
    return {k: float(v) for k, v in ate.items() if isinstance(v, int | float)}


def draw_difference(run_dir: Path, summary: dict[str, Any]) -> Path | None:
    """``maps/difference.png`` from ``maps/{before,after}/layers.npz`` when both exist; None otherwise."""
    maps = Path(run_dir) / "maps"
    before, after = _read_layers(maps / "before" / "layers.npz"), _read_layers(maps / "after" / "layers.npz")
    if before is None or after is None:
        return None
    traj = Path(run_dir) / TRAJECTORY_DIR / OPTIMIZED_TUM
    poses = read_tum(traj)[1] if traj.is_file() else None
    return plot_difference(
        before,
        after,
        maps / DIFFERENCE_PNG,
        path_after_xy_m=None if poses is None else poses[:, :2],
        closures_xy_m=None if poses is None else _closure_segments(summary, poses),
        ate_m=_ate(summary),
    )


def draw_trajectory(
    run_dir: Path, summary: dict[str, Any], maps: dict[str, MapLayers] | None = None
) -> Path | None:
    """``maps/trajectory.png``: the run folder's trajectories with 2-sigma position ellipses of the
    per-scan covariances of ``trajectory/covariances.npz`` (a remap folder: the file its summary names), when
    present, over the final map; None when the folder holds no trajectory. ``maps``: the folder's maps by
    name when the caller holds them in memory (a big building's ``layers.npz`` takes seconds to read back)."""
    run_dir = Path(run_dir)
    traj_dir = run_dir / TRAJECTORY_DIR
    poses: dict[str, NDArray] = {}
    stamps: dict[str, NDArray] = {}
    for name, file in _TRAJECTORIES.items():
        if (traj_dir / file).is_file():
            stamps[name], poses[name] = read_tum(traj_dir / file)
    if not poses:
        return None
    covariances: dict[str, NDArray] = {}
    sources = {name: (traj_dir / COVARIANCES_NPZ, key) for name, key in _COVARIANCE_KEYS.items()}
    if isinstance(summary.get("covariances"), str):  # a remap folder: the covariances the remap used
        sources["remap"] = (Path(summary["covariances"]), "after")
    for name, (file, key) in sources.items():
        if name in poses and file.is_file():
            cov_stamps, cov = read_scan_covariances(file, key)
            covariances[name] = covariances_at(stamps[name], cov_stamps, cov)
    layers = None
    for name in _MAP_ORDER:
        if maps is not None and name in maps:
            layers = maps[name]
        else:
            layers = _read_layers(run_dir / "maps" / name / "layers.npz")
        if layers is not None:
            break
    n = max(len(p) for p in poses.values())
    closures = _closure_segments(summary, poses["after"]) if "after" in poses else None
    return plot_trajectory_covariances(
        run_dir / "maps" / TRAJECTORY_PNG,
        {k: v[:, :2] for k, v in poses.items()},
        covariances,
        every=max(1, n // ELLIPSES_PER_TRAJECTORY),
        closures_xy_m=closures,
        ate_m=_ate(summary),
        layers=layers,
    )


def write_report_figures(
    run_dir: Path, summary: dict[str, Any], maps: dict[str, MapLayers] | None = None
) -> tuple[list[Path], list[str]]:
    """Draw the figures the report shows that ``maps/`` lacks (:func:`draw_difference`,
    :func:`draw_trajectory`, which uses ``maps``, the folder's maps in memory, instead of reading them);
    returns the files drawn and a note for each figure that could not be."""
    drawn: list[Path] = []
    notes: list[str] = []
    folder = Path(run_dir) / "maps"
    draws = (
        (DIFFERENCE_PNG, lambda: draw_difference(run_dir, summary)),
        (TRAJECTORY_PNG, lambda: draw_trajectory(run_dir, summary, maps)),
    )
    for name, draw in draws:
        if (folder / name).is_file():
            continue
        try:
            path = draw()
        except (GpomError, OSError, ValueError) as exc:
            notes.append(f"maps/{name} could not be drawn: {exc}")
            continue
        if path is not None:
            drawn.append(path)
    return drawn, notes


def _figure_list(run_dir: Path) -> list[Path]:
    """The PNGs of ``maps/`` in reading order: the overviews, then each map's layers, then the rest."""
    maps = Path(run_dir) / "maps"
    if not maps.is_dir():
        return []
    found = sorted(p for p in maps.rglob("*.png") if p.is_file())
    rel = {p.relative_to(maps).as_posix(): p for p in found}
    ordered = [rel.pop(k) for k in _ORDER if k in rel]
    folders = sorted({k.split("/")[0] for k in rel if "/" in k})
    folders = [f for f in _MAP_ORDER if f in folders] + [f for f in folders if f not in _MAP_ORDER]
    for folder in folders:
        for layer in _LAYER_ORDER:
            key = f"{folder}/{layer}"
            if key in rel:
                ordered.append(rel.pop(key))
        ordered += [rel.pop(k) for k in sorted(rel) if k.startswith(f"{folder}/")]
    return ordered + [rel[k] for k in sorted(rel)]


def _caption(run_dir: Path, png: Path) -> str:
    """The caption of a figure under ``maps/``: top-level ones by name, a map's layers with the map's name."""
    rel = png.relative_to(Path(run_dir) / "maps")
    folder = rel.parent.as_posix()
    if folder == ".":
        return _CAPTIONS.get(rel.name, "") if rel.name in _ORDER else ""
    text = _CAPTIONS.get(rel.name, "") if rel.name in _LAYER_ORDER else ""
    return text.format(name=folder)


def _cell(value: Any) -> str:
    """One table cell: numbers right-aligned (floats to 4 significant digits), everything escaped."""
    if isinstance(value, bool) or value is None:
        return f"<td>{html.escape(str(value).lower() if value is not None else '-')}</td>"
    if isinstance(value, int):
        return f'<td class="num">{value:,}</td>'
    if isinstance(value, float):
        return f'<td class="num">{value:.4g}</td>'
    if isinstance(value, list | tuple):
        return f"<td>{html.escape(', '.join(_short(v) for v in value))}</td>"
    return f"<td>{html.escape(str(value))}</td>"


def _short(value: Any) -> str:
    return f"{value:.6g}" if isinstance(value, float) else str(value)


def _flatten(data: Any, prefix: str = "") -> list[tuple[str, Any]]:
    """``("a.b.c", value)`` rows of nested dicts; lists of more than 8 items become their length."""
    if isinstance(data, dict):
        rows: list[tuple[str, Any]] = []
        for key, value in data.items():
            rows += _flatten(value, f"{prefix}.{key}" if prefix else str(key))
        return rows
    if isinstance(data, list) and (len(data) > 8 or any(isinstance(v, dict | list) for v in data)):
        return [(prefix, f"{len(data)} items")]
    return [(prefix, data)]


def _table(rows: list[tuple[str, Any]], table_id: str, head: tuple[str, str] | None = None) -> str:
    out = [f'<table id="{table_id}">']
    if head:
        out.append(f"<tr><th>{html.escape(head[0])}</th><th>{html.escape(head[1])}</th></tr>")
    out += [f"<tr><th>{html.escape(str(k))}</th>{_cell(v)}</tr>" for k, v in rows]
    out.append("</table>")
    return "\n".join(out)


def _summary_rows(summary: dict[str, Any]) -> list[tuple[str, Any]]:
    """The summary's own ``table`` (as the command line prints it), else its scalar entries."""
    table = summary.get("table")
    if isinstance(table, dict) and table:
        return list(table.items())
    return [(k, v) for k, v in _flatten(summary) if not isinstance(v, dict)][:40]


def _timings(summary: dict[str, Any]) -> str:
    times = {k: v for k, v in (summary.get("timings_s") or {}).items() if isinstance(v, int | float)}
    if not times:
        return ""
    total = float(times.get("total") or sum(v for k, v in times.items() if k != "total") or 1.0)
    rows = ['<table id="timings"><tr><th>stage</th><th>wall time (s)</th><th>share</th></tr>']
    for name, seconds in times.items():
        share = 100.0 * float(seconds) / total if total > 0 else 0.0
        bar = (
            ""
            if name == "total"
            else f'<span class="bar" style="width:{min(share, 100.0) * 2:.0f}px"></span>'
        )
        rows.append(
            f'<tr><th>{html.escape(name)}</th><td class="num">{float(seconds):.2f}</td>'
            f"<td>{bar} {'' if name == 'total' else f'{share:.0f} %'}</td></tr>"
        )
    rows.append("</table>")
    extra = []
    if isinstance(summary.get("data_duration_s"), int | float):
        extra.append(f"recording duration {summary['data_duration_s']:.1f} s")
    if isinstance(summary.get("realtime_factor"), int | float):
        extra.append(f"real-time factor {summary['realtime_factor']:.1f}")
    return "<h2>Stage times</h2>\n" + "\n".join(rows) + (f"<p>{'; '.join(extra)}</p>" if extra else "")


def _closures(summary: dict[str, Any]) -> str:
    closures = summary.get("loop_closures")
    if not isinstance(closures, list):
        return ""
    counts = summary.get("counts") or {}
    rejected = counts.get("loop_closures_rejected")
    head = f"{len(closures)} accepted" + (f", {rejected} rejected" if rejected is not None else "")
    pairs = [(c.get("query_scan"), c.get("target_scan")) for c in closures if isinstance(c, dict)]
    rows = "".join(f"<tr>{_cell(q)}{_cell(t)}</tr>" for q, t in pairs)
    table = f'<table id="closures"><tr><th>query scan</th><th>matched scan</th></tr>{rows}</table>'
    body = f"<details><summary>the {len(closures)} pairs</summary>{table}</details>" if closures else ""
    return f"<h2>Loop closures</h2>\n<p>{html.escape(head)}.</p>{body}"


def _figure(run_dir: Path, png: Path, embed: bool) -> str:
    rel = png.relative_to(run_dir).as_posix()
    size = png_size(png)
    dims = f' width="{size[0]}" height="{size[1]}"' if size else ""
    if embed:
        src = "data:image/png;base64," + base64.b64encode(png.read_bytes()).decode("ascii")
    else:
        src = html.escape(rel, quote=True)
    caption = html.escape(_caption(run_dir, png))
    pixels = f" ({size[0]} x {size[1]} px)" if size else ""
    link = html.escape(rel, quote=True)
    return (
        f'<figure><a href="{link}"><img src="{src}" alt="{html.escape(rel)}"{dims}></a>'
        f"<figcaption><b>{html.escape(rel)}</b>{pixels}{': ' if caption else ''}{caption}"
        "</figcaption></figure>"
    )


def render_report(
    run_dir: Path, summary: dict[str, Any], notes: list[str] | None = None, embed: bool = False
) -> str:
    """The HTML text of the report of ``run_dir`` with ``summary`` (the figures are those on disk)."""
    run_dir = Path(run_dir)
    if summary.get("input"):
        title = f"gpom run: {summary['input']}"
    elif summary.get("run_dir"):
        title = f"gpom remap of {summary['run_dir']}"
    else:
        title = f"gpom run folder {run_dir.name}"
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        '<meta name="viewport" content="width=device-width, initial-scale=1">',
        f"<title>{html.escape(title)}</title><style>{_CSS}</style></head><body>",
        f"<h1>{html.escape(title)}</h1>",
        "<h2>Summary</h2>",
        _table(_summary_rows(summary), "summary"),
        _timings(summary),
        _closures(summary),
        "<h2>Figures</h2>",
        '<p class="small">Click a figure to open it at full resolution.</p>',
    ]
    parts += [f'<p class="note">{html.escape(n)}</p>' for n in notes or []]
    figures = _figure_list(run_dir)
    parts += [_figure(run_dir, png, embed) for png in figures] or ["<p>This run folder has no figures.</p>"]
    parts += [
        "<h2>All summary fields</h2>",
        "<details><summary>summary.json, flattened</summary>",
        _table([(k, v) for k, v in _flatten(summary)], "fields", ("field", "value")),
        "</details>",
        "</body></html>",
    ]
    return "\n".join(p for p in parts if p) + "\n"


def _plain(obj: Any) -> Any:
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    return str(obj)


def write_report(
    run_dir: Path,
    summary: dict[str, Any] | None = None,
    embed: bool = False,
    maps: dict[str, MapLayers] | None = None,
) -> Path:
    """Write ``run_dir/report.html`` from the run folder (its ``summary.json`` unless ``summary`` is given,
    so that a run can write the report before the summary, which it writes last); draws the missing
    figures first (:func:`write_report_figures`; ``maps``: the folder's maps by name, when the caller
    holds them, so that they are not read back). ``embed``: images inline (base64) instead of relative
    links. Returns the path of the report."""
    run_dir = Path(run_dir)
    if summary is None:
        summary = read_summary(run_dir)
    summary = json.loads(json.dumps(summary, default=_plain))  # plain JSON types, as summary.json holds
    _, notes = write_report_figures(run_dir, summary, maps)
    path = run_dir / REPORT_NAME
    write_text_atomic(path, render_report(run_dir, summary, notes, embed))
    return path
