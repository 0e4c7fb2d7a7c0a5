"""Make README's picture: a held-out fisheye view, ground truth beside geer's render and the error.

    .venv/bin/python docs/make_figure.py --load-config outputs/synthetic_room/geer/<timestamp>/config.yml

Loads the run as ns-eval does, renders its first eval image (inside the camera's mask) on the camera's own pixel rays and writes
docs/images/fisheye_test_view.png (ground truth | geer | |error| x 4), upscaled with nearest neighbours so
each pixel stays a pixel.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

OUT = Path(__file__).resolve().parent / "images" / "fisheye_test_view.png"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--load-config", type=Path, required=True, help="a trained run's config.yml")
    parser.add_argument("--output", type=Path, default=OUT, help="the PNG to write")
    parser.add_argument("--scale", type=int, default=3, help="nearest-neighbour upscaling factor")
    args = parser.parse_args()

    import cv2
    from nerfstudio.utils.eval_utils import eval_setup

    _, pipeline, _, _ = eval_setup(args.load_config, test_mode="test")
    model = pipeline.model
    camera, batch = pipeline.datamanager.next_eval_image(step=0)
    with torch.no_grad():
        outputs = model.get_outputs_for_camera(camera)
    gt = model.composite_with_background(model.get_gt_img(batch["image"]), outputs["background"])
    valid = outputs["valid_rays"].to(gt.device)
    if "mask" in batch:  # the image circle / mask: what the camera really saw
        valid = valid & batch["mask"].to(gt.device).bool().reshape(valid.shape)
    valid = valid.float()
    pred = outputs["rgb"] * valid
    gt = gt * valid
    error = ((pred - gt).abs() * 4).clamp(0, 1)
    gap = torch.ones(gt.shape[0], 2, 3)
    panel = torch.cat([gt.cpu(), gap, pred.cpu(), gap, error.cpu()], dim=1).clamp(0, 1)
    image = (panel.numpy() * 255).round().astype(np.uint8)
    image = cv2.resize(image, None, fx=args.scale, fy=args.scale, interpolation=cv2.INTER_NEAREST)
    args.output.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(args.output), cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
    print(f"wrote {args.output} ({image.shape[1]}x{image.shape[0]})")


if __name__ == "__main__":
    main()
