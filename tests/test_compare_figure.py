"""The comparison figure of run folders (``python -m pipeline.compare_figure``)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from mapping.exports import Classification, MapLayers, write_layers_npz
from pipeline.compare_figure import FREE_CODE, OCCUPIED_CODE, UNKNOWN_CODE, class_codes, main, panel_title


def _layers(probability: np.ndarray, variance: np.ndarray) -> MapLayers:
    prior = np.ones_like(variance, dtype=np.float32)
    c = Classification(prior, unknown_variance_fraction=0.9, occupied_threshold=0.65, free_threshold=0.35)
    p = probability.astype(np.float32)
    return MapLayers(p, p, variance.astype(np.float32), 0.1, (-1.0, 2.0), classification=c)


def test_class_codes_follow_the_planners_classification() -> None:
    p = np.array([[0.9, 0.1, 0.5, 0.9]])
    v = np.array([[0.1, 0.1, 0.1, 0.95]])  # the last cell is unknown whatever its probability
    layers = _layers(p, v)
    assert class_codes(layers).tolist() == [[OCCUPIED_CODE, FREE_CODE, UNKNOWN_CODE, UNKNOWN_CODE]]
    assert "25.0 / 25.0 / 50.0 %" in panel_title("x", layers)


def test_compare_figure_draws_one_row_per_run(tmp_path: Path) -> None:
    pytest.importorskip("matplotlib")
    rng = np.random.default_rng(0)
    runs = []
    for name, mapper in (("a", "gppol"), ("b", "gpfol")):
        run = tmp_path / name
        for which in ("before", "after"):
            (run / "maps" / which).mkdir(parents=True)
            layers = _layers(rng.random((40, 60)), rng.random((40, 60)))
            write_layers_npz(run / "maps" / which / "layers.npz", layers)
        (run / "summary.json").write_text(json.dumps({"mapper": mapper, "map": {"pose_covariances": "none"}}))
        runs.append(run)
    out = tmp_path / "figure.png"
    assert main([str(r) for r in runs] + ["--out", str(out), "--step", "3"]) == 0
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    from matplotlib.image import imread

    height, width = imread(out).shape[:2]
    assert height > width / 2  # two rows of two wide panels
