"""The errors of file reading: each message is one line that names the file."""

__all__ = ["PointFileError", "CurveFileError"]


class PointFileError(ValueError):
    """A point file that cannot be read; the message is one line naming the file."""


class CurveFileError(ValueError):
    """A curve ``.npz`` file that cannot be loaded; the message is one line naming the file."""
