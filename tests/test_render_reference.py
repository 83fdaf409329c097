"""The plain-torch reference against central finite differences, in float64, on a tiny scene."""

from __future__ import annotations

import torch

from agg.render import rasterize
from tests.render_scenes import look_K, random_scene

W, H = 12, 9


def _render(means, quats, scales, opacities, colors, viewmat):
    out = rasterize(means, quats, scales, opacities, colors, K=look_K(W, H, dtype=torch.float64), width=W,
                    height=H, viewmat=viewmat, background=torch.tensor([0.2, 0.5, 0.1], dtype=torch.float64),
                    backend="torch")
    return out.color, out.depth, out.alpha


def test_reference_gradients_match_finite_differences():
    scene = random_scene(5, 3, channels=3, dtype=torch.float64, depth_range=(2.0, 4.0), scale_range=(0.2, 0.6))
    inputs = tuple(scene[k] for k in ("means", "quats", "scales", "opacities", "colors", "viewmat"))
    color, _, alpha = _render(*inputs)
    assert alpha.max() > 0.3  # the Gaussians really cover the tiny image
    assert torch.autograd.gradcheck(_render, inputs, eps=1e-6, atol=1e-6, rtol=1e-4)


def test_reference_sh_gradients_match_finite_differences():
    scene = random_scene(4, 5, sh_degree=3, dtype=torch.float64, depth_range=(2.0, 4.0), scale_range=(0.2, 0.6))

    def f(means, sh, viewmat):
        out = rasterize(means, scene["quats"].detach(), scene["scales"].detach(), scene["opacities"].detach(),
                        sh=sh, K=look_K(W, H, dtype=torch.float64), width=W, height=H, viewmat=viewmat,
                        backend="torch")
        return out.color

    assert torch.autograd.gradcheck(f, (scene["means"], scene["sh"], scene["viewmat"]), eps=1e-6, atol=1e-6,
                                    rtol=1e-4)
