"""Run folders (SPEC section 4): written under a temporary name, renamed when complete, ``summary.json`` last.

A run folder that exists under its final name is complete. While a run is in progress its files live in
``DIR.partial-<pid>`` beside ``DIR``; on any failure or interruption that folder is removed, so nothing
half-written ever looks complete. An existing ``DIR`` is never replaced unless ``overwrite=True``, and then
only after the new run has succeeded.
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from pipeline.errors import PipelineError

SUMMARY_NAME = "summary.json"


def check_output_dir(out_dir: Path, overwrite: bool) -> None:
    """Fail early (before any work) if ``out_dir`` exists and may not be replaced."""
    if out_dir.exists() and not overwrite:
        raise PipelineError(f"{out_dir}: already exists (use --overwrite to replace it)")
    if out_dir.exists() and not out_dir.is_dir():
        raise PipelineError(f"{out_dir}: exists and is not a folder")


@contextmanager
def staged_run_folder(out_dir: Path, overwrite: bool = False) -> Iterator[Path]:
    """Yield a temporary folder to write a run into; on success it becomes ``out_dir``.

    The caller writes every file, ``summary.json`` last (see :func:`write_summary`). If the block raises
    (including KeyboardInterrupt), the temporary folder is deleted and ``out_dir`` is untouched.
    """
    out_dir = Path(out_dir)
    check_output_dir(out_dir, overwrite)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    staging = out_dir.with_name(f"{out_dir.name}.partial-{os.getpid()}")
    if staging.exists():
        shutil.rmtree(staging)
    staging.mkdir()
    try:
        yield staging
        if not (staging / SUMMARY_NAME).is_file():
            raise PipelineError(f"{out_dir}: run finished without writing {SUMMARY_NAME}")
        if out_dir.exists():
            retired = out_dir.with_name(f"{out_dir.name}.replaced-{os.getpid()}")
            out_dir.rename(retired)
            staging.rename(out_dir)
            shutil.rmtree(retired, ignore_errors=True)
        else:
            staging.rename(out_dir)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise


def write_summary(folder: Path, summary: dict[str, Any]) -> Path:
    """Write ``summary.json`` (call it last: its presence marks a complete run)."""
    path = Path(folder) / SUMMARY_NAME
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(summary, indent=2, default=_json_default) + "\n")
    tmp.rename(path)
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
