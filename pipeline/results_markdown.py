"""Results pages: the output of ``evaluate suite`` and ``bench`` as markdown (``--markdown FILE``).

``docs/results.md`` and ``docs/bench.md`` are written by these functions, never typed: each page opens with
where its figures come from (the command line, the date, the commit, the version and the machine of the run,
from the result's ``provenance``, :mod:`pipeline.provenance`), so a reader can tell whether they are current
and regenerate them. A page rendered later from a saved JSON (``--from-json``) reports the run's provenance
and says when and by which commit it was rendered.

Only text is built here; the command line writes it.
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

from datasets.paths import REPO_DIR
from pipeline.evaluate_slam import judged_closures_text
from pipeline.provenance import UNKNOWN, machine_text
from slam.metrics import LOCAL_TRAVEL_M

#: Map protocols of the suite: (key of a row's ``maps``, section title, what it measures).
MAP_PROTOCOLS: tuple[tuple[str, str, str], ...] = (
    (
        "reference_poses",
        "Maps on the reference poses",
        "The mapper alone: maps built from the reference poses (corrected logs; the true poses of the "
        "simulated worlds), scored by the hold-out protocol or, on the simulated worlds, against the "
        "ground-truth raster.",
    ),
    (
        "slam_poses",
        "Maps on our SLAM poses, the reference's test points",
        "The whole pipeline: the same training scans mapped at our SLAM poses after loop closure (aligned "
        "to the reference), scored on the test points computed from the reference poses; its distance to "
        "the table above is what our SLAM costs the map, measured by the reference.",
    ),
    (
        "slam_poses_own_test_points",
        "Maps on our SLAM poses, our own test points",
        "The same map scored on test points computed from our own poses of the held-out scans: the "
        "protocol the reference-pose map is scored by, so neither trajectory is taken as the truth (the "
        "map score of a recording without reference poses).",
    ),
)

MAPPERS = ("gppol", "gpfol", "grid")

CARTOGRAPHER = "Cartographer (Hess et al., ICRA 2016, Table I)"
#: Published errors against the SLAM benchmark's relations after loop closure, and where, by suite row.
PUBLISHED_RELATIONS: dict[str, tuple[str, str]] = {
    "intel": ("0.0229 m / 0.453 deg", CARTOGRAPHER),
    "fr079": ("0.0452 m / 0.538 deg", CARTOGRAPHER),
    "fr-clinic": ("about 0.06 m", CARTOGRAPHER),
}


# ----------------------------------------------------------------------------------------------- helpers


def _cell(value: Any) -> str:
    """A table cell: ``-`` for None, no line breaks, ``|`` escaped."""
    text = "-" if value is None else str(value)
    return " ".join(text.split()).replace("|", "\\|")


def md_table(header: list[str], rows: Iterable[list[Any]]) -> str:
    """A markdown table (GitHub flavour) of ``rows`` under ``header``."""
    lines = ["| " + " | ".join(_cell(h) for h in header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(_cell(v) for v in row) + " |" for row in rows]
    return "\n".join(lines)


def _num(value: Any, fmt: str) -> str:
    """``value`` formatted with ``fmt`` (``-`` for None or non-finite values)."""
    if value is None or isinstance(value, bool) or not isinstance(value, int | float):
        return "-" if value is None else str(value)
    if not math.isfinite(value):
        return "-"
    try:
        return format(value, fmt)
    except ValueError:  # an integer format for a float
        return format(value, ".4g")


def _joined(values: Iterable[Any], fmt: str) -> str:
    """``a / b / c`` of ``values`` formatted with ``fmt``; ``-`` when all are None."""
    values = list(values)
    if all(v is None for v in values):
        return "-"
    return " / ".join(_num(v, fmt) for v in values)


def _duration(seconds: Any) -> str:
    if not isinstance(seconds, int | float) or not math.isfinite(seconds):
        return "-"
    if seconds < 60:
        return f"{seconds:.0f} s"
    minutes, secs = divmod(round(seconds), 60)
    if minutes < 60:
        return f"{minutes} min {secs:02d} s"
    hours, minutes = divmod(minutes, 60)
    return f"{hours} h {minutes:02d} min"


def _shown_path(path: Any) -> str:
    """A path relative to the checkout when it lies beside it (``../shared/data``), else as given."""
    if not path:
        return "-"
    try:
        rel = os.path.relpath(Path(str(path)).resolve(), REPO_DIR)
    except ValueError:
        return str(path)
    return rel if not rel.startswith(os.path.join("..", "..")) else str(path)


def header_lines(
    title: str,
    provenance: dict[str, Any] | None,
    extra: list[tuple[str, str]],
    rendered: dict[str, Any] | None = None,
    source: str | None = None,
) -> list[str]:
    """The title and the table of where the figures come from (``provenance`` of the run; ``rendered``: the
    renderer's, when the page is rendered later from the saved JSON ``source``)."""
    p = provenance or {}
    command = p.get("command")
    rows = [
        ["command", f"`{command}`" if command else UNKNOWN],
        ["date (UTC)", p.get("date_utc") or UNKNOWN],
        ["commit", f"`{p.get('commit') or UNKNOWN}`"],
        ["version", f"gpom {p.get('version') or UNKNOWN}"],
        ["machine", machine_text(p.get("machine"))],
        *([k, v] for k, v in extra),
    ]
    if rendered is not None:
        rows.append(
            [
                "rendered",
                f"from `{source or 'a saved JSON'}` on {rendered.get('date_utc') or UNKNOWN} UTC by "
                f"`{rendered.get('command') or UNKNOWN}` at commit `{rendered.get('commit') or UNKNOWN}`",
            ]
        )
    return [
        f"# {title}",
        "",
        "Generated by the command below; do not edit by hand: run it again to update this page.",
        "",
        md_table(["", ""], rows),
        "",
    ]


# ----------------------------------------------------------------------------------------- suite pages


def _slam(row: dict[str, Any]) -> tuple[dict, dict | None, dict | None]:
    """(the SLAM output of ``evaluate slam``, its SLAM figures, its reference figures) of a suite row."""
    out = row.get("slam") or {}
    return out, out.get("slam"), out.get("reference")


def _relations(out: dict[str, Any]) -> str:
    bench = out.get("relations")
    if not bench:
        return "-"
    return _joined((bench.get("trans_mean_m"), bench.get("rot_mean_deg")), ".4f")


def _precision_recall(ref: dict[str, Any] | None) -> str:
    closures = (ref or {}).get("loop_closures") or {}
    return _joined((closures.get("precision"), closures.get("recall")), ".2f")


def _kept(s: dict[str, Any] | None) -> str:
    if not s:
        return "-"
    dropped = s.get("loop_closures_dropped_by_back_end")
    kept = s.get("loop_closures_accepted")
    return f"{kept}" + ("" if dropped is None else f" ({dropped})")


def _auc_pair(result: dict[str, Any] | None) -> str:
    if not result:
        return "-"
    auc = result.get("auc") or {}
    return _joined((auc.get("gppol"), auc.get("gpfol")), ".4f")


def _status(row: dict[str, Any]) -> str | None:
    if row.get("error"):
        return f"error: {row['error']}"
    if row.get("skipped"):
        return f"skipped: {row['skipped']}"
    return None


def summary_table(rows: list[dict[str, Any]]) -> str:
    """One line per recording: relations, ATE after loop closure, closures kept (dropped by the back end),
    precision / recall, and GPPOL / GPFOL AUC of the three map protocols."""
    header = [
        "recording",
        "relations m / deg",
        "ATE after m",
        "closures kept (dropped)",
        "precision / recall",
        "map from reference poses",
        "ours, reference test points",
        "ours, own test points",
    ]
    lines = []
    for row in rows:
        status = _status(row)
        if status is not None:
            lines.append([row["name"], status, *["-"] * (len(header) - 2)])
            continue
        out, s, ref = _slam(row)
        ate = out.get("ate_rmse_m") or {}
        maps = row.get("maps") or {}
        lines.append(
            [
                row["name"],
                _relations(out),
                _num(ate.get("after"), ".3f"),
                _kept(s),
                _precision_recall(ref),
                *(_auc_pair(maps.get(key)) for key, _, _ in MAP_PROTOCOLS),
            ]
        )
    return md_table(header, lines)


def published_table(rows: list[dict[str, Any]]) -> str | None:
    """Our relations errors beside the published ones (:data:`PUBLISHED_RELATIONS`), for the recordings of
    this run that have both; None when none has."""
    lines = []
    for row in rows:
        published = PUBLISHED_RELATIONS.get(row["name"])
        bench = (row.get("slam") or {}).get("relations")
        if published is None or not bench:
            continue
        theirs, source = published
        ours = f"{bench['trans_mean_m']:.4f} m / {bench['rot_mean_deg']:.3f} deg"
        parts = [_relations_part(bench.get(key)) for key in ("local", "revisit", "wheels_local")]
        lines.append([row["name"], ours, theirs, source, *parts, judged_closures_text(bench.get("closures"))])
    if not lines:
        return None
    header = ["recording", "ours: relations after loop closure", "published", "source"]
    header += ["ours, local relations", "ours, across passes", "wheels alone, local relations"]
    header += ["closures a relation judges: correct / judged"]
    return md_table(header, lines)


def _relations_part(part: dict[str, Any] | None) -> str:
    """``count: m / deg`` of a part of the relations (:func:`pipeline.evaluate_slam.score_relations`), ``-``
    when the run has none (no wheels, or a JSON from before the split)."""
    if not part or not part.get("count"):
        return "-"
    return f"{part['count']}: {part['trans_mean_m']:.4f} / {part['rot_mean_deg']:.3f}"


def slam_table(rows: list[dict[str, Any]]) -> str:
    """The SLAM figures of every recording that ran."""
    header = [
        "recording",
        "scans (matched)",
        "ATE before / after m",
        "NEES before / after",
        "consecutive m / deg",
        "relations (count) m / deg",
        "closures accepted / rejected / dropped",
        "precision / recall",
        "SLAM s",
        "x RT",
        "loop search s (share)",
    ]
    lines = []
    for row in rows:
        out, s, ref = _slam(row)
        if s is None:
            continue
        ate = out.get("ate_rmse_m") or {}
        nees = (ref or {}).get("nees_mean") or {}
        consecutive = (((ref or {}).get("relations_consecutive") or {}).get("after")) or {}
        bench = out.get("relations") or {}
        relations = "-"
        if bench:
            relations = f"({bench.get('count')}) " + _joined(
                (bench.get("trans_mean_m"), bench.get("rot_mean_deg")), ".4f"
            )
        rtf = s.get("realtime_factor")
        share = s.get("loop_search_share")
        loop = "-" if s.get("loop_search_s") is None else f"{s['loop_search_s']:.1f}"
        if share is not None and loop != "-":
            loop += f" ({100 * share:.0f} %)"
        lines.append(
            [
                row["name"],
                f"{s.get('scans')}" + (f" ({ref['matched_scans']})" if ref else ""),
                _joined((ate.get("before"), ate.get("after")), ".3f"),
                _joined((nees.get("before"), nees.get("after")), ".3g"),
                _joined((consecutive.get("trans_mean_m"), consecutive.get("rot_mean_deg")), ".3f"),
                relations,
                " / ".join(
                    _num(s.get(k), "d")
                    for k in (
                        "loop_closures_accepted",
                        "loop_closures_rejected",
                        "loop_closures_dropped_by_back_end",
                    )
                ),
                _precision_recall(ref),
                _num(s.get("wall_s"), ".1f"),
                "-" if rtf is None else (f"{rtf:.0f}" if rtf >= 10 else f"{rtf:.2g}"),
                loop,
            ]
        )
    return md_table(header, lines)


def _unobserved_aucs(result: dict[str, Any]) -> list[float | None]:
    """Mean over the seeds (where defined) of each mapper's AUC over the test points in unobserved cells."""
    out: list[float | None] = []
    for mapper in MAPPERS:
        values = [
            r[f"auc_unobserved_{mapper}"]
            for r in result.get("per_seed") or []
            if r.get(f"auc_unobserved_{mapper}") is not None
        ]
        out.append(sum(values) / len(values) if values else None)
    return out


def _protocol(result: dict[str, Any]) -> str:
    if result.get("protocol") == "ground_truth":
        return "ground-truth raster"
    block = result.get("block_scans")
    seeds = ",".join(str(s) for s in result.get("seeds") or [])
    return f"hold-out, blocks of {block}, seeds {seeds}" if block else f"hold-out, seeds {seeds}"


def _cell_shares(result: dict[str, Any]) -> str:
    shares = result.get("cell_shares")
    if not isinstance(shares, dict) or not shares:
        return "-"
    keys = ("occupied", "free", "unknown")
    if all(isinstance(shares.get(k), int | float) for k in keys):
        return " / ".join(f"{100 * shares[k]:.1f}" for k in keys)
    return ", ".join(f"{k} {_joined((v.get(x) for x in keys), '.3f')}" for k, v in shares.items())


def maps_table(rows: list[dict[str, Any]], key: str) -> str | None:
    """The figures of map protocol ``key`` (:data:`MAP_PROTOCOLS`) for every recording that has them; None
    when none has."""
    results = [(row["name"], (row.get("maps") or {}).get(key)) for row in rows]
    results = [(name, r) for name, r in results if r]
    if not results:
        return None
    with_shares = any(r.get("cell_shares") for _, r in results)
    header = [
        "recording",
        "protocol",
        "AUC GPPOL / GPFOL / grid",
        "log loss GPPOL / GPFOL / grid",
        "AUC observed cells",
        "AUC unobserved cells",
        "unobserved share",
        "GPPOL pose covariance",
    ] + (["cells occupied / free / unknown %"] if with_shares else [])
    lines = []
    for name, r in results:
        auc = r.get("auc") or {}
        loss = r.get("log_loss") or {}
        observed = r.get("auc_observed") or {}
        share = r.get("unobserved_share")
        line = [
            name,
            _protocol(r),
            _joined((auc.get(m) for m in MAPPERS), ".4f"),
            _joined((loss.get(m) for m in MAPPERS), ".3f"),
            _joined((observed.get(m) for m in MAPPERS), ".4f"),
            _joined(_unobserved_aucs(r), ".3f"),
            "-" if share is None else f"{100 * share:.1f} %",
            r.get("gppol_pose_covariance"),
        ]
        lines.append([*line, _cell_shares(r)] if with_shares else line)
    return md_table(header, lines)


TIMING_COLUMNS: tuple[tuple[str, str], ...] = (
    ("simulate_s", "simulate"),
    ("read_s", "read"),
    ("slam_s", "SLAM"),
    ("maps_reference_s", "maps, reference poses"),
    ("maps_slam_s", "maps, ours"),
    ("maps_slam_own_s", "maps, ours, own test points"),
    ("total_s", "total"),
)


def timings_table(rows: list[dict[str, Any]]) -> str:
    """Wall time of each step of each recording (s)."""
    present = [(k, t) for k, t in TIMING_COLUMNS if any(k in (r.get("timings_s") or {}) for r in rows)]
    lines = [[r["name"], *(_num((r.get("timings_s") or {}).get(k), ".1f") for k, _ in present)] for r in rows]
    return md_table(["recording", *(f"{t} s" for _, t in present)], lines)


def notes_list(rows: list[dict[str, Any]]) -> list[str]:
    """One bullet per recording with notes, an error or a skip reason."""
    out = []
    for row in rows:
        notes = list(row.get("notes") or [])
        status = _status(row)
        if status is not None:
            notes.insert(0, status)
        if notes:
            out.append(f"- `{row['name']}`: " + "; ".join(" ".join(n.split()) for n in notes))
    return out


def suite_markdown(
    result: dict[str, Any], rendered: dict[str, Any] | None = None, source: str | None = None
) -> str:
    """The results page of an ``evaluate suite`` result (its ``--json`` object): header, summary, SLAM, the
    three map protocols, timings and notes (``rendered`` / ``source``: see :func:`header_lines`)."""
    rows = list(result.get("datasets") or [])
    seeds = ", ".join(str(s) for s in result.get("seeds") or []) or "-"
    slam_only = bool(result.get("slam_only"))
    extra = [
        ("data", f"`{_shown_path(result.get('data'))}`"),
        ("recordings", str(len(rows))),
        ("maps", "none (`--slam-only`)" if slam_only else f"hold-out seeds {seeds}"),
        ("wall time", _duration(result.get("wall_s"))),
    ]
    lines = header_lines("Evaluation suite: results", result.get("provenance"), extra, rendered, source)
    lines += [
        "What each protocol measures and why: [evaluation.md](evaluation.md). AUC: area under the ROC curve "
        "of p(occupied) (higher is better); log loss: lower is better; precision: of the kept loop closures "
        "against the reference (0.2 m / 2 deg); recall: the share of revisits a correct closure covers.",
        "",
        "## Summary",
        "",
        "AUC as GPPOL / GPFOL, means over the seeds; closures dropped by the robust back end in brackets; "
        "relations: mean translation / rotation error against the benchmark's relations (where "
        "`NAME.relations` lies beside the log).",
        "",
        summary_table(rows),
        "",
    ]
    published = published_table(rows)
    if published is not None:
        lines += [
            "## Against published results",
            "",
            "Mean translation / rotation error against the SLAM benchmark's relations (Kuemmerle et al. "
            "2009) after loop closure; then ours split (count: m / deg) into the local relations (at most "
            f"{LOCAL_TRAVEL_M:g} m of travel apart: the front end) and those across passes (the loop "
            "closures), and the wheel odometry alone on the local ones; last, the accepted loop closures "
            "whose two places a relation joins, judged by it (0.2 m / 2 deg), and of the wrong ones those "
            "the relation's own scans dispute (they overlap more at the closure's pose than at the "
            "relation's: docs/evaluation.md).",
            "",
            published,
            "",
        ]
    lines += [
        "## SLAM",
        "",
        "ATE: RMSE after SE(2) alignment, before / after loop closure; NEES: mean normalised estimation "
        "error squared of the marginals (3 is consistent); consecutive: mean error between consecutive "
        "reference scans after loop closure; x RT: recording duration over SLAM wall time (`-` for "
        "synthetic stamps); loop search: its time and share of the SLAM time.",
        "",
        slam_table(rows),
        "",
    ]
    for key, title, what in MAP_PROTOCOLS:
        table = maps_table(rows, key)
        lines += [f"## {title}", "", what, ""]
        lines += [table if table is not None else "No recording has these maps in this run.", ""]
    lines += [
        "Observed cells: test points in cells (of `mapping.resolution_m`) that a mapped beam's free segment "
        "crosses or its endpoint lies in; the unobserved share is the rest.",
        "",
        "## Timings",
        "",
        timings_table(rows),
        "",
    ]
    notes = notes_list(rows)
    if notes:
        lines += ["## Notes", "", *notes, ""]
    return "\n".join(lines)


# ----------------------------------------------------------------------------------------- bench pages

#: Headline figures of ``bench``: (key, what, format, target, test of the target).
BENCH_FIGURES: tuple[tuple[str, str, str, str, Callable[[float], bool] | None], ...] = (
    (
        "gpfol_queries_per_s",
        "GPFOL query points per second (Intel map at 0.1 m, 15 + 15 neighbours)",
        ",.0f",
        ">= 300,000",
        lambda v: v >= 300_000,
    ),
    (
        "gppol_queries_per_s",
        "GPPOL (SE kernel, closed form) query points per second, same map",
        ",.0f",
        ">= 50,000",
        lambda v: v >= 50_000,
    ),
    ("grid_cells_per_s", "occupancy-grid cell updates per second", ".3g", "", None),
    ("odometry_scans_per_s", "odometry scans per second (intel.clf)", ",.0f", "", None),
    ("slam_intel_wall_s", "SLAM stage on intel.clf, s", ".1f", "", None),
    (
        "slam_intel_realtime_factor",
        "SLAM stage on intel.clf, x real time",
        ".0f",
        ">= 50",
        lambda v: v >= 50,
    ),
    (
        "slam_intel_loop_search_share",
        "loop-closure search, share of the SLAM stage on intel.clf",
        ".0%",
        "<= 20 %",
        lambda v: v <= 0.2,
    ),
    ("slam_fr079_wall_s", "SLAM stage on fr079.clf, s", ".1f", "", None),
    (
        "slam_fr079_realtime_factor",
        "SLAM stage on fr079.clf, x real time",
        ".0f",
        ">= 50",
        lambda v: v >= 50,
    ),
    (
        "slam_fr079_loop_search_share",
        "loop-closure search, share of the SLAM stage on fr079.clf",
        ".0%",
        "<= 20 %",
        lambda v: v <= 0.2,
    ),
    ("pipeline_intel_wall_s", "full pipeline on intel.clf (`run`, both maps, exports), s", ".1f", "", None),
    (
        "pipeline_intel_realtime_factor",
        "full pipeline on intel.clf, x real time",
        ".1f",
        ">= 75",
        lambda v: v >= 75,
    ),
    ("big_building_wall_s", "full pipeline on fr-clinic (maps of 15 M cells), s", ".1f", "", None),
    ("big_building_realtime_factor", "full pipeline on fr-clinic, x real time", ".1f", "", None),
    (
        "big_building_realtime_ratio_to_intel",
        "fr-clinic's real-time factor / intel's (same bench)",
        ".2f",
        ">= 0.5",
        lambda v: v >= 0.5,
    ),
    ("demo_cold_wall_s", "`run.py demo`, numba's cache empty, s", ".1f", "", None),
    ("demo_warm_wall_s", "`run.py demo`, numba's cache filled, s", ".1f", "", None),
    ("large_map_cells", "large map (synthetic city, tiled to disk), cells", ".3g", "", None),
    (
        "large_map_peak_rss_mib",
        "large map, peak memory of its process, MiB",
        ",.0f",
        "< 2,048",
        lambda v: v < 2048,
    ),
    ("tiles_per_s", "large map, tiles per second", ".2f", "", None),
    ("incremental_speedup", "re-render after the Intel loop closure, x a full render", ".2f", "", None),
    ("incremental_add_scans_speedup", "re-render after adding scans, x a full render", ".2f", "", None),
    ("peak_rss_mib", "peak memory of the bench process, MiB", ",.0f", "", None),
)

#: Parts of ``bench`` by key prefix, for the detail tables (first match wins).
BENCH_GROUPS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("Mapping", ("gpfol_", "gppol_", "grid_", "mapping_")),
    ("SLAM", ("slam_", "odometry_")),
    ("Full pipeline", ("pipeline_",)),
    ("Big building", ("big_building_",)),
    ("Demo", ("demo_",)),
    ("Scale", ("large_map_", "incremental_", "tiles_")),
)

