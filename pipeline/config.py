"""The root configuration: one pydantic model per stage, YAML in and out, unknown keys rejected."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any, ClassVar

import yaml
from pydantic import Field, ValidationError

from datasets.config import BoolValueError, InputConfig, MovedKeyError, StageConfig
from datasets.errors import ConfigError, shown
from mapping.config import MappingConfig
from mapping.exports import UNKNOWN_VARIANCE_FRACTION
from pipeline.scale_config import ScaleConfig
from slam.config import SlamConfig

DEFAULT_CONFIG_PATH = Path(__file__).resolve().parent / "default.yaml"
#: The command-line option behind each override key of :func:`load_config` (``run`` / ``remap``), so that a
#: bad value given on the command line is blamed on the option, not on the configuration file.
CLI_OPTIONS: dict[str, str] = {
    "input.scan_topic": "--scan-topic",
    "input.odom_topic": "--odom-topic",
    "mapping.resolution_m": "--resolution",
    "mapping.mapper": "--mapper",
    "scale.scheduler": "--scheduler",
    "export.bag_format": "--bag-format",
}


class ExportConfig(StageConfig):
    """Which map exports a run writes, and the one classification planners get from all of them.

    A cell is unknown when its GP variance exceeds ``unknown_variance_fraction`` of the prior variance;
    a known cell is occupied when p(occ) >= ``mapping.occupied_threshold``, free when p(occ) <=
    ``mapping.free_threshold``, unknown between. The map_server PGM (``trinary``: 0 / 254 / 205) and the
    bag's ``nav_msgs/OccupancyGrid`` (100 / 0 / -1) both carry exactly this classification.
    """

    bag_format: str = Field("mcap", pattern="^(mcap|bag)$", description="maps bag: ROS2 .mcap or ROS1 .bag")
    png: bool = Field(True, description="write PNG figures")
    next_best_views: int = Field(
        5,
        ge=0,
        le=100,
        description="next-best views of each map's exploration plan (mapping.frontier: frontier cells, the "
        "expected variance reduction of a scan at candidate poses): the maps bag's "
        "/NAME/next_best_views and GridMap layers 'frontier' / 'information'; 0: no exploration plan",
    )
    unknown_variance_fraction: float = Field(
        UNKNOWN_VARIANCE_FRACTION,
        gt=0,
        le=1,
        description="a cell whose GP variance exceeds this fraction of the prior variance k(x*, x*) is "
        "unknown in every export (-1 in the OccupancyGrid, grey 205 in the PGM) whatever its p(occ): no "
        "data constrained it. 0.9 = known once the data explain a tenth of the prior variance; it separates "
        "the cells a beam touched from the others best over the demo's and Intel's maps before and after "
        "loop closure (docs/mapping.md, 'Unknown cells'): lower values turn observed cells whose poses are "
        "uncertain unknown, higher ones widen the band of extrapolated cells around the data",
    )


class Config(StageConfig):
    """Everything a run needs, by stage."""

    input: InputConfig = Field(default_factory=InputConfig)
    slam: SlamConfig = Field(default_factory=SlamConfig)
    mapping: MappingConfig = Field(default_factory=MappingConfig)
    export: ExportConfig = Field(default_factory=ExportConfig)
    scale: ScaleConfig = Field(default_factory=ScaleConfig)


def _one_line(text: object, limit: int = 200) -> str:
    """A message (a library's, or a key path) on one printable line of at most ``limit`` characters: runs of
    whitespace made one space, other control characters escaped (:func:`~datasets.errors.shown`)."""
    return shown(" ".join(str(text).split()), limit, bare=True)


def _shown(value: object) -> str:
    """A configuration value in a message: a bounded one-line repr, even of a YAML alias bomb, a string of
    control characters or an integer of thousands of digits (:func:`~datasets.errors.shown`)."""
    return shown(value, 80)


class ConfigLoader(yaml.SafeLoader):
    """PyYAML's safe loader without YAML 1.1's implicit timestamps, and with located construction errors.

    A plain ``2001-02-28`` stays the string it looks like (a topic may be named so; YAML 1.1 would make it a
    ``date``, and ``2001-02-29`` a ValueError); an explicit ``!!timestamp`` still builds a date. A scalar that
    a constructor refuses with a ValueError or OverflowError (``!!float abc``, ``!!int 1.5``, an integer of
    more than 4300 digits, ``!!timestamp 2001-13-45``, ``!!timestamp x``) becomes a ConstructorError with its
    line and column.
    """

    yaml_implicit_resolvers: ClassVar[dict[str, list[tuple[str, re.Pattern[str]]]]] = {
        first: [(tag, regexp) for tag, regexp in resolvers if tag != "tag:yaml.org,2002:timestamp"]
        for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()
    }

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        """The mapping of ``node``; a key written twice in it is a ConstructorError at the second one (YAML
        forbids it, and PyYAML would silently keep the last: a section written twice lost the first's
        keys). Keys a merge (``<<: *base``) brings may be overridden, as YAML says."""
        if isinstance(node, yaml.MappingNode):
            seen: set[Any] = set()
            for key_node, _ in node.value:
                if key_node.tag == "tag:yaml.org,2002:merge":
                    continue
                key = self.construct_object(key_node, deep=deep)
                try:
                    duplicate = key in seen
                    seen.add(key)
                except TypeError:  # (an unhashable key: the base constructor says so)
                    continue
                if duplicate:
                    raise yaml.constructor.ConstructorError(
                        None, None, f"key {shown(key, 40)} is written twice", key_node.start_mark
                    )
        return super().construct_mapping(node, deep=deep)

    def construct_object(self, node: yaml.Node, deep: bool = False) -> Any:
        """The value of ``node``; any error of a constructor is a ConstructorError naming the node's position
        (ValueError and OverflowError of bad values, AttributeError of PyYAML's timestamp constructor on
        ``!!timestamp x``)."""
        try:
            return super().construct_object(node, deep=deep)
        except (yaml.YAMLError, RecursionError):
            raise
        except Exception as exc:
            value = node.value if isinstance(node, yaml.ScalarNode) else node.tag
            problem = f"cannot read {node.tag.rsplit(':', 1)[-1]} {shown(value, 40)} ({_one_line(exc, 120)})"
            raise yaml.constructor.ConstructorError(None, None, problem, node.start_mark) from None


def _yaml_problem(exc: yaml.YAMLError) -> str:
    """One line saying where and what a YAML error is (``line 2, column 1: expected ...``)."""
    mark, problem = getattr(exc, "problem_mark", None), getattr(exc, "problem", None)
    if mark is not None and problem:
        return _one_line(f"line {mark.line + 1}, column {mark.column + 1}: {problem}")
    return _one_line(exc) or type(exc).__name__


def _key_path(loc: tuple[int | str, ...]) -> str:
    """``mapping.resolution_m`` from a pydantic error location (whose keys come from the file)."""
    return ".".join(shown(p, 60, bare=True) for p in loc) or "(root)"


def _format_validation_error(source: str, error: ValidationError) -> str:
    first = error.errors()[0]
    where = _key_path(first["loc"])
    if first["type"] == "extra_forbidden":
        return f"{source}: unknown configuration key '{where}'"
    moved = (first.get("ctx") or {}).get("error")
    if isinstance(moved, MovedKeyError):
        return f"{source}: configuration key '{where}.{moved.old}' is now '{where}.{moved.new}'"
    if isinstance(moved, BoolValueError):
        key = _key_path((*first["loc"], moved.key))
        return f"{source}: invalid value {_shown(moved.value)} for '{key}': a number or text, not true/false"
    value = first.get("input")
    return f"{source}: invalid value {_shown(value)} for '{where}': {_one_line(first['msg'])}"


def _overridden_key(error: ValidationError, overrides: dict[str, dict[str, Any]]) -> str | None:
    """The dotted key (``"mapping.resolution_m"``) of an override that the first error is about, else None."""
    loc = error.errors()[0]["loc"]
    if len(loc) < 2 or not isinstance(loc[0], str) or not isinstance(loc[1], str):
        return None  # (a key of the file that is no string, e.g. an integer of thousands of digits)
    stage, key = loc[0], loc[1]
    if (overrides.get(stage) or {}).get(key) is None:
        return None
    return f"{stage}.{key}"


def config_from_dict(data: dict[str, Any], source: str = "config") -> Config:
    """Validate a nested dict into a :class:`Config`; ConfigError names the first bad key or value."""
    try:
        return Config.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(_format_validation_error(source, exc)) from None


def load_config(path: str | Path | None = None, overrides: dict[str, dict[str, Any]] | None = None) -> Config:
    """Load ``path`` (default: ``pipeline/default.yaml``) and apply per-stage ``overrides``.

    ``overrides`` is ``{"stage": {"key": value}}``, e.g. from command-line options (None values are not
    applied); a bad override value is blamed on its command-line option (:data:`CLI_OPTIONS`), a bad value
    of the file on the file. Any unreadable, non-UTF-8 or malformed file, and any value YAML cannot build
    (``!!float abc``, a 5000-digit integer), is a ConfigError of one printable line. The file is read with
    :class:`ConfigLoader`: a plain date-like value (``scan_topic: 2001-02-28``) is the string it looks like.
    """
    p = Path(path) if path is not None else DEFAULT_CONFIG_PATH
    if p.exists() and not p.is_file() and not p.is_dir():  # (a FIFO would wait for a writer forever)
        raise ConfigError(f"{p}: not a regular file (a pipe, socket or device), not a configuration file")
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"{p}: no such configuration file") from None
    except IsADirectoryError:
        raise ConfigError(f"{p}: is a directory, not a configuration file") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(
            f"{p}: not a UTF-8 text file (byte 0x{exc.object[exc.start]:02x} at offset {exc.start})"
        ) from None
    except OSError as exc:
        raise ConfigError(f"{p}: cannot read configuration: {exc.strerror or exc}") from None
    try:
        data = yaml.load(text, Loader=ConfigLoader) or {}  # a SafeLoader
    except yaml.YAMLError as exc:
        raise ConfigError(f"{p}: not valid YAML ({_yaml_problem(exc)})") from None
    except RecursionError:
        raise ConfigError(f"{p}: not a usable configuration (YAML nested too deeply)") from None
    except (ValueError, ArithmeticError, TypeError, AttributeError) as exc:  # (outside any constructor)
        raise ConfigError(f"{p}: not a usable configuration ({_one_line(exc, 120)})") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{p}: a configuration must be a mapping of stages, got {type(data).__name__}")
    for stage, values in (overrides or {}).items():
        section = data.setdefault(stage, {}) or {}
        if not isinstance(section, dict):
            raise ConfigError(f"{p}: section '{stage}' must be a mapping")
        section.update({k: v for k, v in values.items() if v is not None})
        data[stage] = section
    try:
        return Config.model_validate(data)
    except ValidationError as exc:
        key = _overridden_key(exc, overrides or {})
        if key is None:
            raise ConfigError(_format_validation_error(str(p), exc)) from None
        value = (overrides or {})[key.split(".")[0]][key.split(".")[1]]
        first = exc.errors()[0]
        option = CLI_OPTIONS.get(key, f"the override of '{key}'")
        raise ConfigError(
            f"{option} {_shown(value)}: invalid value for '{key}': {_one_line(first['msg'])}"
        ) from None


def config_to_yaml(config: Config) -> str:
    """The resolved configuration as YAML (every field, defaults included)."""
    return yaml.safe_dump(config.model_dump(mode="json"), sort_keys=False)


def write_config(config: Config, path: str | Path) -> None:
    """Write the resolved configuration to ``path``."""
    Path(path).write_text(config_to_yaml(config))
