"""Results pages that regenerate: ``evaluate suite --markdown FILE`` and ``bench --markdown FILE`` write the
tables with the command line, date, commit, version and machine of the run; ``--from-json`` renders the
page of a saved run and keeps that run's provenance."""

from __future__ import annotations

import datetime
import json
import re
import subprocess
import sys
import tomllib

import pytest

from pipeline.provenance import git_commit, machine, provenance
from pipeline.results_markdown import bench_markdown, md_table, suite_markdown
from tests.conftest import REPO, data_file

FAST = "mapping:\n  train: {anneal_evaluations: 40, lbfgs_iterations: 40, problems: 48}\n"


def run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "run.py", *args], cwd=REPO, capture_output=True, text=True, timeout=900
    )


def sections(page: str) -> dict[str, str]:
    """``{title: text}`` of the page's ``##`` sections (the header, before the first one, as ``""``)."""
    parts = re.split(r"^## (.+)$", page, flags=re.M)
    out = {"": parts[0]}
    out.update({parts[i]: parts[i + 1] for i in range(1, len(parts), 2)})
    return out


def table(text: str) -> list[dict[str, str]]:
    """The rows of the first markdown table in ``text`` as dicts (column -> cell)."""
    lines = [ln for ln in text.splitlines() if ln.startswith("|")]
    split = [[c.strip() for c in re.split(r"(?<!\\)\|", ln)[1:-1]] for ln in lines]
    header, body = split[0], split[2:]
    assert set(lines[1]) <= {"|", "-"}, lines[1]
    return [dict(zip(header, row, strict=True)) for row in body]


def header_of(page: str) -> dict[str, str]:
    """The page's header table (before the first section) as ``{field: value}``."""
    lines = [ln for ln in sections(page)[""].splitlines() if ln.startswith("|")][2:]
    cells = [[c.strip() for c in re.split(r"(?<!\\)\|", ln)[1:-1]] for ln in lines]
    return {field: value for field, value in cells}


def by_first(rows: list[dict[str, str]]) -> dict[str, dict[str, str]]:
    return {next(iter(r.values())): r for r in rows}


def pyproject_version() -> str:
    with open(REPO / "pyproject.toml", "rb") as f:
        return tomllib.load(f)["project"]["version"]


@pytest.fixture(scope="module")
def suite_run(tmp_path_factory):
    """One real, small suite run through the command line: intel (raw log, corrected twin, benchmark
    relations), seattle (its own reference), a broken log and a bag without scans; hold-out seed 0 with a
    short training; ``--json`` on stdout and ``--markdown`` into a file."""
    root = tmp_path_factory.mktemp("suite-md")
    data = root / "data"
    links = {
        "intel/intel.clf.bz2": "intel/intel.clf.bz2",
        "intel/intel.gfs.log": "intel/intel.gfs.log",
        "intel/intel.relations": "intel/intel.relations",
        "seattle/seattle-corrected.log.gz": "radish-corrected/seattle-corrected.log.gz",
        "jackal/test2.bag": "jackal/test2.bag",
    }
    for rel, target in links.items():
        (data / rel).parent.mkdir(parents=True, exist_ok=True)
        (data / rel).symlink_to(data_file(target))
    (data / "broken").mkdir()
    (data / "broken" / "broken.clf").write_text("FLASER 3 1.0 2.0\n")
    config = root / "fast.yaml"
    config.write_text(FAST)
    page = root / "results.md"
    argv = [
        "-q", "evaluate", "suite", "--data", str(data), "--only", "intel", "seattle", "broken", "jackal",
        "--seed", "0", "--config", str(config), "--no-simulated", "--json", "--markdown", str(page),
    ]  # fmt: skip
    started = datetime.datetime.now(datetime.UTC)
    done = run_cli(*argv)
    assert done.returncode == 0, done.stderr
    saved = root / "suite.json"
    saved.write_text(done.stdout)
    return {
        "argv": argv,
        "started": started,
        "result": json.loads(done.stdout),
        "page": page.read_text(),
        "json": saved,
        "root": root,
    }


