"""The commands of ``run.py``: each turns parsed arguments into calls of the stages and reports results.

``run.py`` parses; this module decides what to call. Printing goes through the ``emit_json`` callback or
:func:`_say`, never from the stages themselves.

Each command's entry point lives in its own module, imported when the command runs (``--help`` stays fast):

=================  =========================================================
command            entry point
=================  =========================================================
simulate           ``datasets.simulation.simulate``
convert            ``pipeline.convert.convert_recording``
evaluate map       ``pipeline.evaluate_map.evaluate_map``
evaluate slam      ``pipeline.evaluate_slam.evaluate_slam``
evaluate suite     ``pipeline.evaluate_suite.evaluate_suite``
bench              ``pipeline.bench.run_bench``
run / demo         ``pipeline.run.run_pipeline`` / ``pipeline.run.run_demo``
remap              ``pipeline.remap.remap_run``
=================  =========================================================
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from pipeline.errors import PipelineError, stage_boundary
from pipeline.progress import progress_for_terminal
from pipeline.provenance import package_version

EmitJson = Callable[[Any], None]

#: The argument naming what a command works on, in order of preference (for error messages).
SUBJECT_ARGS = ("input", "run_dir", "data", "out")


def dispatch(args: argparse.Namespace, emit_json: EmitJson) -> int:
    """Run the command named by ``args.command``; returns the exit status."""
    handler = {
        "demo": cmd_demo,
        "run": cmd_run,
        "remap": cmd_remap,
        "simulate": cmd_simulate,
        "convert": cmd_convert,
        "evaluate": cmd_evaluate,
        "bench": cmd_bench,
    }[args.command]
    # the last line of defence: a library exception no stage translated is still one line naming the input
    subject = next((str(v) for k in SUBJECT_ARGS if (v := getattr(args, k, None)) is not None), args.command)
    with stage_boundary(args.command, subject, name_known_errors=False):
        return handler(args, emit_json)


def version_line() -> str:
    """What ``run.py --version`` prints: ``gpom X.Y.Z``."""
    return f"gpom {package_version()}"


def _say(text: str) -> None:
    """One human-readable line on stdout (the CLI's, not the library's)."""
    sys.stdout.write(text + "\n")


def print_summary(title: str, rows: dict[str, Any]) -> None:
    """A two-column table of ``rows`` on stdout (rich when stdout is a terminal, plain text otherwise)."""
    from rich.console import Console
    from rich.table import Table

    table = Table(title=title, show_header=False)
    table.add_column("what", style="bold")
    table.add_column("value", justify="right")
    for key, value in rows.items():
        if isinstance(value, float):
            value = f"{value:.4g}"
        table.add_row(str(key), "-" if value is None else str(value))
    Console(file=sys.stdout, width=120).print(table)


def print_columns(title: str, rows: list[dict[str, str]], caption: str | None = None) -> None:
    """A table of ``rows`` (one dict of column -> text each, the columns of the first) on stdout; cells wrap
    to the terminal's width, or to 200 characters in a pipe."""
    from rich.console import Console
    from rich.table import Table

    table = Table(title=title, caption=caption, caption_justify="left", show_lines=True)
    columns = list(rows[0]) if rows else []
    for i, column in enumerate(columns):
        last = i == len(columns) - 1
        table.add_column(column, justify="left" if i == 0 or last else "right", no_wrap=i == 0)
    for row in rows:
        table.add_row(*(str(row.get(c, "-")) for c in columns))
    Console(file=sys.stdout, width=None if sys.stdout.isatty() else 200).print(table)


def _report(result: dict[str, Any], args: argparse.Namespace, emit_json: EmitJson, title: str) -> int:
    if getattr(args, "json", False):
        emit_json(result)
    else:
        print_summary(title, result.get("table", result))
    return 0


def cmd_demo(args: argparse.Namespace, emit_json: EmitJson) -> int:
    from pipeline.run import run_demo

    result = run_demo(
        out=args.out,
        seed=args.seed,
        overwrite=args.overwrite,
        progress=progress_for_terminal(args.quiet or args.json),
        scheduler=args.scheduler,
    )
    return _report(result, args, emit_json, "demo")


def cmd_run(args: argparse.Namespace, emit_json: EmitJson) -> int:
    from pipeline.config import load_config
    from pipeline.run import run_pipeline

    config = load_config(
        args.config,
        {
            "input": {"scan_topic": args.scan_topic, "odom_topic": args.odom_topic},
            "mapping": {"resolution_m": args.resolution, "mapper": args.mapper},
            "scale": {"scheduler": args.scheduler},
            "export": {"bag_format": args.bag_format},
        },
    )
    from pipeline.run import default_run_dir

    out_dir = args.out if args.out is not None else default_run_dir(args.input)
    _check_rerun(args, args.input)
    result = run_pipeline(
        args.input,
        out_dir,
        config,
        overwrite=args.overwrite,
        progress=progress_for_terminal(args.quiet or args.json),
    )
    _write_rerun(args, out_dir)
    return _report(result, args, emit_json, f"run {args.input}")


