"""The Gaussian scene graph: a camera node, a background node and only the other nodes the scene needs.

- ``camera`` (``nodes/camera.py``): per-frame SE(3) refinement of the pose prior.
- ``background`` (``nodes/gaussians.py``): static world-frame Gaussians.
- ``rigid`` (``nodes/rigid.py``): rigid agents, only when the priors have rigid tracklets (or topology evolution
  spawns one).
- ``nonrigid`` (``nodes/nonrigid.py``): agents with a deformation MLP, only for non-rigid tracklets.
- ``sky`` (``nodes/sky.py``): far-field Gaussians, only when the frames show sky.

``compose(frame)`` gives the world Gaussians of every node at a frame, concatenated, with ``node`` [N] naming the
slot each came from: 0 for the static nodes (background, sky), ``1 + j`` for agent slot j, where slots run over
the rigid instances and then the non-rigid ones (``slot_track_ids()`` gives each slot's tracklet id). Per-request
``agent_poses`` / ``agent_valid`` ({track id: world_from_box [4, 4] / bool}) override the node's own poses, which
is how held-out frames (interpolated poses) and simulators (moved or hidden agents) render.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor, nn

from agg.io.bundle import SceneBundle
from agg.io.video import intrinsics_at
from agg.nodes.camera import CameraNode
from agg.nodes.gaussians import GaussianParams
from agg.nodes.init import InitConfig, box_pose, init_from_bundle
from agg.nodes.rigid import RigidAgents
from agg.render import rasterize
from agg.render.projection import invert_rigid

KEYS = ("means", "quats", "scales", "opacities", "sh")


def _track_poses(bundle: SceneBundle, rows: list[int]) -> tuple[Tensor, Tensor]:
    """world_from_box [T, K, 4, 4] and valid [T, K] of the given tracklet rows."""
    tr, t = bundle.tracklets, bundle.num_frames
    wfb = torch.eye(4).repeat(t, len(rows), 1, 1)
    for j, k in enumerate(rows):
        for i in range(t):
            if tr.valid[k, i] and torch.isfinite(torch.as_tensor(tr.boxes[k, i][[0, 1, 2, 6]])).all():
                box = tr.boxes[k, i].copy()
                wfb[i, j] = torch.as_tensor(box_pose(box), dtype=torch.float32)
    valid = torch.as_tensor(tr.valid[rows].T.copy())  # [T, K]
    return wfb, valid


def _track_half_extents(bundle: SceneBundle, rows: list[int]) -> Tensor:
    """[K, 3] box half extents (x = l, y = h, z = w) of the given tracklet rows: half their median box (NaN where a
    track has no size; the node treats it as unknown)."""
    return torch.as_tensor(np.array([0.5 * bundle.tracklets.box_size(k) for k in rows]).reshape(-1, 3),
                           dtype=torch.float32)


class SceneGraph(nn.Module):
    def __init__(self, camera: CameraNode, background: GaussianParams, K: Tensor, width: int, height: int,
                 rigid: RigidAgents | None = None, nonrigid: RigidAgents | None = None, sky: nn.Module | None = None):
        super().__init__()
        self.camera, self.background, self.rigid, self.nonrigid, self.sky = camera, background, rigid, nonrigid, sky
        self.register_buffer("K", torch.as_tensor(K, dtype=torch.float32).reshape(-1, 3, 3))  # [T or 1, 3, 3]
        self.width, self.height = int(width), int(height)

    def __setattr__(self, name: str, value) -> None:
        super().__setattr__(name, value)
        if name in ("rigid", "nonrigid") and value is not None:
            value.camera_delta = self.camera_delta  # anchored agents follow the camera node (nodes/rigid.py)

    def camera_delta(self, frame: int) -> Tensor:
        """[4, 4] the camera node's correction at ``frame`` in world coordinates: ``world_from_camera @
        inv(prior)``, so ``delta @ prior = world_from_camera`` (identity where the correction is zero)."""
        cam = self.camera
        prior = cam.prior[frame]  # [4, 4]
        return cam.world_from_camera(torch.tensor([frame], device=prior.device))[0] @ invert_rigid(prior)

    @property
    def num_frames(self) -> int:
        return len(self.camera)

    @classmethod
    def from_bundle(cls, bundle: SceneBundle, config: InitConfig = InitConfig(), *, sky: bool | None = None,
                    deform=None) -> "SceneGraph":
        """Nodes initialised from the bundle's priors. A bundle without rigid (non-rigid) tracklets gets no rigid
        (non-rigid) node; the sky node is made when ``sky`` is True, or when None and ``has_sky(bundle)``."""
        init = init_from_bundle(bundle, config)
        ids = bundle.tracklets.ids if bundle.tracklets is not None else []
        rigid = nonrigid = None
        if init["rigid"] is not None:
            g, instance, rows = init["rigid"]
            wfb, valid = _track_poses(bundle, rows)
            rigid = RigidAgents(g, torch.as_tensor(instance), wfb, valid, torch.as_tensor(ids[rows]),
                                _track_half_extents(bundle, rows))
        if init["non-rigid"] is not None:
            from agg.nodes.nonrigid import DeformConfig, NonRigidAgents

            g, instance, rows = init["non-rigid"]
            wfb, valid = _track_poses(bundle, rows)
            nonrigid = NonRigidAgents(g, torch.as_tensor(instance), wfb, valid, torch.as_tensor(ids[rows]),
                                      config=deform or DeformConfig(), half_extents=_track_half_extents(bundle, rows))
        sky_node = None
        from agg.nodes.sky import SkyNode, has_sky

        if sky or (sky is None and has_sky(bundle)):
            sky_node = SkyNode.from_bundle(bundle, n=max(500, config.background_budget // 10), sh_degree=config.sh_degree)
        return cls(CameraNode(torch.as_tensor(bundle.world_from_camera)), init["background"],
                   torch.as_tensor(bundle.intrinsics), bundle.width, bundle.height, rigid, nonrigid, sky_node)

    def agent_nodes(self) -> list[RigidAgents]:
        return [n for n in (self.rigid, self.nonrigid) if n is not None]

    def slot_track_ids(self) -> Tensor:
        """[S] tracklet id of every agent slot (rigid instances, then non-rigid); node id = slot + 1."""
        ids = [n.track_ids for n in self.agent_nodes()]
        return torch.cat(ids) if ids else torch.zeros(0, dtype=torch.long)

    @property
    def num_agents(self) -> int:
        return sum(n.num_instances for n in self.agent_nodes())

    def static_parts(self) -> list[dict[str, Tensor]]:
        parts = [self.background.activated()]
        if self.sky is not None:
            parts.append(self.sky.compose())
        return parts

    def compose(self, frame: int, t: float | None = None, agent_poses: dict | None = None,
                agent_valid: dict | None = None) -> dict[str, Tensor]:
        """World Gaussians of every node at ``frame``: means, quats, scales, opacities, sh, node [N]."""
        parts = self.static_parts()
        nodes = [torch.zeros(len(p["means"]), dtype=torch.long, device=p["means"].device) for p in parts]
        offset = 1
        for node in self.agent_nodes():
            poses = valid = None
            if agent_poses or agent_valid:
                poses = node.world_from_box(frame).detach().clone() if agent_poses else None
                valid = node.valid[frame].clone()
                for j, tid in enumerate(node.track_ids.tolist()):
                    if agent_poses and tid in agent_poses:
                        poses[j] = torch.as_tensor(agent_poses[tid], dtype=poses.dtype)
                    if agent_valid and tid in agent_valid:
                        valid[j] = bool(agent_valid[tid])
                if poses is None:
                    poses = node.world_from_box(frame)
            parts.append(node.compose(frame, world_from_box=poses, valid=valid, t=t))
            nodes.append(node.instance + offset)
            offset += node.num_instances
        out = {k: torch.cat([p[k] for p in parts], 0) for k in KEYS}
        out["node"] = torch.cat(nodes, 0)
        return out

    def render(self, frame: int, world_from_camera: Tensor | None = None, K: Tensor | None = None,  # noqa: N803
               width: int | None = None, height: int | None = None, agent_poses: dict | None = None,
               agent_valid: dict | None = None, t: float | None = None, colors: Tensor | None = None, **kwargs):
        """``RenderOutput`` of the composed graph at ``frame`` through the refined camera of that frame (or the
        given ``world_from_camera`` / ``K`` / size). ``colors`` [N, C] replaces the SH colours (e.g. node ids)."""
        g = self.compose(frame, t=t, agent_poses=agent_poses, agent_valid=agent_valid)
        if world_from_camera is None:
            view = {"viewmat": self.camera.camera_from_world(torch.tensor([frame]))[0]}
        else:
            view = {"world_from_camera": torch.as_tensor(world_from_camera, dtype=torch.float32)}
        if K is None:
            K = intrinsics_at(self.K, frame)  # noqa: N806
        if colors is None:
            kwargs["sh"] = g["sh"]
        return rasterize(g["means"], g["quats"], g["scales"], g["opacities"], colors, K=K,
                         width=width or self.width, height=height or self.height, **view, **kwargs)

    def node_slices(self) -> dict[str, slice]:
        """Rows of each Gaussian set in ``compose`` order: background, sky, rigid, nonrigid."""
        out, start = {}, 0
        for name, n in (("background", len(self.background)),
                        ("sky", len(self.sky) if self.sky is not None else 0),
                        ("rigid", len(self.rigid.gaussians) if self.rigid is not None else 0),
                        ("nonrigid", len(self.nonrigid.gaussians) if self.nonrigid is not None else 0)):
            out[name] = slice(start, start + n)
            start += n
        return out

    def gaussian_sets(self) -> dict[str, GaussianParams]:
        """Every GaussianParams by node name (the densifier's keys)."""
        out = {"background": self.background}
        if self.sky is not None:
            out["sky"] = self.sky  # a GaussianParams with a centre and radius
        for name in ("rigid", "nonrigid"):
            node = getattr(self, name)
            if node is not None:
                out[name] = node.gaussians
        return out

    def num_gaussians(self) -> int:
        return sum(len(g) for g in self.gaussian_sets().values())

    def state(self) -> dict:
        """Tensors that rebuild the graph with ``from_state`` (sizes may differ from the initial graph)."""
        cam = self.camera
        return {"camera": {"prior": cam.prior.clone(), "omega": cam.omega.detach().clone(),
                           "tau": cam.tau.detach().clone(), "free": cam.free.clone()},
                "background": self.background.state(), "K": self.K.clone(), "width": self.width,
                "height": self.height,
                "rigid": self.rigid.state() if self.rigid is not None else None,
                "nonrigid": self.nonrigid.state() if self.nonrigid is not None else None,
                "sky": self.sky.state() if self.sky is not None else None}

    @classmethod
    def from_state(cls, state: dict) -> "SceneGraph":
        c = state["camera"]
        camera = CameraNode(c["prior"])
        with torch.no_grad():
            camera.omega.copy_(c["omega"])
            camera.tau.copy_(c["tau"])
            camera.free.copy_(c["free"])
        rigid = RigidAgents.from_state(state["rigid"]) if state.get("rigid") is not None else None
        nonrigid = sky = None
        if state.get("nonrigid") is not None:
            from agg.nodes.nonrigid import NonRigidAgents

            nonrigid = NonRigidAgents.from_state(state["nonrigid"])
        if state.get("sky") is not None:
            from agg.nodes.sky import SkyNode

            sky = SkyNode.from_state(state["sky"])
        return cls(camera, GaussianParams.from_state(state["background"]), state["K"], state["width"],
                   state["height"], rigid, nonrigid, sky)
