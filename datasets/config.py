"""Configuration of the input stage (readers)."""

from __future__ import annotations

import types
import typing
from typing import Any, ClassVar, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator


class MovedKeyError(ValueError):
    """A configuration key of a former flat section, now in a nested section: ``old`` -> ``new`` (dotted,
    relative to the section)."""

    def __init__(self, old: str, new: str) -> None:
        super().__init__(f"'{old}' is now '{new}' (a nested section)")
        self.old, self.new = old, new


class BoolValueError(ValueError):
    """A YAML ``true`` / ``false`` given to the configuration key ``key`` (relative to its section), which
    takes a number or text."""

    def __init__(self, key: str, value: Any) -> None:
        super().__init__(f"'{key}' takes a number or text, not true/false")
        self.key, self.value = key, value


def refuse_moved_keys(data: Any, moved: dict[str, str]) -> Any:
    """``data`` unchanged; MovedKeyError for the first of its keys that ``moved`` says went elsewhere (use
    in a ``model_validator(mode="before")``)."""
    if isinstance(data, dict):
        for old, new in moved.items():
            if old in data:
                raise MovedKeyError(old, new)
    return data


def _takes_bool(annotation: Any) -> bool:
    """Whether a field of this type may hold a YAML ``true``/``false`` here: ``bool`` (or a ``Literal`` of
    one) anywhere in it, ``Any``, or a section (left to pydantic's own message)."""
    if annotation is bool or annotation is Any or isinstance(annotation, bool):
        return True
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return True  # (a section: pydantic says it wants a mapping)
    origin = typing.get_origin(annotation)
    if origin is None and not isinstance(annotation, types.UnionType):
        return False
    return any(_takes_bool(arg) for arg in typing.get_args(annotation))


def _holds_bool(value: Any) -> bool:
    """Whether ``value`` is a bool or a list / tuple with one among its items (not walked deeper: a YAML
    alias bomb of nested lists stays pydantic's to refuse, and a nested mapping is a section itself)."""
    if isinstance(value, bool):
        return True
    return isinstance(value, (list, tuple)) and any(isinstance(v, bool) for v in value)


class StageConfig(BaseModel):
    """A section of the configuration: unknown keys, NaN and infinity refused, frozen; a YAML ``true`` or
    ``false`` (or ``yes``, ``on``, ...) is refused where the key takes a number or text.

    Pydantic's lax mode would read ``resolution_m: true`` as 1.0 and ``k: false`` as 0: a slip of the
    pen that runs with a value nobody chose. A section whose key takes a bool on purpose through a
    validator of its own (``slam.wheel_odometry: off``) lists it in ``bool_keys``.
    """

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
    bool_keys: ClassVar[frozenset[str]] = frozenset()

    @model_validator(mode="before")
    @classmethod
    def _no_bool_numbers(cls, data: Any) -> Any:
        if isinstance(data, dict):
            for key, value in data.items():
                field = cls.model_fields.get(key) if isinstance(key, str) else None
                if field is None or key in cls.bool_keys or not _holds_bool(value):
                    continue
                if not _takes_bool(field.annotation):
                    raise BoolValueError(key, value)
        return data


class InputConfig(StageConfig):
    """How a recording is read: topics, CARMEN record types, and the 3D-to-2D height band."""

    scan_topic: str | None = Field(
        None,
        description="LaserScan or PointCloud2 topic; null auto-detects (exactly one candidate), "
        "'all' reads every LaserScan topic (several platforms), 'none' reads a bag without scans",
    )
    odom_topic: str | None = Field(
        None, description="nav_msgs/Odometry topic; null auto-detects; 'none' reads no odometry"
    )
    reference_topic: str | None = Field(
        None, description="ground-truth pose topic; null auto-detects a topic named '*ground_truth*'"
    )
    carmen_laser: Literal["auto", "FLASER", "RLASER", "ROBOTLASER1"] = Field(
        "auto", description="CARMEN laser record type to read; auto takes the most frequent one"
    )
    carmen_range_max_m: float = Field(
        80.0,
        gt=0,
        description="CARMEN ranges at or beyond this are no returns (SICK LMS: 80 m maximum; no-return "
        "readings are logged as 81.83 m in intel.clf, 81.91 m in fr079.clf)",
    )
    carmen_range_min_m: float = Field(
        0.05, ge=0, description="CARMEN ranges below this are invalid (0 marks a failed reading in some logs)"
    )
    carmen_stamp_jitter_s: float = Field(
        1.0,
        ge=0,
        description="a raw CARMEN log's timestamps may step back by at most this much (intel.clf: 0.90 s); "
        "a larger step back is an error",
    )
    cloud_height_band_m: tuple[float, float] = Field(
        (-0.25, 0.25), description="z band (sensor frame, m) of a 3D cloud turned into a 2D scan"
    )
    cloud_scan_beams: int = Field(720, ge=8, le=100_000, description="beams of the 2D scan made from a cloud")
    cloud_range_max_m: float = Field(80.0, gt=0, description="range_max of the 2D scan made from a cloud")

    @model_validator(mode="after")
    def _band_ordered(self) -> InputConfig:
        lo, hi = self.cloud_height_band_m
        if not lo < hi:
            raise ValueError(f"cloud_height_band_m must be (low, high) with low < high, got {lo}, {hi}")
        if not self.carmen_range_min_m < self.carmen_range_max_m:
            raise ValueError(
                f"carmen_range_min_m ({self.carmen_range_min_m:g}) must be below carmen_range_max_m "
                f"({self.carmen_range_max_m:g})"
            )
        return self
