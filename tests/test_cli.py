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
        # the global options (-q) are also accepted after every command: the first line documents them
        options = {s for a in sub._actions for s in a.option_strings if s.startswith("--") and s != "--help"}
        options -= top
        assert options == documented, f"{name}: --help has {sorted(options)}, README {sorted(documented)}"


@pytest.mark.parametrize("command", [["evaluate", "map", "x.log"], ["evaluate", "suite"]])
def test_hold_out_seeds_as_words_lists_ranges_or_repeated_flags(command: list[str]) -> None:
    """--seed takes what its help names (3, 1,2, 0-4) and repeated flags add up, once each; a positional
    argument after it stays one; without it the protocol's default applies (None here)."""
    from run import build_parser

    parser = build_parser()

    def seeds(*words: str) -> list[int] | None:
        return parser.parse_args([*command, *words]).seed

    assert seeds() is None
    assert seeds("--seed", "3") == [3]
    assert seeds("--seed", "1,2") == [1, 2]
    assert seeds("--seed", "0-2,7") == [0, 1, 2, 7]
    assert seeds("--seed", "1", "--seed", "3,1") == [1, 3]
    if command[1] == "map":
        args = parser.parse_args(["evaluate", "map", "--seed", "0-1", "x.log"])
        assert args.seed == [0, 1] and str(args.input) == "x.log"


@pytest.mark.parametrize("word", ["x", "3-1", "1,", "-1", "0-100000000", "99999999999999999999999"])
def test_a_bad_seed_is_a_usage_error_naming_it(word: str) -> None:
    """Including ranges too long to run (a hundred million hold-out maps) and seeds numpy's generators
    cannot take: said at once, not after minutes of work (or gigabytes of a list of seeds)."""
    result = subprocess.run(
        [sys.executable, "run.py", "evaluate", "map", "x.log", f"--seed={word}"],
        cwd=REPO,
        capture_output=True,
        text=True,
    )
    assert result.returncode == 2
    assert f"'{word}'" in result.stderr and "--seed" in result.stderr


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["evaluate", "map", "x.log", "--seed", "0-999", "--seed", "1000-1001"], "1002 seeds; at most 1000"),
        (["simulate", "loop", "--out", "x.mcap", "--seed", "-1"], "'-1': a seed lies between 0 and"),
        (["demo", "--seed", "4294967296"], "'4294967296': a seed lies between 0 and"),
        (["evaluate", "slam", "x.log", "--relations", "r", "--seed", "y"], "'y' is not an integer seed"),
    ],
)
def test_every_seed_option_is_checked_as_a_usage_error(args: list[str], message: str) -> None:
    result = subprocess.run(
        [sys.executable, "run.py", *args], cwd=REPO, capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 2 and message in result.stderr and "--seed" in result.stderr


def test_version_is_the_one_of_pyproject() -> None:
    import tomllib

    with open(REPO / "pyproject.toml", "rb") as f:
        version = tomllib.load(f)["project"]["version"]
    result = run_cli("--version")
    assert result.returncode == 0, result.stderr
    assert result.stdout == f"gpom {version}\n" and result.stderr == ""


@pytest.mark.parametrize(
    ("argv", "quiet"),
    [
        (["run", "x.bag"], False),
        (["-q", "run", "x.bag"], True),
        (["run", "x.bag", "-q"], True),
        (["run", "--quiet", "x.bag", "--json"], True),
        (["-q", "remap", "r"], True),
        (["remap", "r", "-q"], True),
        (["evaluate", "map", "x.clf", "-q"], True),
        (["evaluate", "map", "x.clf", "--breakdown", "-q"], True),
        (["evaluate", "-q", "suite"], True),
        (["convert", "a", "b", "-q"], True),
        (["bench"], False),
    ],
)
def test_quiet_before_or_after_the_command(argv: list[str], quiet: bool) -> None:
    from run import build_parser

    assert build_parser().parse_args(argv).quiet is quiet


def test_run_bag_format_overrides_the_configuration(monkeypatch, tmp_path) -> None:
    import pipeline.run
    from pipeline.commands import dispatch
    from run import build_parser

    seen = {}

    def fake_run_pipeline(input_path, out_dir, config, **kwargs):
        seen["config"] = config
        return {"table": {}}

    monkeypatch.setattr(pipeline.run, "run_pipeline", fake_run_pipeline)
    for argv, expected in (
        (["--bag-format", "bag"], "bag"),
        (["--bag-format", "mcap"], "mcap"),
        ([], "mcap"),
    ):
        args = build_parser().parse_args(["run", str(tmp_path / "x.bag"), "--json", *argv])
        assert dispatch(args, lambda _obj: None) == 0
        assert seen["config"].export.bag_format == expected, argv
    config = tmp_path / "ros1.yaml"
    config.write_text("export: {bag_format: bag}\n")
    args = build_parser().parse_args(["run", "x.bag", "--config", str(config), "--json"])
    dispatch(args, lambda _obj: None)
    assert seen["config"].export.bag_format == "bag"  # no flag: the file's value stands
    result = run_cli("run", "x.bag", "--bag-format", "zip")
    assert result.returncode == 2 and "--bag-format: invalid choice: 'zip'" in result.stderr


def test_a_bad_bag_format_override_is_blamed_on_the_flag() -> None:
    from datasets.errors import ConfigError
    from pipeline.config import load_config

    with pytest.raises(ConfigError, match=r"^--bag-format 'zip': invalid value for 'export.bag_format'"):
        load_config(None, {"export": {"bag_format": "zip"}})


@pytest.fixture
def run_folder_stub(tmp_path):
    """The two files ``remap`` reads before its size check: a run's summary (map bounds) and configuration."""
    import json

    from pipeline.config import load_config, write_config

    run = tmp_path / "run"
    run.mkdir()
    (run / "summary.json").write_text(json.dumps({"map": {"bounds_xy_m": [-20.0, -8.0, 102.0, 44.0]}}))
    write_config(load_config(), run / "config.yaml")
    return run


def test_remap_too_fine_resolution_names_the_flag(run_folder_stub, tmp_path) -> None:
    out = tmp_path / "out"
    result = run_cli("remap", str(run_folder_stub), "--resolution", "0.001", "--out", str(out), "-q")
    assert result.returncode == 1, result.stderr
    line = result.stderr.strip()
    assert "\n" not in line and line.startswith(
        f"error: {run_folder_stub}: the remap with --resolution 0.001: "
    )
    assert "above scale.max_map_cells" in line and not out.exists()
    result = run_cli("remap", str(run_folder_stub), "--bounds=-2000,-2000,2000,2000", "--out", str(out))
    assert result.returncode == 1 and "the remap with --bounds -2000,-2000,2000,2000:" in result.stderr


@pytest.mark.parametrize("value", ["-1", "0", "nan"])
def test_remap_bad_resolution_is_blamed_on_the_flag(run_folder_stub, tmp_path, value: str) -> None:
    result = run_cli("remap", str(run_folder_stub), "--resolution", value, "--out", str(tmp_path / "o"))
    assert result.returncode == 1, result.stderr
    line = result.stderr.strip()
    assert line.startswith(f"error: --resolution {float(value)}: invalid value for 'mapping.resolution_m'")
    assert "\n" not in line and "config.yaml" not in line and "default.yaml" not in line
