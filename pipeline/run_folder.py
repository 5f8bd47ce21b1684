"""Run folders (SPEC section 4): written under a temporary name, renamed when complete, ``summary.json`` last.

A run folder that exists under its final name is complete. While a run is in progress its files live in
``DIR.partial-<pid>`` beside ``DIR``; on any failure or interruption that folder is removed, so nothing
half-written ever looks complete; the staging folders of processes killed outright (SIGKILL) are removed by
the next run into the same folder. An existing ``DIR`` is never replaced unless ``overwrite=True``, and then
only after the new run has succeeded.
"""

from __future__ import annotations

import glob
import json
import os
import re
import shutil
import tempfile
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from datasets.errors import GpomError
from datasets.files import write_text_atomic
from pipeline.errors import PipelineError, reworded

SUMMARY_NAME = "summary.json"


#: Free space a run folder needs at least, checked before any work (bytes): about twice the demo's run folder
#: (two 0.1 m maps of a 120 x 50 m loop with every export), so below this floor even a small run cannot
#: finish. A disk that fills up later is still a one-line error (the stages' I/O
#: errors are translated) and leaves nothing behind.
MIN_FREE_BYTES = 64 * 2**20


class _Interrupts:
    """The last interrupting signal the command line received (SIGINT or SIGTERM), or None.

    Python drops an exception raised while it runs a finaliser or a weakref callback ("Exception ignored
    in ..."), so a Ctrl-C that lands there would be lost and the run would finish as if nothing happened.
    The command line's handlers therefore also record the signal here, and :func:`staged_run_folder`
    refuses to complete a run folder while one is pending.
    """

    signum: int | None = None


def note_interrupt(signum: int | None) -> None:
    """Record an interrupting signal (the command line's signal handlers; None clears it)."""
    _Interrupts.signum = signum


def pending_interrupt() -> int | None:
    """The interrupting signal received so far, or None."""
    return _Interrupts.signum


def probe_writable(folder: Path) -> str | None:
    """Whether a file can be created in ``folder`` (a real probe: permissions, read-only file systems and
    ACLs all count): None if so, else the reason."""
    try:
        with tempfile.TemporaryFile(dir=folder, prefix=".gpom-write-probe-"):
            pass
    except OSError as exc:
        return str(exc.strerror or exc)
    return None


def check_output_dir(
    out_dir: Path, overwrite: bool, min_free_bytes: int = MIN_FREE_BYTES, reads: Iterable[Path | None] = ()
) -> None:
    """Fail early (before any work) if ``out_dir`` exists and may not be replaced, or cannot be written.

    ``--overwrite`` replaces a run folder (one holding ``summary.json``) or an empty folder, never a folder
    of other files, and never one that is or holds a path in ``reads`` (the command's input, the run folder
    it remaps, its pose files): replacing it would delete what the run reads.
    Writable means: the nearest existing ancestor is a folder in which a file can be created (a real probe:
    permissions, read-only file systems and ACLs all count) on a disk with ``min_free_bytes`` free.
    """
    out_dir = Path(out_dir)
    if out_dir.exists() and not overwrite:
        raise PipelineError(f"{out_dir}: already exists (use --overwrite to replace it)")
    if out_dir.exists() and not out_dir.is_dir():
        raise PipelineError(f"{out_dir}: exists and is not a folder")
    if out_dir.exists():
        _check_replaceable(out_dir, reads)
    ancestor = writable_ancestor(out_dir)
    longest = len(f"{out_dir.name}.replaced-{2**22}".encode())  # the staging names (pids up to 2^22)
    if longest > _name_max(ancestor):
        raise PipelineError(
            f"{out_dir}: a name of {len(out_dir.name.encode())} bytes is too long for its staging folder "
            f"(at most {_name_max(ancestor) - (longest - len(out_dir.name.encode()))} bytes)"
        )
    free = shutil.disk_usage(ancestor).free
    if free < min_free_bytes:
        raise PipelineError(
            f"{out_dir}: only {free / 2**20:.0f} MiB free on the disk of {ancestor} "
            f"(a run needs at least {min_free_bytes / 2**20:.0f} MiB)"
        )


