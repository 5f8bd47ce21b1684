"""Configuration of tiled rendering (:mod:`pipeline.scale`): tile size, update tolerances, the engine."""

from __future__ import annotations

from pydantic import Field

from datasets.config import StageConfig

SCHEDULER_PATTERN = r"^(local|(tcp|tls|ws|wss|inproc|ucx)://\S+)$"


class ScaleConfig(StageConfig):
    """Tiled rendering and where it runs."""

    tile_cells: int = Field(
        64, ge=8, le=4096, description="maps are rendered in tiles of this many cells a side (any size gives "
        "the same map; smaller tiles make incremental updates finer, larger ones cost less overhead)"
    )  # fmt: skip
    pose_tolerance_m: float = Field(
        1e-6, ge=0, le=10, description="remap: beams that moved less than this keep their old position. "
        "1 um ignores the float noise of text round trips (TUM's yaw -> quaternion -> yaw changes the last "
        "bits); 0 makes the result equal a full recomputation bit for bit"
    )  # fmt: skip
    covariance_tolerance: float = Field(
        0.0, ge=0, le=100, description="remap (gppol): scan covariances that changed less than this in every "
        "entry (m^2, rad^2) are kept (0: exact)"
    )  # fmt: skip
    scheduler: str | None = Field(
        None, pattern=SCHEDULER_PATTERN, description="where tiles are rendered: null in this process, "
        "'local' a local Dask cluster, or the address of a Dask scheduler (tcp://HOST:PORT)"
    )  # fmt: skip
    connect_timeout_s: float = Field(
        20.0, gt=0, le=3600, description="how long to wait for a remote Dask scheduler"
    )
    max_map_cells: int = Field(
        50_000_000, ge=1, description="largest map (cells) a run or remap may render, checked before any "
        "allocation: a rendered map costs ~80 bytes per cell at its peak (a run renders two), so 5e7 cells "
        "(700 m x 700 m at 0.1 m) need ~4 GB per map"
    )  # fmt: skip
    workers: int = Field(2, ge=1, le=512, description="worker processes of a 'local' cluster")
    threads_per_worker: int = Field(1, ge=1, le=512, description="threads per worker of a 'local' cluster")
