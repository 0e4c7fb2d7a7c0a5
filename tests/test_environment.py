"""The installed environment: the contrib OpenCV build wins over the plain wheels nerfstudio pulls in."""

from __future__ import annotations

import importlib.metadata


def test_cv2_has_contrib_modules():
    import cv2

    assert hasattr(cv2, "omnidir"), "cv2.omnidir missing: a non-contrib opencv wheel overwrote cv2/"
    assert hasattr(cv2, "fisheye")
    assert hasattr(cv2.omnidir, "projectPoints") and hasattr(cv2.fisheye, "undistortPoints")


def test_pinned_host_versions():
    assert importlib.metadata.version("nerfstudio") == "1.1.5"
    assert importlib.metadata.version("gsplat") == "1.4.0"
    assert importlib.metadata.version("torch").startswith("2.14.1")
