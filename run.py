#!/usr/bin/env python3
"""Command line of the GP occupancy-mapping tool (the README's "Command line"; SPEC section 3).

This file only parses arguments, loads the configuration, calls :mod:`pipeline` and turns known errors
(:class:`datasets.errors.GpomError`) into one line on stderr with exit status 1. Usage errors exit 2;
Ctrl-C exits 130 and SIGTERM 143, both after removing what the interrupted command had half written.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import signal
import sys
import threading
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from datasets.errors import GpomError  # noqa: E402

DESCRIPTION = """\
Gaussian-process occupancy maps with variance (O'Callaghan & Ramos, IJRR 2012) from ROS bags and CARMEN
logs, before and after loop closure. With no command, runs the demo on a simulated loop world."""

EPILOG = """\
Documentation in the checkout: README.md (start here); docs/run-folder.md (what a run writes, loading it in
nav2, Foxglove, Rerun or Python); docs/mapping.md, docs/slam.md (the methods); docs/evaluation.md (the
protocols of 'evaluate' and the figures of 'bench'); docs/results.md, docs/bench.md (the latest results)."""


class _VersionAction(argparse.Action):
    """``--version``: print ``gpom X.Y.Z`` on stdout and exit 0 (the version is looked up only when asked)."""

    def __init__(self, option_strings: list[str], dest: str = argparse.SUPPRESS, help: str | None = None):
        super().__init__(option_strings, dest=dest, default=argparse.SUPPRESS, nargs=0, help=help)

    def __call__(
        self,
        parser: argparse.ArgumentParser,
        namespace: argparse.Namespace,
        values: object,
        option_string: str | None = None,
    ) -> None:
        from pipeline.commands import version_line

        sys.stdout.write(version_line() + "\n")
        parser.exit()


#: The largest seed numpy's generators take.
MAX_SEED = 2**32 - 1
#: The most hold-out seeds one command evaluates (each maps the recording again: seconds to minutes).
MAX_SEEDS = 1000


def seed_int(text: str) -> int:
    """One random seed, 0 to :data:`MAX_SEED`; argparse.ArgumentTypeError otherwise (a usage error)."""
    try:
        seed = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not an integer seed") from None
    if not 0 <= seed <= MAX_SEED:
        raise argparse.ArgumentTypeError(f"'{text}': a seed lies between 0 and {MAX_SEED} (2**32 - 1)")
    return seed


def seed_list(text: str) -> list[int]:
    """The hold-out seeds one ``--seed`` word names: ``3``, ``1,2``, ``0-4`` or a mix (``0-2,7``), each at
    most :data:`MAX_SEED`, at most :data:`MAX_SEEDS` of them; argparse.ArgumentTypeError otherwise (a usage
    error, exit 2)."""
    seeds: list[int] = []
    for part in text.split(","):
        lo, sep, hi = part.strip().partition("-")
        try:
            first, last = int(lo), int(hi if sep else lo)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"'{text}' is not a seed, a list (1,2) or a range (0-4)"
            ) from None
        if first < 0 or last < first:
            raise argparse.ArgumentTypeError(f"'{text}': seeds are integers >= 0, ranges run upwards")
        if last > MAX_SEED:
            raise argparse.ArgumentTypeError(f"'{text}': a seed lies between 0 and {MAX_SEED} (2**32 - 1)")
        if len(seeds) + last - first + 1 > MAX_SEEDS:
            raise argparse.ArgumentTypeError(
                f"'{text}': {len(seeds) + last - first + 1} seeds; at most {MAX_SEEDS} in one command"
            )
        seeds.extend(range(first, last + 1))
    return seeds


class _SeedsAction(argparse.Action):
    """``--seed`` words (:func:`seed_list`) add up, each seed once: ``--seed 0-4``, ``--seed 0 --seed 3``.
    One word per flag, so that a positional argument after it is never taken for a seed."""

    def __call__(
        self,
        parser: argparse.ArgumentParser,
        namespace: argparse.Namespace,
        values: Any,
        option_string: str | None = None,
    ) -> None:
        seeds = list(getattr(namespace, self.dest) or [])
        seeds.extend(s for s in values if s not in seeds)
        if len(seeds) > MAX_SEEDS:
            parser.error(f"argument --seed: {len(seeds)} seeds; at most {MAX_SEEDS} in one command")
        setattr(namespace, self.dest, seeds)


def _add_seeds(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--seed",
        type=seed_list,
        action=_SeedsAction,
        metavar="SEEDS",
        help="seed(s) of the hold-out split: 3, 1,2 or 0-4; repeat the flag to add more (default: 0-4)",
    )


def _quiet_option() -> argparse.ArgumentParser:
    """``-q`` for every command, so that it may also follow the command (``run.py run X -q``); absent there,
    it keeps the value given before the command."""
    p = argparse.ArgumentParser(add_help=False)
    p.add_argument("-q", "--quiet", action="store_true", default=argparse.SUPPRESS, help="no progress bars")
    return p


def _add_json(p: argparse.ArgumentParser) -> None:
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout and nothing else")


def _add_rerun(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--rerun",
        type=Path,
        metavar="FILE.rrd",
        help="also write a Rerun recording of the finished run folder to FILE.rrd, checked before the run "
        "(an existing FILE.rrd is replaced only with --overwrite; open it: rerun FILE.rrd)",
    )


def _add_results(p: argparse.ArgumentParser, what: str, example: str) -> None:
    """``--markdown FILE`` and ``--from-json FILE`` of ``evaluate suite`` and ``bench``."""
    p.add_argument(
        "--markdown",
        type=Path,
        metavar="FILE",
        help=f"also write the {what} as a markdown page (with the date, commit, version, machine and command "
        f"line of the run), e.g. {example}",
    )
    p.add_argument(
        "--from-json",
        type=Path,
        metavar="FILE",
        help="run nothing: read the JSON a former run printed with --json and show it (with --markdown: "
        "render its page; the page reports that run's commit and machine)",
    )


#: Options that choose what ``evaluate suite`` / ``bench`` runs, meaningless with ``--from-json``.
RUN_OPTIONS = {
    "suite": ("data", "only", "seed", "config", "slam_only", "no_simulated", "breakdown"),
    "bench": ("only",),
}


def check_usage(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Combinations argparse cannot express: ``--from-json`` runs nothing, so the options that choose what
    to run are usage errors beside it (exit 2)."""
    which = "suite" if getattr(args, "target", None) == "suite" else args.command
    if getattr(args, "from_json", None) is None or which not in RUN_OPTIONS:
        return
    given = [name for name in RUN_OPTIONS[which] if getattr(args, name, None) not in (None, False)]
    if given:
        flags = ", ".join("--" + name.replace("_", "-") for name in given)
        parser.error(f"--from-json runs nothing: {flags} cannot be used with it")


def _add_scheduler(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        help="render map tiles on Dask: 'local' (a local cluster) or a scheduler address tcp://HOST:PORT "
        "(default: in this process)",
    )


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python run.py",
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "-q", "--quiet", action="store_true", help="no progress bars (also accepted after the command)"
    )
    parser.add_argument("--version", action=_VersionAction, help="print the version (gpom X.Y.Z) and exit")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    quiet = [_quiet_option()]

    p = sub.add_parser(
        "demo", parents=quiet, help="simulate the loop world, run the full pipeline on it, print a summary"
    )
    p.add_argument("--out", type=Path, default=Path("out/demo"), help="run folder (default: out/demo)")
    p.add_argument("--seed", type=seed_int, default=0, help="simulation seed (default: 0)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing run folder")
    _add_scheduler(p)
    _add_json(p)

    p = sub.add_parser("run", parents=quiet, help="full pipeline on a ROS1/ROS2 bag or a CARMEN log")
    p.add_argument("input", type=Path, help="ROS1 .bag, ROS2 bag (folder, .mcap, .db3), CARMEN log")
    p.add_argument("--out", type=Path, help="run folder (default: out/<input name>)")
    p.add_argument("--config", type=Path, help="YAML configuration (default: pipeline/default.yaml)")
    p.add_argument(
        "--scan-topic",
        help="LaserScan / PointCloud2 topic (default: auto-detect); 'all': every LaserScan topic",
    )
    p.add_argument(
        "--odom-topic", help="nav_msgs/Odometry topic (default: auto-detect; none: run on the scans alone)"
    )
    p.add_argument("--resolution", type=float, help="map cell size in metres")
    p.add_argument("--mapper", choices=["gppol", "gpfol"], help="GP with uncertain (gppol) or exact inputs")
    p.add_argument(
        "--bag-format",
        choices=["mcap", "bag"],
        help="maps bag: ROS2 .mcap or ROS1 .bag (default: the configuration's export.bag_format)",
    )
    p.add_argument("--overwrite", action="store_true", help="replace an existing run folder")
    _add_rerun(p)
    _add_scheduler(p)
    _add_json(p)

    p = sub.add_parser(
        "remap", parents=quiet, help="new maps from a run folder with other poses, without the bag"
    )
    p.add_argument("run_dir", type=Path, help="a run folder written by 'run' or 'demo'")
    p.add_argument("--poses", type=Path, help="trajectory (.g2o or .tum) to map with")
    p.add_argument("--covariances", type=Path, help="covariances .npz (keys as trajectory/covariances.npz)")
    p.add_argument("--resolution", type=float, help="map cell size in metres")
    p.add_argument(
        "--bounds",
        help="XMIN,YMIN,XMAX,YMAX in metres (default: the run's map bounds); a negative XMIN needs the '=' "
        "form, --bounds=-10,-5,30,20",
    )
    p.add_argument("--out", type=Path, help="output folder (default: RUN_DIR/remap)")
    p.add_argument(
        "--recompute", action="store_true", help="render even when nothing changed (default: copy the map)"
    )
    p.add_argument("--overwrite", action="store_true", help="replace an existing output folder")
    _add_rerun(p)
    _add_scheduler(p)
    _add_json(p)

    p = sub.add_parser(
        "simulate", parents=quiet, help="write a simulated run as a bag plus its ground-truth raster"
    )
    p.add_argument("world", choices=["street", "two-platform", "loop"], help="simulated world")
    p.add_argument("--out", type=Path, required=True, help="bag path: .bag (ROS1), .mcap or a folder (ROS2)")
    p.add_argument("--seed", type=seed_int, default=0, help="random seed (default: 0)")

    p = sub.add_parser("convert", parents=quiet, help="CARMEN log (or any readable recording) to a ROS bag")
    p.add_argument("input", type=Path, help="recording to read")
    p.add_argument("output", type=Path, help=".bag (ROS1), .mcap or a folder (ROS2)")
    p.add_argument("--scan-topic", help="scan topic of a bag input ('all': every one, 'none': odometry only)")
    p.add_argument("--odom-topic", help="odometry topic of the input, if a bag (none: without odometry)")

    p = sub.add_parser(
        "evaluate",
        parents=quiet,
        help="map or SLAM metrics (protocols: docs/evaluation.md)",
        description="Map and SLAM metrics: the map hold-out and ground-truth protocols, maps from our own "
        "SLAM, relations and ATE, the suite of every recording. What each protocol measures and why: "
        "docs/evaluation.md; the latest suite results: docs/results.md.",
    )
    ev = p.add_subparsers(dest="target", metavar="TARGET", required=True)
    q = ev.add_parser(
        "map", parents=quiet, help="AUC of GPPOL, GPFOL and the occupancy grid (ground truth or hold-out)"
    )
    q.add_argument("input", type=Path, help="a simulated bag (with INPUT.gt.npz) or a recording")
    _add_seeds(q)
    q.add_argument("--config", type=Path, help="YAML configuration")
    q.add_argument("--scan-topic", help="LaserScan topic of a bag (default: auto-detect); 'all': every one")
    q.add_argument(
        "--perturb-poses",
        metavar="SIGMA_XY_M,SIGMA_THETA_RAD",
        help="map from seeded noisy poses (GPPOL gets their covariance), score against the true ones; "
        "at most 100 m and pi rad",
    )
    q.add_argument(
        "--breakdown",
        action="store_true",
        help="hold-out protocol: also each AUC by the test points' distance from their laser, by the "
        "mapped beam endpoints within 1 m of them and by their distance from the nearest one, with the "
        "part of the whole AUC's shortfall on each bin's occupied and free points (where a map wins or "
        "loses)",
    )
    _add_json(q)
    q = ev.add_parser("slam", parents=quiet, help="relations error and ATE of the SLAM trajectory")
    q.add_argument("input", type=Path, help="recording with odometry and scans")
    g = q.add_mutually_exclusive_group(required=True)
    g.add_argument("--relations", type=Path, help="relations file: t1 t2 x y z roll pitch yaw")
    g.add_argument("--reference", type=Path, help="reference log (e.g. a GMapping-corrected CARMEN log)")
    q.add_argument("--config", type=Path, help="YAML configuration")
    q.add_argument(
        "--inject-false-closures",
        type=float,
        metavar="FRACTION",
        help="fault injection: add FRACTION x (accepted closures) wrong closures (random keyframe pairs, "
        "off by 2-20 m and up to 90 deg, with the information of real ones) before the final optimisation; "
        "the report says how many the back end kept",
    )
    q.add_argument("--seed", type=seed_int, default=0, help="seed of the injected closures (default 0)")
    _add_json(q)
    q = ev.add_parser(
        "suite",
        parents=quiet,
        help="every recording of a data folder: SLAM metrics and map AUCs, one table (a row each)",
    )
    q.add_argument(
        "--data", type=Path, metavar="DIR", help="data folder (default: ../shared/data beside the checkout)"
    )
    q.add_argument(
        "--only",
        nargs="+",
        action="extend",
        metavar="NAME",
        help="only these datasets, named as in the table (intel, fr079, seattle, fr-clinic, loop-0, ...)",
    )
    _add_seeds(q)
    q.add_argument("--config", type=Path, help="YAML configuration")
    q.add_argument("--slam-only", action="store_true", help="SLAM metrics only, no maps")
    q.add_argument(
        "--no-simulated", action="store_true", help="leave out the simulated loop world (loop-0 to loop-2)"
    )
    q.add_argument(
        "--breakdown",
        action="store_true",
        help="the hold-out protocols' per-seed rows also split each AUC as evaluate map --breakdown does "
        "(in --json; the tables stay as they are)",
    )
    _add_json(q)
    _add_results(q, "result tables", "docs/results.md")

    p = sub.add_parser(
        "bench",
        parents=quiet,
        help="performance figures: GP query rates, SLAM and pipeline speed, memory (docs/evaluation.md)",
        description="Performance figures, measured as benchmarks: GPFOL / GPPOL query rates, the SLAM stage "
        "and the full pipeline on intel.clf, the demo with numba's cache empty and filled, a 10^8-cell map "
        "tiled to disk. What each figure means: docs/evaluation.md (Benchmarks); the latest: docs/bench.md.",
    )
    from pipeline.bench import PART_NAMES

    p.add_argument(
        "--only",
        nargs="+",
        action="extend",
        choices=PART_NAMES,
        metavar="PART",
        help=f"only these parts ({', '.join(PART_NAMES)}; default: all, 15-50 minutes)",
    )
    _add_json(p)
    _add_results(p, "figures", "docs/bench.md")
    return parser


