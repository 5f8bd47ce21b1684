"""The Python front door (``pipeline.api``): README's example runs as written, and the GP map it rebuilds
from a run folder is the map the run stored."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mapping.exports import MapLayers
from pipeline.api import cell_centres_xy_m, load_run
from pipeline.errors import PipelineError
from tests.conftest import REPO
from tests.layer_checks import assert_same_map

FAST_TRAINING = {"mapping": {"train": {"anneal_evaluations": 20, "lbfgs_iterations": 20}}}


@pytest.fixture(scope="module")
def small_run(tmp_path_factory) -> Path:
    """A GPPOL run of the simulated loop world at 0.25 m (its ground truth removed: no AUC stage)."""
    from datasets.simulation import ground_truth_path, simulate
    from pipeline.config import load_config
    from pipeline.run import run_pipeline

    folder = tmp_path_factory.mktemp("api")
    bag = folder / "loop.mcap"
    simulate("loop", bag, seed=0)
    ground_truth_path(bag).unlink()
    config = load_config(
        None, {**FAST_TRAINING, "mapping": {**FAST_TRAINING["mapping"], "resolution_m": 0.25}}
    )
    run_pipeline(bag, folder / "run", config)
    return folder / "run"


def readme_example() -> str:
    """The code block of README's "Python API" section."""
    text = (REPO / "README.md").read_text()
    section = text.split("\n## Python API\n", 1)[1].split("\n## ", 1)[0]
    return section.split("```python\n", 1)[1].split("```", 1)[0]


def as_layers(query, like: MapLayers) -> MapLayers:
    """(H*W,) float64 query results as float32 layers shaped like ``like``."""
    mean, variance, probability = (np.asarray(v).reshape(like.shape).astype(np.float32) for v in query)
    return MapLayers(probability, mean, variance, like.resolution_m, like.origin_xy_m)


def test_readme_example_runs_and_queries_the_stored_map(small_run) -> None:
    code = readme_example()
    assert 'load_run("out/demo/run")' in code and len(code.splitlines()) <= 12
    namespace: dict = {}
    exec(compile(code.replace('"out/demo/run"', repr(str(small_run))), "README.md", "exec"), namespace)
    run = namespace["run"]
    n_scans = run.summary["counts"]["scans"]
    assert namespace["poses"].shape == (n_scans, 3) and namespace["cov"].shape == (n_scans, 3, 3)
    p = len(namespace["xy_m"])
    for name in ("mean", "variance", "probability"):
        assert namespace[name].shape == (p,), name
    assert ((namespace["probability"] >= 0) & (namespace["probability"] <= 1)).all()
    assert (namespace["variance"] > 0).all()
    coarse = namespace["coarse"]
    assert coarse.resolution_m == 0.5 and coarse.origin_xy_m == run.bounds_xy_m[:2]
    # the rebuilt map at the centres of the stored grid is the stored map (to the ulp caveat of layer_checks)
    stored = run.layers
    assert stored.resolution_m == 0.25
    assert_same_map(as_layers(run.query(cell_centres_xy_m(stored)), stored), stored)


def test_before_map_renders_as_stored_and_differs_from_after(small_run) -> None:
    before = load_run(small_run, map="before")
    assert_same_map(before.render(), before.layers)
    # the stored maps and the rebuilt one leave the same unknown places to the prior: the run's fraction
    assert before.gp_map.unknown_variance_fraction == before.config.export.unknown_variance_fraction
    after = load_run(small_run)
    np.testing.assert_array_equal(before.trajectory.stamps_ns, after.trajectory.stamps_ns)
    assert np.abs(before.trajectory.poses_before_xytheta - before.trajectory.poses_after_xytheta).max() > 0.1
    assert not np.array_equal(before.covariances.before, before.covariances.after)
    xy = after.trajectory.poses_after_xytheta[::20, :2]
    assert not np.array_equal(before.query(xy).probability, after.query(xy).probability)


def test_load_run_errors_are_one_line(small_run, tmp_path) -> None:
    with pytest.raises(PipelineError, match=r"no such run folder"):
        load_run(tmp_path / "none")
    with pytest.raises(PipelineError, match=r"not a complete run folder"):
        load_run(tmp_path)
    with pytest.raises(PipelineError, match=r"no map 'remap' in a run folder \(its maps: before, after\)"):
        load_run(small_run, map="remap")
    run = load_run(small_run)
    with pytest.raises(PipelineError, match=r"shape \(P, 2\), got \(4,\)"):
        run.query([1.0, 2.0, 3.0, 4.0])
    with pytest.raises(PipelineError, match=r"points must be finite"):
        run.query([[0.0, np.nan]])
    with pytest.raises(PipelineError, match=r"max > min"):
        run.render((0.0, 0.0, -1.0, 1.0), 0.1)
    with pytest.raises(PipelineError, match=r"above scale.max_map_cells"):
        run.render((0.0, 0.0, 1e4, 1e4), 0.01)


def test_covariances_that_are_none_are_refused_also_at_the_runs_own_stamps(small_run, tmp_path) -> None:
    """The run's own per-scan covariances (stamps equal to the scans') skipped the checks that stamps of
    another file get: negated matrices reached the caller as covariances."""
    import shutil

    run_dir = tmp_path / "run"
    shutil.copytree(small_run, run_dir)
    path = run_dir / "trajectory" / "covariances.npz"
    with np.load(path) as z:
        arrays = {
            key: -value if value.ndim == 3 and value.shape[1:] == (3, 3) else value
            for key, value in z.items()
        }
    np.savez(path, **arrays)
    run = load_run(run_dir)
    for name in ("covariances", "mapper_covariances"):
        with pytest.raises(PipelineError, match=r"covariances: entry \d+ is not symmetric positive semi-def"):
            getattr(run, name)


def test_mapping_exports_its_main_names_lazily() -> None:
    from mapping import GPOccupancyMap, MapBuilder, MapLayers
    from mapping.build import MapBuilder as Builder
    from mapping.exports import MapLayers as Layers
    from mapping.gpmap import GPOccupancyMap as Map

    assert (GPOccupancyMap, MapBuilder, MapLayers) == (Map, Builder, Layers)
    code = "import sys, mapping; print(sorted({'numba', 'scipy', 'numpy'} & set(sys.modules)))"
    result = subprocess.run(
        [sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 0 and result.stdout.strip() == "[]", result.stderr
