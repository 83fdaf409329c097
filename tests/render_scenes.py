"""Small random Gaussian scenes for the renderer tests (seeded)."""

from __future__ import annotations

import math

import torch


def look_K(width: int, height: int, fov_deg: float = 60.0, dtype=torch.float32) -> torch.Tensor:
    f = 0.5 * width / math.tan(math.radians(fov_deg) / 2)
    return torch.tensor([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1]], dtype=dtype)


def random_scene(n: int, seed: int, channels: int = 3, sh_degree: int | None = None, dtype=torch.float32,
                 depth_range=(2.0, 8.0), scale_range=(0.05, 0.4)):
    """Gaussians in front of an identity camera; returns a dict of leaf tensors requiring grad."""
    g = torch.Generator().manual_seed(seed)
    z = torch.empty(n).uniform_(*depth_range, generator=g)
    xy = (torch.rand(n, 2, generator=g) - 0.5) * 1.2 * z.unsqueeze(-1)
    means = torch.cat([xy, z.unsqueeze(-1)], -1)
    quats = torch.randn(n, 4, generator=g)
    scales = torch.empty(n, 3).uniform_(*scale_range, generator=g)
    opac = torch.empty(n).uniform_(0.2, 0.95, generator=g)
    scene = {"means": means, "quats": quats, "scales": scales, "opacities": opac}
    if sh_degree is None:
        scene["colors"] = torch.rand(n, channels, generator=g)
    else:
        sh = torch.randn(n, (sh_degree + 1) ** 2, 3, generator=g) * 0.3
        scene["sh"] = sh
    view = torch.eye(4)
    # A small camera rotation and offset so the view matrix is not trivial.
    ang = 0.05
    view[:3, :3] = torch.tensor([[math.cos(ang), 0, math.sin(ang)], [0, 1, 0], [-math.sin(ang), 0, math.cos(ang)]])
    view[:3, 3] = torch.tensor([0.1, -0.05, 0.2])
    scene["viewmat"] = view
    return {k: v.to(dtype).requires_grad_(True) for k, v in scene.items()}
