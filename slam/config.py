"""Configuration of the SLAM stage (odometry, keyframes, loop closure, pose graph)."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field


class SlamConfig(BaseModel):
    """Odometry, keyframing, loop closure and pose-graph settings."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    keyframe_distance_m: float = Field(0.5, gt=0, description="new keyframe after this much travel")
    keyframe_rotation_rad: float = Field(0.5, gt=0, description="new keyframe after this much rotation")
