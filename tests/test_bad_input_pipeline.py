"""Bad input to the pipeline stages: resources checked before work, output folders that cannot be
written, staging folders of killed runs, damaged run folders for ``remap``, library exceptions turned into one
line at the stage boundary, messages that name the file.

The run is a real one: the first 80 scans of the raw Intel log (intel.clf), mapped with GPFOL and short
training so the module's run takes seconds.
"""

from __future__ import annotations

import bz2
import errno
import json
import os
import shutil
import subprocess
import sys
from collections import namedtuple
from pathlib import Path

import pytest
import yaml

from datasets.errors import ConfigError, GpomError
from mapping.build import MapBuilder
from pipeline import run as run_module
from pipeline.config import load_config
from pipeline.errors import PipelineError, stage_boundary
from pipeline.remap import remap_run
from pipeline.run import run_pipeline
from pipeline.run_folder import remove_stale_staging, staged_run_folder, write_summary
from tests.conftest import REPO, data_file

FAST = {"mapping": {"train": {"anneal_evaluations": 10, "lbfgs_iterations": 10}, "mapper": "gpfol"}}


def _config(folder: Path, overrides: dict) -> Path:
    path = folder / "config.yaml"
    merged = {k: dict(v) for k, v in FAST.items()}
    for section, values in overrides.items():
        merged.setdefault(section, {}).update(values)
    path.write_text(yaml.safe_dump(merged))
    return path


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "run.py", "-q", *args], cwd=REPO, capture_output=True, text=True, timeout=600
    )


def _one_line_error(proc: subprocess.CompletedProcess, pattern: str) -> str:
    import re

    assert proc.returncode == 1, proc.stderr
    assert "Traceback" not in proc.stderr, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), proc.stderr
    assert re.search(pattern, lines[0]), lines[0]
    return lines[0]


@pytest.fixture(scope="module")
def small_log(tmp_path_factory) -> Path:
    """The first 80 laser scans of intel.clf (with their odometry), as a plain CARMEN log."""
    lines, scans = [], 0
    with bz2.open(data_file("intel/intel.clf.bz2"), "rt") as f:
        for line in f:
            lines.append(line)
            scans += line.startswith(("FLASER", "ROBOTLASER1"))
            if scans == 80:
                break
    path = tmp_path_factory.mktemp("log") / "intel-80.clf"
    path.write_text("".join(lines))
    return path