def test_suite_page_header_names_the_run(suite_run) -> None:
    result, page = suite_run["result"], suite_run["page"]
    assert page.startswith("# Evaluation suite: results\n")
    header = header_of(page)
    command = "python run.py " + " ".join(suite_run["argv"])
    assert header["command"] == f"`{command}`"
    stamp = datetime.datetime.strptime(header["date (UTC)"], "%Y-%m-%d %H:%M").replace(tzinfo=datetime.UTC)
    assert abs(stamp - suite_run["started"]) < datetime.timedelta(minutes=2)
    assert header["commit"] == f"`{git_commit()}`" and re.fullmatch(
        r"`[0-9a-f]{7,}(\+dirty)?`", header["commit"]
    )
    assert header["version"] == f"gpom {pyproject_version()}"
    here = machine()
    assert f"{here['cores']} cores" in header["machine"] and f"Python {here['python']}" in header["machine"]
    assert header["maps"] == "hold-out seeds 0" and header["recordings"] == "4"
    assert "rendered" not in header
    # the JSON carries the same provenance, recorded when the run started
    origin = result["provenance"]
    assert origin["command"] == command and origin["date_utc"] == header["date (UTC)"]
    assert origin["commit"] == git_commit() and origin["version"] == pyproject_version()
    assert origin["machine"] == here


def test_suite_page_tables_hold_the_json_figures(suite_run) -> None:
    result, parts = suite_run["result"], sections(suite_run["page"])
    rows = {r["name"]: r for r in result["datasets"]}
    intel = rows["intel"]

    summary = by_first(table(parts["Summary"]))
    assert list(summary) == [r["name"] for r in result["datasets"]]  # the suite's order
    assert set(summary) == {"broken", "jackal", "intel", "seattle"}
    rel = intel["slam"]["relations"]
    assert summary["intel"]["relations m / deg"] == f"{rel['trans_mean_m']:.4f} / {rel['rot_mean_deg']:.4f}"
    assert summary["intel"]["ATE after m"] == f"{intel['slam']['ate_rmse_m']['after']:.3f}"
    s = intel["slam"]["slam"]
    kept = f"{s['loop_closures_accepted']} ({s['loop_closures_dropped_by_back_end']})"
    assert summary["intel"]["closures kept (dropped)"] == kept
    assert summary["seattle"]["relations m / deg"] == "-"  # no relations file beside it
    assert summary["broken"]["relations m / deg"].startswith("error: CarmenError: ")
    assert summary["jackal"]["relations m / deg"].startswith("skipped: no laser scans")

    published = by_first(table(parts["Against published results"]))
    assert list(published) == ["intel"]  # the only row here with relations and a published figure
    ours = f"{rel['trans_mean_m']:.4f} m / {rel['rot_mean_deg']:.3f} deg"
    assert published["intel"]["ours: relations after loop closure"] == ours
    assert published["intel"]["published"] == "0.0229 m / 0.453 deg"
    local, revisit, wheels = (rel[k] for k in ("local", "revisit", "wheels_local"))
    assert local["count"] + revisit["count"] == rel["count"]
    local_text = f"{local['count']}: {local['trans_mean_m']:.4f} / {local['rot_mean_deg']:.3f}"
    assert published["intel"]["ours, local relations"] == local_text
    wheels_text = f"{wheels['count']}: {wheels['trans_mean_m']:.4f} / {wheels['rot_mean_deg']:.3f}"
    assert published["intel"]["wheels alone, local relations"] == wheels_text
    # the closures whose places a relation joins: measured 44 of 45 correct, the other 0.17 m / 2.1 deg off
    judged = rel["closures"]
    assert judged["judged"] >= 30 and judged["correct"] >= 0.95 * judged["judged"]
    assert all(w["error_m"] < 0.4 and w["error_deg"] < 4.0 for w in judged["wrong"])  # none grossly wrong
    column = "closures a relation judges: correct / judged"
    assert published["intel"][column].startswith(f"{judged['correct']} / {judged['judged']}")

    slam = by_first(table(parts["SLAM"]))
    assert set(slam) == {"intel", "seattle"}  # the rows that ran SLAM
    ref = intel["slam"]["reference"]
    assert slam["intel"]["scans (matched)"] == f"{s['scans']} ({ref['matched_scans']})"
    assert slam["intel"]["relations (count) m / deg"].startswith(f"({rel['count']}) ")

    for key, title in (
        ("reference_poses", "Maps on the reference poses"),
        ("slam_poses", "Maps on our SLAM poses, the reference's test points"),
        ("slam_poses_own_test_points", "Maps on our SLAM poses, our own test points"),
    ):
        maps = by_first(table(parts[title]))
        assert set(maps) == {"intel", "seattle"}, title
        for name in maps:
            got = rows[name]["maps"][key]
            auc = " / ".join(f"{got['auc'][m]:.4f}" for m in ("gppol", "gpfol", "grid"))
            loss = " / ".join(f"{got['log_loss'][m]:.3f}" for m in ("gppol", "gpfol", "grid"))
            assert maps[name]["AUC GPPOL / GPFOL / grid"] == auc, (title, name)
            assert maps[name]["log loss GPPOL / GPFOL / grid"] == loss, (title, name)
            assert maps[name]["unobserved share"] == f"{100 * got['unobserved_share']:.1f} %"
        assert maps["seattle"]["protocol"] == "hold-out, blocks of 10, seeds 0"
        assert maps["intel"]["protocol"] == "hold-out, blocks of 40, seeds 0"
    timings = by_first(table(parts["Timings"]))
    assert timings["intel"]["SLAM s"] == f"{intel['timings_s']['slam_s']:.1f}"
    assert "`jackal`: skipped: no laser scans" in parts["Notes"]
    assert "`seattle`: input = reference" in parts["Notes"]