def writable_ancestor(path: Path) -> Path:
    """The nearest existing folder above ``path``, in which a file can be created (:func:`probe_writable`);
    PipelineError naming ``path`` if it is no folder or cannot be written into."""
    ancestor = Path(path).absolute().parent
    while not ancestor.exists() and ancestor != ancestor.parent:
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        raise PipelineError(f"{path}: cannot be created ({ancestor} is not a folder)")
    reason = probe_writable(ancestor)
    if reason is not None:
        raise PipelineError(f"{path}: cannot write into {ancestor} ({reason})")
    return ancestor


def _name_max(folder: Path) -> int:
    """The longest file name (bytes) the file system of ``folder`` takes (255 where it does not say)."""
    try:
        return int(os.pathconf(folder, "PC_NAME_MAX"))
    except (OSError, ValueError):
        return 255


def _check_replaceable(out_dir: Path, reads: Iterable[Path | None]) -> None:
    """PipelineError unless ``--overwrite`` may replace the existing folder ``out_dir`` (see
    :func:`check_output_dir`)."""
    target = out_dir.resolve()
    for read in reads:
        if read is None:
            continue
        path = Path(read).resolve()
        if path == target or target in path.parents:
            raise PipelineError(
                f"{out_dir}: holds {read}, which this command reads; --overwrite would delete it "
                "(choose another --out)"
            )
    if not (target / SUMMARY_NAME).is_file() and any(target.iterdir()):
        raise PipelineError(
            f"{out_dir}: exists and is not a run folder (no {SUMMARY_NAME}); --overwrite replaces only run "
            "folders (choose another --out)"
        )


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def remove_stale_staging(out_dir: Path) -> list[Path]:
    """Remove the ``DIR.partial-PID`` / ``DIR.replaced-PID`` folders of ``out_dir`` whose process is dead.

    A run killed by SIGKILL (or a power cut) cannot clean up after itself; the next run into the same folder
    does. Folders of live processes (another run in progress) are left alone. A ``DIR.replaced-PID`` where
    ``DIR`` is missing (a run killed between retiring the old folder and renaming its own) is the old run: it
    is renamed back to ``DIR``, not removed. Returns what was removed.
    """
    out_dir = Path(out_dir)
    removed = []
    if not out_dir.parent.is_dir():
        return removed
    for kind in ("partial", "replaced"):
        for path in out_dir.parent.glob(f"{glob.escape(out_dir.name)}.{kind}-*"):
            pid_text = path.name.rsplit("-", 1)[-1]
            if not pid_text.isdigit() or int(pid_text) == os.getpid() or _pid_alive(int(pid_text)):
                continue
            if kind == "replaced" and not out_dir.exists():  # killed between its two renames: the old
                path.rename(out_dir)  # run is all there is, so it goes back
                continue
            shutil.rmtree(path, ignore_errors=True)
            removed.append(path)
    return removed


@contextmanager
def staged_run_folder(
    out_dir: Path, overwrite: bool = False, reads: Iterable[Path | None] = ()
) -> Iterator[Path]:
    """Yield a temporary folder to write a run into; on success it becomes ``out_dir`` (``overwrite`` and
    ``reads``: :func:`check_output_dir`).

    The caller writes every file, ``summary.json`` last (see :func:`write_summary`). If the block raises
    (including KeyboardInterrupt, and SIGTERM, which the command line turns into one), the temporary folder
    is deleted and ``out_dir`` is untouched; staging folders left by dead processes are removed first. If
    ``out_dir`` appeared (or changed so that it may no longer be replaced) while the block ran, the finished
    run goes to ``DIR-2`` (the first free such name) and a PipelineError says so: neither is lost.
    """
    out_dir = Path(out_dir)
    remove_stale_staging(out_dir)  # first: an old run it puts back is checked like any existing folder
    check_output_dir(out_dir, overwrite, reads=reads)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    staging = out_dir.with_name(f"{out_dir.name}.partial-{os.getpid()}")
    if staging.exists():
        shutil.rmtree(staging)
    staging.mkdir()
    try:
        yield staging
        if pending_interrupt() is not None:  # an interrupt whose exception Python dropped
            raise KeyboardInterrupt
        if not (staging / SUMMARY_NAME).is_file():
            raise PipelineError(f"{out_dir}: run finished without writing {SUMMARY_NAME}")
        if out_dir.exists():
            problem = _no_longer_replaceable(out_dir, overwrite, reads)
            if problem is not None:  # (another run, or the user, wrote it while this run worked)
                kept = _free_sibling(out_dir)
                staging.rename(kept)
                raise PipelineError(f"{out_dir}: {problem}; this run's result is kept in {kept}")
            retired = out_dir.with_name(f"{out_dir.name}.replaced-{os.getpid()}")
            try:
                out_dir.rename(retired)
                staging.rename(out_dir)
            except BaseException:  # (an interrupt between the two renames) the old run goes back
                if retired.exists() and not out_dir.exists():
                    retired.rename(out_dir)
                raise
            shutil.rmtree(retired, ignore_errors=True)
        else:
            staging.rename(out_dir)
    except BaseException as exc:
        shutil.rmtree(staging, ignore_errors=True)
        if isinstance(exc, (GpomError, OSError)):
            named = _named_for_the_run(exc, staging, out_dir)
            if named is not exc:
                raise named from exc
        raise