@pytest.fixture(scope="module")
def small_run(small_log, tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("run")
    out = folder / "run"
    run_pipeline(small_log, out, load_config(_config(folder, {})))
    return out


def _fail(*_args, **_kwargs):
    raise AssertionError("this stage must not run")


# --- resources, before any work ---------------------------------------------------------------------------


def test_a_map_finer_than_memory_allows_fails_before_slam(small_log, tmp_path, monkeypatch) -> None:
    monkeypatch.setattr("pipeline.run.run_slam_recording", _fail)
    single_scan = r"the map of a single scan: .* cells, above scale\.max_map_cells"
    with pytest.raises(PipelineError, match=single_scan):
        run_pipeline(
            small_log, tmp_path / "r", load_config(_config(tmp_path, {}), {"mapping": {"resolution_m": 1e-4}})
        )
    assert list(tmp_path.iterdir()) == [tmp_path / "config.yaml"]


def test_the_run_bounds_are_checked_before_training(small_log, tmp_path, monkeypatch) -> None:
    """A map larger than the limit only because of where SLAM put the scans fails before training and
    rendering (here the single-scan estimate is disabled so that the check on the run's bounds is what
    catches it)."""
    monkeypatch.setattr(run_module, "scan_reach_m", lambda scans: 1e-3)  # a return, of no reach
    monkeypatch.setattr(MapBuilder, "fit", _fail)
    cfg = _config(tmp_path, {"scale": {"max_map_cells": 1000}})
    whole_run = rf"{small_log}: the maps of the run: .* cells, above .* = 1e\+03"
    with pytest.raises(PipelineError, match=whole_run):
        run_pipeline(small_log, tmp_path / "r", load_config(cfg))
    assert not (tmp_path / "r").exists() and not list(tmp_path.glob("r.partial-*"))


def test_cli_remap_over_huge_bounds_is_one_line_before_reading(small_run, tmp_path) -> None:
    proc = _cli("remap", str(small_run), "--bounds=-1e6,-1e6,1e6,1e6", "--out", str(tmp_path / "m"))
    flag = r"the remap with --bounds -1e6,-1e6,1e6,1e6: "
    _one_line_error(proc, flag + r"2e\+06 x 2e\+06 m at 0\.1 m is .* cells, above scale\.max_map_cells")
    assert not (tmp_path / "m").exists()
    # bounds whose size no float holds: the message still names the option (it named neither)
    proc = _cli("remap", str(small_run), "--bounds=-1e308,-1e308,1e308,1e308", "--out", str(tmp_path / "m"))
    _one_line_error(proc, r"the remap with --bounds -1e308,-1e308,1e308,1e308: a map over .* than any float")
    assert not (tmp_path / "m").exists()


def test_remap_checks_the_size_before_reading_the_scans(small_run, tmp_path, monkeypatch) -> None:
    monkeypatch.setattr("pipeline.remap.read_scans", _fail)
    with pytest.raises(PipelineError, match=r"cells, above scale\.max_map_cells"):
        remap_run(small_run, resolution_m=1e-5, out_dir=tmp_path / "m")


def test_output_below_a_file_fails_before_reading(small_log, tmp_path, monkeypatch) -> None:
    (tmp_path / "file").write_text("")
    monkeypatch.setattr("pipeline.run.open_dataset", _fail)
    with pytest.raises(PipelineError, match=r"file/run: cannot be created \(.*file is not a folder\)"):
        run_pipeline(small_log, tmp_path / "file" / "run")


def test_unwritable_output_folder_fails_before_reading(small_log, tmp_path, monkeypatch) -> None:
    """The probe creates a file (root passes permission bits, so the refusal is simulated at the probe)."""

    def refuse(*_a, **_k):
        raise PermissionError(errno.EACCES, "Permission denied")

    monkeypatch.setattr("pipeline.run.open_dataset", _fail)
    monkeypatch.setattr("pipeline.run_folder.tempfile.TemporaryFile", refuse)
    with pytest.raises(PipelineError, match=r"out/run: cannot write into .* \(Permission denied\)"):
        run_pipeline(small_log, tmp_path / "out" / "run")


def test_full_disk_fails_before_reading(small_log, tmp_path, monkeypatch) -> None:
    usage = namedtuple("usage", "total used free")
    one_mib_free = usage(10**9, 10**9 - 2**20, 2**20)
    monkeypatch.setattr("pipeline.run_folder.shutil.disk_usage", lambda _p: one_mib_free)
    monkeypatch.setattr("pipeline.run.open_dataset", _fail)
    with pytest.raises(PipelineError, match=r"only 1 MiB free on the disk of .* needs at least 64 MiB"):
        run_pipeline(small_log, tmp_path / "run")


def test_disk_full_while_writing_is_one_line_and_leaves_nothing(small_log, tmp_path, monkeypatch) -> None:
    def no_space(folder, *_a, **_k):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(Path(folder) / "after" / "occupancy.png"))

    monkeypatch.setattr("pipeline.run.write_maps", no_space)
    out = tmp_path / "run"
    with pytest.raises(
        PipelineError, match=r"run: writing failed: OSError: No space left on device: .*png"
    ) as err:
        run_pipeline(small_log, out, load_config(_config(tmp_path, {})))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["config.yaml"]
    # the file is named where the run was going, not in the staging folder that no longer exists
    assert ".partial-" not in str(err.value) and f"{out}{os.sep}" in str(err.value)
    assert str(err.value).endswith(f"{os.sep}after{os.sep}occupancy.png (GPOM_TRACEBACK=1 shows where)")


