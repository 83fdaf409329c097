"""A set of 3D Gaussians as learnable parameters, their initialisation, and optimiser-state surgery.

Parameters are stored unconstrained (gsplat/3DGS convention): means [N, 3] (node frame), ``log_scales`` [N, 3],
``quats`` [N, 4] wxyz (raw, normalised where used), ``opacity_logits`` [N], ``sh`` [N, K, 3] with K = (d + 1)^2
(degree-0 coefficient ``(rgb - 0.5) / SH_C0``). ``activated()`` gives what ``agg.render.rasterize`` takes.

Adding and removing Gaussians (densification, pruning, topology evolution) must resize the optimiser state with
them, or Adam's moments stop matching their rows: ``keep_rows`` and ``append_rows`` do both at once.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor, nn

SH_C0 = 0.28209479177387814  # Y_0^0
PARAM_NAMES = ("means", "log_scales", "quats", "opacity_logits", "sh")


def rgb_to_sh0(rgb: Tensor) -> Tensor:
    """[N, 3] colours in [0, 1] -> [N, 3] degree-0 SH coefficients (colour = SH_C0 * c0 + 0.5)."""
    return (rgb - 0.5) / SH_C0


def knn_scales(xyz: np.ndarray, k: int = 3, min_scale: float = 1e-4, max_scale: float | None = None) -> np.ndarray:
    """[N] isotropic initial scales: the RMS distance to the k nearest other points, clamped.

    Duplicate points give a distance of 0, whose log is -inf (drivestudio #62): ``min_scale`` clamps it. An upper
    clamp (``max_scale``, e.g. a fraction of the scene extent) stops isolated points from becoming huge.
    """
    from sklearn.neighbors import NearestNeighbors

    xyz = np.asarray(xyz, np.float64)
    n = len(xyz)
    if n == 0:
        return np.zeros(0)
    if n == 1:
        return np.full(1, max_scale if max_scale is not None else 1.0)
    kk = min(k, n - 1)
    dist, _ = NearestNeighbors(n_neighbors=kk + 1).fit(xyz).kneighbors(xyz)  # [N, kk + 1], column 0 is self
    s = np.sqrt((dist[:, 1:] ** 2).mean(1))
    return np.clip(s, min_scale, max_scale if max_scale is not None else np.inf)


class GaussianParams(nn.Module):
    """N Gaussians in a node's own frame (world for the background, canonical for an agent)."""

    def __init__(self, means: Tensor, log_scales: Tensor, quats: Tensor, opacity_logits: Tensor, sh: Tensor):
        super().__init__()
        n = means.shape[0]
        if not (log_scales.shape == (n, 3) and quats.shape == (n, 4) and opacity_logits.shape == (n,)
                and sh.ndim == 3 and sh.shape[0] == n and sh.shape[2] == 3):
            raise ValueError("GaussianParams: means [N,3], log_scales [N,3], quats [N,4], opacity_logits [N], "
                             f"sh [N,K,3]; got {[tuple(t.shape) for t in (means, log_scales, quats, opacity_logits, sh)]}")
        for name, value in zip(PARAM_NAMES, (means, log_scales, quats, opacity_logits, sh)):
            setattr(self, name, nn.Parameter(value.detach().clone().float()))

    @classmethod
    def from_points(cls, xyz: np.ndarray, rgb: np.ndarray, sh_degree: int = 1, opacity: float = 0.1,
                    scales: np.ndarray | None = None, max_scale: float | None = None) -> "GaussianParams":
        """Isotropic Gaussians at points xyz [N, 3] with colours rgb [N, 3] in [0, 1]; scales [N] default to
        ``knn_scales`` (clamped); identity rotations; higher SH bands zero."""
        if not 0 <= sh_degree <= 3:
            raise ValueError(f"sh_degree must be 0..3, got {sh_degree}")
        if not 0 < opacity < 1:
            raise ValueError(f"opacity must be in (0, 1), got {opacity}")
        xyz_t = torch.as_tensor(np.asarray(xyz, np.float32)).reshape(-1, 3)
        n = xyz_t.shape[0]
        s = knn_scales(xyz, max_scale=max_scale) if scales is None else np.asarray(scales, np.float64)
        log_s = torch.as_tensor(np.log(s), dtype=torch.float32)[:, None].repeat(1, 3)
        quats = torch.zeros(n, 4)
        quats[:, 0] = 1.0
        sh = torch.zeros(n, (sh_degree + 1) ** 2, 3)
        sh[:, 0] = rgb_to_sh0(torch.as_tensor(np.asarray(rgb, np.float32)).reshape(-1, 3))
        logit = torch.full((n,), math.log(opacity / (1 - opacity)))
        return cls(xyz_t, log_s, quats, logit, sh)

    def __len__(self) -> int:
        return int(self.means.shape[0])

    def state(self) -> dict[str, Tensor]:
        """Detached parameters by name (``from_state`` rebuilds the set, whatever its size)."""
        return {n: getattr(self, n).detach().clone() for n in PARAM_NAMES}

    @classmethod
    def from_state(cls, state: dict[str, Tensor]) -> "GaussianParams":
        return cls(*(torch.as_tensor(state[n]) for n in PARAM_NAMES))

    @classmethod
    def empty(cls, sh_degree: int = 1) -> "GaussianParams":
        return cls(torch.zeros(0, 3), torch.zeros(0, 3), torch.zeros(0, 4), torch.zeros(0),
                   torch.zeros(0, (sh_degree + 1) ** 2, 3))

    @property
    def sh_degree(self) -> int:
        return int(round(math.sqrt(self.sh.shape[1]))) - 1

    def activated(self) -> dict[str, Tensor]:
        """means [N,3], quats [N,4] (normalised, zero-safe), scales [N,3], opacities [N], sh [N,K,3]."""
        q = self.quats / self.quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        return {"means": self.means, "quats": q, "scales": self.log_scales.exp(),
                "opacities": torch.sigmoid(self.opacity_logits), "sh": self.sh}

    def param_groups(self, prefix: str, lrs: dict[str, float]) -> list[dict]:
        """Optimiser groups named ``prefix#param`` (drivestudio's ``Class#component``) with the given lrs."""
        return [{"name": f"{prefix}#{n}", "params": [getattr(self, n)], "lr": float(lrs[n])} for n in PARAM_NAMES]


def swap_param(optimizer: torch.optim.Optimizer | None, old: nn.Parameter, new: nn.Parameter, rows) -> None:
    """Point the optimiser at ``new`` and carry over its state through ``rows(state_tensor)`` (any tensor state
    whose first dimension matches ``old``'s, e.g. Adam's moments; scalars such as ``step`` are kept)."""
    if optimizer is None:
        return
    for group in optimizer.param_groups:
        for i, p in enumerate(group["params"]):
            if p is old:
                group["params"][i] = new
                state = optimizer.state.pop(old, None)
                if state is not None:
                    optimizer.state[new] = {k: rows(v) if torch.is_tensor(v) and v.shape[:1] == old.shape[:1]
                                            and v.ndim > 0 else v for k, v in state.items()}


def keep_rows(params: GaussianParams, keep: Tensor, optimizer: torch.optim.Optimizer | None = None) -> None:
    """Keep the Gaussians where ``keep`` [N] (bool) is True, in the parameters and the optimiser state."""
    keep = keep.to(torch.bool)
    if keep.shape != (len(params),):
        raise ValueError(f"keep must be [{len(params)}] bool, got {tuple(keep.shape)}")
    for name in PARAM_NAMES:
        old = getattr(params, name)
        new = nn.Parameter(old.detach()[keep].clone())
        swap_param(optimizer, old, new, lambda v: v[keep].clone())
        setattr(params, name, new)


def append_rows(params: GaussianParams, other: GaussianParams,
                optimizer: torch.optim.Optimizer | None = None) -> None:
    """Append the Gaussians of ``other`` (same SH degree); their optimiser moments start at zero."""
    if other.sh.shape[1:] != params.sh.shape[1:]:
        raise ValueError(f"SH shapes differ: {tuple(other.sh.shape[1:])} vs {tuple(params.sh.shape[1:])}")
    for name in PARAM_NAMES:
        old, extra = getattr(params, name), getattr(other, name).detach()
        new = nn.Parameter(torch.cat([old.detach(), extra.to(old)], 0))
        swap_param(optimizer, old, new, lambda v, e=extra: torch.cat([v, torch.zeros_like(e).to(v)], 0))
        setattr(params, name, new)