def test_suite_page_from_the_saved_json_reports_the_run(suite_run, tmp_path) -> None:
    """``--from-json`` runs nothing: the page has the run's command, date and commit, and says when and by
    which command it was rendered; its tables are the run's page's, byte for byte."""
    page = tmp_path / "again.md"
    done = run_cli("evaluate", "suite", "--from-json", str(suite_run["json"]), "--markdown", str(page))
    assert done.returncode == 0, done.stderr
    assert done.stdout.rstrip().endswith(f"wrote {page}") and "intel" in done.stdout  # the console table
    again, first = sections(page.read_text()), sections(suite_run["page"])
    header, first_header = header_of(page.read_text()), header_of(suite_run["page"])
    for key in ("command", "date (UTC)", "commit", "version", "machine", "data", "wall time"):
        assert header[key] == first_header[key], key
    assert header["rendered"].startswith(f"from `{suite_run['json']}` on ")
    assert f"--from-json {suite_run['json']}" in header["rendered"]
    assert {k: v for k, v in again.items() if k} == {k: v for k, v in first.items() if k}


def test_results_options_are_checked_before_anything_runs(suite_run, tmp_path) -> None:
    done = run_cli("evaluate", "suite", "--from-json", str(suite_run["json"]), "--only", "intel")
    assert done.returncode == 2 and "--from-json runs nothing: --only" in done.stderr
    done = run_cli("bench", "--from-json", str(suite_run["json"]), "--only", "slam")
    assert done.returncode == 2 and "--from-json runs nothing: --only" in done.stderr
    missing = tmp_path / "nowhere" / "results.md"
    done = run_cli("evaluate", "suite", "--markdown", str(missing))  # would run every recording
    assert done.returncode == 1 and done.stdout == ""
    assert (
        done.stderr.strip()
        == f"error: {missing}: cannot write the markdown page: no such folder {missing.parent}"
    )
    not_json = tmp_path / "suite.json"
    not_json.write_text("FLASER 3\n")
    done = run_cli("evaluate", "suite", "--from-json", str(not_json), "--markdown", str(tmp_path / "p.md"))
    assert done.returncode == 1 and done.stderr.startswith(f"error: {not_json}: not JSON (")
    done = run_cli("bench", "--from-json", str(suite_run["json"]), "--markdown", str(tmp_path / "p.md"))
    assert done.returncode == 1
    assert (
        done.stderr.strip()
        == f"error: {suite_run['json']}: not the JSON of bench --json (no 'gpfol_queries_per_s' key)"
    )
    assert not (tmp_path / "p.md").exists()


