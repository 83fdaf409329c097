"""Plain-PyTorch reference compositor: the ground truth that the native kernels are tested against.

Dense over (pixel, Gaussian) pairs, chunked over pixels to bound memory. Slow; use it for tests, tiny images,
and as the last-resort backend. It applies exactly the rules of csrc/rasterize.cpp:

- pairs are composited front to back in order of increasing camera depth (stable: ties keep input order);
- a pair is skipped iff sigma < 0 or sigma > log(255 * opacity), i.e. when alpha would be below 1/255;
- alpha = min(0.99, opacity * exp(-sigma));
- a pixel stops at the first pair whose inclusion would take its transmittance below 1e-4 (that pair is excluded).
"""

from __future__ import annotations

import torch
from torch import Tensor

from agg.render.projection import ALPHA_MAX, T_MIN, opacity_threshold


def composite_torch(
    means2d: Tensor,  # [N, 2] px
    conics: Tensor,  # [N, 3]
    colors: Tensor,  # [N, C]
    opacities: Tensor,  # [N]
    depths: Tensor,  # [N] sort key (camera z)
    visible: Tensor,  # [N] bool
    width: int,
    height: int,
    max_pairs: int = 1 << 22,
) -> tuple[Tensor, Tensor]:
    """Returns (accumulated colour [H, W, C] = sum_i T_i alpha_i c_i, alpha [H, W] = 1 - T_final)."""
    C = colors.shape[-1]
    idx = torch.nonzero(visible, as_tuple=True)[0]
    order = idx[torch.argsort(depths.detach()[idx], stable=True)]  # [M] front to back
    if order.numel() == 0 or width * height == 0:
        # Keep every input in the graph so that backward gives (zero) gradients, like the native backend.
        zero = 0.0 * (colors.sum() + means2d.sum() + conics.sum() + opacities.sum())
        return colors.new_zeros(height, width, C) + zero, colors.new_zeros(height, width) + zero
    m2 = means2d[order]  # [M, 2]
    con = conics[order]  # [M, 3]
    col = colors[order]  # [M, C]
    opa = opacities[order]  # [M]
    thr = opacity_threshold(opa)  # [M]

    ys, xs = torch.meshgrid(
        torch.arange(height, dtype=means2d.dtype, device=means2d.device),
        torch.arange(width, dtype=means2d.dtype, device=means2d.device),
        indexing="ij",
    )
    pix = torch.stack([xs.reshape(-1), ys.reshape(-1)], -1)  # [P, 2]
    chunk = max(1, max_pairs // order.numel())
    accums, alphas = [], []
    for start in range(0, pix.shape[0], chunk):
        p = pix[start : start + chunk]  # [p, 2]
        d = m2.unsqueeze(0) - p.unsqueeze(1)  # [p, M, 2]
        dx, dy = d[..., 0], d[..., 1]
        # Same expression and order as sigma_of() in csrc/rasterize.cpp, so both skip the same pairs.
        sigma = 0.5 * con[:, 0] * dx * dx + 0.5 * con[:, 2] * dy * dy + con[:, 1] * dy * dx  # [p, M]
        keep = (sigma >= 0) & (sigma <= thr)  # [p, M]
        alpha = torch.clamp(opa * torch.exp(-sigma), max=ALPHA_MAX)
        alpha = torch.where(keep, alpha, torch.zeros_like(alpha))
        with torch.no_grad():
            # A pixel terminates at the first pair whose inclusion takes T below T_MIN.
            t_incl = torch.cumprod(1.0 - alpha, dim=1)  # [p, M]
            dead = torch.cumsum((t_incl < T_MIN).to(torch.int32), dim=1) > 0
        alpha = torch.where(dead, torch.zeros_like(alpha), alpha)
        one_minus = 1.0 - alpha
        T_excl = torch.cumprod(torch.cat([torch.ones_like(one_minus[:, :1]), one_minus[:, :-1]], 1), 1)
        w = alpha * T_excl  # [p, M]
        accums.append(w @ col)  # [p, C]
        alphas.append(1.0 - torch.prod(one_minus, dim=1))  # [p]
    accum = torch.cat(accums, 0).reshape(height, width, C)
    alpha_img = torch.cat(alphas, 0).reshape(height, width)
    return accum, alpha_img