def _named_for_the_run(exc: GpomError | OSError, staging: Path, out_dir: Path) -> GpomError | OSError:
    """``exc`` with the staging folder, which is gone when its message is read, named as the run folder it
    was to become (``exc`` itself when it does not name the staging folder): a known error's message, an
    OS error's file names."""
    # the staging folder's name as a whole path component (not the prefix of another process's)
    here = re.compile(re.escape(str(staging)) + r"(?![^\s/\\:;,'\")])")

    def there(text: str) -> str:
        return here.sub(lambda _match: str(out_dir), text)

    if isinstance(exc, OSError):
        names = [exc.filename, exc.filename2]
        if exc.errno is None or not any(isinstance(n, str) and here.search(n) for n in names):
            return exc
        moved = [there(n) if isinstance(n, str) else n for n in names]
        return type(exc)(exc.errno, exc.strerror, moved[0], None, moved[1])
    text = str(exc)
    return reworded(exc, there(text)) if here.search(text) else exc


def _no_longer_replaceable(out_dir: Path, overwrite: bool, reads: Iterable[Path | None]) -> str | None:
    """Why the finished run may not replace ``out_dir``, which exists now (it may have appeared, or changed,
    since :func:`check_output_dir` let the run start); None if it may."""
    if not overwrite:
        return "appeared while the run worked (without --overwrite it is not replaced)"
    if not out_dir.is_dir():
        return "became something other than a folder while the run worked"
    try:
        _check_replaceable(out_dir, reads)
    except PipelineError as exc:
        return f"changed while the run worked ({str(exc).removeprefix(f'{out_dir}: ')})"
    return None


def _free_sibling(out_dir: Path) -> Path:
    """``DIR-2``, ``DIR-3``, ...: the first name beside ``out_dir`` that nothing holds."""
    k = 2
    while out_dir.with_name(f"{out_dir.name}-{k}").exists():
        k += 1
    return out_dir.with_name(f"{out_dir.name}-{k}")


def params_path(maps_dir: Path) -> Path:
    """The learnt GP parameters of a run folder's ``maps/`` (``params.json``, SPEC section 4)."""
    return Path(maps_dir) / "params.json"


def write_summary(folder: Path, summary: dict[str, Any]) -> Path:
    """Write ``summary.json`` (call it last: its presence marks a complete run)."""
    path = Path(folder) / SUMMARY_NAME
    write_text_atomic(path, json.dumps(summary, indent=2, default=_json_default) + "\n")
    return path


def read_summary(folder: Path) -> dict[str, Any]:
    """Read the summary of a complete run folder; PipelineError if the folder is not a complete run."""
    path = Path(folder) / SUMMARY_NAME
    if not Path(folder).is_dir():
        raise PipelineError(f"{folder}: no such run folder")
    if not path.is_file():
        raise PipelineError(f"{folder}: not a complete run folder (no {SUMMARY_NAME})")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise PipelineError(f"{path}: corrupt summary ({exc.msg})") from None


def _json_default(obj: Any) -> Any:
    import numpy as np

    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")
