"""Semantic attention maps M_bg and M_ag from the PCA-reduced features F_low (paper Sec. 3.2).

    M_i(u) = sum_{c in C_i} (F_low^c(u) - min F_low) / (max F_low - min F_low),   i in {bg, ag}

with **global latent normalisation**: one min and one max over every spatial position and channel (here over the
whole clip, so a frame without agents keeps a low M_ag instead of stretching its noise to [0, 1] — the "feature
scale trap" of per-channel min-max). ``norm="percentile"`` uses the clip-wide 1st / 99th percentiles instead of
the extrema and clips to [0, 1]: the builtin (non-DINO) features have a few extreme values that squash the
contrast under min / max (docs/PRIORS.md). The maps are bilinearly resized to the training resolution.

**The maps must separate the agents** (``semantic_gate``). Eq. 3 routes the error to the background in a Tick and
to the agents in a Tock only as far as M_bg and M_ag differ between agent and background pixels. The contrast of
M_ag is its mean on the priors' dynamic masks over its mean elsewhere, that of M_bg the other way round. The suite's
synthetic features give 8.5-26 and 5.1-7.3; the builtin descriptors on the dashcam sample give 1.16 and 1.08, where
Eq. 3 is a near-uniform extra L1 that measured to cost the clip's held-out PSNR (docs/TRAINING.md "The semantic loss
needs maps that separate the agents"). Below ``min_contrast`` on either map, or where no mask pixels measure it,
the loss is off for the scene.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F  # noqa: N812
from torch import Tensor


def attention_maps(features: np.ndarray, c_bg: list[int], c_ag: list[int], height: int, width: int,
                   norm: str = "global") -> tuple[Tensor, Tensor]:
    """(M_bg, M_ag), each [T, height, width] float32 >= 0, from features [T, h, w, C]."""
    f = torch.as_tensor(np.asarray(features, np.float32))  # [T, h, w, C]
    if norm == "global":
        lo, hi = float(f.min()), float(f.max())
    elif norm == "percentile":
        sample = f.reshape(-1)[:: max(1, f.numel() // 2_000_000)]
        lo, hi = (float(v) for v in torch.quantile(sample, torch.tensor([0.01, 0.99])))
    else:
        raise ValueError(f"norm must be 'global' or 'percentile', got {norm!r}")
    f = (f - lo) / max(hi - lo, 1e-12)
    if norm == "percentile":
        f = f.clamp(0.0, 1.0)
    maps = []
    for chans in (c_bg, c_ag):
        if len(chans) == 0:
            m = torch.zeros(f.shape[:3])
        else:
            m = f[..., list(chans)].sum(-1)  # [T, h, w]
        m = F.interpolate(m[:, None], size=(height, width), mode="bilinear", align_corners=False)[:, 0]
        maps.append(m.clamp_min(0.0).contiguous())
    return maps[0], maps[1]


def attention_contrast(m: Tensor, masks: Tensor) -> float:
    """Mean of a map [T, H, W] on the pixels of ``masks`` [T, H, W] bool over its mean elsewhere (how well the map
    separates them); inf where only the masks carry weight, nan where either side is empty or the map is 0."""
    inside, outside = m[masks], m[~masks]
    if inside.numel() == 0 or outside.numel() == 0:
        return float("nan")
    num, den = float(inside.mean()), float(outside.mean())
    if den == 0:
        return float("inf") if num > 0 else float("nan")
    return num / den


def semantic_gate(m_bg: Tensor, m_ag: Tensor, masks: Tensor | None, min_contrast: float | None) -> dict:
    """Whether Eq. 3 trains this scene: {"active", "contrast_ag", "contrast_bg", "reason"}.

    m_bg, m_ag [T, H, W]; masks [T, H, W] bool, the priors' dynamic masks at the same size (None: none). contrast_ag
    is M_ag on the masks over M_ag elsewhere, contrast_bg M_bg off the masks over M_bg on them. The loss is off when
    either is below ``min_contrast``, or cannot be measured (no masks, or masks that are empty or cover every
    pixel: no agent to route the error to, and nothing that shows the maps would); always on when ``min_contrast``
    is None (the paper's rule)."""
    c_ag = c_bg = float("nan")
    if masks is not None:
        masks = masks.to(m_ag.device)
        c_ag, c_bg = attention_contrast(m_ag, masks), attention_contrast(m_bg, ~masks)
    out = {"active": True, "contrast_ag": round(c_ag, 3) if math.isfinite(c_ag) else None,  # JSON: inf -> None
           "contrast_bg": round(c_bg, 3) if math.isfinite(c_bg) else None, "reason": None}
    if min_contrast is None:
        return out
    if math.isnan(c_ag) or math.isnan(c_bg):
        if masks is None or not bool(masks.any()):
            reason = "no dynamic-mask pixels to measure the attention maps' contrast on"
        elif bool(masks.all()):
            reason = "the dynamic masks cover every pixel"
        else:
            reason = "an attention map is 0 on every pixel"
        out.update(active=False, reason=reason)
        return out
    low = [f"{name} {c:.2f}" for name, c in (("M_ag", c_ag), ("M_bg", c_bg)) if c < min_contrast]
    if low:
        out.update(active=False, reason=f"the attention maps do not separate the priors' dynamic masks "
                                        f"(contrast {', '.join(low)} < {min_contrast:g})")
    return out
