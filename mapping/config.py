"""Configuration of the mapping stage."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field


class MappingConfig(BaseModel):
    """GP occupancy-map settings (paper defaults where the paper gives one)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    mapper: Literal["gppol", "gpfol"] = Field("gppol", description="GPPOL (uncertain inputs) or GPFOL")
    resolution_m: float = Field(0.1, gt=0, le=100, description="cell size of rendered maps")
    k_occupied: int = Field(15, ge=1, le=200, description="occupied neighbours per query (paper: 15)")
    k_free: int = Field(15, ge=1, le=200, description="free-space beam neighbours per query (paper: 15)")
    occupied_threshold: float = Field(0.65, gt=0, lt=1, description="p(occ) >= this is occupied")
    free_threshold: float = Field(0.35, gt=0, lt=1, description="p(occ) <= this is free")
