"""The output folder of one geer-process-data run: what the run may replace, and what a failure leaves behind.

A run writes only the dataset's entries (ENTRIES) and, while it runs, a marker file naming itself. It never
touches anything else in the folder, and a failure never loses what was there before:

- success: the marker goes, and the previous dataset too when --overwrite replaced one;
- a failure whose explanation points at what the run wrote (a model with too few images, a camera model that
  does not fit: ProcessDataError.keeps_output) leaves that output and the marker, so a re-run into the folder
  replaces it without --overwrite; the same holds after a killed run;
- any other failure removes everything the run wrote and puts a dataset that --overwrite moved aside back; a
  folder the run created is removed again.

With --overwrite, the previous dataset is moved into a hidden sub-folder until the run has succeeded.
"""

from __future__ import annotations

import json
import shutil
import time
from pathlib import Path
from types import TracebackType
from typing import List, Optional, Type

from nerfstudio.utils.rich_utils import CONSOLE

from geer_ns.process_data.frames import ProcessDataError

ENTRIES = ("images", "masks", "sparse", "colmap", "transforms.json", "points3d.ply", "process_data_report.json")
MARKER = ".geer-process-data-run.json"  # present while a run writes, and after a failure that kept its output
PREVIOUS = ".geer-process-data-previous"  # the dataset --overwrite replaces, until the run has succeeded


def _present(folder: Path) -> List[str]:
    return [name for name in ENTRIES if (folder / name).exists() or (folder / name).is_symlink()]


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    else:
        path.unlink()


def _move(names: List[str], src: Path, dst: Path) -> None:
    dst.mkdir(parents=True, exist_ok=True)
    for name in names:
        (src / name).rename(dst / name)


class OutputRun:
    """Context manager around one run writing into `folder` (see the module docstring)."""

    def __init__(self, folder: Path, data: Path, overwrite: bool) -> None:
        self.folder, self.data, self.overwrite = folder, data, overwrite
        self.created = False
        self.previous: Optional[Path] = None

    def __enter__(self) -> "OutputRun":
        out = self.folder
        if self.data.is_dir() and out.resolve().is_relative_to(self.data.resolve()):
            raise ProcessDataError(f"--output-dir {out} lies inside --data {self.data}; choose another folder")
        if (out / MARKER).exists():
            self._undo_unfinished_run()
        existing = _present(out)
        if existing and not self.overwrite:
            raise ProcessDataError(f"{out} already holds a dataset ({', '.join(existing)}); use --overwrite")
        self.created = not out.exists()
        out.mkdir(parents=True, exist_ok=True)
        if existing:
            self.previous = out / PREVIOUS
            _move(existing, out, self.previous)
        record = {"data": str(self.data), "started": time.strftime("%Y-%m-%d %H:%M:%S"),
                  "previous": self.previous is not None}
        (out / MARKER).write_text(json.dumps(record), encoding="utf8")
        return self

    def _undo_unfinished_run(self) -> None:
        """What an earlier run left (it failed with its output kept, or was killed): its entries are removed
        and a dataset it had moved aside is put back, so the folder is as before that run."""
        out = self.folder
        record = json.loads((out / MARKER).read_text(encoding="utf8"))
        left = _present(out)
        for name in left:
            _remove(out / name)
        restored = []
        if record.get("previous") and (out / PREVIOUS).is_dir():
            restored = sorted(p.name for p in (out / PREVIOUS).iterdir())
            _move(restored, out / PREVIOUS, out)
            (out / PREVIOUS).rmdir()
        (out / MARKER).unlink()
        CONSOLE.print(f"[yellow]{out}: removed what the unfinished run of {record.get('started', '?')} left "
                      f"({', '.join(left) or 'nothing'})"
                      + (f" and put back the dataset it was replacing ({', '.join(restored)})" if restored else ""))

    def __exit__(self, kind: Optional[Type[BaseException]], error: Optional[BaseException],
                 traceback: Optional[TracebackType]) -> None:
        out = self.folder
        if error is None:
            if self.previous is not None:
                shutil.rmtree(self.previous)
            (out / MARKER).unlink()
            return
        if isinstance(error, ProcessDataError) and error.keeps_output:
            note = (f"A re-run into {out} replaces what this run left there (no --overwrite needed)."
                    if self.previous is None else
                    f"The dataset that was in {out} before this run is kept in {self.previous}: a re-run with "
                    "--overwrite replaces both, a re-run without puts it back.")
            error.args = (f"{error}\n{note}",)
            return
        for name in _present(out):
            _remove(out / name)
        if self.previous is not None:
            _move(sorted(p.name for p in self.previous.iterdir()), self.previous, out)
            self.previous.rmdir()
        (out / MARKER).unlink()
        if self.created and not any(out.iterdir()):
            out.rmdir()