def test_a_failed_copy_names_where_it_was_going(tmp_path) -> None:
    """A copy onto a full disk fails at its destination: the one line names both ends, not just the
    (healthy) source."""
    src, dst = tmp_path / "run" / "params.json", tmp_path / "full" / "params.json"
    with (
        pytest.raises(PipelineError) as err,
        stage_boundary("remap", tmp_path / "run", name_known_errors=False),
    ):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(src), None, str(dst))
    assert str(err.value).startswith(
        f"{tmp_path / 'run'}: remap failed: OSError: No space left on device: {src} -> {dst}"
    )


# --- staging folders of killed runs -----------------------------------------------------------------------


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_staging_folders_of_dead_processes_are_removed(tmp_path) -> None:
    out = tmp_path / "run"
    dead, live = _dead_pid(), os.getppid()
    for name in (f"run.partial-{dead}", f"run.replaced-{dead}", f"run.partial-{live}", "run.partial-x"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "a.txt").write_text("x")
    (tmp_path / f"other.partial-{dead}").mkdir()  # another run folder's: not ours to touch
    out.mkdir()  # an earlier run: beside it, a dead run's retired folder is garbage (without it, see
    write_summary(out, {})  # test_run_folder: it is the old run and goes back)
    with staged_run_folder(out, overwrite=True) as stage:
        write_summary(stage, {})
    left = sorted(p.name for p in tmp_path.iterdir())
    assert left == sorted(["run", f"run.partial-{live}", "run.partial-x", f"other.partial-{dead}"])
    assert remove_stale_staging(tmp_path / "other") == [tmp_path / f"other.partial-{dead}"]


# --- library exceptions and messages ----------------------------------------------------------------------


def test_a_gtsam_failure_in_slam_is_one_line_naming_the_input(small_log, tmp_path, monkeypatch) -> None:
    def indeterminate(*_a, **_k):  # what GTSAM's IndeterminateSystemException looks like from Python
        raise RuntimeError(
            "\nIndeterminant linear system detected while working near variable\n7 (Symbol: x7).\n\n"
            "Thrown when a linear system is ill-posed."
        )

    monkeypatch.setattr("pipeline.run.run_slam_recording", indeterminate)
    with pytest.raises(PipelineError) as info:
        run_pipeline(small_log, tmp_path / "r", load_config(_config(tmp_path, {})))
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith(f"{small_log}: SLAM failed: RuntimeError: Indeterminant linear system")


def test_gp_training_failure_names_the_input(small_log, tmp_path) -> None:
    """200 occupied neighbours per query cannot be found in the first scan: the message says of which file."""
    cfg = _config(
        tmp_path,
        {"mapping": {"k_occupied": 200, "k_free": 200, "train": {"scans": 1, "anneal_evaluations": 10}}},
    )
    with pytest.raises(GpomError, match=rf"^{small_log}: cannot train the GP: no training neighbourhood"):
        run_pipeline(small_log, tmp_path / "r", load_config(cfg))


@pytest.mark.parametrize("value", ["0.00", "81.90"], ids=["below_range_min", "no_return"])
def test_a_log_without_any_return_is_one_line_before_slam(small_log, tmp_path, monkeypatch, value) -> None:
    """Every range below range_min, or every one the no-return reading: nothing to map, said before SLAM
    (not as a failed GP training or a traceback after it)."""
    lines = []
    for line in small_log.read_text().splitlines():
        if line.startswith("FLASER"):
            parts = line.split()
            n = int(parts[1])
            parts[2 : 2 + n] = [value] * n
            line = " ".join(parts)
        lines.append(line)
    log = tmp_path / "blank.clf"
    log.write_text("\n".join(lines) + "\n")
    monkeypatch.setattr(run_module, "run_slam_recording", _fail)
    with pytest.raises(PipelineError, match=rf"^{log}: no scan has a return .*: nothing to map$"):
        run_pipeline(log, tmp_path / "r", load_config(_config(tmp_path, {})))
    assert not (tmp_path / "r").exists()


