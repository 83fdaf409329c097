"""Rigid agent nodes: canonical Gaussians per instance plus per-frame poses [T, K] and a frame-validity mask.

All rigid instances share one ``GaussianParams`` (canonical box frame, docs/BUNDLE.md box axes) with an
``instance`` index [N]. Each instance k has a pose prior ``world_from_box`` [T, K, 4, 4] (from the tracklets) and
learnable per-frame corrections ``omega`` [T, K, 3] (so(3), box frame) and ``tau`` [T, K, 3] (box frame), zero at
the start: ``world_from_box = prior @ [exp(omega) | tau]``. ``valid`` [T, K] says where an instance exists; in
other frames its Gaussians get opacity 0 (drivestudio's validity mask), so they neither render nor receive
gradients. ``half_extents`` [K, 3] is each instance's box (half length, height, width along the box axes; +inf
where unknown): ``confine`` keeps the canonical means inside it, grown by a margin, so that an agent models its
object and not the road or the scene around it.

An instance can also carry a track-speed correction ``rate`` [K] (``speed_free`` [K] says which; zero and
fixed for the others): its prior translations are scaled about their mean over the valid frames,
``p_t + rate (p_t - p_ref)``, before the per-frame correction. Topology evolution frees it for the agents it
spawns: their prior is a Kalman track of gradient clusters, and on seed 2 of the synthetic suite it ran 6 % too
fast, so the box fell 0.4 m to 1.45 m ahead of the car over 23 frames. A per-frame ``tau`` is trained only when its
frame is drawn (about 26 Tock steps each), which moves it a few centimetres; every frame's step trains ``rate``.
A constant shift along the track is not learnable this way (it is the gauge between the box origin and the
canonical Gaussians, ``topology_anchor``), but a wrong speed is: no canonical shift renders it.

An instance can be anchored to the camera (``anchored`` [K]): a tracklet that the priors lifted into the world
through their estimated cameras carries each frame's camera error, so when the camera node corrects frame t, the
box moves with it: ``world_from_box = D_t @ prior @ corr``, with ``D_t = world_from_camera_t @ inv(prior_t)`` the
camera node's correction in world coordinates (``camera_delta``, which the scene graph sets). The box then keeps
its place in the frame's view whatever the camera does, so its pixels neither pull the camera nor fall off their
object when the background moves the camera. Unanchored instances (the default) keep their world poses.
"""

from __future__ import annotations

import torch
from kornia.geometry.liegroup import So3
from torch import Tensor, nn

