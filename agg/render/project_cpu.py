"""Native CPU projection (csrc/project.cpp) with an autograd wrapper.

Same contract as :func:`agg.render.projection.project_gaussians`, its plain-torch twin, for float32 CPU tensors.
The intrinsics K are treated as constants (no gradient).
"""

from __future__ import annotations

import torch
from torch import Tensor

from agg.render import native
from agg.render.projection import Projected, finish_projection


class _Project(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, viewmat, K, width, height, near):
        args = tuple(t.detach().float().contiguous() for t in (means, quats, scales, viewmat, K))
        means2d, conics, depths = native.load().project_forward(*args, width, height, near)
        ctx.args = args
        ctx.cam = (width, height, near)
        return means2d, conics, depths

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_means2d, g_conics, g_depths):
        n = ctx.args[0].shape[0]
        g_means2d = torch.zeros(n, 2) if g_means2d is None else g_means2d.float().contiguous()
        g_conics = torch.zeros(n, 3) if g_conics is None else g_conics.float().contiguous()
        g_depths = torch.zeros(n) if g_depths is None else g_depths.float().contiguous()
        g_m, g_q, g_s, g_v = native.load().project_backward(*ctx.args, *ctx.cam, g_means2d, g_conics, g_depths)
        return g_m, g_q, g_s, g_v, None, None, None, None


def project_gaussians_cpu(
    means: Tensor,  # [N, 3] world
    quats: Tensor,  # [N, 4] wxyz
    scales: Tensor,  # [N, 3] linear
    opacities: Tensor,  # [N]
    viewmat: Tensor,  # [4, 4] camera_from_world
    K: Tensor,  # [3, 3]
    width: int,
    height: int,
    near: float,
    far: float,
) -> Projected:
    means2d, conics, depths = _Project.apply(means, quats, scales, viewmat, K, int(width), int(height), float(near))
    return finish_projection(means2d, conics, depths, opacities, width, height, near, far)
