"""Losses: the photometric loss (L1 + SSIM at weight 0.2) and the semantic attention loss (paper Eq. 3).

The semantic attention maps come from ``agg.train.semantic.attention_maps``; Eq. 3 routes the L1 error through
``M_bg`` in the Tick phase and through ``M_ag`` in the Tock phase:

    L_sem = lambda_sem * sum_u M(u) |I_render(u) - I_gt(u)|_1 / (sum_u M(u) + delta)

where |.|_1 sums over the colour channels (as written in the paper). The total loss is L_photo + L_sem.
"""

from __future__ import annotations

from kornia.metrics import ssim as kornia_ssim
from torch import Tensor


def _ssim_map(pred: Tensor, gt: Tensor, window: int = 11) -> Tensor:
    """[1, 3, H, W] SSIM map of two [H, W, 3] images in [0, 1] (kornia, window x window Gaussian window)."""
    return kornia_ssim(pred.permute(2, 0, 1)[None], gt.permute(2, 0, 1)[None], window)


def ssim_value(pred: Tensor, gt: Tensor, window: int = 11) -> Tensor:
    """Mean SSIM of two [H, W, 3] images in [0, 1] (kornia, 11x11 Gaussian window)."""
    return _ssim_map(pred, gt, window).mean()


def photometric_loss(pred: Tensor, gt: Tensor, ssim_weight: float = 0.2, weight: Tensor | None = None) -> Tensor:
    """(1 - w) * L1 + w * (1 - SSIM) of [H, W, 3] images (3DGS's form of "L1 plus SSIM at weight w").
    ``weight`` [H, W] >= 0 makes both terms weighted means over the pixels (the SSIM map's, 11x11 window)."""
    if weight is None:
        l1 = (pred - gt).abs().mean()
        if ssim_weight <= 0:
            return l1
        return (1.0 - ssim_weight) * l1 + ssim_weight * (1.0 - ssim_value(pred, gt))
    mass = weight.sum().clamp_min(1e-6)
    l1 = ((pred - gt).abs().mean(-1) * weight).sum() / mass
    if ssim_weight <= 0:
        return l1
    ssim = _ssim_map(pred, gt)[0].mean(0)  # [H, W]
    return (1.0 - ssim_weight) * l1 + ssim_weight * (1.0 - (ssim * weight).sum() / mass)


def semantic_attention_loss(pred: Tensor, gt: Tensor, attention: Tensor, lambda_sem: float = 0.8,
                            delta: float = 1e-6) -> Tensor:
    """Eq. 3: the attention-weighted L1 error. pred, gt [H, W, 3]; attention [H, W] (M_bg or M_ag), >= 0."""
    err = (pred - gt).abs().sum(-1)  # [H, W]
    return lambda_sem * (attention * err).sum() / (attention.sum() + delta)
