"""The errors a user can fix: each names the file or setting and the problem in one line.

The command-line entry points catch `MeshsegError` and print `error: <message>`; anything else
(a programming error) propagates with its traceback. Each subclass is also a `ValueError`, so code
that validates input keeps the conventional exception type.
"""

from __future__ import annotations


class MeshsegError(Exception):
    """Base of every error meant for the user (bad input, bad configuration)."""


class ConfigError(MeshsegError, ValueError):
    """A configuration value that is not allowed; the message names the setting and what is allowed."""


class MeshDataError(MeshsegError, ValueError):
    """Bad mesh, label or split data; the message names the file and the problem."""

    def __init__(self, source: object, problem: str):
        super().__init__(f"{source}: {problem}")
        self.source = str(source)
        self.problem = problem

    def __reduce__(self):  # pickled across joblib / submitit workers: rebuild from both parts
        return type(self), (self.source, self.problem)


class ManifestError(MeshsegError, ValueError):
    """A study manifest (experiments/*.yaml) that cannot be used; the message names the file."""


class TrackingError(MeshsegError):
    """The tracking store cannot be used (bad uri, server not answering)."""
