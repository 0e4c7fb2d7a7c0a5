"""LPIPS for the evaluation metrics, built only from AlexNet weights already on disk.

splatfacto builds torchmetrics' LPIPS in its constructor, which downloads AlexNet through torch.hub: with no
network the model cannot even be built. geer builds it at the first evaluation, from the torch hub cache only,
and otherwise reports LPIPS as missing (said once).
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Optional

import torch

_LOG = logging.getLogger("geer_ns")
_warned = False


def alexnet_weights_path() -> Path:
    """Where torch.hub keeps torchvision's default AlexNet weights."""
    import torchvision

    url = torchvision.models.AlexNet_Weights.DEFAULT.url
    return Path(torch.hub.get_dir()) / "checkpoints" / os.path.basename(url)


def build_lpips_if_cached() -> Optional[torch.nn.Module]:
    """torchmetrics LPIPS (AlexNet, inputs in [0, 1]) when its weights are cached locally, else None."""
    global _warned
    path = alexnet_weights_path()
    if path.is_file():
        from torchmetrics.image.lpip import LearnedPerceptualImagePatchSimilarity

        return LearnedPerceptualImagePatchSimilarity(normalize=True)
    if not _warned:
        _warned = True
        message = f"LPIPS unavailable: AlexNet weights not found at {path} (no download attempted); lpips is omitted"
        _LOG.warning(message)
        from nerfstudio.utils.rich_utils import CONSOLE

        CONSOLE.print(f"[yellow]{message}")
    return None
