"""The commands of ``run.py``: each turns parsed arguments into calls of the stages and reports results.

``run.py`` parses; this module decides what to call. Printing goes through the ``emit_json`` callback or
:func:`_say`, never from the stages themselves.

Stage entry points live in their own modules, one per command, so that they can land independently:

=================  ===================================================  =====
command            entry point                                          issue
=================  ===================================================  =====
simulate           ``datasets.simulation.simulate``                     3
evaluate map       ``pipeline.evaluate_map.evaluate_map``               4
evaluate slam      ``pipeline.evaluate_slam.evaluate_slam``             6
bench              ``pipeline.bench.run_bench``                         4-8
run / demo         ``pipeline.run.run_pipeline`` / ``pipeline.run.run_demo``  7
remap              ``pipeline.remap.remap_run``                         7
=================  ===================================================  =====
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Callable
from typing import Any

from pipeline.errors import not_yet_available
from pipeline.progress import progress_for_terminal

EmitJson = Callable[[Any], None]

# command -> (module, function, issue, what) of its entry point
ENTRY_POINTS: dict[str, tuple[str, str, int, str]] = {
    "simulate": ("datasets.simulation", "simulate", 3, "the simulated worlds"),
    "evaluate map": ("pipeline.evaluate_map", "evaluate_map", 4, "the GP mapper and map evaluation"),
    "evaluate slam": ("pipeline.evaluate_slam", "evaluate_slam", 6, "the SLAM back end and its metrics"),
    "bench": ("pipeline.bench", "run_bench", 4, "the benchmarks"),
    "run": ("pipeline.run", "run_pipeline", 7, "the full pipeline (read, SLAM, GP maps, exports)"),
    "demo": ("pipeline.run", "run_demo", 7, "the full pipeline (read, SLAM, GP maps, exports)"),
    "remap": ("pipeline.remap", "remap_run", 7, "re-mapping from a run folder"),
}


def entry_point(command: str) -> Callable[..., Any]:
    """The function behind ``command``, or a one-line NotYetAvailableError if its stage has not landed."""
    module_name, func_name, issue, what = ENTRY_POINTS[command]
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        if exc.name is not None and module_name.startswith(exc.name):
            raise not_yet_available(command, issue, what) from None
        raise
    func = getattr(module, func_name, None)
    if func is None:
        raise not_yet_available(command, issue, what)
    return func


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
    return handler(args, emit_json)


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


def _report(result: dict[str, Any], args: argparse.Namespace, emit_json: EmitJson, title: str) -> int:
    if getattr(args, "json", False):
        emit_json(result)
    else:
        print_summary(title, result.get("table", result))
    return 0


def cmd_demo(args: argparse.Namespace, emit_json: EmitJson) -> int:
    run_demo = entry_point("demo")
    result = run_demo(
        out=args.out,
        seed=args.seed,
        overwrite=args.overwrite,
        progress=progress_for_terminal(args.quiet or args.json),
        scheduler=args.scheduler,
    )
    return _report(result, args, emit_json, "demo")


def cmd_run(args: argparse.Namespace, emit_json: EmitJson) -> int:
    run_pipeline = entry_point("run")
    result = run_pipeline(
        input_path=args.input,
        out_dir=args.out,
        config_path=args.config,
        scan_topic=args.scan_topic,
        odom_topic=args.odom_topic,
        resolution_m=args.resolution,
        mapper=args.mapper,
        overwrite=args.overwrite,
        progress=progress_for_terminal(args.quiet or args.json),
        scheduler=args.scheduler,
    )
    return _report(result, args, emit_json, f"run {args.input}")


def cmd_remap(args: argparse.Namespace, emit_json: EmitJson) -> int:
    remap_run = entry_point("remap")
    result = remap_run(
        run_dir=args.run_dir,
        poses=args.poses,
        covariances=args.covariances,
        resolution_m=args.resolution,
        bounds=args.bounds,
        out_dir=args.out,
        overwrite=args.overwrite,
        recompute=args.recompute,
        progress=progress_for_terminal(args.quiet or args.json),
        scheduler=args.scheduler,
    )
    return _report(result, args, emit_json, f"remap {args.run_dir}")


def cmd_simulate(args: argparse.Namespace, emit_json: EmitJson) -> int:
    simulate = entry_point("simulate")
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
        evaluate_map = entry_point("evaluate map")
        result = evaluate_map(
            input_path=args.input,
            seeds=args.seed,
            config_path=args.config,
            progress=progress,
            perturb_poses=args.perturb_poses,
            scan_topic=args.scan_topic,
        )
        return _report(result, args, emit_json, f"map evaluation of {args.input}")
    evaluate_slam = entry_point("evaluate slam")
    result = evaluate_slam(
        input_path=args.input,
        relations_path=args.relations,
        reference_path=args.reference,
        config_path=args.config,
        progress=progress,
    )
    return _report(result, args, emit_json, f"SLAM evaluation of {args.input}")


def cmd_bench(args: argparse.Namespace, emit_json: EmitJson) -> int:
    run_bench = entry_point("bench")
    result = run_bench(progress=progress_for_terminal(args.quiet or args.json))
    return _report(result, args, emit_json, "benchmarks")