def fake_bench() -> dict:
    """A bench result shaped as ``run_bench`` returns it after ``--only mapping slam`` (figures invented)."""
    slam = {
        f"slam_{name}_{k}": v
        for name, wall in (("intel", 9.5), ("fr079", 6.1))
        for k, v in {
            "wall_s": wall,
            "data_duration_s": 2691.0 if name == "intel" else 1061.0,
            "realtime_factor": (2691.0 if name == "intel" else 1061.0) / wall,
            "total_s": wall,
            "loop_search_s": 2.5 if name == "intel" else 0.61,
            "loop_search_share": 0.25 if name == "intel" else 0.1,
            "breakdown_s": {"odometry_s": 5.0, "graph_batch_s": 0.2},
            "odometry_scans_per_s": 957.0,
            "scans": 13631 if name == "intel" else 4934,
            "keyframes": 1500,
            "loop_closures": 163,
            "wheel_odometry": "ODOM records",
        }.items()
    }
    return {
        "gpfol_queries_per_s": 420_000.0,
        "gppol_queries_per_s": 40_000.0,
        "grid_cells_per_s": 1.5e8,
        "odometry_scans_per_s": 957.0,
        "slam_intel_wall_s": 9.5,
        "pipeline_intel_wall_s": None,
        "pipeline_intel_realtime_factor": None,
        "peak_rss_mib": 812.0,
        "mapping_bench": {"map_shape": [310, 310], "neighbours": [15, 15], "threads": 2},
        "gppol_choices": [{"kernel": "se", "expectation": "girard", "queries_per_s": 51_000.0}],
        **slam,
        "parts": ["mapping", "slam"],
        "wall_s": 754.0,
        "provenance": provenance("python run.py bench --only mapping slam --json"),
    }


