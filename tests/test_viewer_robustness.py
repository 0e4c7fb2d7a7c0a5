"""The viewer's render thread survives cameras geer cannot render; two-keyframe camera paths work."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from nerfstudio.cameras.cameras import CameraType
from nerfstudio.viewer.utils import CameraState, get_camera

from conftest import start_in_thread
from test_nerfstudio_model import make_model

C2W = torch.eye(4)[:3]


def _viewer_camera(fov: float, c2w: torch.Tensor = C2W, height: int = 24, width: int = 32,
                   camera_type=CameraType.PERSPECTIVE):
    """What nerfstudio's viewer builds from its camera state (viewer.utils.get_camera)."""
    state = CameraState(fov=fov, aspect=width / height, c2w=c2w, camera_type=camera_type)
    return get_camera(state, height, width)


def _in_thread(fn):
    """Run fn in a non-main thread, like nerfstudio's RenderStateMachine; returns (result, error)."""
    thread, box = start_in_thread(fn)
    thread.join()
    return box.get("result"), box.get("error")


def _bad_cameras():
    nan_pose = C2W.clone()
    nan_pose[0, 3] = float("nan")
    empty = _viewer_camera(math.radians(60))
    empty.width = torch.zeros_like(empty.width)
    return {
        "fx = inf (zero field of view)": _viewer_camera(0.0),  # the render panel's initial preview_fov
        "pinhole field of view of 180.0 degrees": _viewer_camera(math.pi),
        "pose has NaN/Inf": _viewer_camera(math.radians(60), nan_pose),
        "image size 0x24 is empty": empty,
    }


def test_bad_cameras_give_the_last_good_frame_and_one_line_each(capsys):
    model = make_model().eval()
    good, error = _in_thread(lambda: model.get_outputs_for_camera(_viewer_camera(math.radians(60))))
    assert error is None and good["rgb"].shape == (24, 32, 3)
    capsys.readouterr()
    for problem, camera in _bad_cameras().items():
        for _ in range(2):  # logged once, however often the viewer asks
            out, error = _in_thread(lambda: model.get_outputs_for_camera(camera))
            assert error is None, (problem, error)
            assert out["rgb"] is good["rgb"]
        printed = capsys.readouterr().out
        assert printed.count("cannot render this camera") == 1 and problem in printed.replace("\n", ""), printed
    after, error = _in_thread(lambda: model.get_outputs_for_camera(_viewer_camera(math.radians(50))))
    assert error is None and after["rgb"] is not good["rgb"]  # good cameras render again


def test_bad_camera_before_any_good_one_gives_the_background():
    model = make_model(background_color="white").eval()
    out, error = _in_thread(lambda: model.get_outputs_for_camera(_viewer_camera(0.0)))
    assert error is None
    assert out["rgb"].shape == (24, 32, 3) and bool((out["rgb"] == 1.0).all())


def test_outside_the_viewer_a_bad_camera_is_an_error():
    model = make_model().eval()
    with pytest.raises(ValueError, match=r"cannot render this camera: fx = inf \(zero field of view\)"):
        model.get_outputs_for_camera(_viewer_camera(0.0))


def test_render_errors_in_the_viewer_thread_do_not_kill_it(monkeypatch):
    model = make_model().eval()

    def broken(camera):
        raise RuntimeError("out of memory")

    monkeypatch.setattr(model, "get_outputs", broken)
    out, error = _in_thread(lambda: model.get_outputs_for_camera(_viewer_camera(math.radians(60))))
    assert error is None and out["rgb"].shape == (24, 32, 3)
    with pytest.raises(RuntimeError, match="out of memory"):  # the main thread (ns-render, ns-eval) sees it
        model.get_outputs_for_camera(_viewer_camera(math.radians(60)))


def test_two_keyframe_camera_path_spline_is_the_slerp():
    """nerfstudio's render panel call (splines 0.3.0 raises for two keyframes without geer's fix)."""
    import splines.quaternion

    from geer_ns import compat

    compat.install()  # as building any geer model does (ns-viewer, ns-render)

    angle = 1.2
    keyframes = [np.array([0.0, 0.0, 0.0, 1.0]), np.array([0.0, 0.0, math.sin(angle / 2), math.cos(angle / 2)])]
    spline = splines.quaternion.KochanekBartels(
        [splines.quaternion.UnitQuaternion.from_unit_xyzw(q) for q in keyframes],
        tcb=(0.3, 0.0, 0.0), endconditions="natural",
    )
    for t in (0.0, 0.3, 0.5, 1.0):
        q = spline.evaluate(t)
        assert q.scalar == pytest.approx(math.cos(t * angle / 2), abs=1e-12)
        assert q.vector[2] == pytest.approx(math.sin(t * angle / 2), abs=1e-12)
    three = splines.quaternion.KochanekBartels(  # more keyframes: splines' own code, unchanged
        [splines.quaternion.UnitQuaternion.from_unit_xyzw(q) for q in keyframes + keyframes[:1]],
        tcb=(0.3, 0.0, 0.0), endconditions="natural",
    )
    assert three.evaluate(2.0).scalar == pytest.approx(1.0)
