"""Rigid agent nodes: canonical Gaussians per instance plus per-frame poses [T, K] and a frame-validity mask.

All rigid instances share one ``GaussianParams`` (canonical box frame, docs/BUNDLE.md box axes) with an
``instance`` index [N]. Each instance k has a pose prior ``world_from_box`` [T, K, 4, 4] (from the tracklets) and
learnable per-frame corrections ``omega`` [T, K, 3] (so(3), box frame) and ``tau`` [T, K, 3] (box frame), zero at
the start: ``world_from_box = prior @ [exp(omega) | tau]``. ``valid`` [T, K] says where an instance exists; in
other frames its Gaussians get opacity 0 (drivestudio's validity mask), so they neither render nor receive
gradients.
"""

from __future__ import annotations

import torch
from kornia.geometry.liegroup import So3
from torch import Tensor, nn

from agg.nodes.gaussians import GaussianParams


def quat_multiply(a: Tensor, b: Tensor) -> Tensor:
    """Hamilton product of wxyz quaternions [..., 4] (the rotation a then applied after b: R(a) R(b))."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([aw * bw - ax * bx - ay * by - az * bz,
                        aw * bx + ax * bw + ay * bz - az * by,
                        aw * by - ax * bz + ay * bw + az * bx,
                        aw * bz + ax * by - ay * bx + az * bw], -1)


def matrix_to_quat(r: Tensor) -> Tensor:
    """[..., 3, 3] rotation matrices -> [..., 4] unit wxyz quaternions (w >= 0)."""
    return So3.from_matrix(r.reshape(-1, 3, 3)).q.data.reshape(*r.shape[:-2], 4)


class RigidAgents(nn.Module):
    """K rigid instances: canonical Gaussians ``gaussians`` with ``instance`` [N] in 0..K-1, and their poses."""

    def __init__(self, gaussians: GaussianParams, instance: Tensor, world_from_box: Tensor, valid: Tensor):
        super().__init__()
        wfb = torch.as_tensor(world_from_box, dtype=torch.float32)
        if wfb.ndim != 4 or wfb.shape[2:] != (4, 4):
            raise ValueError(f"world_from_box must be [T, K, 4, 4], got {tuple(wfb.shape)}")
        t, k = wfb.shape[:2]
        valid = torch.as_tensor(valid, dtype=torch.bool)
        instance = torch.as_tensor(instance, dtype=torch.long)
        if valid.shape != (t, k) or instance.shape != (len(gaussians),):
            raise ValueError(f"valid must be [{t}, {k}] and instance [{len(gaussians)}]")
        if len(instance) and (instance.min() < 0 or instance.max() >= k):
            raise ValueError(f"instance indices must be in [0, {k})")
        if not torch.isfinite(wfb[valid]).all():
            raise ValueError("world_from_box must be finite where valid")
        self.gaussians = gaussians
        self.register_buffer("instance", instance)  # [N]
        self.register_buffer("prior", torch.where(valid[..., None, None], wfb, torch.eye(4)))  # [T, K, 4, 4]
        self.register_buffer("valid", valid)  # [T, K]
        self.omega = nn.Parameter(torch.zeros(t, k, 3))  # [T, K, 3]
        self.tau = nn.Parameter(torch.zeros(t, k, 3))  # [T, K, 3]

    @property
    def num_instances(self) -> int:
        return int(self.prior.shape[1])

    def world_from_box(self, frame: int) -> Tensor:
        """[K, 4, 4] refined poses of every instance at an integer frame."""
        corr = torch.eye(4, device=self.prior.device).repeat(self.num_instances, 1, 1)
        corr[:, :3, :3] = So3.exp(self.omega[frame]).matrix()
        corr[:, :3, 3] = self.tau[frame]
        return self.prior[frame] @ corr

    def compose(self, frame: int) -> dict[str, Tensor]:
        """World-frame Gaussians at ``frame`` (the renderer's arguments); invalid instances get opacity 0."""
        g = self.gaussians.activated()
        pose = self.world_from_box(frame)[self.instance]  # [N, 4, 4]
        rot = pose[:, :3, :3]
        means = (rot @ g["means"][..., None])[..., 0] + pose[:, :3, 3]  # [N, 3]
        quats = quat_multiply(matrix_to_quat(rot), g["quats"])  # [N, 4]
        opacities = g["opacities"] * self.valid[frame][self.instance].to(g["opacities"])
        # view-dependent colour: SH is defined in the canonical frame; evaluating it in world directions is the
        # usual approximation (3DGS agents, OmniRe) and exact for degree 0
        return {"means": means, "quats": quats, "scales": g["scales"], "opacities": opacities, "sh": g["sh"]}

    def param_groups(self, prefix: str, gaussian_lrs: dict[str, float], pose_lr: float) -> list[dict]:
        """``prefix#means`` ... for the Gaussians, ``prefix#omega`` / ``prefix#tau`` for the poses."""
        return self.gaussians.param_groups(prefix, gaussian_lrs) + [
            {"name": f"{prefix}#omega", "params": [self.omega], "lr": float(pose_lr)},
            {"name": f"{prefix}#tau", "params": [self.tau], "lr": float(pose_lr)}]
