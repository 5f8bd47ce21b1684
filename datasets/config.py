"""Configuration of the input stage (readers)."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator


class MovedKeyError(ValueError):
    """A configuration key of a former flat section, now in a nested section: ``old`` -> ``new`` (dotted,
    relative to the section)."""

    def __init__(self, old: str, new: str) -> None:
        super().__init__(f"'{old}' is now '{new}' (a nested section)")
        self.old, self.new = old, new


def refuse_moved_keys(data: Any, moved: dict[str, str]) -> Any:
    """``data`` unchanged; MovedKeyError for the first of its keys that ``moved`` says went elsewhere (use
    in a ``model_validator(mode="before")``)."""
    if isinstance(data, dict):
        for old, new in moved.items():
            if old in data:
                raise MovedKeyError(old, new)
    return data


class InputConfig(BaseModel):
    """How a recording is read: topics, CARMEN record types, and the 3D-to-2D height band."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

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
