"""Exception hierarchy for known errors.

Every error a user can cause (bad file, bad topic, bad configuration value) is raised as a subclass of
:class:`GpomError`. The command line prints ``str(error)`` on one line and exits with status 1; anything
else is a bug and keeps its traceback. Library code never prints or exits.
"""

from __future__ import annotations


class GpomError(Exception):
    """Base class of every known error of the project (the CLI turns it into one line, exit 1)."""


class DatasetError(GpomError):
    """A recording cannot be read or written: missing, unreadable, corrupt or inconsistent input."""


class UnknownFormatError(DatasetError):
    """The format of a path cannot be guessed or is not supported."""


class TopicError(DatasetError):
    """A requested topic is missing, or auto-detection found zero or several candidates."""


class ConfigError(GpomError):
    """A configuration file or value is invalid."""