_BENCH_META = ("provenance", "parts", "wall_s")


def _flatten(prefix: str, value: Any, out: list[tuple[str, Any]]) -> None:
    if isinstance(value, dict):
        for k, v in value.items():
            _flatten(f"{prefix}.{k}" if prefix else str(k), v, out)
    elif isinstance(value, list) and value and all(isinstance(v, dict) for v in value):
        for i, v in enumerate(value):
            _flatten(f"{prefix}[{i}]", v, out)
    else:
        out.append((prefix, value))


def _value(value: Any) -> str:
    if isinstance(value, bool) or value is None:
        return "-" if value is None else str(value).lower()
    if isinstance(value, int):
        return f"{value:,}" if abs(value) >= 10_000 else str(value)
    if isinstance(value, float):
        if not math.isfinite(value):
            return "-"
        return f"{value:,.0f}" if abs(value) >= 10_000 else f"{value:.4g}"
    if isinstance(value, list):
        return ", ".join(_value(v) for v in value)
    return str(value)


def bench_headline_table(result: dict[str, Any]) -> str:
    lines = []
    for key, what, fmt, target, test in BENCH_FIGURES:
        value = result.get(key)
        number = isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
        shown = format(value, fmt) if number else "not measured"
        met = "-" if test is None or not number else ("met" if test(float(value)) else "**not met**")
        lines.append([what, shown, target or "-", met, f"`{key}`"])
    return md_table(["figure", "measured", "target", "", "key"], lines)