from agg.nodes.gaussians import GaussianParams, append_rows, keep_rows, swap_param


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

    def __init__(self, gaussians: GaussianParams, instance: Tensor, world_from_box: Tensor, valid: Tensor,
                 track_ids: Tensor | None = None, half_extents: Tensor | None = None):
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
        ids = torch.arange(k) if track_ids is None else torch.as_tensor(track_ids, dtype=torch.long).reshape(-1)
        if ids.shape != (k,):
            raise ValueError(f"track_ids must be [{k}]")
        self.register_buffer("track_ids", ids.clone())  # [K] the tracklet id of each instance
        self.register_buffer("half_extents", _half_extents(half_extents, k))  # [K, 3] box half sizes (inf: unknown)
        self.rate = nn.Parameter(torch.zeros(k))  # [K] track-speed correction (module doc)
        self.register_buffer("speed_free", torch.zeros(k, dtype=torch.bool))  # [K] where ``rate`` applies
        self.register_buffer("rate_ref", _rate_ref(self.prior, valid))  # [K, 3] mean valid prior translation
        self.register_buffer("anchored", torch.zeros(k, dtype=torch.bool))  # [K] poses follow the camera node
        self.camera_delta = None  # frame -> [4, 4] the camera node's correction in world coordinates (SceneGraph)

    @property
    def num_instances(self) -> int:
        return int(self.prior.shape[1])

    @property
    def num_frames(self) -> int:
        return int(self.prior.shape[0])

    def world_from_box(self, frame: int) -> Tensor:
        """[K, 4, 4] refined poses of every instance at an integer frame."""
        corr = torch.eye(4, device=self.prior.device).repeat(self.num_instances, 1, 1)
        corr[:, :3, :3] = So3.exp(self.omega[frame]).matrix()
        corr[:, :3, 3] = self.tau[frame]
        out = self.prior[frame] @ corr  # [K, 4, 4]
        if not bool(self.speed_free.any()):
            return self._anchor(frame, out)
        rate = self.rate * (self.speed_free & self.valid[frame]).to(self.rate)  # [K] (invalid: prior is eye)
        shift = rate[:, None] * (self.prior[frame, :, :3, 3] - self.rate_ref)  # [K, 3]
        # [R | t + s] @ [Rc | tc] = prior @ corr + s in the translation column
        return self._anchor(frame, out + torch.nn.functional.pad(shift[..., None], (3, 0, 0, 1)))

    def _anchor(self, frame: int, poses: Tensor) -> Tensor:
        """``poses`` [K, 4, 4] with the anchored instances' moved by the camera node's correction at ``frame``."""
        if self.camera_delta is None or not bool(self.anchored.any()):
            return poses
        delta = self.camera_delta(frame).to(poses)  # [4, 4]
        return torch.where(self.anchored[:, None, None], delta @ poses, poses)

    def canonical(self, frame: int, t: float) -> dict[str, Tensor]:
        """Canonical-frame Gaussians at a frame / continuous time (a non-rigid node adds its deformation)."""
        return self.gaussians.activated()

    def compose(self, frame: int, world_from_box: Tensor | None = None, valid: Tensor | None = None,
                t: float | None = None) -> dict[str, Tensor]:
        """World-frame Gaussians at ``frame`` (the renderer's arguments); invalid instances get opacity 0.

        ``world_from_box`` [K, 4, 4] and ``valid`` [K] override the node's own poses and validity (interpolated
        poses of a held-out frame, a simulator's per-request agent overrides); ``t`` in [0, 1] is the continuous
        time (default ``frame / (T - 1)``)."""
        if t is None:
            t = frame / max(self.num_frames - 1, 1)
        g = self.canonical(frame, t)
        poses = self.world_from_box(frame) if world_from_box is None else world_from_box
        poses = poses.to(g["means"])  # [K, 4, 4]
        rot = poses[:, :3, :3][self.instance]  # [N, 3, 3]
        means = (rot @ g["means"][..., None])[..., 0] + poses[:, :3, 3][self.instance]  # [N, 3]
        quats = quat_multiply(matrix_to_quat(poses[:, :3, :3])[self.instance], g["quats"])  # [N, 4]
        valid = self.valid[frame] if valid is None else torch.as_tensor(valid, dtype=torch.bool)
        opacities = g["opacities"] * valid.to(g["opacities"].device)[self.instance].to(g["opacities"])
        # view-dependent colour: SH is defined in the canonical frame; evaluating it in world directions is the
        # usual approximation (3DGS agents, OmniRe) and exact for degree 0
        return {"means": means, "quats": quats, "scales": g["scales"], "opacities": opacities, "sh": g["sh"]}

    def param_groups(self, prefix: str, gaussian_lrs: dict[str, float], pose_lr: float,
                     rotation_lr: float | None = None, rate_lr: float = 0.0) -> list[dict]:
        """``prefix#means`` ... for the Gaussians, ``prefix#omega`` (rotation, at ``rotation_lr``; ``pose_lr`` when
        None) / ``prefix#tau`` (translation, at ``pose_lr``) for the poses, ``prefix#rate`` (the track-speed
        correction, at ``rate_lr``; it only moves where ``speed_free``)."""
        return self.gaussians.param_groups(prefix, gaussian_lrs) + [
            {"name": f"{prefix}#omega", "params": [self.omega],
             "lr": float(pose_lr if rotation_lr is None else rotation_lr)},
            {"name": f"{prefix}#tau", "params": [self.tau], "lr": float(pose_lr)},
            {"name": f"{prefix}#rate", "params": [self.rate], "lr": float(rate_lr)}]

    def pose_params(self) -> list[nn.Parameter]:
        """Parameters with a per-instance axis 1 ([T, K, ...]); ``add_instances`` / ``remove_instances`` resize them."""
        return [self.omega, self.tau]

    def confine(self, margin: float, instances: Tensor | None = None) -> None:
        """Clamp every canonical mean into its instance's box grown by ``margin`` (a fraction of the half extents),
        in place; instances of unknown size are left free. Called after each optimiser step on the agents: a
        projected gradient step, so no Gaussian can drift out to model the road beside or under its agent.
        ``instances`` [k] (instance indices): only their Gaussians (topology evolution puts a spawn into its box)."""
        lim = (self.half_extents * (1.0 + margin))[self.instance]  # [N, 3]
        if instances is not None:  # the others' limits open up
            lim = torch.where(torch.isin(self.instance, instances.to(self.instance))[:, None], lim, torch.inf)
        if len(lim) and torch.isfinite(lim).any():
            with torch.no_grad():
                means = self.gaussians.means
                means.copy_(torch.maximum(torch.minimum(means, lim), -lim))

    def add_instances(self, gaussians: GaussianParams, instance: Tensor, world_from_box: Tensor, valid: Tensor,
                      track_ids: Tensor, optimizer: torch.optim.Optimizer | None = None,
                      half_extents: Tensor | None = None, speed_free: bool = False) -> None:
        """Append k instances: their canonical Gaussians with local ``instance`` [M] in 0..k-1, pose priors
        ``world_from_box`` [T, k, 4, 4], ``valid`` [T, k], ``track_ids`` [k] and box ``half_extents`` [k, 3]
        (None: unknown); new rows start with zero corrections and zero optimiser moments. ``speed_free``: their
        track-speed correction is trained (module doc)."""
        wfb = torch.as_tensor(world_from_box, dtype=torch.float32).to(self.prior)
        valid = torch.as_tensor(valid, dtype=torch.bool).to(self.valid.device)
        k_new = wfb.shape[1]
        if wfb.shape != (self.num_frames, k_new, 4, 4) or valid.shape != (self.num_frames, k_new):
            raise ValueError(f"world_from_box must be [{self.num_frames}, k, 4, 4] and valid [{self.num_frames}, k]")
        k0 = self.num_instances
        append_rows(self.gaussians, gaussians, optimizer)
        self.instance = torch.cat([self.instance, torch.as_tensor(instance, dtype=torch.long).to(self.instance) + k0])
        self.prior = torch.cat([self.prior, torch.where(valid[..., None, None], wfb, torch.eye(4).to(wfb))], 1)
        self.valid = torch.cat([self.valid, valid], 1)
        self.track_ids = torch.cat([self.track_ids, torch.as_tensor(track_ids, dtype=torch.long).reshape(-1)])
        self.half_extents = torch.cat([self.half_extents, _half_extents(half_extents, k_new).to(self.half_extents)])
        new_prior = self.prior[:, k0:]
        self.rate_ref = torch.cat([self.rate_ref, _rate_ref(new_prior, valid).to(self.rate_ref)])
        self.speed_free = torch.cat([self.speed_free, torch.full((k_new,), bool(speed_free)).to(self.speed_free)])
        self.anchored = torch.cat([self.anchored, self.anchored.new_zeros(k_new)])  # a spawn's track is the map's
        self._resize_instances(optimizer, lambda v: torch.cat([v, v.new_zeros(v.shape[0], k_new, *v.shape[2:])], 1))

    def remove_instances(self, keep: Tensor, optimizer: torch.optim.Optimizer | None = None) -> None:
        """Keep the instances where ``keep`` [K] is True (their Gaussians, poses and optimiser state)."""
        keep = torch.as_tensor(keep, dtype=torch.bool).to(self.valid.device)
        if keep.shape != (self.num_instances,):
            raise ValueError(f"keep must be [{self.num_instances}] bool")
        keep_rows(self.gaussians, keep[self.instance], optimizer)
        new_index = torch.cumsum(keep.long(), 0) - 1  # [K] old instance -> new
        self.instance = new_index[self.instance[keep[self.instance]]]
        self.prior, self.valid, self.track_ids = self.prior[:, keep], self.valid[:, keep], self.track_ids[keep]
        self.half_extents = self.half_extents[keep]
        self.rate_ref, self.speed_free, self.anchored = self.rate_ref[keep], self.speed_free[keep], self.anchored[keep]
        self._resize_instances(optimizer, lambda v: v[:, keep].clone())

    def _resize_instances(self, optimizer, fn) -> None:
        for name in ("omega", "tau"):
            old = getattr(self, name)
            new = nn.Parameter(fn(old.detach()))
            swap_param(optimizer, old, new, fn)
            setattr(self, name, new)
        rows = lambda v: fn(v[None])[0]  # noqa: E731  [K] through the [T, K, ...] rule
        new = nn.Parameter(rows(self.rate.detach()))
        swap_param(optimizer, self.rate, new, rows)
        self.rate = new
        self._resize_extra(optimizer, fn)

    def _resize_extra(self, optimizer, fn) -> None:
        """Hook for subclasses with more per-instance parameters."""

    def state(self) -> dict:
        """Tensors that rebuild the node with ``from_state`` (whatever its size)."""
        return {"gaussians": self.gaussians.state(), "instance": self.instance.clone(), "prior": self.prior.clone(),
                "valid": self.valid.clone(), "track_ids": self.track_ids.clone(),
                "half_extents": self.half_extents.clone(),
                "omega": self.omega.detach().clone(), "tau": self.tau.detach().clone(),
                "rate": self.rate.detach().clone(), "speed_free": self.speed_free.clone(),
                "rate_ref": self.rate_ref.clone(), "anchored": self.anchored.clone()}

    def load_pose_state(self, state: dict) -> None:
        """Copy the learnt pose corrections of ``state`` (checkpoints before the track-speed correction: none)."""
        with torch.no_grad():
            self.omega.copy_(state["omega"])
            self.tau.copy_(state["tau"])
            if "rate" in state:
                self.rate.copy_(state["rate"])
                self.speed_free.copy_(state["speed_free"])
                self.rate_ref.copy_(state["rate_ref"])
            if "anchored" in state:  # checkpoints before camera anchoring: none anchored
                self.anchored.copy_(state["anchored"])

    @classmethod
    def from_state(cls, state: dict) -> "RigidAgents":
        node = cls(GaussianParams.from_state(state["gaussians"]), state["instance"], state["prior"], state["valid"],
                   state["track_ids"], state.get("half_extents"))  # checkpoints before boxes: sizes unknown
        node.load_pose_state(state)
        return node


def _rate_ref(prior: Tensor, valid: Tensor) -> Tensor:
    """[K, 3] mean prior translation of each instance over its valid frames (prior [T, K, 4, 4], valid [T, K])."""
    w = valid.to(prior)[..., None]  # [T, K, 1]
    return (prior[..., :3, 3] * w).sum(0) / w.sum(0).clamp_min(1.0)


def _half_extents(half: Tensor | None, k: int) -> Tensor:
    """[k, 3] float32 box half extents (+inf rows where ``half`` is None or not finite and positive)."""
    if half is None:
        return torch.full((k, 3), float("inf"))
    h = torch.as_tensor(half, dtype=torch.float32).reshape(k, 3).clone()
    bad = ~(torch.isfinite(h) & (h > 0)).all(-1)
    h[bad] = float("inf")
    return h