def test_laser_noise_of_a_source_the_recording_lacks_is_an_error_before_slam(
    small_log, tmp_path, monkeypatch
):
    """mapping.sources naming a source the log does not have (a typo: 'scan' for the log's 'FLASER') was
    ignored without a word, the default noise used; it is a one-line error right after reading."""
    monkeypatch.setattr(run_module, "run_slam_recording", _fail)
    cfg = _config(tmp_path, {"mapping": {"sources": {"scan": {"range_var_m2": 0.0004}}}})
    with pytest.raises(
        ConfigError, match=rf"^{small_log}: mapping.sources names 'scan', which is no scan source "
    ):
        run_pipeline(small_log, tmp_path / "r", load_config(cfg))
    assert not (tmp_path / "r").exists()
    proc = _cli("evaluate", "map", str(small_log), "--config", str(cfg), "--seed", "0")
    _one_line_error(
        proc, r"mapping\.sources names 'scan', which is no scan source of it \(its sources: 'FLASER'\)"
    )


# --- remap on damaged run folders --------------------------------------------------------------------------


@pytest.fixture
def damaged(small_run, tmp_path) -> Path:
    copy = tmp_path / "copy"
    shutil.copytree(small_run, copy)
    return copy


NOT_BOUNDS = r"map\.bounds_xy_m is not XMIN, YMIN, XMAX, YMAX"


@pytest.mark.parametrize(
    ("summary", "pattern"),
    [
        ([], r"no map bounds \(map\.bounds_xy_m\): damaged, or not a run folder"),
        ({"map": 3}, r"no map bounds"),
        ({"map": {"bounds_xy_m": [0, 0, "x", 1]}}, r"no map bounds"),
        ({"map": {"bounds_xy_m": [0, 0, 1]}}, NOT_BOUNDS),
        ({"map": {"bounds_xy_m": [0, 0, float("nan"), 1]}}, NOT_BOUNDS),
    ],
)
def test_remap_on_a_summary_of_the_wrong_shape(damaged, tmp_path, summary, pattern) -> None:
    (damaged / "summary.json").write_text(json.dumps(summary))
    proc = _cli("remap", str(damaged), "--out", str(tmp_path / "m"))
    _one_line_error(proc, rf"{damaged}/summary\.json: {pattern}")


@pytest.mark.parametrize("poses", [None, "g2o"])
def test_remap_without_covariances(damaged, tmp_path, poses) -> None:
    (damaged / "trajectory" / "covariances.npz").unlink()
    extra = [] if poses is None else ["--poses", str(damaged / "trajectory" / "pose_graph.g2o")]
    proc = _cli("remap", str(damaged), "--out", str(tmp_path / "m"), *extra)
    _one_line_error(proc, r"covariances\.npz: no such file or directory")


@pytest.mark.parametrize(
    ("key", "mode"), [("scan_relative_after", "relative"), ("scan_after", "world")], ids=["relative", "world"]
)
def test_remap_with_non_finite_covariances(damaged, tmp_path, key: str, mode: str) -> None:
    """A non-finite entry in the covariances the map is built with (mapping.gppol.pose_covariances of the
    run's config.yaml) is a one-line error."""
    import numpy as np

    path = damaged / "trajectory" / "covariances.npz"
    with np.load(path) as z:
        arrays = dict(z)
    arrays[key][3, 0, 0] = np.nan
    np.savez(path, **arrays)
    config = damaged / "config.yaml"
    text = config.read_text()
    assert "pose_covariances: relative" in text
    config.write_text(text.replace("pose_covariances: relative", f"pose_covariances: {mode}"))
    proc = _cli("remap", str(damaged), "--out", str(tmp_path / "m"))
    _one_line_error(proc, r"covariances: not every entry is finite")


