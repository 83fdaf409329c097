"""The `cuda` backend: gsplat's fused CUDA rasteriser behind our ``rasterize`` contract.

gsplat samples pixel (i, j) at (j + 0.5, i + 0.5); our convention (OpenCV) samples it at (j, i), so the principal
point is shifted by half a pixel on the way in and the returned 2D means by half a pixel on the way out (their
``.grad`` still receives dL/dmeans2d, see ``_screen_means``). gsplat's
skip rules (alpha < 1/255, alpha <= 0.99, T >= 1e-4, opacity-aware 3.33-sigma boxes) match the CPU kernels.
"""

from __future__ import annotations

import weakref

import torch
from torch import Tensor


def rasterize_gsplat(means, quats, scales, opacities, colors, sh, K, width, height, viewmat, near, far, background):
    from gsplat import rasterization

    from agg.render.rasterize import RenderMeta, RenderOutput

    K_gs = K.clone()
    K_gs[0, 2] = K_gs[0, 2] + 0.5
    K_gs[1, 2] = K_gs[1, 2] + 0.5
    if sh is not None:
        values, sh_degree = sh, int(round(sh.shape[1] ** 0.5)) - 1
    else:
        values, sh_degree = colors, None
    render, alphas, meta = rasterization(
        means=means,
        quats=quats,
        scales=scales,
        opacities=opacities,
        colors=values,
        viewmats=viewmat[None],
        Ks=K_gs[None],
        width=int(width),
        height=int(height),
        near_plane=float(near),
        far_plane=float(far),
        eps2d=0.3,
        sh_degree=sh_degree,
        packed=False,
        render_mode="RGB+ED",
    )
    color = render[0, ..., :-1]  # [H, W, C]
    depth = render[0, ..., -1]  # [H, W], expected depth (accum / alpha)
    alpha = alphas[0, ..., 0]  # [H, W]
    if background is not None:
        bg = torch.as_tensor(background, dtype=color.dtype, device=color.device)
        color = color + (1.0 - alpha).unsqueeze(-1) * bg
    radii: Tensor = meta["radii"][0]
    if radii.dim() == 1:  # gsplat < 1.5 returns one radius per Gaussian
        radii = radii.unsqueeze(-1).expand(-1, 2)
    out_meta = RenderMeta(
        means2d=_screen_means(meta["means2d"]),
        radii=radii.to(torch.int32),
        visible=(radii > 0).all(-1),
        depths=meta["depths"][0],
        conics=meta["conics"][0],
        backend="cuda",
    )
    return RenderOutput(color=color, depth=depth, alpha=alpha, meta=out_meta)


def _screen_means(used: Tensor) -> Tensor:
    """[N, 2] our pixel convention's 2D means, whose ``.grad`` receives dL/dmeans2d in backward.

    gsplat composites from its own ``used`` [1, N, 2]: a tensor derived from it (the index, the half-pixel shift)
    is not on the loss's path, so autograd would never fill its ``.grad`` (and densification would see no
    gradient). A hook on ``used`` copies each backward pass's gradient there, accumulating as autograd does."""
    ours = used[0] - 0.5
    if used.requires_grad:
        ours.retain_grad()  # marks .grad as meant to be read (no warning); autograd itself never fills it
        ref = weakref.ref(ours)  # a strong reference would make a cycle through the autograd graph (a leak)

        def copy_grad(grad: Tensor) -> None:
            target = ref()
            if target is not None:
                g = grad[0].detach()
                target.grad = g.clone() if target.grad is None else target.grad + g

        used.register_hook(copy_grad)
    return ours