@pytest.mark.parametrize(
    ("saved", "pattern"),
    [
        ({"datasets": "x"}, r"'datasets' is not a list of recordings"),
        ({"datasets": [{"name": 3}]}, r"'datasets' is not a list of recordings"),
        ({"datasets": [{"name": "a", "slam": 3}]}, r"a value has the wrong shape: AttributeError"),
        ({"datasets": [{"name": "a", "slam": {"relations": "x"}}]}, r"wrong shape: TypeError"),
    ],
)
def test_a_saved_suite_json_of_the_wrong_shape_is_one_line(tmp_path, saved, pattern: str) -> None:
    """``--from-json`` reads a file the user names: values of the wrong shape are a one-line error naming
    it, and no page is written."""
    path = tmp_path / "suite.json"
    path.write_text(json.dumps(saved))
    page = tmp_path / "p.md"
    done = run_cli("evaluate", "suite", "--from-json", str(path), "--markdown", str(page))
    assert done.returncode == 1 and "Traceback" not in done.stderr, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: {path}: not the JSON of evaluate suite --json (")
    assert re.search(pattern, lines[0]), lines[0]
    assert not page.exists()


def test_bench_page_headline_targets_slam_runs_and_every_figure() -> None:
    result = fake_bench()
    page = bench_markdown(result)
    parts, header = sections(page), header_of(page)
    assert header["command"] == "`python run.py bench --only mapping slam --json`"
    assert header["parts"] == "mapping, slam" and header["commit"] == f"`{git_commit()}`"
    assert header["wall time"] == "12 min 34 s"
    headline = {r["key"].strip("`"): r for r in table(parts["Headline figures"])}
    assert headline["gpfol_queries_per_s"]["measured"] == "420,000"
    assert headline["gpfol_queries_per_s"][""] == "met"
    assert headline["gppol_queries_per_s"][""] == "**not met**"  # 40,000 against 50,000
    assert headline["slam_intel_loop_search_share"]["measured"] == "25%"
    assert headline["slam_intel_loop_search_share"][""] == "**not met**"
    assert headline["slam_fr079_realtime_factor"][""] == "met"
    assert headline["pipeline_intel_wall_s"]["measured"] == "not measured"  # a part that did not run
    assert headline["pipeline_intel_realtime_factor"][""] == "-"
    slam = by_first(table(parts["SLAM runs"]))
    assert list(slam) == ["intel", "fr079"]
    assert slam["intel"]["x RT"] == "283" and slam["intel"]["loop search s (share)"] == "2.50 (25 %)"
    every = parts["Every figure"]
    assert "| `mapping_bench.map_shape` | 310, 310 |" in every
    assert "| `gppol_choices[0].queries_per_s` | 51,000 |" in every
    assert "| `slam_intel_breakdown_s.odometry_s` | 5 |" in every
    assert "provenance" not in every and "pipeline_intel_wall_s" not in every and "`wall_s`" not in every


def test_bench_page_from_a_saved_json(tmp_path) -> None:
    saved = tmp_path / "bench.json"
    saved.write_text(json.dumps(fake_bench()))
    page = tmp_path / "bench.md"
    done = run_cli("bench", "--from-json", str(saved), "--markdown", str(page), "--json")
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["gpfol_queries_per_s"] == 420_000.0  # --json: nothing else on stdout
    header = header_of(page.read_text())
    assert header["command"] == "`python run.py bench --only mapping slam --json`"
    assert header["rendered"].startswith(f"from `{saved}` on ")


def test_markdown_cells_stay_in_their_column() -> None:
    text = md_table(["a", "b"], [["x | y", "two\nlines"], [None, 0.5]])
    assert text.splitlines() == ["| a | b |", "|---|---|", "| x \\| y | two lines |", "| - | 0.5 |"]
    rows = table(text)
    assert rows == [{"a": "x \\| y", "b": "two lines"}, {"a": "-", "b": "0.5"}]


def test_commit_is_unknown_outside_git_and_dirty_when_edited(tmp_path) -> None:
    assert git_commit(tmp_path) == "unknown"
    git = ["git", "-C", str(tmp_path), "-c", "user.name=t", "-c", "user.email=t@example.org"]
    subprocess.run([*git, "init", "-q"], check=True)
    (tmp_path / "a.txt").write_text("a\n")
    subprocess.run([*git, "add", "a.txt"], check=True)
    subprocess.run([*git, "commit", "-q", "-m", "a"], check=True)
    clean = git_commit(tmp_path)
    assert re.fullmatch(r"[0-9a-f]{7,}", clean)
    (tmp_path / "b.txt").write_text("untracked files do not count\n")
    assert git_commit(tmp_path) == clean
    (tmp_path / "a.txt").write_text("edited\n")
    assert git_commit(tmp_path) == clean + "+dirty"


def test_a_suite_page_without_provenance_says_unknown() -> None:
    """A JSON written before runs recorded their provenance still renders, saying what it does not know."""
    page = suite_markdown({"data": "x", "seeds": [0], "slam_only": True, "datasets": [], "wall_s": 5.0})
    header = header_of(page)
    assert header["command"] == "unknown" and header["commit"] == "`unknown`"
    assert header["maps"] == "none (`--slam-only`)" and header["wall time"] == "5 s"
