"""Semantic attention maps M_bg and M_ag from the PCA-reduced features F_low (paper Sec. 3.2).

    M_i(u) = sum_{c in C_i} (F_low^c(u) - min F_low) / (max F_low - min F_low),   i in {bg, ag}

with **global latent normalisation**: one min and one max over every spatial position and channel (here over the
whole clip, so a frame without agents keeps a low M_ag instead of stretching its noise to [0, 1] — the "feature
scale trap" of per-channel min-max). ``norm="percentile"`` uses the clip-wide 1st / 99th percentiles instead of
the extrema and clips to [0, 1]: the builtin (non-DINO) features have a few extreme values that squash the
contrast under min / max (docs/PRIORS.md). The maps are bilinearly resized to the training resolution.
"""

from __future__ import annotations

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


def attention_contrast(m_ag: Tensor, agent_masks: Tensor) -> float:
    """Mean of M_ag on agent pixels over its mean elsewhere (how well the map separates agents); nan if undefined."""
    inside, outside = m_ag[agent_masks], m_ag[~agent_masks]
    if inside.numel() == 0 or outside.numel() == 0 or float(outside.mean()) == 0:
        return float("nan")
    return float(inside.mean() / outside.mean())
