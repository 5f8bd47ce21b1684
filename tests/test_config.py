"""Configuration: YAML in and out, unknown keys and out-of-range values rejected with one clear line."""

from __future__ import annotations

import pytest

from datasets.errors import ConfigError
from pipeline.config import DEFAULT_CONFIG_PATH, Config, config_to_yaml, load_config


def test_default_file_matches_model_defaults() -> None:
    assert load_config() == Config()
    body = [line for line in DEFAULT_CONFIG_PATH.read_text().splitlines(True) if not line.startswith("#")]
    assert "".join(body) == config_to_yaml(Config())


def test_yaml_round_trip(tmp_path) -> None:
    cfg = load_config(overrides={"mapping": {"resolution_m": 0.25, "mapper": "gpfol"}})
    assert cfg.mapping.resolution_m == 0.25
    path = tmp_path / "c.yaml"
    path.write_text(config_to_yaml(cfg))
    assert load_config(path) == cfg


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("mapping:\n  resolutoin_m: 0.2\n", r"unknown configuration key 'mapping\.resolutoin_m'"),
        ("maping: {}\n", "unknown configuration key 'maping'"),
        ("mapping:\n  resolution_m: -1\n", r"invalid value -1 for 'mapping\.resolution_m'"),
        ("mapping: [unclosed\n", "not valid YAML"),
        # a bound on a hyperparameter that neither configured kernel has is a typo, not a silent no-op
        (
            "mapping:\n  kernel_bounds:\n    sigam: [0.1, 10]\n",
            r"kernel_bounds\.sigam: no such hyperparameter of the nn or se",
        ),
        # the keys of the former flat mapping section name their new, nested place
        (
            "mapping:\n  train_scans: 10\n",
            r"^\S+c\.yaml: configuration key 'mapping\.train_scans' is now 'mapping\.train\.scans'$",
        ),
        ("mapping:\n  ut_kappa: 1\n", r"'mapping\.ut_kappa' is now 'mapping\.gppol\.ut\.kappa'$"),
        (
            "mapping:\n  gppol:\n    kernel: nn\n    expectation: girard\n",
            r"'girard' is the SE kernel's closed form",
        ),
        (
            "input:\n  carmen_range_max_m: 0.01\n  carmen_range_min_m: 5\n",
            r"carmen_range_min_m \(5\) must be below carmen_range_max_m \(0\.01\)",
        ),
        # YAML forbids a key twice; PyYAML kept the last (a section written twice lost the first's keys)
        (
            "mapping:\n  resolution_m: 0.3\nmapping:\n  mapper: gpfol\n",
            r"line 3, column 1: key 'mapping' is written twice",
        ),
        (
            "mapping:\n  resolution_m: 0.3\n  resolution_m: 0.2\n",
            r"line 3, column 3: key 'resolution_m' is written twice",
        ),
    ],
    ids=[
        "unknown-key",
        "unknown-stage",
        "out-of-range",
        "not-yaml",
        "misspelt-kernel-bound",
        "moved-key",
        "moved-nested-key",
        "girard-needs-se",
        "carmen-range-limits-reversed",
        "section-twice",
        "key-twice",
    ],
)
def test_bad_config_is_rejected_with_one_line(tmp_path, text: str, message: str) -> None:
    path = tmp_path / "c.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=message):
        load_config(path)


def test_missing_file(tmp_path) -> None:
    with pytest.raises(ConfigError, match="no such configuration file"):
        load_config(tmp_path / "absent.yaml")


def test_kernel_bounds_of_either_configured_kernel_are_accepted(tmp_path) -> None:
    """``kernel_bounds`` may name hyperparameters of the GPFOL kernel (nn: sigma) and of the GPPOL one
    (se: length_scale)."""
    path = tmp_path / "c.yaml"
    path.write_text("mapping:\n  kernel_bounds:\n    sigma: [0.1, 10]\n    length_scale: [0.1, 5]\n")
    bounds = load_config(path).mapping.kernel_bounds
    assert bounds == {"sigma": (0.1, 10.0), "length_scale": (0.1, 5.0)}


def test_every_moved_key_points_at_an_existing_field() -> None:
    """Each hint of a former flat key names a field that exists, with that field's default."""
    from mapping.config import MOVED_KEYS, MappingConfig

    cfg = MappingConfig()
    for new in MOVED_KEYS.values():
        obj = cfg
        for part in new.split("."):
            assert part in type(obj).model_fields, new
            obj = getattr(obj, part)


@pytest.mark.parametrize(
    ("text", "expected"),
    [("off", "off"), ("'off'", "off"), ("on", "auto"), ("auto", "auto"), ("true", "auto"), ("false", "off")],
)
def test_wheel_odometry_reads_yamls_unquoted_off_as_meant(tmp_path, text: str, expected: str) -> None:
    """YAML 1.1 reads an unquoted ``off`` as false and ``on`` as true; the switch takes them as meant and
    still rejects anything else with one line."""
    path = tmp_path / "c.yaml"
    path.write_text(f"slam:\n  wheel_odometry: {text}\n")
    assert load_config(path).slam.wheel_odometry == expected
    path.write_text("slam:\n  wheel_odometry: never\n")
    with pytest.raises(ConfigError, match=r"slam\.wheel_odometry"):
        load_config(path)


def _leaf_keys(model: type, prefix: tuple[str, ...] = ()) -> list[tuple[tuple[str, ...], object]]:
    """(key path, annotation) of every leaf key of a configuration section, nested sections walked."""
    from pydantic import BaseModel

    leaves = []
    for name, field in model.model_fields.items():
        ann = field.annotation
        if isinstance(ann, type) and issubclass(ann, BaseModel):
            leaves += _leaf_keys(ann, (*prefix, name))
        else:
            leaves.append(((*prefix, name), ann))
    return leaves


def _yaml_at(path: tuple[str, ...], value: str) -> str:
    return "".join(f"{'  ' * i}{key}:\n" for i, key in enumerate(path[:-1])) + (
        f"{'  ' * (len(path) - 1)}{path[-1]}: {value}\n"
    )


def test_true_or_false_is_refused_where_a_key_takes_a_number_or_text(tmp_path) -> None:
    """Pydantic's lax mode would read ``resolution_m: true`` as 1.0 and a count ``false`` as 0: every key
    that takes a number or text refuses YAML's true / false (yes, no, on, off) with one line naming it; every
    switch still takes them."""
    path = tmp_path / "c.yaml"
    refused = taken = 0
    for keys, annotation in _leaf_keys(Config):
        path.write_text(_yaml_at(keys, "yes"))
        if annotation is bool or keys == ("slam", "wheel_odometry"):
            load_config(path)  # a switch (wheel_odometry takes YAML's on / off as meant)
            taken += 1
            continue
        dotted = ".".join(keys).replace(".", r"\.")
        with pytest.raises(ConfigError, match=rf"invalid value True for '{dotted}': "):
            load_config(path)
        refused += 1
    assert refused > 100 and taken >= 8
    path.write_text("input:\n  cloud_height_band_m: [-0.2, false]\n")
    with pytest.raises(ConfigError, match=r"invalid value \[-0\.2, False\] for 'input\.cloud_height_band_m'"):
        load_config(path)
