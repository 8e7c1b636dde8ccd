"""The package's exceptions.

Every error spacepose raises on purpose derives from :class:`SpaceposeError`, so a caller (and the
CLI, which maps it to a one-line message and exit code 1) can tell a problem with the input or the
configuration from a bug.
"""

from __future__ import annotations

from pathlib import Path


def _located(error: Exception, message: str, source: str | Path | None) -> str:
    """Store ``source`` and ``reason`` on ``error``; the message with the source prefixed."""
    error.source = None if source is None else str(source)
    error.reason = message
    return f"{error.source}: {message}" if error.source else message


class SpaceposeError(Exception):
    """Base class of every error spacepose raises on purpose."""


class InputError(SpaceposeError, ValueError):
    """Bad input data: wrong shape, empty, non-finite, too few points.

    Parameters
    ----------
    message
        What is wrong, in one sentence.
    source
        The file (or other named source) the data came from, if any; it is prefixed to the
        message so the user sees which file is at fault.
    """

    def __init__(self, message: str, source: str | Path | None = None) -> None:
        super().__init__(_located(self, message, source))


class FileFormatError(InputError):
    """A file that cannot be read: unknown extension, corrupt or truncated content, bad header."""


class DegenerateGeometryError(InputError):
    """Geometry that does not determine the quantity asked for (collinear points, one plane)."""


class PredictionGapError(InputError):
    """A gap between frames too long for a filter to predict across: its state no longer says
    where the target is (the navigators start again after it)."""


class ConfigError(SpaceposeError, ValueError):
    """An invalid configuration: unknown option, value out of range, unreadable config file."""


class RegistrationError(SpaceposeError):
    """A registration that cannot produce a transform (no correspondences, no consensus)."""


class Interrupted(SpaceposeError):
    """A run stopped by the user (Ctrl-C), its outputs written up to the last whole frame.

    Parameters
    ----------
    message
        How far the run got and what its outputs hold.
    source
        The output the message concerns (prefixed as for :class:`InputError`).
    """

    def __init__(self, message: str, source: str | Path | None = None) -> None:
        super().__init__(_located(self, message, source))


class SpaceposeWarning(UserWarning):
    """Input that is accepted but looks wrong (coordinates in millimetres, a skipped file).

    Parameters
    ----------
    message
        What looks wrong, in one sentence.
    source
        The file it concerns, if any; prefixed to the message as for :class:`InputError`.
    """

    def __init__(self, message: str, source: str | Path | None = None) -> None:
        super().__init__(_located(self, message, source))
