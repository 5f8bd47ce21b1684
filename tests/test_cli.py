"""The command line: every command in --help, usage errors exit 2, known errors one line and exit 1."""

from __future__ import annotations

import subprocess
import sys

import pytest

from tests.conftest import REPO

COMMANDS = ["demo", "run", "remap", "simulate", "convert", "evaluate", "bench"]


def run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "run.py", *args], cwd=REPO, capture_output=True, text=True, timeout=600
    )


def test_help_lists_every_command() -> None:
    result = run_cli("--help")
    assert result.returncode == 0
    for command in COMMANDS:
        assert f"    {command} " in result.stdout, command


@pytest.mark.parametrize("command", COMMANDS)
def test_every_command_has_help(command: str) -> None:
    result = run_cli(command, "--help")
    assert result.returncode == 0, result.stderr
    assert "usage:" in result.stdout


def test_unknown_command_is_a_usage_error() -> None:
    result = run_cli("frobnicate")
    assert result.returncode == 2
    assert "invalid choice" in result.stderr


def test_missing_argument_is_a_usage_error() -> None:
    result = run_cli("convert")
    assert result.returncode == 2


def test_known_error_is_one_line_exit_1(tmp_path) -> None:
    missing = tmp_path / "nothing.clf"
    result = run_cli("convert", str(missing), str(tmp_path / "out.bag"))
    assert result.returncode == 1
    assert result.stderr.strip() == f"error: {missing}: no such file or directory"
    assert "Traceback" not in result.stderr
    assert not (tmp_path / "out.bag").exists()
