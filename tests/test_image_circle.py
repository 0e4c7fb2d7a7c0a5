"""Fisheye image-circle detection against circles known by construction and by calibration."""

import math

import numpy as np
import pytest

from geer_ns.data.image_circle import ImageCircle, detect_image_circle, detect_image_circle_from_files
from conftest import shared_data


def _fisheye_like(h, w, circle, black=16, n=4, seed=0):
    """Textured disc on a noisy black level, the disc drawn from `circle` by an independent rasteriser."""
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:h, 0:w] + 0.5
    inside = (u - circle[0]) ** 2 + (v - circle[1]) ** 2 <= circle[2] ** 2
    images = []
    for _ in range(n):
        img = rng.integers(40, 256, (h, w, 3)).astype(np.uint8)
        img[~inside] = black + rng.integers(0, 4, ((~inside).sum(), 3))
        images.append(img)
    return images


@pytest.mark.parametrize("circle", [(205.3, 148.7, 140.2), (200.0, 150.0, 210.0)])  # whole disc; corners only
def test_recovers_a_known_circle(circle):
    found = detect_image_circle(_fisheye_like(300, 400, circle))
    assert found is not None
    assert math.hypot(found.cx - circle[0], found.cy - circle[1]) < 0.5
    assert abs(found.radius - circle[2]) < 0.7


def test_no_border_means_no_circle():
    rng = np.random.default_rng(1)
    assert detect_image_circle([rng.integers(0, 256, (120, 160, 3)).astype(np.uint8)]) is None


def test_mask_keeps_pixel_centres_inside():
    mask = ImageCircle(5.0, 5.0, 3.0).mask(10, 10, margin=0.0)
    assert mask[4, 4] and mask[5, 7] and not mask[0, 0] and not mask[5, 8]  # (7.5-5)=2.5 in, (8.5-5)=3.5 out
    assert mask.sum() == sum((i + 0.5 - 5) ** 2 + (j + 0.5 - 5) ** 2 <= 9 for i in range(10) for j in range(10))


def test_dev_room_fisheye_circle_matches_its_lens():
    """180° equidistant lens, f = 384/π: the image circle has radius f·π/2 = 192 px about (192, 192)."""
    root = shared_data("fisheye_room_dev")
    found = detect_image_circle_from_files(sorted((root / "images_fisheye").glob("*.jpg")))
    assert found is not None
    assert math.hypot(found.cx - 192.0, found.cy - 192.0) < 1.0
    assert abs(found.radius - 192.0) < 2.0
    assert detect_image_circle_from_files(sorted((root / "images_pinhole").glob("*.jpg"))) is None


@pytest.mark.parametrize("cam,principal", [("cam001", (424.355, 393.742)), ("cam002", (417.246, 400.402))])
def test_t265_circle_is_centred_near_its_calibrated_principal_point(cam, principal):
    files = sorted(shared_data("t265_fisheye").glob(f"{cam}_*.jpg"))
    found = detect_image_circle_from_files(files)
    assert found is not None
    assert math.hypot(found.cx - principal[0], found.cy - principal[1]) < 12.0
    assert 370 < found.radius < 420  # ~163° field of view at f ≈ 285 px (equidistant: 285·1.42 ≈ 405)


def test_unreadable_file_is_named(tmp_path):
    bad = tmp_path / "broken.jpg"
    bad.write_bytes(b"not an image")
    with pytest.raises(ValueError, match="broken.jpg"):
        detect_image_circle_from_files([bad])