def bench_slam_table(result: dict[str, Any]) -> str | None:
    names = [m.group(1) for k in result if (m := re.fullmatch(r"slam_(.+)_wall_s", k))]
    if not names:
        return None
    lines = []
    for n in names:

        def get(key: str, n: str = n) -> Any:
            return result.get(f"slam_{n}_{key}")

        share = get("loop_search_share")
        loop = _num(get("loop_search_s"), ".2f")
        if share is not None and loop != "-":
            loop += f" ({100 * share:.0f} %)"
        lines.append(
            [
                n,
                _num(get("wall_s"), ".1f"),
                _num(get("data_duration_s"), ".0f"),
                _num(get("realtime_factor"), ".0f"),
                loop,
                _num(get("odometry_scans_per_s"), ".0f"),
                _num(get("scans"), "d"),
                _num(get("keyframes"), "d"),
                _num(get("loop_closures"), "d"),
                get("wheel_odometry"),
            ]
        )
    header = [
        "log",
        "SLAM s",
        "data s",
        "x RT",
        "loop search s (share)",
        "odometry scans/s",
        "scans",
        "keyframes",
        "closures",
        "wheel odometry",
    ]
    return md_table(header, lines)


def bench_markdown(
    result: dict[str, Any], rendered: dict[str, Any] | None = None, source: str | None = None
) -> str:
    """The page of a ``bench`` result (its ``--json`` object): header, the headline figures with their
    targets, the SLAM runs, then every figure of each part (``rendered`` / ``source``: see
    :func:`header_lines`)."""
    parts = result.get("parts")
    extra = [("parts", ", ".join(parts) if parts else "all"), ("wall time", _duration(result.get("wall_s")))]
    lines = header_lines("Benchmarks", result.get("provenance"), extra, rendered, source)
    lines += [
        "What each figure measures: [evaluation.md](evaluation.md#benchmarks). Timings depend on the "
        "machine's load (the machine may be shared); `not measured`: a part that did not run "
        "(`bench --only`).",
        "",
        "## Headline figures",
        "",
        bench_headline_table(result),
        "",
    ]
    slam = bench_slam_table(result)
    if slam is not None:
        lines += ["## SLAM runs", "", slam, ""]
    groups: dict[str, list[tuple[str, Any]]] = {title: [] for title, _ in BENCH_GROUPS}
    groups["Other"] = []
    for key, value in result.items():
        if key in _BENCH_META or value is None:
            continue
        title = next((t for t, prefixes in BENCH_GROUPS if key.startswith(prefixes)), "Other")
        _flatten(key, value, groups[title])
    lines += ["## Every figure", ""]
    for title, items in groups.items():
        if items:
            table = md_table(["key", "value"], ([f"`{k}`", _value(v)] for k, v in items))
            lines += [f"### {title}", "", table, ""]
    return "\n".join(lines)
