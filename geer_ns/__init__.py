"""geer-ns: 3DGEER (exact, efficient 3D Gaussian rendering for generic cameras) as a nerfstudio plugin."""

__version__ = "0.1.0"

# Before anything below imports nerfstudio: filter the host's known import-time warnings (exactly those).
from geer_ns import host_fixes as _host_fixes  # noqa: E402

_host_fixes.quiet_known_warnings()