def cmd_remap(args: argparse.Namespace, emit_json: EmitJson) -> int:
    from pipeline.remap import default_remap_dir, remap_run

    out_dir = args.out if args.out is not None else default_remap_dir(args.run_dir)
    _check_rerun(args, args.run_dir, args.poses, args.covariances)
    result = remap_run(
        run_dir=args.run_dir,
        poses=args.poses,
        covariances=args.covariances,
        resolution_m=args.resolution,
        bounds=args.bounds,
        out_dir=out_dir,
        overwrite=args.overwrite,
        recompute=args.recompute,
        progress=progress_for_terminal(args.quiet or args.json),
        scheduler=args.scheduler,
    )
    _write_rerun(args, out_dir)
    return _report(result, args, emit_json, f"remap {args.run_dir}")


def _check_rerun(args: argparse.Namespace, *reads: Path | None) -> None:
    """``--rerun FILE.rrd`` checked before any work (a run of minutes must not end on a bad path or replace
    a recording without --overwrite)."""
    if args.rerun is not None:
        from pipeline.viewer import check_rerun_path

        check_rerun_path(args.rerun, args.overwrite, reads)


def _write_rerun(args: argparse.Namespace, folder: Path) -> None:
    """``--rerun FILE.rrd``: a Rerun recording of the finished run folder (:mod:`pipeline.viewer`)."""
    if args.rerun is not None:
        from pipeline.viewer import write_rerun

        try:
            write_rerun(folder, args.rerun)
        except PipelineError as exc:  # the run folder itself is complete: say so, keep one line
            raise PipelineError(f"{exc}; the run folder {folder} is complete") from None


def cmd_simulate(args: argparse.Namespace, emit_json: EmitJson) -> int:
    from datasets.simulation import simulate

    report = simulate(args.world, args.out, seed=args.seed)
    _say(f"wrote {args.out}: " + ", ".join(f"{k} {v}" for k, v in report.items()))
    return 0


def cmd_convert(args: argparse.Namespace, emit_json: EmitJson) -> int:
    from pipeline.convert import convert_recording

    progress = progress_for_terminal(args.quiet)
    report = convert_recording(
        args.input, args.output, scan_topic=args.scan_topic, odom_topic=args.odom_topic, progress=progress
    )
    _say(
        f"wrote {report['output']}: {report['scans']} scans, {report['odometry']} odometry messages, "
        f"{report['poses']} reference poses"
    )
    return 0


def cmd_evaluate(args: argparse.Namespace, emit_json: EmitJson) -> int:
    progress = progress_for_terminal(args.quiet or args.json)
    if args.target == "map":
        from pipeline.evaluate_map import evaluate_map

        result = evaluate_map(
            input_path=args.input,
            seeds=args.seed,
            config_path=args.config,
            progress=progress,
            perturb_poses=args.perturb_poses,
            scan_topic=args.scan_topic,
            breakdown=args.breakdown,
        )
        return _report(result, args, emit_json, f"map evaluation of {args.input}")
    if args.target == "suite":
        return _evaluate_suite(args, emit_json, progress)
    from pipeline.evaluate_slam import evaluate_slam

    result = evaluate_slam(
        input_path=args.input,
        relations_path=args.relations,
        reference_path=args.reference,
        config_path=args.config,
        progress=progress,
        inject_false_closures=args.inject_false_closures,
        seed=args.seed,
    )
    return _report(result, args, emit_json, f"SLAM evaluation of {args.input}")


def _check_markdown_target(path: Path | None) -> None:
    """Fail before a long run if the ``--markdown`` page cannot be written (its folder is missing or not
    writable, or the path is a folder)."""
    if path is None:
        return
    folder = path.absolute().parent
    if path.is_dir():
        raise PipelineError(f"{path}: --markdown names a folder, not a file")
    if not folder.is_dir():
        raise PipelineError(f"{path}: cannot write the markdown page: no such folder {folder}")
    from pipeline.run_folder import probe_writable

    reason = probe_writable(folder)
    if reason is not None:
        raise PipelineError(f"{path}: cannot write the markdown page ({reason})")


