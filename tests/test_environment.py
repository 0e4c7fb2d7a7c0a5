"""The installed environment: the contrib OpenCV build wins over the plain wheels nerfstudio pulls in."""

from __future__ import annotations

import importlib.metadata


def test_cv2_has_contrib_modules():
    import cv2

    assert hasattr(cv2, "omnidir"), "cv2.omnidir missing: a non-contrib opencv wheel overwrote cv2/"
    assert hasattr(cv2, "fisheye")
    assert hasattr(cv2.omnidir, "projectPoints") and hasattr(cv2.fisheye, "undistortPoints")


def _requirements():
    import tomllib
    from pathlib import Path

    from packaging.requirements import Requirement

    root = Path(__file__).resolve().parents[1]
    project = tomllib.loads((root / "pyproject.toml").read_text())["project"]
    ranges = {r.name: r for r in map(Requirement, project["dependencies"] + project["optional-dependencies"]["test"])}
    pins = dict(line.split("==") for line in (root / "constraints.txt").read_text().splitlines()
                if line and not line.startswith("#"))
    return ranges, pins


def test_constraints_pin_versions_inside_the_declared_ranges():
    ranges, pins = _requirements()
    assert {"torch", "torchvision", "nerfstudio", "pycolmap"} <= set(pins)
    assert not [str(r) for r in ranges.values() if any(s.operator == "==" for s in r.specifier)]
    outside = [f"{name}=={version}" for name, version in pins.items()
               if name in ranges and not ranges[name].specifier.contains(version)]
    assert not outside, f"constraints.txt pins outside pyproject.toml's ranges: {outside}"


def test_installed_versions_inside_the_declared_ranges():
    ranges, _ = _requirements()
    outside = []
    for name, requirement in ranges.items():
        version = importlib.metadata.version(name).split("+")[0]  # torch's local build tag (+cu130) aside
        if not requirement.specifier.contains(version):
            outside.append(f"{name} {version} not in {requirement.specifier}")
    assert not outside, outside
