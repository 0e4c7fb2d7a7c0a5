"""Errors that more than one floor of the package raises or handles: no geer imports, so anything may import it."""

from __future__ import annotations

import sys

__all__ = ["DatasetError", "report_dataset_errors_in_one_line"]


class DatasetError(ValueError):
    """A dataset problem, reported as one line naming the file, the frame or line, and the field."""


def report_dataset_errors_in_one_line() -> None:
    """ns-train gives a plugin no place to catch a broken dataset, so a DatasetError would end a geer run under a
    page of nerfstudio's stack: this process's excepthook prints its one line instead (exit status 1). Every
    other exception keeps its traceback. Installed by geer's trainer config for its own runs only."""
    previous = sys.excepthook
    if getattr(previous, "geer_dataset_hook", False):
        return

    def hook(kind, value, traceback):
        if isinstance(value, DatasetError):
            print(value, file=sys.stderr)
        else:
            previous(kind, value, traceback)

    hook.geer_dataset_hook = True  # type: ignore[attr-defined]
    sys.excepthook = hook