def _print_json(obj: Any) -> None:
    sys.stdout.write(json.dumps(obj, indent=2, default=float) + "\n")


def _dispatch(args: argparse.Namespace) -> int:
    from pipeline import commands

    return commands.dispatch(args, _print_json)


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised like Ctrl-C so that every stage unwinds the same way (no partial run folder left)."""


def _in_finaliser(frame: Any) -> bool:
    """Whether ``frame`` or one of its callers is a ``__del__`` (Python drops, and prints with a traceback,
    an exception raised there: numba's code generator finalises LLVM objects)."""
    while frame is not None:
        if frame.f_code.co_name == "__del__":
            return True
        frame = frame.f_back
    return False


def _send_again(signum: int) -> None:
    """Send ``signum`` to this process again shortly, from a thread: it is raised once the finaliser or
    callback it landed in has returned."""
    timer = threading.Timer(0.02, os.kill, (os.getpid(), signum))
    timer.daemon = True
    timer.start()


def _on_signal(signum: int, frame: Any) -> None:
    from pipeline.run_folder import note_interrupt

    note_interrupt(signum)  # kept even if Python drops the exception below (raised inside a callback)
    if _in_finaliser(frame):
        _send_again(signum)
        return
    raise Terminated() if signum == signal.SIGTERM else KeyboardInterrupt()


def _on_unraisable(unraisable: Any) -> None:
    """``sys.unraisablehook``: an interrupt raised where Python drops exceptions (a weakref callback, e.g.
    ``WeakKeyDictionary``'s) would print a traceback and be lost; it is sent again instead, quietly (the
    signal is recorded, see :func:`_on_signal`). Anything else goes to the default hook."""
    from pipeline.run_folder import pending_interrupt

    if isinstance(unraisable.exc_value, KeyboardInterrupt) and pending_interrupt() is not None:
        _send_again(pending_interrupt())
        return
    sys.__unraisablehook__(unraisable)


def _install_handlers() -> dict[int, Any]:
    """Our handlers for SIGTERM, and for SIGINT unless it is ignored (a background job's); the old ones."""
    previous = {signal.SIGTERM: signal.signal(signal.SIGTERM, _on_signal)}
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        previous[signal.SIGINT] = signal.signal(signal.SIGINT, _on_signal)
    return previous


def _interrupted(signum: int) -> int:
    print("terminated" if signum == signal.SIGTERM else "interrupted", file=sys.stderr)
    return 128 + signum


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    words = list(sys.argv[1:] if argv is None else argv)
    if args.command is None:
        args = parser.parse_args([*words, "demo"])
    check_usage(parser, args)
    args.command_line = shlex.join(["python", "run.py", *words])
    from pipeline.memory import keep_freed_memory
    from pipeline.run_folder import note_interrupt, pending_interrupt

    keep_freed_memory()  # a big building's steps reuse each other's memory (pipeline.memory)

    note_interrupt(None)
    in_main_thread = threading.current_thread() is threading.main_thread()
    previous = _install_handlers() if in_main_thread else {}
    unraisable_hook = sys.unraisablehook
    if in_main_thread:
        sys.unraisablehook = _on_unraisable
    try:
        status = _dispatch(args)
    except GpomError as exc:
        message = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        print(f"error: {message}", file=sys.stderr)
        return 1
    except Terminated:
        return _interrupted(signal.SIGTERM)
    except KeyboardInterrupt:  # (also a SIGTERM that a finaliser swallowed and the run folder raised again)
        return _interrupted(pending_interrupt() or signal.SIGINT)
    except Exception:
        # a signal's exception raised inside a C callback comes back wrapped (numba's cache loader:
        # "SystemError: ... returned a result with an exception set"); the recorded signal still decides
        pending = pending_interrupt()
        if pending is None:
            raise
        return _interrupted(pending)
    finally:
        sys.unraisablehook = unraisable_hook
        for signum, handler in previous.items():
            signal.signal(signum, handler)
        signum = pending_interrupt()
        note_interrupt(None)  # a later call in this process (tests, notebooks) starts clean
    return status if signum is None else _interrupted(signum)


if __name__ == "__main__":
    sys.exit(main())
