"""The root configuration: one pydantic model per stage, YAML in and out, unknown keys rejected."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from datasets.config import InputConfig
from datasets.errors import ConfigError
from mapping.config import MappingConfig
from pipeline.scale_config import ScaleConfig
from slam.config import SlamConfig

DEFAULT_CONFIG_PATH = Path(__file__).resolve().parent / "default.yaml"


class ExportConfig(BaseModel):
    """Which map exports a run writes."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    bag_format: str = Field("mcap", pattern="^(mcap|bag)$", description="maps bag: ROS2 .mcap or ROS1 .bag")
    png: bool = Field(True, description="write PNG figures")


class Config(BaseModel):
    """Everything a run needs, by stage."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    input: InputConfig = Field(default_factory=InputConfig)
    slam: SlamConfig = Field(default_factory=SlamConfig)
    mapping: MappingConfig = Field(default_factory=MappingConfig)
    export: ExportConfig = Field(default_factory=ExportConfig)
    scale: ScaleConfig = Field(default_factory=ScaleConfig)


def _format_validation_error(source: str, error: ValidationError) -> str:
    first = error.errors()[0]
    where = ".".join(str(p) for p in first["loc"]) or "(root)"
    if first["type"] == "extra_forbidden":
        return f"{source}: unknown configuration key '{where}'"
    value = first.get("input")
    return f"{source}: invalid value {value!r} for '{where}': {first['msg']}"


def config_from_dict(data: dict[str, Any], source: str = "config") -> Config:
    """Validate a nested dict into a :class:`Config`; ConfigError names the first bad key or value."""
    try:
        return Config.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(_format_validation_error(source, exc)) from None


def load_config(path: str | Path | None = None, overrides: dict[str, dict[str, Any]] | None = None) -> Config:
    """Load ``path`` (default: ``pipeline/default.yaml``) and apply per-stage ``overrides``.

    ``overrides`` is ``{"stage": {"key": value}}``, e.g. from command-line options.
    """
    p = Path(path) if path is not None else DEFAULT_CONFIG_PATH
    try:
        text = p.read_text()
    except FileNotFoundError:
        raise ConfigError(f"{p}: no such configuration file") from None
    except OSError as exc:
        raise ConfigError(f"{p}: cannot read configuration: {exc.strerror}") from None
    try:
        data = yaml.safe_load(text) or {}
    except yaml.YAMLError as exc:
        raise ConfigError(f"{p}: not valid YAML ({str(exc).splitlines()[0]})") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{p}: a configuration must be a mapping of stages, got {type(data).__name__}")
    for stage, values in (overrides or {}).items():
        section = data.setdefault(stage, {}) or {}
        if not isinstance(section, dict):
            raise ConfigError(f"{p}: section '{stage}' must be a mapping")
        section.update({k: v for k, v in values.items() if v is not None})
        data[stage] = section
    return config_from_dict(data, str(p))


def config_to_yaml(config: Config) -> str:
    """The resolved configuration as YAML (every field, defaults included)."""
    return yaml.safe_dump(config.model_dump(mode="json"), sort_keys=False)


def write_config(config: Config, path: str | Path) -> None:
    """Write the resolved configuration to ``path``."""
    Path(path).write_text(config_to_yaml(config))