def _load_result(path: Path, key: str, what: str) -> dict[str, Any]:
    """The JSON object a former ``--json`` run printed (``key`` must be in it); one-line errors."""
    try:
        result = json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise PipelineError(f"{path}: no such file") from None
    except OSError as exc:
        raise PipelineError(f"{path}: cannot read it ({exc.strerror or exc})") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        message = exc.msg if isinstance(exc, json.JSONDecodeError) else "not UTF-8 text"
        raise PipelineError(f"{path}: not JSON ({message})") from None
    if not isinstance(result, dict) or key not in result:
        raise PipelineError(f"{path}: not the JSON of {what} (no '{key}' key)")
    return result


@contextmanager
def _saved_json(path: Path | None, what: str) -> Iterator[None]:
    """Within the block, a saved ``--json`` result (``path``; None: a fresh run, errors pass) whose values
    have the wrong shape to render is a one-line PipelineError naming the file, not a traceback."""
    try:
        yield
    except (KeyError, TypeError, AttributeError, ValueError, IndexError) as exc:
        if path is None:
            raise
        detail = f"{type(exc).__name__}: {exc}"
        raise PipelineError(
            f"{path}: not the JSON of {what} (a value has the wrong shape: {detail})"
        ) from None


def _write_markdown(path: Path | None, text: str | None, emit_json: bool) -> None:
    """Write the page ``text`` to ``path`` (nothing when either is None); ``wrote PATH`` unless JSON."""
    if path is None or text is None:
        return
    from datasets.files import write_text_atomic

    try:
        write_text_atomic(path, text)
    except OSError as exc:
        raise PipelineError(f"{path}: cannot write the markdown page ({exc.strerror or exc})") from None
    if not emit_json:
        _say(f"wrote {path}")


def _rendered(args: argparse.Namespace) -> dict[str, Any] | None:
    """The renderer's provenance when the page comes from a saved JSON, else None."""
    if args.from_json is None:
        return None
    from pipeline.provenance import provenance

    return provenance(getattr(args, "command_line", None))


def _source(args: argparse.Namespace) -> str | None:
    return None if args.from_json is None else str(args.from_json)


def _evaluate_suite(args: argparse.Namespace, emit_json: EmitJson, progress: Any) -> int:
    """``evaluate suite``: exit status 0 when every recording ran, failed or not (failures are rows)."""
    from pipeline.evaluate_suite import TABLE_LEGEND, evaluate_suite, table_row

    _check_markdown_target(args.markdown)
    if args.from_json is not None:
        result = _load_result(args.from_json, "datasets", "evaluate suite --json")
        rows = result["datasets"]
        if not isinstance(rows, list) or not all(
            isinstance(r, dict) and isinstance(r.get("name"), str) for r in rows
        ):
            raise PipelineError(
                f"{args.from_json}: not the JSON of evaluate suite --json ('datasets' is not a list of "
                "recordings, each with its 'name')"
            )
        with _saved_json(args.from_json, "evaluate suite --json"):
            result["table"] = [table_row(r) for r in rows]
    else:
        result = evaluate_suite(
            data_dir=args.data,
            only=args.only,
            seeds=args.seed,
            config_path=args.config,
            slam_only=args.slam_only,
            simulated=not args.no_simulated,
            progress=progress,
            command=getattr(args, "command_line", None),
            breakdown=args.breakdown,
        )
    page = None
    if args.markdown is not None:
        from pipeline.results_markdown import suite_markdown

        with _saved_json(args.from_json, "evaluate suite --json"):
            page = suite_markdown(result, _rendered(args), _source(args))
    if args.json:
        emit_json({k: v for k, v in result.items() if k != "table"})
    else:
        seeds = ",".join(map(str, result.get("seeds") or []))
        maps = "SLAM only" if result.get("slam_only") else f"maps: hold-out seeds {seeds}"
        wall = result.get("wall_s")
        took = f"; {wall:.0f} s" if isinstance(wall, int | float) else ""
        title = f"evaluation suite of {result.get('data')} ({maps}{took})"
        print_columns(title, result["table"], TABLE_LEGEND)
    _write_markdown(args.markdown, page, args.json)
    return 0


def cmd_bench(args: argparse.Namespace, emit_json: EmitJson) -> int:
    from pipeline.bench import run_bench

    _check_markdown_target(args.markdown)
    if args.from_json is not None:
        result = _load_result(args.from_json, "gpfol_queries_per_s", "bench --json")
    else:
        result = run_bench(
            progress=progress_for_terminal(args.quiet or args.json),
            parts=args.only,
            command=getattr(args, "command_line", None),
        )
    page = None
    if args.markdown is not None:
        from pipeline.results_markdown import bench_markdown

        with _saved_json(args.from_json, "bench --json"):
            page = bench_markdown(result, _rendered(args), _source(args))
    shown = result if args.json else {k: v for k, v in result.items() if k != "provenance"}
    _report(shown, args, emit_json, "benchmarks")
    _write_markdown(args.markdown, page, args.json)
    return 0
