"""Non-rigid agent nodes (pedestrians, cyclists): canonical Gaussians per instance deformed by a small MLP.

Paper Eq. 2 (OmniRe's deformable node): ``G(t) = T_a(t) ⊗ (G_canon ⊕ F_phi(t))``. ``NonRigidAgents`` is a
``RigidAgents`` (canonical Gaussians in the box frame, per-frame box poses with learnable corrections, validity
mask) whose ``canonical(frame, t)`` first applies a deformation field

    F_phi(gamma(x_canon), gamma(t), e_k) -> (dmu [N, 3], dq [N, 4] wxyz unit quaternion, ds [N, 3] log-scale)

with ``gamma`` a Fourier positional encoding, ``x_canon`` the canonical mean of each Gaussian, ``t`` in [0, 1]
the continuous clip time (held-out frames included) and ``e_k`` [E] a learnable embedding of the Gaussian's
instance k. The deformed Gaussian is ``mu + dmu``, ``normalise(dq ⊗ q)``, ``exp(log_s + ds)``; opacity and
colour are not deformed. The MLP's last layer is zero-initialised, so a new node is exactly its canonical
Gaussians (dq = identity), and gradients reach the hidden layers and the embeddings from the first optimiser step
on (the zero head passes none before it moves).

Adding and removing instances resizes the embedding table ``embeddings`` [K, E] with its Adam moments, like the
pose corrections; the MLP is shared by all instances and keeps its size.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch
from torch import Tensor, nn

from agg.nodes.gaussians import GaussianParams, swap_param
from agg.nodes.rigid import RigidAgents, quat_multiply


@dataclass(frozen=True)
class DeformConfig:
    """The deformation MLP: ``depth`` hidden layers of ``width`` ReLU units on the encoded (x, t, embedding)."""

    width: int = 64
    depth: int = 3
    embed_dim: int = 16  # E, per-instance latent code
    pos_freqs: int = 6  # Fourier bands of x: sin/cos(2^k pi x / pos_scale), k < pos_freqs
    time_freqs: int = 6  # Fourier bands of t in [0, 1]
    pos_scale: float = 1.0  # metres mapped to 1 before encoding (about a pedestrian's half height)
    embed_std: float = 0.1  # initial embeddings ~ N(0, embed_std^2)
    seed: int = 0  # initial MLP weights and embeddings

    def __post_init__(self) -> None:
        if min(self.width, self.depth, self.embed_dim) < 1 or min(self.pos_freqs, self.time_freqs) < 0 \
                or self.pos_scale <= 0 or self.embed_std < 0:
            raise ValueError(f"DeformConfig: width, depth, embed_dim >= 1, freqs >= 0, pos_scale > 0; got {self}")

    @property
    def in_dim(self) -> int:
        return 3 * (1 + 2 * self.pos_freqs) + (1 + 2 * self.time_freqs) + self.embed_dim


def fourier_encode(x: Tensor, n_freqs: int) -> Tensor:
    """[..., D] -> [..., D (1 + 2 n_freqs)]: x, sin(2^k pi x), cos(2^k pi x) for k < n_freqs."""
    if n_freqs == 0:
        return x
    freqs = math.pi * 2.0 ** torch.arange(n_freqs, dtype=x.dtype, device=x.device)  # [F]
    arg = (x[..., None] * freqs).flatten(-2)  # [..., D F]
    return torch.cat([x, arg.sin(), arg.cos()], -1)


class DeformationField(nn.Module):
    """F_phi: (x_canon [N, 3], t scalar, embedding [N, E]) -> (dmu [N, 3], dq [N, 4] unit wxyz, ds [N, 3])."""

    def __init__(self, config: DeformConfig = DeformConfig()):
        super().__init__()
        self.config = config
        layers: list[nn.Module] = []
        d = config.in_dim
        for _ in range(config.depth):
            layers += [nn.Linear(d, config.width), nn.ReLU()]
            d = config.width
        self.hidden = nn.Sequential(*layers)
        self.head = nn.Linear(d, 10)  # dmu 3, dq 4, ds 3
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)

    def forward(self, x: Tensor, t: float | Tensor, embedding: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        cfg = self.config
        n = x.shape[0]
        tt = torch.as_tensor(t, dtype=x.dtype, device=x.device).reshape(1, 1).expand(n, 1)  # [N, 1]
        feats = torch.cat([fourier_encode(x / cfg.pos_scale, cfg.pos_freqs), fourier_encode(tt, cfg.time_freqs),
                           embedding.to(x)], -1)  # [N, in_dim]
        out = self.head(self.hidden(feats))  # [N, 10]
        identity = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=x.dtype, device=x.device)
        dq = identity + out[:, 3:7]
        dq = dq / dq.norm(dim=-1, keepdim=True).clamp_min(1e-12)  # [N, 4]
        return out[:, :3], dq, out[:, 7:10]


class NonRigidAgents(RigidAgents):
    """K non-rigid instances: ``RigidAgents`` plus a shared ``DeformationField`` and per-instance embeddings."""

    def __init__(self, gaussians: GaussianParams, instance: Tensor, world_from_box: Tensor, valid: Tensor,
                 track_ids: Tensor | None = None, config: DeformConfig = DeformConfig(),
                 half_extents: Tensor | None = None):
        super().__init__(gaussians, instance, world_from_box, valid, track_ids, half_extents)
        self.config = config
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(config.seed)
            self.deform = DeformationField(config)
            self.embeddings = nn.Parameter(torch.randn(self.num_instances, config.embed_dim) * config.embed_std)

    def deformation(self, t: float | Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """(dmu [N, 3], dq [N, 4], ds [N, 3]) of every Gaussian at continuous time t in [0, 1]."""
        means = self.gaussians.means
        return self.deform(means, t, self.embeddings[self.instance.to(means.device)])

    def canonical(self, frame: int, t: float | Tensor) -> dict[str, Tensor]:
        """Deformed canonical-frame Gaussians at continuous time ``t`` (``frame`` is unused: the deformation is
        a function of time only, so held-out frames work)."""
        g = self.gaussians.activated()
        if len(self.gaussians) == 0:
            return g
        dmu, dq, ds = self.deformation(t)
        q = quat_multiply(dq, g["quats"])  # [N, 4]
        return {"means": g["means"] + dmu, "quats": q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12),
                "scales": (self.gaussians.log_scales + ds).exp(), "opacities": g["opacities"], "sh": g["sh"]}

    def param_groups(self, prefix: str, gaussian_lrs: dict[str, float], pose_lr: float,
                     deform_lr: float = 1e-3, rotation_lr: float | None = None, rate_lr: float = 0.0) -> list[dict]:
        """The rigid groups plus ``prefix#deform`` (the MLP's weights and the instance embeddings)."""
        return super().param_groups(prefix, gaussian_lrs, pose_lr, rotation_lr, rate_lr) + [
            {"name": f"{prefix}#deform", "params": [*self.deform.parameters(), self.embeddings],
             "lr": float(deform_lr)}]

    def _resize_extra(self, optimizer, fn) -> None:
        """Resize ``embeddings`` [K, E] as ``fn`` resizes axis 1 of [T, K, ...]; new rows get fresh codes."""
        old = self.embeddings
        rows = lambda v: fn(v[None])[0]  # noqa: E731  [K, E] through the [T, K, ...] rule
        data = rows(old.detach())
        k_old = old.shape[0]
        if data.shape[0] > k_old:  # appended instances: fn pads zeros; give them random codes (zero moments)
            data[k_old:] = torch.randn(data.shape[0] - k_old, data.shape[1]).to(data) * self.config.embed_std
        new = nn.Parameter(data)
        swap_param(optimizer, old, new, rows)
        self.embeddings = new

    def state(self) -> dict:
        """The rigid state plus ``deform``: config, MLP weights and embeddings."""
        out = super().state()
        out["deform"] = {"config": asdict(self.config),
                         "mlp": {k: v.detach().clone() for k, v in self.deform.state_dict().items()},
                         "embeddings": self.embeddings.detach().clone()}
        return out

    @classmethod
    def from_state(cls, state: dict) -> "NonRigidAgents":
        d = state["deform"]
        node = cls(GaussianParams.from_state(state["gaussians"]), state["instance"], state["prior"], state["valid"],
                   state["track_ids"], DeformConfig(**d["config"]), state.get("half_extents"))
        node.deform.load_state_dict(d["mlp"])
        node.load_pose_state(state)
        with torch.no_grad():
            node.embeddings.copy_(d["embeddings"])
        return node
