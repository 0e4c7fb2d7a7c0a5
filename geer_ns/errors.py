"""Errors that more than one floor of the package raises or handles: no imports, so anything may import it
(host_fixes reports a DatasetError raised by the data parsers without importing them)."""

from __future__ import annotations

__all__ = ["DatasetError"]


class DatasetError(ValueError):
    """A dataset problem, reported as one line naming the file, the frame or line, and the field."""
