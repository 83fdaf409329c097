"""Fitting: ~2k Gaussians started from noise reach a PSNR floor on an image rendered from known Gaussians."""

from __future__ import annotations

import torch

from agg.render import rasterize
from tests.render_scenes import look_K, random_scene

W, H = 96, 64
STEPS = 300
PSNR_FLOOR_DB = 35.0


def test_fit_from_noise_reaches_psnr_floor():
    torch.manual_seed(0)
    K = look_K(W, H)
    gt = {k: v.detach() for k, v in random_scene(300, 42, channels=3, scale_range=(0.1, 0.5)).items()}
    with torch.no_grad():
        target = rasterize(gt["means"], gt["quats"], gt["scales"], gt["opacities"], gt["colors"], K=K, width=W,
                           height=H, viewmat=gt["viewmat"], background=torch.zeros(3), backend="cpu").color

    g = torch.Generator().manual_seed(1)
    n = 2000
    z = torch.empty(n).uniform_(2.0, 8.0, generator=g)
    xy = (torch.rand(n, 2, generator=g) - 0.5) * 1.2 * z.unsqueeze(-1)
    params = {
        "means": torch.cat([xy, z.unsqueeze(-1)], -1),
        "quats": torch.randn(n, 4, generator=g),
        "log_scales": torch.log(torch.full((n, 3), 0.05)),
        "opacity_logits": torch.zeros(n),
        "color_logits": torch.randn(n, 3, generator=g),
    }
    params = {k: v.requires_grad_(True) for k, v in params.items()}
    opt = torch.optim.Adam(
        [
            {"params": [params["means"]], "lr": 0.01},
            {"params": [params["quats"]], "lr": 0.01},
            {"params": [params["log_scales"]], "lr": 0.02},
            {"params": [params["opacity_logits"]], "lr": 0.05},
            {"params": [params["color_logits"]], "lr": 0.05},
        ]
    )
    first = None
    for _ in range(STEPS):
        out = rasterize(params["means"], params["quats"], params["log_scales"].exp(),
                        torch.sigmoid(params["opacity_logits"]), torch.sigmoid(params["color_logits"]), K=K,
                        width=W, height=H, viewmat=gt["viewmat"], background=torch.zeros(3), backend="cpu")
        loss = (out.color - target).abs().mean()
        first = first if first is not None else loss.item()
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        out = rasterize(params["means"], params["quats"], params["log_scales"].exp(),
                        torch.sigmoid(params["opacity_logits"]), torch.sigmoid(params["color_logits"]), K=K,
                        width=W, height=H, viewmat=gt["viewmat"], background=torch.zeros(3), backend="cpu")
        mse = ((out.color - target) ** 2).mean()
        psnr = -10 * torch.log10(mse)
    assert psnr >= PSNR_FLOOR_DB, f"PSNR {psnr:.2f} dB after {STEPS} steps (loss {first:.4f} -> {loss.item():.4f})"
