"""The T265 sample (/work/shared/data/t265_fisheye, kapture samples/t265, BSD-3-Clause) as a geer-compare capture.

    python benchmarks/t265_capture.py OUT [--camera 1] [--factor 4]

Writes OUT/transforms.json and OUT/images/: one camera's 3 frames (the sample has 3 per camera, two cameras with
different calibrations, and geer-compare takes one camera), downscaled by `factor` (cv2.INTER_AREA; fx, fy, cx, cy
scaled, the OPENCV_FISHEYE k1..k4 are angle-space and stay), grey levels as RGB; frames 1 and 3 train, frame 2 is
the test view. COLMAP's world-to-camera (OpenCV axes) becomes nerfstudio's camera-to-world (OpenGL axes). The
sample has no points: every method starts from its random initialisation. Prints the transforms path.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np

SRC = Path("/work/shared/data/t265_fisheye")


def qvec_to_rotation(qw: float, qx: float, qy: float, qz: float) -> np.ndarray:
    """COLMAP's (Hamilton, w first) unit quaternion as a 3x3 rotation matrix."""
    q = np.array([qw, qx, qy, qz]) / np.linalg.norm([qw, qx, qy, qz])
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("--camera", type=int, default=1)
    parser.add_argument("--factor", type=int, default=4)
    args = parser.parse_args()
    cams = {}
    for line in (SRC / "cameras.txt").read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            tok = line.split()
            cams[int(tok[0])] = (int(tok[2]), int(tok[3]), [float(v) for v in tok[4:]])
    w, h, params = cams[args.camera]
    fx, fy, cx, cy = (v / args.factor for v in params[:4])
    frames = []
    for line in (SRC / "images.txt").read_text().splitlines():
        if not line.strip() or line.startswith("#"):
            continue
        tok = [t.strip() for t in line.split(",")]
        if int(tok[8]) != args.camera:
            continue
        number = int(Path(tok[9]).stem.split("_")[-1])
        rot = qvec_to_rotation(*map(float, tok[1:5]))
        w2c = np.eye(4)
        w2c[:3, :3], w2c[:3, 3] = rot, [float(v) for v in tok[5:8]]
        c2w = np.linalg.inv(w2c) @ np.diag([1.0, -1.0, -1.0, 1.0])  # OpenCV axes to OpenGL axes
        image = cv2.imread(str(SRC / f"cam{args.camera:03d}_frame_{number}.jpg"), cv2.IMREAD_GRAYSCALE)
        small = cv2.resize(image, (w // args.factor, h // args.factor), interpolation=cv2.INTER_AREA)
        name = f"images/frame_{number}.png"
        (args.out / "images").mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(args.out / name), cv2.cvtColor(small, cv2.COLOR_GRAY2BGR))
        frames.append({"file_path": name, "transform_matrix": c2w.tolist()})
    frames.sort(key=lambda f: f["file_path"])
    names = [f["file_path"] for f in frames]
    meta = {"camera_model": "OPENCV_FISHEYE", "fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy, "w": w // args.factor,
            "h": h // args.factor, "k1": params[4], "k2": params[5], "k3": params[6], "k4": params[7],
            "frames": frames, "train_filenames": [names[0], names[2]], "val_filenames": [names[1]],
            "test_filenames": [names[1]]}
    path = args.out / "transforms.json"
    path.write_text(json.dumps(meta, indent=1))
    print(path)


if __name__ == "__main__":
    main()
