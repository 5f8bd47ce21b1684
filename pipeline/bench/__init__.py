"""``bench``: the performance figures of SPEC section 7, measured as benchmarks (never as timed tests).

Each part is a function ``(progress) -> dict`` in its own module of this package: :mod:`.mapping` (GP and
grid query rates), :mod:`.slam` (the SLAM stage), :mod:`.pipeline` (``run`` end to end),
:mod:`.big_building` (``run`` on the fr-clinic hospital, maps of 15 M cells), :mod:`.demo` (the
demo with numba's cache empty and filled) and :mod:`.scale` (a map larger than memory, incremental
updates). They live apart from the product stages they time; their keys are merged into one object with
the keys of SPEC section 3 first, then ``parts`` (the parts that ran: ``bench --only`` runs some) and
``provenance`` (date, commit, version, machine and command line of the run, :mod:`pipeline.provenance`).
What each figure means: ``docs/evaluation.md``; the page of a run: ``bench --markdown FILE``.
"""

from __future__ import annotations

import importlib
import resource
import sys
import time
from pathlib import Path
from typing import Any

from pipeline.progress import Progress

SPEC_KEYS = (
    "gpfol_queries_per_s",
    "gppol_queries_per_s",
    "grid_cells_per_s",
    "odometry_scans_per_s",
    "slam_intel_wall_s",
    "pipeline_intel_wall_s",
    "pipeline_intel_realtime_factor",
    "peak_rss_mib",
)

# (module, function) of each part, run in this order.
PARTS: tuple[tuple[str, str], ...] = (
    ("pipeline.bench.mapping", "bench_mapping"),
    ("pipeline.bench.slam", "bench_slam"),
    ("pipeline.bench.pipeline", "bench_pipeline"),
    ("pipeline.bench.big_building", "bench_big_building"),
    ("pipeline.bench.demo", "bench_demo"),
    ("pipeline.bench.scale", "bench_scale"),
)


def peak_rss_mib() -> float:
    """Peak resident memory of this process (MiB).

    On Linux the high-water mark of its own memory (``VmHWM``): ``getrusage``'s max RSS of a process started
    by ``fork`` + ``exec`` begins at its parent's resident size, so it cannot measure a child alone (the
    large-map benchmark runs in a child process; ``tests/test_scale.py`` checks this)."""
    status = Path("/proc/self/status")
    if status.is_file():
        for line in status.read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return kib / 1024.0 if sys.platform != "darwin" else kib / 2**20


def part_name(module_name: str) -> str:
    """The name of a part (``mapping`` for ``pipeline.bench.mapping``), as ``bench --only`` takes it."""
    return module_name.rsplit(".", 1)[1]


PART_NAMES: tuple[str, ...] = tuple(part_name(m) for m, _ in PARTS)


def run_bench(
    progress: Progress | None = None, parts: list[str] | None = None, command: str | None = None
) -> dict[str, Any]:
    """Run the benchmark parts named in ``parts`` (default: every one, in :data:`PARTS` order); returns the
    SPEC keys (None where a part that did not run would measure them) plus extras, ``parts``, ``wall_s``
    (of them all) and ``provenance`` (recorded before the first part, with the command line ``command``)."""
    from pipeline.errors import PipelineError
    from pipeline.provenance import provenance

    progress = progress or Progress()
    unknown = sorted(set(parts or ()) - set(PART_NAMES))
    if unknown:
        names = ", ".join(PART_NAMES)
        raise PipelineError(f"bench --only: no part named {', '.join(unknown)} (parts: {names})")
    chosen = [(m, f) for m, f in PARTS if not parts or part_name(m) in parts]
    result: dict[str, Any] = dict.fromkeys(SPEC_KEYS)
    origin = provenance(command)
    t0 = time.perf_counter()
    for module_name, func_name in chosen:
        result.update(getattr(importlib.import_module(module_name), func_name)(progress))
    intel, big = result.get("pipeline_intel_realtime_factor"), result.get("big_building_realtime_factor")
    result["big_building_realtime_ratio_to_intel"] = big / intel if intel and big else None
    result["peak_rss_mib"] = peak_rss_mib()
    result["parts"] = [part_name(m) for m, _ in chosen]
    result["wall_s"] = time.perf_counter() - t0
    result["provenance"] = origin
    return result
