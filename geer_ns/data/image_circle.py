"""The image circle of a fisheye lens, found from the images themselves.

Many fisheye captures come without a mask: the lens projects a disc onto the sensor and the corners
(or a whole ring) stay at the sensor's black level. Those pixels must never enter the loss, and features
there must not be matched. The circle is detected from a few images of the same camera:

1. the per-pixel maximum over the images (a pixel the lens reaches is bright in at least one of them);
2. the sensor's black level from the image corners (JPEG and sensors rarely give exact 0: the T265's is 16);
3. the dark region connected to the image border (dark scene content inside the circle is not connected
   to it through dark pixels in every image at once);
4. a circle through that region's inner boundary (RANSAC, then least squares on the inliers), accepted
   only when everything outside it is unlit (not dark content at the edge of a pinhole image).

No border region (a pinhole image, a fisheye cropped inside its circle) gives None: nothing to mask.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Optional, Sequence

import cv2
import numpy as np

# Below this fraction of border-connected dark pixels there is no black border worth masking.
MIN_BORDER_FRACTION = 0.002


@dataclass(frozen=True)
class ImageCircle:
    """A circle in pixel coordinates (pixel centers at integer + 0.5, as nerfstudio's cx/cy)."""

    cx: float
    cy: float
    radius: float

    def mask(self, width: int, height: int, margin: float = 1.0) -> np.ndarray:
        """[H, W] bool: pixel centers at least `margin` px inside the circle (the rim pixel is blended)."""
        u = np.arange(width) + 0.5
        v = np.arange(height) + 0.5
        r2 = (u[None, :] - self.cx) ** 2 + (v[:, None] - self.cy) ** 2
        return r2 <= (self.radius - margin) ** 2


def _gray(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim == 3:
        image = image.max(axis=2)
    if image.dtype != np.uint8:
        scale = 255.0 if np.issubdtype(image.dtype, np.floating) and image.max() <= 1.0 else 1.0
        image = np.clip(image.astype(np.float64) * scale, 0, 255).astype(np.uint8)
    return image


def _black_level(peak: np.ndarray) -> float:
    """Brightness of the darkest corner patch: the sensor's black level where the corners are outside."""
    h, w = peak.shape
    s = max(2, min(h, w) // 40)
    corners = [peak[:s, :s], peak[:s, -s:], peak[-s:, :s], peak[-s:, -s:]]
    return float(min(np.median(c) for c in corners))


def _fit_circle(u: np.ndarray, v: np.ndarray) -> tuple[float, float, float]:
    """Algebraic least-squares circle: u² + v² + a u + b v + c = 0."""
    a = np.stack([u, v, np.ones_like(u)], 1)
    rhs = -(u**2 + v**2)
    (p, q, c), *_ = np.linalg.lstsq(a, rhs, rcond=None)
    cx, cy = -p / 2, -q / 2
    return float(cx), float(cy), float(np.sqrt(max(cx**2 + cy**2 - c, 0.0)))


def detect_image_circle(images: Iterable[np.ndarray], tolerance: float = 10.0) -> Optional[ImageCircle]:
    """The lens's image circle from images of one camera (uint8 or float in [0, 1], gray or color).

    Returns None when the images have no dark border (nothing to mask). `tolerance` is how far above the
    black level (in 8-bit units) a pixel still counts as unlit.
    """
    peak = None
    for image in images:
        gray = _gray(image)
        if peak is not None and gray.shape != peak.shape:
            raise ValueError(f"image circle: images of one camera differ in size ({gray.shape} vs {peak.shape})")
        peak = gray if peak is None else np.maximum(peak, gray)
    if peak is None:
        raise ValueError("image circle: no images given")
    h, w = peak.shape
    dark = (peak <= _black_level(peak) + tolerance).astype(np.uint8)
    dark = cv2.morphologyEx(dark, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
    # Keep only dark components that touch the image border.
    count, labels = cv2.connectedComponents(dark, connectivity=4)
    edge_labels = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
    edge_labels = edge_labels[edge_labels != 0]
    outside = np.isin(labels, edge_labels)
    if outside.mean() < MIN_BORDER_FRACTION:
        return None
    # Inner boundary: lit pixels 4-adjacent to the outside region, away from the image edge.
    grown = cv2.dilate(outside.astype(np.uint8), np.array([[0, 1, 0], [1, 1, 1], [0, 1, 0]], np.uint8)).astype(bool)
    rim = grown & ~outside
    rim[:1] = rim[-1:] = False
    rim[:, :1] = rim[:, -1:] = False
    v, u = np.nonzero(rim)
    if len(u) < 16:
        return None
    # Boundary between a lit pixel center and an unlit one: half a pixel outwards of the lit center.
    u = u + 0.5
    v = v + 0.5
    fit = _ransac_circle(u, v, w, h)
    if fit is None:
        return None
    cx, cy, r = fit
    if not (r > 0.2 * min(h, w)) or not (0 <= cx <= w and 0 <= cy <= h):
        return None
    circle = ImageCircle(cx, cy, r + 0.5)
    # A lens border leaves the circle's whole complement unlit (dark scene content inside the circle may
    # leak into the border region, so only this direction is checked); a circle fitted to dark content at
    # a pinhole image's edge leaves lit pixels outside it.
    predicted = ~circle.mask(w, h, margin=-2.0)
    if predicted.mean() < MIN_BORDER_FRACTION or (outside & predicted).sum() < 0.85 * predicted.sum():
        return None
    return circle


def _ransac_circle(u: np.ndarray, v: np.ndarray, width: int, height: int, inlier_px: float = 2.5,
                   iterations: int = 300):
    """The circle through most rim points: dark scene content joined to the border adds rim points off it,
    glare at a soft lens edge removes some from it. Accepted when its inliers cover a quarter of its arc
    inside the image."""
    rng = np.random.default_rng(0)  # deterministic: the same images give the same mask
    best = None
    for _ in range(iterations):
        i = rng.choice(len(u), 3, replace=False)
        cx, cy, r = _fit_circle(u[i], v[i])
        inliers = np.abs(np.hypot(u - cx, v - cy) - r) <= inlier_px
        if best is None or inliers.sum() > best.sum():
            best = inliers
    cx, cy, r = _fit_circle(u[best], v[best])
    angles = np.linspace(0, 2 * np.pi, 720, endpoint=False)
    au, av = cx + r * np.cos(angles), cy + r * np.sin(angles)
    arc = 2 * np.pi * r * np.mean((au > 1) & (au < width - 1) & (av > 1) & (av < height - 1))
    return (cx, cy, r) if best.sum() >= 0.25 * arc else None


def detect_image_circle_from_files(paths: Sequence[Path], max_images: int = 12) -> Optional[ImageCircle]:
    """`detect_image_circle` over up to `max_images` files spread evenly over `paths`."""
    if not paths:
        raise ValueError("image circle: no image files given")
    picks = np.unique(np.linspace(0, len(paths) - 1, min(max_images, len(paths))).round().astype(int))

    def read(path: Path) -> np.ndarray:
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise ValueError(f"{path}: not a readable image (while detecting the fisheye image circle)")
        return image

    return detect_image_circle(read(Path(paths[i])) for i in picks)
