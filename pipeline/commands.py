"""The commands of ``run.py``: each turns parsed arguments into calls of the stages and reports results.

``run.py`` parses; this module decides what to call. Printing goes through the ``emit_json`` callback or
the console given by the CLI, never from the stages themselves.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from typing import Any

from pipeline.errors import not_yet_available
from pipeline.progress import progress_for_terminal

EmitJson = Callable[[Any], None]


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


def cmd_demo(args: argparse.Namespace, emit_json: EmitJson) -> int:
    raise not_yet_available("demo", 7, "the full pipeline (read, SLAM, GP maps, exports)")


def cmd_run(args: argparse.Namespace, emit_json: EmitJson) -> int:
    raise not_yet_available("run", 7, "the full pipeline (read, SLAM, GP maps, exports)")


def cmd_remap(args: argparse.Namespace, emit_json: EmitJson) -> int:
    raise not_yet_available("remap", 7, "re-mapping from a run folder")


def cmd_simulate(args: argparse.Namespace, emit_json: EmitJson) -> int:
    raise not_yet_available("simulate", 3, "the simulated worlds")


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
    if args.target == "map":
        raise not_yet_available("evaluate map", 4, "the GP mapper and map evaluation")
    raise not_yet_available("evaluate slam", 6, "the SLAM back end and its metrics")


def cmd_bench(args: argparse.Namespace, emit_json: EmitJson) -> int:
    raise not_yet_available("bench", 4, "the mapper benchmarks")
