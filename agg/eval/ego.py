"""The recording vehicle's own pixels: left out of training and of the scores.

A dashcam sees its car's bonnet (or dashboard) at the same pixels in every frame. It moves with the camera, so no
scene fixed in the world can render it from a new viewpoint, and a simulator must not find it baked into the road.
The priors find it (``agg.priors.masks.ego_vehicle_region``) and store it as the bundle's ``ego_mask``
(docs/BUNDLE.md); training weighs those pixels 0 in every loss, and ``agg eval`` scores the other pixels only.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F  # noqa: N812
from torch import Tensor


def scene_pixels(bundle, width: int, height: int) -> Tensor | None:
    """[height, width] bool: the pixels at that size that no part of the bundle's ego mask covers (area
    resampling, so a pixel the mask's edge crosses is left out too); None when the bundle has no ego mask."""
    ego = bundle.ego_mask
    if ego is None:
        return None
    x = torch.as_tensor(np.asarray(ego, np.float32))[None, None]  # [1, 1, H, W]
    if x.shape[-2:] != (height, width):
        x = F.interpolate(x, size=(height, width), mode="area")
    return x[0, 0] <= 0.0


def with_ego_from(target: Tensor, render: Tensor, scene: Tensor | None) -> Tensor:
    """[H, W, 3] ``render`` with the ego vehicle's pixels (``scene`` [H, W] False or 0 there) taken from
    ``target``: what a windowed score (SSIM, LPIPS) or loss compares, so no window reads the render's ego pixels
    and no gradient reaches them. ``render`` itself when ``scene`` is None."""
    if scene is None:
        return render
    return torch.where(scene[..., None] > 0, render, target)
