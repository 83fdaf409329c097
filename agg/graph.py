"""The Gaussian scene graph: a camera node, a background node and (only when the scene has agents) agent nodes.

``compose(frame)`` gives the world-frame Gaussians of every node at an integer frame, concatenated, with
``node`` [N] saying which node each came from (0 = background, k + 1 = rigid instance k), so instance ids can
be rendered as an extra colour channel and gradients read per node. ``render(frame)`` draws them through the
refined camera of that frame with ``agg.render.rasterize``.

Still to come (issue 4): the non-rigid node (deformation MLP), the sky node, continuous time ``t``.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from agg.io.bundle import SceneBundle
from agg.nodes.camera import CameraNode
from agg.nodes.gaussians import GaussianParams
from agg.nodes.init import InitConfig, box_pose, init_from_bundle
from agg.nodes.rigid import RigidAgents
from agg.render import rasterize


class SceneGraph(nn.Module):
    def __init__(self, camera: CameraNode, background: GaussianParams, K: Tensor, width: int, height: int,
                 rigid: RigidAgents | None = None, track_rows: list[int] | None = None):
        super().__init__()
        self.camera, self.background, self.rigid = camera, background, rigid
        self.register_buffer("K", torch.as_tensor(K, dtype=torch.float32).reshape(-1, 3, 3))  # [T or 1, 3, 3]
        self.width, self.height = int(width), int(height)
        self.track_rows = list(track_rows or [])  # bundle tracklet row of each rigid instance

    @classmethod
    def from_bundle(cls, bundle: SceneBundle, config: InitConfig = InitConfig()) -> "SceneGraph":
        """Nodes initialised from the bundle's priors; a bundle without rigid tracklets gets no agent node."""
        init = init_from_bundle(bundle, config)
        rigid = None
        rows: list[int] = []
        if init["rigid"] is not None:
            g, instance, rows = init["rigid"]
            tr = bundle.tracklets
            t = bundle.num_frames
            wfb = torch.eye(4).repeat(t, len(rows), 1, 1)
            for j, k in enumerate(rows):
                for i in range(t):
                    if tr.valid[k, i]:
                        wfb[i, j] = torch.as_tensor(box_pose(tr.boxes[k, i]), dtype=torch.float32)
            valid = torch.as_tensor(tr.valid[rows].T.copy())  # [T, K]
            rigid = RigidAgents(g, torch.as_tensor(instance), wfb, valid)
        return cls(CameraNode(torch.as_tensor(bundle.world_from_camera)), init["background"],
                   torch.as_tensor(bundle.intrinsics), bundle.width, bundle.height, rigid, rows)

    def compose(self, frame: int) -> dict[str, Tensor]:
        """World Gaussians of every node at ``frame``: means, quats, scales, opacities, sh, node [N]."""
        parts = [self.background.activated()]
        nodes = [torch.zeros(len(self.background), dtype=torch.long)]
        if self.rigid is not None:
            parts.append(self.rigid.compose(frame))
            nodes.append(self.rigid.instance + 1)
        out = {k: torch.cat([p[k] for p in parts], 0) for k in ("means", "quats", "scales", "opacities", "sh")}
        out["node"] = torch.cat(nodes, 0)
        return out

    def render(self, frame: int, **kwargs):
        """``RenderOutput`` of the composed graph through the refined camera of ``frame``."""
        g = self.compose(frame)
        viewmat = self.camera.camera_from_world(torch.tensor([frame]))[0]
        K = self.K[frame if self.K.shape[0] > 1 else 0]  # noqa: N806
        return rasterize(g["means"], g["quats"], g["scales"], g["opacities"], sh=g["sh"], viewmat=viewmat, K=K,
                         width=self.width, height=self.height, **kwargs)
