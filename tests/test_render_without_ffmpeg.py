"""`ns-render interpolate` and `ns-render camera-path` write videos on a machine without a system ffmpeg.

A tiny model (3 steps on the embedded room) is rendered by the real ns-render command lines with a PATH that
holds no `ffmpeg`; geer_ns.compat.provide_ffmpeg links imageio-ffmpeg's binary in.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from geer_ns.data.synthetic_room import default_scene_dir

from conftest import tiny_trainer_config, train_in_process

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    config = tiny_trainer_config(default_scene_dir(), tmp_path_factory.mktemp("render"), "room", 3)
    config.save_config()
    train_in_process(config)
    return config.get_base_dir() / "config.yml"


def _env_without_ffmpeg(tmp_path: Path) -> dict:
    path = os.pathsep.join([str(BIN), "/usr/bin", "/bin"])
    assert shutil.which("ffmpeg", path=path) is None, "this test needs a machine without a system ffmpeg on PATH"
    # a fresh cache: the `ffmpeg` link is made anew, as on a fresh machine; PYTHONPATH: this checkout's geer_ns
    return dict(os.environ, PATH=path, GEER_NS_CACHE=str(tmp_path / "cache"), PYTHONPATH=str(ROOT),
                PYTHONUNBUFFERED="1")


def _assert_video(path: Path) -> None:
    data = path.read_bytes()
    assert len(data) > 1000 and b"ftyp" in data[:64], len(data)  # an MP4 container


@pytest.fixture(scope="module")
def videos(trained, tmp_path_factory):
    """Both ns-render commands, started together (each interpreter's imports take ~11 s of CPU)."""
    tmp = tmp_path_factory.mktemp("videos")
    pose = [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0]
    path = {
        "render_height": 24, "render_width": 32, "seconds": 1.0, "crop": None,
        "camera_path": [{"camera_to_world": pose, "fov": fov, "aspect": 32 / 24} for fov in (50.0, 60.0, 70.0)],
    }
    camera_path = tmp / "camera_path.json"
    camera_path.write_text(json.dumps(path))
    commands = {
        "interpolate": [str(BIN / "ns-render"), "interpolate", "--load-config", str(trained), "--output-path",
                        str(tmp / "interpolate.mp4"), "--interpolation-steps", "2", "--frame-rate", "4",
                        "--pose-source", "eval"],
        "camera-path": [str(BIN / "ns-render"), "camera-path", "--load-config", str(trained),
                        "--camera-path-filename", str(camera_path), "--output-path", str(tmp / "path.mp4")],
    }
    running = {k: subprocess.Popen(v, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                   env=_env_without_ffmpeg(tmp / k)) for k, v in commands.items()}
    for name, proc in running.items():
        stdout, stderr = proc.communicate(timeout=600)
        assert proc.returncode == 0, (name, stdout[-3000:] + stderr[-3000:])
    return tmp


def test_ns_render_interpolate_without_system_ffmpeg(videos):
    _assert_video(videos / "interpolate.mp4")


def test_ns_render_camera_path_without_system_ffmpeg(videos):
    _assert_video(videos / "path.mp4")
