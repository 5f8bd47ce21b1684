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


def _subparsers(parser) -> dict:
    """{'run': parser, 'evaluate map': parser, ...} of ``parser``'s sub-commands, nested ones joined."""
    import argparse

    out = {}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                nested = _subparsers(sub)
                out.update({f"{name} {k}": v for k, v in nested.items()} if nested else {name: sub})
    return out


def test_readme_synopsis_lists_every_option_of_every_command() -> None:
    """The README's command-line block names every command and every option its --help has."""
    import re

    from run import build_parser

    text = (REPO / "README.md").read_text()
    block = text.split("## Command line", 1)[1].split("```", 2)[1]
    lines = [ln.split("#")[0] for ln in block.splitlines() if ln.startswith("python run.py ")]
    parser = build_parser()
    top = {s for a in parser._actions for s in a.option_strings if s.startswith("--") and s != "--help"}
    assert top <= set(re.findall(r"--[a-z][a-z-]*", lines[0])), f"README's first line lacks {sorted(top)}"
    subs = _subparsers(parser)
    for name, sub in subs.items():
        line = next((ln for ln in lines if ln.startswith(f"python run.py {name} ")), None)
        assert line is not None, f"README synopsis lacks '{name}'"
        documented = set(re.findall(r"--[a-z][a-z-]*", line))
        options = {s for a in sub._actions for s in a.option_strings if s.startswith("--") and s != "--help"}
        assert options == documented, f"{name}: --help has {sorted(options)}, README {sorted(documented)}"
