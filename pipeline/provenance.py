"""Where a result came from: the date, the code, the machine and the command line.

``evaluate suite`` and ``bench`` record :func:`provenance` in their JSON when they start, so that a results
page rendered later (``--from-json``) reports the run's commit and machine, not the renderer's. Nothing here
raises for a missing tool: a checkout without git gives the commit ``"unknown"``, an unreadable
``/proc/cpuinfo`` the CPU ``"unknown"``.
"""

from __future__ import annotations

import datetime
import importlib.metadata
import os
import platform
import subprocess
import tomllib
from pathlib import Path
from typing import Any

from datasets.paths import REPO_DIR

UNKNOWN = "unknown"


def package_version(repo: Path = REPO_DIR) -> str:
    """The version of gpom: ``project.version`` of the checkout's ``pyproject.toml`` (the project runs from
    its checkout, whose file is the truth even when an old install left metadata behind), else the installed
    distribution's metadata, else ``"unknown"``."""
    try:
        with open(repo / "pyproject.toml", "rb") as f:
            return str(tomllib.load(f)["project"]["version"])
    except (OSError, tomllib.TOMLDecodeError, KeyError, TypeError):
        pass
    try:
        return importlib.metadata.version("gpom")
    except importlib.metadata.PackageNotFoundError:
        return UNKNOWN


def _git(repo: Path, *args: str) -> str | None:
    """stdout of ``git -C repo ARGS`` (stripped), None when git is missing or fails."""
    try:
        done = subprocess.run(
            ["git", "-C", str(repo), *args], capture_output=True, text=True, timeout=30, check=False
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return done.stdout.strip() if done.returncode == 0 else None


def git_commit(repo: Path = REPO_DIR) -> str:
    """The checkout's short commit hash, with ``+dirty`` when tracked files differ from it; ``"unknown"``
    outside a git checkout or without git."""
    commit = _git(repo, "rev-parse", "--short", "HEAD")
    if not commit:
        return UNKNOWN
    status = _git(repo, "status", "--porcelain", "--untracked-files=no")
    return commit + ("+dirty" if status else "")


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.lower().startswith(("model name", "hardware", "cpu model")) and ":" in line:
                return " ".join(line.split(":", 1)[1].split())
    except OSError:
        pass
    return platform.processor() or UNKNOWN


def _memory_gib() -> float | None:
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal:"):
                return int(line.split()[1]) / 2**20
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30
    except (ValueError, OSError, AttributeError):
        return None


def _os_name() -> str:
    try:
        for line in Path("/etc/os-release").read_text().splitlines():
            if line.startswith("PRETTY_NAME="):
                return f"{line.split('=', 1)[1].strip().strip(chr(34))} (Linux {platform.release()})"
    except OSError:
        pass
    return platform.platform()


def machine() -> dict[str, Any]:
    """``{"cpu", "cores", "memory_gib", "os", "python"}`` of this machine (cores: the ones this process may
    use)."""
    try:
        cores = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        cores = os.cpu_count()
    memory = _memory_gib()
    return {
        "cpu": _cpu_model(),
        "cores": cores,
        "memory_gib": None if memory is None else round(memory, 1),
        "os": _os_name(),
        "python": platform.python_version(),
    }


def provenance(command: str | None = None, repo: Path = REPO_DIR) -> dict[str, Any]:
    """``{"date_utc", "commit", "version", "machine", "command"}`` now: the date as ``YYYY-MM-DD HH:MM``
    UTC, :func:`git_commit`, :func:`package_version`, :func:`machine` and the command line (None if not
    given)."""
    now = datetime.datetime.now(datetime.UTC)
    return {
        "date_utc": now.strftime("%Y-%m-%d %H:%M"),
        "commit": git_commit(repo),
        "version": package_version(repo),
        "machine": machine(),
        "command": command,
    }


def machine_text(m: dict[str, Any] | None) -> str:
    """One line for a :func:`machine` dict: ``CPU, N cores, X GiB RAM, OS, Python V``."""
    if not m:
        return UNKNOWN
    memory = m.get("memory_gib")
    parts = [
        str(m.get("cpu") or UNKNOWN),
        f"{m['cores']} cores" if m.get("cores") else None,
        f"{memory:g} GiB RAM" if memory else None,
        str(m["os"]) if m.get("os") else None,
        f"Python {m['python']}" if m.get("python") else None,
    ]
    return ", ".join(p for p in parts if p)
