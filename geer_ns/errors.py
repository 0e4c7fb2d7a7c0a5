"""Errors that more than one floor of the package raises or handles: no geer imports, so anything may import it."""

from __future__ import annotations

import sys

__all__ = ["DatasetError", "OptionError", "report_input_errors_in_one_line"]


class DatasetError(ValueError):
    """A dataset problem, reported as one line naming the file, the frame or line, and the field."""


class OptionError(ValueError):
    """A command-line option's value geer cannot run with, reported as one line naming the option."""


def report_input_errors_in_one_line() -> None:
    """ns-train gives a plugin no place to catch a broken dataset or a bad option, so a DatasetError or an
    OptionError would end a geer run under a page of nerfstudio's stack: this process's excepthook prints its one
    line instead (exit status 1). Every other exception keeps its traceback. Installed by geer's trainer config for
    its own runs only."""
    previous = sys.excepthook
    if getattr(previous, "geer_input_hook", False):
        return

    def hook(kind, value, traceback):
        if isinstance(value, (DatasetError, OptionError)):
            print(value, file=sys.stderr)
        else:
            previous(kind, value, traceback)

    hook.geer_input_hook = True  # type: ignore[attr-defined]
    sys.excepthook = hook
