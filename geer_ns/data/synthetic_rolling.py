"""Rolling-shutter captures of the synthetic room: the ground truth for geer's shutter model.

Each frame of a fast handheld capture (the room's camera loop, every frame turning `turn_deg` about a random axis
and moving `move` metres along a random direction during its readout) is rendered by the analytic ray caster
(synthetic_room.render_room_rays) with every sensor row at its own pose: the pose at the row's readout fraction,
rotation by scipy's Slerp between the start and end poses, centre linearly (independent of geer_ns.cameras),
each pixel the box-filtered mean of sub-pixel rays taken at its row's time. The matching global-shutter frame is
taken at the mid-readout pose. Three nerfstudio files share the held-out views (global-shutter frames at the
mid-readout poses: the static scene every run is scored on):

    transforms.json            train: the rolling-shutter frames, rolling_shutter + transform_matrix_end
    transforms_as_global.json  train: the same frames, described as global-shutter images at the mid pose
    transforms_global.json     train: the global-shutter frames of the same path

CLI: ``python -m geer_ns.data.synthetic_rolling OUT_DIR [--n-views N --size S --turn-deg D --move M --seed K]``
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import List

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from geer_ns.data.ply import write_ply_points
from geer_ns.data.synthetic_cameras import fisheye_intrinsics, fisheye_pixel_dirs
from geer_ns.data.synthetic_room import (
    SUPERSAMPLE,
    _render_view,
    _seed_points,
    _splits,
    _to_u8,
    _write_png,
    camera_poses,
    opencv_to_nerfstudio_c2w,
    render_room_rays,
)

READOUT = "top-to-bottom"


def readout_poses(mid: np.ndarray, turn_deg: float, move: float, rng: np.random.Generator):
    """(start, end) OpenCV camera-to-world 4x4 of a frame whose mid-readout pose is `mid`: a turn of turn_deg about
    a random axis and a move of `move` along a random direction, centred on mid."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    step = rng.normal(size=3)
    step *= move / np.linalg.norm(step)
    half = Rotation.from_rotvec(axis * np.deg2rad(turn_deg) / 2).as_matrix()
    start, end = mid.copy(), mid.copy()
    start[:3, :3], end[:3, :3] = half.T @ mid[:3, :3], half @ mid[:3, :3]
    start[:3, 3], end[:3, 3] = mid[:3, 3] - step / 2, mid[:3, 3] + step / 2
    return start, end


def rolling_image(start: np.ndarray, end: np.ndarray, dirs_cam: np.ndarray, s: int) -> np.ndarray:
    """[h, w, 3] image whose pixel row i is read at fraction i / (h - 1) of the readout from start to end (sub-pixel
    rays dirs_cam [h*s, w*s, 3], box-averaged)."""
    hs, ws, _ = dirs_cam.shape
    h = hs // s
    times = (np.arange(hs) // s) / max(h - 1, 1)  # each sub-pixel row at its pixel row's time
    rot = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([start[:3, :3], end[:3, :3]])))(times).as_matrix()
    centre = (1 - times)[:, None] * start[:3, 3] + times[:, None] * end[:3, 3]
    d = np.einsum("rij,rwj->rwi", rot, dirs_cam).reshape(-1, 3)
    o = np.repeat(centre, ws, axis=0)
    rgb, _, _ = render_room_rays(o, d)
    return rgb.reshape(h, s, ws // s, s, 3).mean(axis=(1, 3))


def write_rolling_room(root: Path, n_views: int = 24, size: int = 96, turn_deg: float = 8.0, move: float = 0.05,
                       seed: int = 0) -> None:
    """Write the capture (module docstring) to `root` (created; must not exist)."""
    root.mkdir(parents=True)
    rng = np.random.default_rng(seed + 7)
    s = SUPERSAMPLE
    dirs, _ = fisheye_pixel_dirs(size * s)
    _, mask = fisheye_pixel_dirs(size)
    (root / "masks").mkdir()
    _write_png(root / "masks/fisheye_mask.png", (mask * 255).astype(np.uint8))
    (root / "images_rolling").mkdir()
    (root / "images_global").mkdir()
    held = set(_splits(n_views, list(range(n_views)))["test_filenames"])
    rolling, as_global, still, test = [], [], [], []
    mids = camera_poses(n_views, seed)
    write_ply_points(root / "points3d.ply", *_seed_points(mids, 4000, rng))  # the room's seed cloud, as synthetic_room's
    for i, mid in enumerate(mids):
        start, end = readout_poses(mid, turn_deg, move, rng)
        pose = lambda c2w: np.round(opencv_to_nerfstudio_c2w(c2w), 12).tolist()  # noqa: E731
        name = f"frame_{i:05d}.png"
        still_img = _render_view(mid, dirs, s)
        still_img[~mask] = 0.0
        _write_png(root / "images_global" / name, _to_u8(still_img))
        frame_still = {"file_path": f"images_global/{name}", "transform_matrix": pose(mid),
                       "mask_path": "masks/fisheye_mask.png"}
        if i in held:
            test.append(frame_still)
            continue
        img = rolling_image(start, end, dirs, s)
        img[~mask] = 0.0
        _write_png(root / "images_rolling" / name, _to_u8(img))
        rolling.append({"file_path": f"images_rolling/{name}", "transform_matrix": pose(start),
                        "transform_matrix_end": pose(end), "rolling_shutter": {"readout": READOUT},
                        "mask_path": "masks/fisheye_mask.png"})
        as_global.append({"file_path": f"images_rolling/{name}", "transform_matrix": pose(mid),
                          "mask_path": "masks/fisheye_mask.png"})
        still.append(frame_still)
    intrinsics = {**fisheye_intrinsics(size), "k1": 0.0, "k2": 0.0, "k3": 0.0, "k4": 0.0,
                  "fisheye_crop_radius": size / 2.0}
    for file, train in (("transforms.json", rolling), ("transforms_as_global.json", as_global),
                        ("transforms_global.json", still)):
        names = [f["file_path"] for f in train]
        held_names = [f["file_path"] for f in test]
        meta = {"camera_model": "OPENCV_FISHEYE", **intrinsics, "orientation_override": "none",
                "ply_file_path": "points3d.ply",
                "train_filenames": names, "val_filenames": held_names, "test_filenames": held_names,
                "frames": train + test}
        (root / file).write_text(json.dumps(meta, indent=2) + "\n")
    (root / "capture.json").write_text(json.dumps({"generator": "geer_ns.data.synthetic_rolling", "n_views": n_views,
                                                   "size": size, "turn_deg": turn_deg, "move": move, "seed": seed,
                                                   "readout": READOUT}, indent=2) + "\n")


def main(argv: List[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("out_dir", type=Path)
    p.add_argument("--n-views", type=int, default=24)
    p.add_argument("--size", type=int, default=96)
    p.add_argument("--turn-deg", type=float, default=8.0, help="rotation during one frame's readout (degrees)")
    p.add_argument("--move", type=float, default=0.05, help="camera travel during one frame's readout (metres)")
    p.add_argument("--seed", type=int, default=0)
    a = p.parse_args(argv)
    write_rolling_room(a.out_dir, a.n_views, a.size, a.turn_deg, a.move, a.seed)
    print(f"wrote {a.out_dir}")


if __name__ == "__main__":
    main()
