"""EWA projection of 3D Gaussians to screen-space 2D Gaussians (plain torch, differentiable).

Shared by every CPU-side backend, so the `cpu` and `torch` rasterisers see identical 2D Gaussians and only the
per-pixel compositing differs. The field's known pitfalls are designed out here:

- z = 0 / behind the camera: depths are clamped to the near plane *before* dividing, so culled Gaussians keep
  finite (zero) gradients instead of 0 * inf = NaN.
- Off-screen Gaussians: x/z and y/z are clamped to the field of view plus 30 % in the projection Jacobian.
- Degenerate covariances: the 2D covariance is A A^T with A = J R S, its determinant is taken by Cauchy-Binet
  (a sum of squares, never negative), and it is dilated by 0.3 px^2 so the determinant is >= 0.09.
- A zero quaternion: its norm is clamped, which makes it the identity rotation with zero gradient.

Pixel convention (OpenCV): pixel (row i, column j) is sampled at image point (x, y) = (j, i).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

# Compositing constants shared by every backend; the kernels repeat them (csrc/rasterize.cpp).
ALPHA_MIN = 1.0 / 255.0  # contributions below this are skipped
ALPHA_MAX = 0.99  # alpha is clamped here; where clamped, opacity and conic gradients are zero
T_MIN = 1e-4  # a pixel stops once its transmittance would fall below this
EPS_2D = 0.3  # screen-space dilation (px^2)
FOV_CLAMP = 1.3  # Jacobian clamps x/z, y/z to 1.3x the half field of view
MAX_EXTENT = 1.0e6  # px; caps the screen box of huge Gaussians (they are clipped to the image anyway)


@dataclass
class Projected:
    """Screen-space Gaussians for one camera. N is the number of input Gaussians (culled ones included)."""

    means2d: Tensor  # [N, 2] pixel coordinates (x right, y down)
    conics: Tensor  # [N, 3] inverse 2D covariance (a, b, c) of [[a, b], [b, c]], px^-2
    depths: Tensor  # [N] camera z in metres (not clamped)
    visible: Tensor  # [N] bool: in front of the near plane, before the far plane, opacity >= 1/255, on screen
    radii: Tensor  # [N, 2] int32 half extents (x, y) of the opacity-aware box in px; 0 where not visible


def normalize_quats(quats: Tensor, eps: float = 1e-12, dim: int = -1) -> Tensor:
    """wxyz quaternions along ``dim`` -> unit quaternions; a zero quaternion maps to zero (the identity rotation
    in quat_to_rotmat, with zero gradient)."""
    norm = torch.sqrt((quats * quats).sum(dim, keepdim=True).clamp_min(eps * eps))
    return quats / norm


def quat_to_rotmat(quats: Tensor, dim: int = -1) -> Tensor:
    """wxyz quaternions (normalised here) -> rotation matrices.

    dim=-1: [N, 4] -> [N, 3, 3].  dim=0: [4, N] -> [3, 3, N] (structure of arrays).
    """
    w, x, y, z = normalize_quats(quats, dim=dim).unbind(dim)
    rows = [
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ]
    if dim == 0:
        return torch.stack(rows, 0).reshape((3, 3) + quats.shape[1:])
    return torch.stack(rows, dim=-1).reshape(quats.shape[:-1] + (3, 3))


def opacity_threshold(opacities: Tensor) -> Tensor:
    """[N] -> [N] sigma threshold: alpha = o * exp(-sigma) >= 1/255  <=>  sigma <= log(255 * o).

    Every backend skips a pixel-Gaussian pair iff sigma < 0 or sigma > this threshold, so no exp() is needed for
    pairs that cannot reach 1/255 and forward and backward agree exactly on which pairs count.
    """
    return torch.log(opacities.detach().clamp_min(1e-30) * 255.0)


def screen_extent(conics: Tensor, thresholds: Tensor) -> Tensor:
    """[N, 3] conics, [N] sigma thresholds -> [N, 2] float half extents (x, y) of the box {sigma <= thr}.

    The axis-aligned box of the ellipse d^T Q d <= 2 thr is |dx| <= sqrt(2 thr c / det Q), |dy| <= sqrt(2 thr a /
    det Q). A non-positive-definite conic (rounding in extreme cases) gets MAX_EXTENT. Detached: boxes are not
    differentiable. The C++ kernel computes the same box and widens it slightly, so it never cuts the ellipse.
    """
    a, b, c = conics.detach().unbind(-1)
    det = a * c - b * b
    thr = thresholds.clamp_min(0.0)
    ok = det > 0
    safe_det = torch.where(ok, det, torch.ones_like(det))
    ex = torch.where(ok, torch.sqrt(2.0 * thr * c.abs() / safe_det), torch.full_like(det, MAX_EXTENT))
    ey = torch.where(ok, torch.sqrt(2.0 * thr * a.abs() / safe_det), torch.full_like(det, MAX_EXTENT))
    return torch.stack([ex, ey], -1).clamp(max=MAX_EXTENT).nan_to_num(nan=MAX_EXTENT)


def project_gaussians(
    means: Tensor,  # [N, 3] world
    quats: Tensor,  # [N, 4] wxyz
    scales: Tensor,  # [N, 3] linear, metres
    opacities: Tensor,  # [N]
    viewmat: Tensor,  # [4, 4] camera_from_world, OpenCV axes
    K: Tensor,  # [3, 3]
    width: int,
    height: int,
    near: float,
    far: float,
) -> Projected:
    """Project Gaussians into one pinhole camera. Differentiable w.r.t. means, quats, scales and viewmat.

    Works on structure-of-arrays ([k, N]) layouts: every op then runs on contiguous rows, which makes the
    autograd graph several times faster on the CPU than [N, 3, 3] batches.
    """
    R_cw = viewmat[:3, :3]  # [3, 3]
    t_cw = viewmat[:3, 3:]  # [3, 1]
    means_c = R_cw @ means.t() + t_cw  # [3, N]
    x, y, z = means_c[0], means_c[1], means_c[2]  # each [N], contiguous
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]

    # Clamp before dividing: culled Gaussians (z <= near) then give zero, not NaN, gradients.
    inv_z = 1.0 / z.clamp_min(near)  # [N]

    # Jacobian of the perspective projection with x/z, y/z clamped to 1.3x the field of view.
    margin_x = (FOV_CLAMP - 1.0) * 0.5 * width / fx
    margin_y = (FOV_CLAMP - 1.0) * 0.5 * height / fy
    tx = torch.minimum(torch.maximum(x * inv_z, -(cx / fx + margin_x)), (width - cx) / fx + margin_x)  # [N]
    ty = torch.minimum(torch.maximum(y * inv_z, -(cy / fy + margin_y)), (height - cy) / fy + margin_y)  # [N]
    j00, j02 = fx * inv_z, -fx * tx * inv_z  # [N] each: J = [[j00, 0, j02], [0, j11, j12]]
    j11, j12 = fy * inv_z, -fy * ty * inv_z

    # 2D covariance = A A^T with A = J R_cw R S.
    R = quat_to_rotmat(quats.t().contiguous(), dim=0)  # [3, 3, N]
    M = (R_cw @ R.reshape(3, -1)).reshape(3, 3, -1) * scales.t().unsqueeze(0)  # [3, 3, N], columns scaled
    a0 = j00 * M[0] + j02 * M[2]  # [3, N] first row of A
    a1 = j11 * M[1] + j12 * M[2]  # [3, N] second row of A
    cov_xx = (a0 * a0).sum(0)  # [N]
    cov_xy = (a0 * a1).sum(0)
    cov_yy = (a1 * a1).sum(0)
    cross = torch.linalg.cross(a0, a1, dim=0)  # Cauchy-Binet: det(A A^T) = |a0 x a1|^2 >= 0
    det = (cross * cross).sum(0) + EPS_2D * (cov_xx + cov_yy) + EPS_2D * EPS_2D  # [N], >= 0.09
    inv_det = 1.0 / det
    conics = torch.stack([(cov_yy + EPS_2D) * inv_det, -cov_xy * inv_det, (cov_xx + EPS_2D) * inv_det], -1)  # [N, 3]

    means2d = torch.stack([fx * x * inv_z + cx, fy * y * inv_z + cy], dim=-1)  # [N, 2]
    return finish_projection(means2d, conics, z, opacities, width, height, near, far)


def finish_projection(
    means2d: Tensor,  # [N, 2]
    conics: Tensor,  # [N, 3]
    depths: Tensor,  # [N] camera z
    opacities: Tensor,  # [N]
    width: int,
    height: int,
    near: float,
    far: float,
) -> Projected:
    """Visibility and opacity-aware screen boxes (not differentiable), shared by the torch and native projections."""
    extent = screen_extent(conics, opacity_threshold(opacities))  # [N, 2]
    with torch.no_grad():
        m2 = means2d.detach()
        z = depths.detach()
        finite = torch.isfinite(m2).all(-1) & torch.isfinite(conics.detach()).all(-1) & torch.isfinite(z)
        on_screen = (
            (m2[:, 0] + extent[:, 0] >= 0)
            & (m2[:, 0] - extent[:, 0] <= width - 1)
            & (m2[:, 1] + extent[:, 1] >= 0)
            & (m2[:, 1] - extent[:, 1] <= height - 1)
        )
        visible = (z > near) & (z < far) & (opacities.detach() >= 1.0 / 255.0) & finite & on_screen
        radii = torch.where(visible.unsqueeze(-1), torch.ceil(extent), torch.zeros_like(extent)).to(torch.int32)
    return Projected(means2d=means2d, conics=conics, depths=depths, visible=visible, radii=radii)


def invert_rigid(T: Tensor) -> Tensor:
    """[4, 4] rigid transform a_from_b -> b_from_a (differentiable)."""
    R = T[:3, :3]
    t = T[:3, 3]
    out = torch.zeros_like(T)
    out[:3, :3] = R.T
    out[:3, 3] = -(R.T @ t)
    out[3, 3] = 1.0
    return out


def camera_center(viewmat: Tensor) -> Tensor:
    """[4, 4] camera_from_world -> [3] camera centre in world coordinates."""
    R = viewmat[:3, :3]
    return -(R.T @ viewmat[:3, 3])


__all__ = [
    "ALPHA_MIN",
    "ALPHA_MAX",
    "T_MIN",
    "EPS_2D",
    "Projected",
    "project_gaussians",
    "quat_to_rotmat",
    "normalize_quats",
    "opacity_threshold",
    "screen_extent",
    "invert_rigid",
    "camera_center",
]
