"""``geer-process-data``: fisheye (or other) images or a video -> a geer dataset, via pycolmap SfM.

``python -m geer_ns.process_data --help`` runs the same command line.
"""

from geer_ns.process_data.cli import ProcessDataConfig, entrypoint, run
from geer_ns.process_data.frames import ProcessDataError

__all__ = ["ProcessDataConfig", "ProcessDataError", "entrypoint", "run"]