@pytest.mark.parametrize("damage", ["negated", "asymmetric"])
def test_remap_with_covariances_that_are_none(damaged, tmp_path, damage: str) -> None:
    """Negated (negative-definite) covariances gave GPPOL inputs of no spread and a placement layer of
    zeros; an asymmetric matrix is no covariance either."""
    import numpy as np

    path = damaged / "trajectory" / "covariances.npz"
    with np.load(path) as z:
        arrays = dict(z)
    key = "scan_relative_after"
    if damage == "negated":
        arrays[key] = -arrays[key]
    else:
        arrays[key][4, 0, 1] += 1.0
    np.savez(path, **arrays)
    proc = _cli("remap", str(damaged), "--out", str(tmp_path / "m"), "--recompute")
    _one_line_error(proc, r"covariances: entry \d+ is not symmetric positive semi-definite")


def _damage_scans(path: Path, how: str) -> None:
    import numpy as np

    if how == "truncated":
        data = path.read_bytes()
        path.write_bytes(data[: len(data) // 2])
        return
    with np.load(path) as z:
        arrays = dict(z)
    if how == "laser_nan":
        arrays["laser_in_base_xytheta"][0] = np.nan
    elif how == "offsets_beyond":
        arrays["offsets"][-1] = 10**9
    elif how == "offsets_decreasing":
        arrays["offsets"][5] = arrays["offsets"][4] - 1
    elif how == "fewer_stamps":
        arrays["stamps_ns"] = arrays["stamps_ns"][:-50]
    elif how == "negative_range":
        arrays["ranges_m"][7] = -1.0
    np.savez(path, **arrays)


@pytest.mark.parametrize(
    ("how", "pattern"),
    [
        ("truncated", r"not a scans archive \(File is not a zip file\)"),
        ("laser_nan", r"laser_in_base_xytheta is not a finite x, y, theta"),
        ("offsets_beyond", r"offsets do not split its \d+ beams"),
        ("offsets_decreasing", r"offsets do not split"),
        ("fewer_stamps", r"\d+ scans but \d+ stamps"),
        ("negative_range", r"negative ranges \(beam 7\)"),
    ],
)
def test_remap_on_damaged_scans_is_one_line(damaged, tmp_path, how: str, pattern: str) -> None:
    _damage_scans(damaged / "scans.npz", how)
    proc = _cli("remap", str(damaged), "--out", str(tmp_path / "m"))
    _one_line_error(proc, rf"{damaged}/scans\.npz: .*{pattern}")
    assert not (tmp_path / "m").exists()


def test_overwrite_refuses_to_delete_the_input_or_the_run_it_remaps(small_log, damaged, tmp_path) -> None:
    """--out naming the folder that holds the input (or the run folder being remapped, or a folder of
    other files) with --overwrite is a one-line error before any work, and deletes nothing."""
    data = tmp_path / "data"
    data.mkdir()
    log = data / small_log.name
    shutil.copy(small_log, log)
    proc = _cli("run", str(log), "--out", str(data), "--overwrite")
    _one_line_error(proc, rf"{data}: holds {log}, which this command reads; --overwrite would delete it")
    proc = _cli("remap", str(damaged), "--out", str(damaged), "--overwrite")
    _one_line_error(proc, rf"{damaged}: holds {damaged}, which this command reads")
    proc = _cli("remap", str(damaged), "--out", str(damaged.parent), "--overwrite")
    _one_line_error(proc, rf"{damaged.parent}: holds {damaged}, which this command reads")
    (data / "notes.txt").write_text("mine")
    proc = _cli("run", str(small_log), "--out", str(data), "--overwrite")
    _one_line_error(proc, rf"{data}: exists and is not a run folder \(no summary\.json\)")
    assert sorted(p.name for p in data.iterdir()) == sorted([log.name, "notes.txt"])
    assert (damaged / "scans.npz").is_file() and (damaged / "summary.json").is_file()


# --- Ctrl-C under a local Dask cluster ---------------------------------------------------------------------


@pytest.mark.slow
def test_ctrl_c_under_a_local_cluster_prints_no_worker_traceback(small_log, tmp_path) -> None:
    """A terminal's Ctrl-C reaches the whole process group: the cluster's workers must not print
    tracebacks of their own while the run unwinds."""
    import signal
    import time

    out = tmp_path / "run"
    cfg = _config(tmp_path, {})
    args = ["run", str(small_log), "--out", str(out), "--config", str(cfg), "--scheduler", "local"]
    proc = subprocess.Popen(
        [sys.executable, "run.py", "-q", *args],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,  # its own process group, as a terminal's foreground job
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    import psutil

    def workers() -> int:  # the cluster's processes (a resource tracker and one per worker)
        try:
            return len(psutil.Process(proc.pid).children(recursive=True))
        except psutil.NoSuchProcess:
            return 0

    def ignores_sigint() -> bool:  # while the cluster starts, the run ignores SIGINT (pipeline.scale)
        with open(f"/proc/{proc.pid}/status") as f:
            mask = next(line.split()[1] for line in f if line.startswith("SigIgn:"))
        return bool(int(mask, 16) & (1 << (signal.SIGINT - 1)))

    deadline = time.monotonic() + 300
    while (workers() < 3 or ignores_sigint()) and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.01)
    assert proc.poll() is None, "the run ended before it could be interrupted"
    assert workers() >= 3 and not ignores_sigint(), "the cluster never started"
    os.killpg(proc.pid, signal.SIGINT)
    _, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 130, stderr
    assert "interrupted" in stderr and "Traceback" not in stderr and "KeyboardInterrupt" not in stderr, stderr
    assert not out.exists() and not list(tmp_path.glob("run.partial-*"))


@pytest.mark.parametrize(
    "exc",
    [MemoryError(), OSError(errno.ENOSPC, "No space left on device"), RuntimeError("Indeterminant\nsystem")],
)
def test_any_command_turns_a_library_exception_into_one_line(small_log, tmp_path, monkeypatch, capsys, exc):
    """The command line's last line of defence, for the commands without stages of their own (convert)."""
    import run

    def explode(*_a, **_k):
        raise exc

    monkeypatch.setattr("pipeline.convert.convert_recording", explode)
    assert run.main(["-q", "convert", str(small_log), str(tmp_path / "x.bag")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    expected = f"error: {small_log}: convert failed: {type(exc).__name__}"
    assert len(err) == 1 and err[0].startswith(expected), err


def test_an_interrupt_python_dropped_still_stops_the_run(tmp_path, monkeypatch, capsys) -> None:
    """Python drops a KeyboardInterrupt raised inside a weakref callback or a finaliser ("Exception ignored
    in ..."); a test run saw a Ctrl-C land there and the run complete with status 0. The signal is also
    recorded, and neither the run folder nor the exit status ignore it."""
    import signal

    import run
    from pipeline.run_folder import note_interrupt

    out = tmp_path / "run"
    try:
        with pytest.raises(KeyboardInterrupt), staged_run_folder(out) as stage:
            write_summary(stage, {})
            note_interrupt(signal.SIGINT)  # the handler ran; its exception was lost
    finally:
        note_interrupt(None)  # never leave a pending interrupt to the rest of the session
    assert list(tmp_path.iterdir()) == []

    def finishes_anyway(args, emit_json):
        note_interrupt(signal.SIGTERM)
        return 0

    monkeypatch.setattr("pipeline.commands.dispatch", finishes_anyway)
    assert run.main(["bench"]) == 143
    assert capsys.readouterr().err.strip() == "terminated"
    from pipeline.run_folder import pending_interrupt

    assert pending_interrupt() is None  # main() leaves nothing pending behind it

    def wrapped_by_c(args, emit_json):  # a Ctrl-C landing in numba's cache loader (a CI run saw it)
        note_interrupt(signal.SIGINT)
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as exc:
            raise SystemError("_numba_unpickle returned a result with an exception set") from exc

    monkeypatch.setattr("pipeline.commands.dispatch", wrapped_by_c)
    assert run.main(["bench"]) == 130
    assert capsys.readouterr().err.strip() == "interrupted"
    assert pending_interrupt() is None

    def plain_bug(args, emit_json):  # without a signal, an unexpected error still escapes as itself
        raise SystemError("a bug")

    monkeypatch.setattr("pipeline.commands.dispatch", plain_bug)
    with pytest.raises(SystemError, match="a bug"):
        run.main(["bench"])


@pytest.mark.parametrize("resolution_m", [1e-300, 1e-320])
def test_absurdly_fine_resolutions_are_one_line_errors(resolution_m: float) -> None:
    """Cell counts beyond the float range (1e-300 m) and sides beyond it (a subnormal cell size) are known
    errors, not OverflowErrors from formatting or rounding them."""
    from pipeline.map_bounds import check_map_cells

    with pytest.raises(PipelineError, match=r"cells") as info:
        check_map_cells((0.0, 0.0, 100.0, 50.0), resolution_m, 50_000_000, "the map")
    assert "\n" not in str(info.value) and len(str(info.value)) < 300


def test_a_signal_inside_a_finaliser_is_raised_after_it(capsys) -> None:
    """A Ctrl-C that lands in a ``__del__`` (numba's code generator finalises LLVM objects; a CI run saw
    "Exception ignored in: <function ObjectRef.__del__ ...>" and a traceback) is raised in the code that
    the finaliser interrupted, once it returns, instead of being printed and dropped there."""
    import os
    import signal

    import run
    from pipeline.run_folder import note_interrupt

    class Finalised:
        def __del__(self) -> None:
            os.kill(os.getpid(), signal.SIGINT)
            for _ in range(10_000):  # bytecode boundaries inside the finaliser, where the handler runs
                pass

    import time

    previous = signal.signal(signal.SIGINT, run._on_signal)
    try:
        with pytest.raises(KeyboardInterrupt):
            obj = Finalised()
            del obj
            end = time.monotonic() + 5.0
            while time.monotonic() < end:  # the signal is raised here
                pass
    finally:
        signal.signal(signal.SIGINT, previous)
        note_interrupt(None)
    assert "Exception ignored" not in capsys.readouterr().err


def test_a_signal_inside_a_weakref_callback_is_raised_after_it_without_a_traceback(
    monkeypatch, capsys
) -> None:
    """A Ctrl-C during the export landed in ``WeakKeyDictionary``'s callback (the second sweep: 5 of 16
    runs printed "Exception ignored in: ... KeyboardInterrupt" with a traceback): the unraisable hook sends
    it again, quietly, and it is raised in the code the callback interrupted. A SIGTERM whose exception a
    callback swallowed ends as a SIGTERM (143, "terminated"), not as Ctrl-C."""
    import os
    import signal
    import sys
    import time
    import weakref

    import run
    from pipeline.run_folder import note_interrupt

    class Target:
        pass

    def callback(_ref) -> None:
        os.kill(os.getpid(), signal.SIGINT)
        for _ in range(10_000):  # bytecode boundaries inside the callback, where the handler runs
            pass

    previous = signal.signal(signal.SIGINT, run._on_signal)
    monkeypatch.setattr(sys, "unraisablehook", run._on_unraisable)
    try:
        with pytest.raises(KeyboardInterrupt):
            target = Target()
            ref = weakref.ref(target, callback)
            del target
            end = time.monotonic() + 5.0
            while time.monotonic() < end:  # the signal is raised here
                pass
        assert ref() is None
    finally:
        signal.signal(signal.SIGINT, previous)
        note_interrupt(None)
    assert "Exception ignored" not in capsys.readouterr().err

    def terminated_in_a_callback(args, emit_json):
        note_interrupt(signal.SIGTERM)
        raise KeyboardInterrupt  # (as staged_run_folder raises a pending interrupt)

    monkeypatch.setattr("pipeline.commands.dispatch", terminated_in_a_callback)
    assert run.main(["bench"]) == 143
    assert capsys.readouterr().err.strip() == "terminated"
