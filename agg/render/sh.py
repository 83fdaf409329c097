"""Real spherical harmonics, degrees 0-3, evaluated to RGB (the 3DGS / gsplat convention).

Colour = max(SH(dir) + 0.5, 0), where dir is the unit vector from the camera centre to the Gaussian.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def sh_degree_from_coeffs(num_coeffs: int) -> int:
    """K = (d + 1)^2 coefficients per channel -> degree d in 0..3."""
    degree = int(round(math.sqrt(num_coeffs))) - 1
    if (degree + 1) ** 2 != num_coeffs or not 0 <= degree <= 3:
        raise ValueError(f"SH needs K = (d+1)^2 coefficients with d in 0..3, got K = {num_coeffs}")
    return degree


def eval_sh(sh: Tensor, dirs: Tensor) -> Tensor:
    """Evaluate SH to colour.

    sh:   [N, K, 3] coefficients, K = (d+1)^2, d in 0..3
    dirs: [N, 3] viewing directions (camera centre -> Gaussian); normalised here
    returns [N, 3] colours, >= 0
    """
    degree = sh_degree_from_coeffs(sh.shape[1])
    # Normalise with a clamped norm: a zero direction (Gaussian at the camera centre) stays finite.
    dirs = dirs / torch.sqrt((dirs * dirs).sum(-1, keepdim=True).clamp_min(1e-24))
    out = C0 * sh[:, 0]  # [N, 3]
    if degree >= 1:
        x, y, z = (d.unsqueeze(-1) for d in dirs.unbind(-1))  # each [N, 1]
        out = out - C1 * y * sh[:, 1] + C1 * z * sh[:, 2] - C1 * x * sh[:, 3]
        if degree >= 2:
            xx, yy, zz = x * x, y * y, z * z
            xy, yz, xz = x * y, y * z, x * z
            out = (
                out
                + C2[0] * xy * sh[:, 4]
                + C2[1] * yz * sh[:, 5]
                + C2[2] * (2.0 * zz - xx - yy) * sh[:, 6]
                + C2[3] * xz * sh[:, 7]
                + C2[4] * (xx - yy) * sh[:, 8]
            )
            if degree >= 3:
                out = (
                    out
                    + C3[0] * y * (3.0 * xx - yy) * sh[:, 9]
                    + C3[1] * xy * z * sh[:, 10]
                    + C3[2] * y * (4.0 * zz - xx - yy) * sh[:, 11]
                    + C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy) * sh[:, 12]
                    + C3[4] * x * (4.0 * zz - xx - yy) * sh[:, 13]
                    + C3[5] * z * (xx - yy) * sh[:, 14]
                    + C3[6] * x * (xx - 3.0 * yy) * sh[:, 15]
                )
    return torch.clamp_min(out + 0.5, 0.0)


def rgb_to_sh0(rgb: Tensor) -> Tensor:
    """Inverse of degree-0 evaluation: [N, 3] colour -> [N, 3] DC coefficient."""
    return (rgb - 0.5) / C0
