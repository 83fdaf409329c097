"""The `cpu` backend: native C++/OpenMP compositing with an autograd wrapper.

Same contract as :func:`agg.render.raster_torch.composite_torch`.
"""

from __future__ import annotations

import torch
from torch import Tensor

from agg.render import native
from agg.render.projection import opacity_threshold


class _Composite(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, colors, opacities, thresholds, depths, visible, width, height):
        ext = native.load()
        args = (
            means2d.detach().float().contiguous(),
            conics.detach().float().contiguous(),
            colors.detach().float().contiguous(),
            opacities.detach().float().contiguous(),
            thresholds.detach().float().contiguous(),
            depths.detach().float().contiguous(),
            visible.contiguous(),
        )
        accum, T_final, last = ext.forward(*args, width, height)
        ctx.args = args
        ctx.size = (width, height)
        ctx.save_for_backward(T_final, last)
        ctx.mark_non_differentiable(T_final)
        return accum, 1.0 - T_final

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_accum, grad_alpha):
        T_final, last = ctx.saved_tensors
        width, height = ctx.size
        if grad_accum is None:
            grad_accum = torch.zeros((height, width, ctx.args[2].shape[1]), dtype=torch.float32)
        if grad_alpha is None:
            grad_alpha = torch.zeros((height, width), dtype=torch.float32)
        g_m, g_con, g_col, g_op = native.load().backward(
            *ctx.args, width, height, T_final, last, grad_accum.float().contiguous(), grad_alpha.float().contiguous()
        )
        return g_m, g_con, g_col, g_op, None, None, None, None, None


def composite_cpu(
    means2d: Tensor,  # [N, 2] px
    conics: Tensor,  # [N, 3]
    colors: Tensor,  # [N, C]
    opacities: Tensor,  # [N]
    depths: Tensor,  # [N] sort key (camera z)
    visible: Tensor,  # [N] bool
    width: int,
    height: int,
) -> tuple[Tensor, Tensor]:
    """Returns (accumulated colour [H, W, C], alpha [H, W]); float32, on the CPU."""
    accum, alpha = _Composite.apply(
        means2d, conics, colors, opacities, opacity_threshold(opacities), depths, visible, int(width), int(height)
    )
    return accum, alpha
