"""The camera node: per-frame SE(3) refinement of the camera-pose prior.

``world_from_camera[i] = prior[i] @ [exp(omega_i) | tau_i]``: a correction applied in camera i's own frame, with
``omega`` [T, 3] an so(3) vector (kornia ``So3.exp``) and ``tau`` [T, 3] a translation in scene units, both
initialised at zero so the node starts exactly at the prior. Frame 0 defines the world (``world_from_camera[0] =
I``, docs/CONVENTIONS.md): its correction is held at zero (a gauge fix), so the world frame never drifts.
"""

from __future__ import annotations

import torch
from kornia.geometry.liegroup import So3
from torch import Tensor, nn


class CameraNode(nn.Module):
    """Learnable per-frame camera poses around a prior [T, 4, 4] (camera-to-world, OpenCV axes)."""

    def __init__(self, world_from_camera: Tensor, fix_first: bool = True):
        super().__init__()
        p = torch.as_tensor(world_from_camera, dtype=torch.float32)
        if p.ndim != 3 or p.shape[1:] != (4, 4):
            raise ValueError(f"world_from_camera must be [T, 4, 4], got {tuple(p.shape)}")
        if not torch.isfinite(p).all():
            raise ValueError("world_from_camera has non-finite values")
        self.register_buffer("prior", p.clone())  # [T, 4, 4]
        t = p.shape[0]
        self.omega = nn.Parameter(torch.zeros(t, 3))  # [T, 3] rotation correction (so(3))
        self.tau = nn.Parameter(torch.zeros(t, 3))  # [T, 3] translation correction, camera frame
        self.register_buffer("free", torch.ones(t, 1))  # [T, 1] 0 where the correction is held at zero
        if fix_first:
            self.free[0] = 0.0

    def __len__(self) -> int:
        return int(self.prior.shape[0])

    def correction(self, frames: Tensor | None = None) -> Tensor:
        """[F, 4, 4] ``prior_camera_from_refined_camera`` for the given frame indices (all when None)."""
        idx = torch.arange(len(self), device=self.prior.device) if frames is None else torch.as_tensor(frames)
        idx = idx.reshape(-1).to(self.prior.device)
        free = self.free[idx]  # [F, 1]
        rot = So3.exp(self.omega[idx] * free).matrix()  # [F, 3, 3]
        out = torch.eye(4, device=self.prior.device, dtype=rot.dtype).repeat(len(idx), 1, 1)
        out[:, :3, :3] = rot
        out[:, :3, 3] = self.tau[idx] * free
        return out

    def world_from_camera(self, frames: Tensor | None = None) -> Tensor:
        """[F, 4, 4] refined camera-to-world poses (differentiable w.r.t. ``omega`` and ``tau``)."""
        idx = torch.arange(len(self), device=self.prior.device) if frames is None else torch.as_tensor(frames)
        idx = idx.reshape(-1).to(self.prior.device)
        return self.prior[idx] @ self.correction(idx)

    def camera_from_world(self, frames: Tensor | None = None) -> Tensor:
        """[F, 4, 4] view matrices (the renderer's ``viewmat``): the rigid inverse of ``world_from_camera``."""
        p = self.world_from_camera(frames)
        rt = p[:, :3, :3].transpose(1, 2)
        out = torch.zeros_like(p)
        out[:, :3, :3] = rt
        out[:, :3, 3] = -(rt @ p[:, :3, 3:4])[..., 0]
        out[:, 3, 3] = 1.0
        return out

    def param_groups(self, lr: float) -> list[dict]:
        """Optimiser groups ``camera#omega`` and ``camera#tau`` (the paper's camera pose lr is 1e-5)."""
        return [{"name": "camera#omega", "params": [self.omega], "lr": float(lr)},
                {"name": "camera#tau", "params": [self.tau], "lr": float(lr)}]
