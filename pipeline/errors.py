"""Known errors raised by the pipeline (run folders, commands not yet available)."""

from __future__ import annotations

from datasets.errors import GpomError


class PipelineError(GpomError):
    """A run cannot proceed: existing output folder, inconsistent run folder, missing inputs."""


class NotYetAvailableError(GpomError):
    """A command whose stage has not landed yet."""


def not_yet_available(command: str, issue: int, what: str) -> NotYetAvailableError:
    """The one-line error of a command whose stage lands in a later issue."""
    return NotYetAvailableError(f"'{command}' is not available yet: {what} lands with issue #{issue}")
