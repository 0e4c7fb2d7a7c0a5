"""Accuracy of recovered poses against known ones, up to the similarity SfM cannot recover.

``python -m geer_ns.process_data.evaluate RECOVERED/transforms.json TRUE/transforms.json`` prints the mean
rotation error, the mean position error relative to the extent of the true camera path (after the similarity
of :func:`align_poses`, and for comparison after Umeyama on the centers), and the focal lengths.
Frames are paired by image file name.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path
from typing import Dict, Sequence, Tuple

import numpy as np
import torch


def umeyama(src: np.ndarray, dst: np.ndarray) -> Tuple[float, np.ndarray, np.ndarray]:
    """Similarity (s, R, t) minimizing sum |s R src_i + t - dst_i|^2 (Umeyama 1991)."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    cov = (dst - mu_d).T @ (src - mu_s) / len(src)
    u, d, vt = np.linalg.svd(cov)
    e = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        e[2, 2] = -1
    r = u @ e @ vt
    s = float(np.trace(np.diag(d) @ e) / ((src - mu_s) ** 2).sum(1).mean())
    return s, r, mu_d - s * r @ mu_s


def align_poses(estimated: Sequence[np.ndarray], truth: Sequence[np.ndarray]) -> Tuple[float, np.ndarray, np.ndarray]:
    """Similarity (s, R, t) from estimated to true camera-to-world poses: R is the rotation closest to the
    mean of R_true R_est^T (chordal mean), s and t the least-squares fit of the camera centers given R.

    Why not Umeyama on the centers alone: a camera path that is nearly planar (a walk at head height) fixes
    the tilt of that plane poorly, so center noise of a few millimeters tilts the whole alignment by tenths
    of a degree and shows up as rotation error of every camera (measured: 0.43 vs 0.17 deg on the dev room).
    """
    from geer_ns.refinement.refined_frame import fit_similarity

    fit = fit_similarity(torch.from_numpy(np.stack([e[:3, :4] for e in estimated]).astype(np.float64)),
                         torch.from_numpy(np.stack([t[:3, :4] for t in truth]).astype(np.float64)), guard_scale=False)
    return fit.scale, fit.rotation.numpy(), fit.translation.numpy()


def pose_errors(estimated: Dict[str, np.ndarray], truth: Dict[str, np.ndarray],
                alignment: str = "poses") -> Tuple[float, float, float]:
    """(mean rotation error in degrees, mean position error / path extent, max rotation error) over the keys of
    ``estimated`` (4x4 camera-to-world, the same camera axes in both; the worlds may differ by a similarity).
    ``alignment``: "poses" (:func:`align_poses`) or "centers" (Umeyama on the camera centers)."""
    keys = sorted(estimated)
    est = [estimated[k] for k in keys]
    ref = [truth[k] for k in keys]
    c_est = np.array([e[:3, 3] for e in est])
    c_ref = np.array([t[:3, 3] for t in ref])
    s, r, t = align_poses(est, ref) if alignment == "poses" else umeyama(c_est, c_ref)
    pos = np.linalg.norm((s * (r @ c_est.T)).T + t - c_ref, axis=1)
    extent = float(np.linalg.norm(c_ref.max(0) - c_ref.min(0)))
    rot = []
    for e, t_ in zip(est, ref):
        cos = (np.trace((r @ e[:3, :3]).T @ t_[:3, :3]) - 1) / 2
        rot.append(math.degrees(math.acos(min(1.0, max(-1.0, cos)))))
    return float(np.mean(rot)), float(pos.mean() / extent), float(np.max(rot))


def _frames(path: Path) -> Dict[str, np.ndarray]:
    meta = json.loads(path.read_text())
    return {Path(f["file_path"]).name: np.array(f["transform_matrix"], dtype=np.float64) for f in meta["frames"]}


def main(argv=None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 2:
        raise SystemExit("usage: python -m geer_ns.process_data.evaluate RECOVERED.json TRUE.json")
    rec_path, true_path = Path(argv[0]), Path(argv[1])
    rec, ref = _frames(rec_path), _frames(true_path)
    missing = sorted(set(ref) - set(rec))
    rot, pos, rot_max = pose_errors(rec, ref)
    rot_c, pos_c, rot_max_c = pose_errors(rec, ref, alignment="centers")
    meta_r, meta_t = json.loads(rec_path.read_text()), json.loads(true_path.read_text())
    print(f"frames: {len(rec)} recovered of {len(ref)} ({len(missing)} missing: {missing[:5]})")
    print(f"rotation error: mean {rot:.3f} deg, max {rot_max:.3f} deg")
    print(f"position error: mean {100 * pos:.3f} % of the camera path's extent")
    print(f"(Umeyama on the centers only: rotation mean {rot_c:.3f} deg, max {rot_max_c:.3f} deg, position "
          f"{100 * pos_c:.3f} %)")
    for key in ("fl_x", "fl_y"):
        if key in meta_r and key in meta_t:
            err = 100 * (meta_r[key] - meta_t[key]) / meta_t[key]
            print(f"{key}: {meta_r[key]:.3f} px (true {meta_t[key]:.3f}, {err:+.3f} %)")


if __name__ == "__main__":
    main()
