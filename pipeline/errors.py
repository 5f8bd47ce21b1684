"""Known errors raised by the pipeline (run folders, inputs, stored parameters)."""

from __future__ import annotations

from datasets.errors import GpomError


class PipelineError(GpomError):
    """A run cannot proceed: existing output folder, inconsistent run folder, missing inputs."""
