"""Densification and pruning of Gaussian parameter sets (3DGS adaptive density control, gsplat-style).

One ``Densifier`` serves every node of a scene graph; its statistics are kept per *key* (a node name such as
"background" or "rigid"). The training loop calls, for each key:

1. ``accumulate(key, grad2d, radii, visible, width, height)`` after ``loss.backward()``: ``grad2d`` [N, 2] is
   dL/dmeans2d of that node's rows (``RenderMeta.means2d.retain_grad()``), one call per rendered camera;
2. ``step(key, params, optimizer, iteration)`` after ``optimizer.step()``: at refine iterations it prunes, clones
   and splits, resizing the optimiser state with the rows, and returns ``src`` [N'] (the old row each new row came
   from) so the caller can carry per-row buffers (``instance = instance[src]``); ``None`` when no row changed.

What happens at a refine iteration (``refine_start < it < refine_stop``, ``it % refine_every == 0``):

- the mean screen-space gradient norm of each row since the last refine is computed in normalised units (the
  pixel gradient times half the image size, as gsplat and 3DGS do; ``grad_threshold`` 2e-4 is their default);
- prune: opacity < ``prune_opacity``; once ``it > size_prune_start``, also rows whose largest scale exceeds
  ``max_scale`` x extent (``oversize="prune"``) and rows whose largest screen radius since the last refine exceeds
  ``max_screen_fraction`` of the image's larger side. ``oversize="clamp"`` clamps the scales instead, at every
  refine. Each group (the whole set, or the ``groups`` [N] given to ``step``, e.g. an agent node's ``instance``)
  keeps at least ``min_gaussians_to_keep`` rows, the most opaque ones;
- grow: rows with a mean gradient above ``grad_threshold`` are cloned when their largest scale is at most
  ``split_scale`` x extent (an exact copy next to the original) and split otherwise (the parent is replaced by two
  children sampled from it, scales / ``split_shrink`` = 1.6);
- cap: a set never holds more than ``max_gaussians`` rows after a step: when growth would exceed it only the
  highest-gradient candidates grow, and a set already above it loses its least opaque rows;
- the statistics of the key are reset.

Every ``reset_every`` iterations before ``refine_stop`` the opacities are clamped to 2 x ``prune_opacity`` and their
Adam moments zeroed (3DGS's opacity reset). After ``refine_stop`` no row changes, but ``max_scale`` is still enforced
by clamping every ``refine_every`` iterations (scales keep growing while the loss falls, gsplat #613).

Optimiser state: kept rows keep their Adam moments; new rows (clones and both split children) start at zero, as in
3DGS and gsplat (``append_rows``); a split parent's moments are dropped with it. Splits draw their noise from a
CPU ``torch.Generator`` seeded from ``DensifyConfig.seed`` and saved by ``state_dict``, so a resumed run splits
exactly as an uninterrupted one, on any device.
"""

from __future__ import annotations

import logging
import math
from dataclasses import asdict, dataclass, replace

import torch
from torch import Tensor

from agg.nodes.gaussians import PARAM_NAMES, GaussianParams, append_rows, keep_rows
from agg.render.projection import quat_to_rotmat

log = logging.getLogger(__name__)
OVERSIZE_MODES = ("prune", "clamp")
STAT_NAMES = ("grad", "count", "radius")


def highest(score: Tensor, cap: int) -> Tensor:
    """[N] bool: the ``cap`` rows of highest ``score`` [N] (stable: the earlier row wins a tie)."""
    keep = torch.zeros(len(score), dtype=torch.bool, device=score.device)
    keep[torch.sort(score, descending=True, stable=True).indices[:cap]] = True
    return keep


@dataclass
class DensifyConfig:
    """Densification schedule and thresholds (sizes are fractions of the scene extent given to ``Densifier``)."""

    grad_threshold: float = 2e-4  # mean normalised screen-space gradient norm above which a row grows
    refine_start: int = 500  # refine at iterations strictly after this ...
    refine_stop: int = 15_000  # ... and strictly before this
    refine_every: int = 100
    reset_every: int = 3_000  # opacity reset period (0: never)
    prune_opacity: float = 0.005
    split_scale: float = 0.01  # largest scale / extent above which a growing row is split rather than cloned
    max_scale: float | None = 0.1  # largest scale / extent allowed (None: no limit)
    oversize: str = "prune"  # what happens to rows above max_scale: "prune" | "clamp"
    max_screen_fraction: float | None = 0.15  # largest screen radius / max(width, height) allowed (None: no limit)
    size_prune_start: int = 3_000  # size-based pruning only after this iteration (3DGS: the first opacity reset)
    max_gaussians: int = 1_000_000  # hard cap per parameter set (per key)
    min_gaussians_to_keep: int = 8  # per group, pruning never goes below this (nor below the group's size)
    split_shrink: float = 1.6
    seed: int = 0

    def __post_init__(self) -> None:
        if self.oversize not in OVERSIZE_MODES:
            raise ValueError(f"oversize must be one of {OVERSIZE_MODES}, got {self.oversize!r}")
        if self.refine_every < 0 or self.reset_every < 0:
            raise ValueError("refine_every and reset_every must be >= 0 (0 disables)")
        if self.max_gaussians < 0 or self.min_gaussians_to_keep < 0:
            raise ValueError("max_gaussians and min_gaussians_to_keep must be >= 0")
        if not (self.grad_threshold > 0 and self.split_scale > 0 and self.split_shrink > 1):
            raise ValueError("need grad_threshold > 0, split_scale > 0 and split_shrink > 1")
        if self.max_scale is not None and self.max_scale <= 0:
            raise ValueError(f"max_scale must be > 0 or None, got {self.max_scale}")
        if self.max_screen_fraction is not None and self.max_screen_fraction <= 0:
            raise ValueError(f"max_screen_fraction must be > 0 or None, got {self.max_screen_fraction}")

    def scaled(self, factor: float) -> "DensifyConfig":
        """The same schedule with every iteration milestone multiplied by ``factor`` (periods stay >= 1)."""
        if factor <= 0:
            raise ValueError(f"factor must be > 0, got {factor}")

        def period(v: int) -> int:
            return 0 if v == 0 else max(1, round(v * factor))

        return replace(self, refine_start=round(self.refine_start * factor),
                       refine_stop=round(self.refine_stop * factor), refine_every=period(self.refine_every),
                       reset_every=period(self.reset_every), size_prune_start=round(self.size_prune_start * factor))

    def is_refine(self, iteration: int) -> bool:
        return (self.refine_every > 0 and self.refine_start < iteration < self.refine_stop
                and iteration % self.refine_every == 0)

    def is_reset(self, iteration: int) -> bool:
        return self.reset_every > 0 and 0 < iteration < self.refine_stop and iteration % self.reset_every == 0


class Densifier:
    """Per-key screen-gradient statistics and the clone / split / prune / opacity-reset steps (module docstring)."""

    def __init__(self, config: DensifyConfig, scene_extent: float):
        if not scene_extent > 0:
            raise ValueError(f"scene_extent must be > 0, got {scene_extent}")
        self.config = config
        self.scene_extent = float(scene_extent)
        self.stats: dict[str, dict[str, Tensor]] = {}  # key -> grad [N], count [N], radius [N] (float32)
        self.last: dict[str, dict[str, int]] = {}  # key -> counts of the latest refine
        self.generator = torch.Generator().manual_seed(int(config.seed))

    # ----------------------------------------------------------------------------------------------- statistics
    def accumulate(self, key: str, grad2d: Tensor | None, radii: Tensor, visible: Tensor, width: int, height: int,
                   renders: int = 1) -> None:
        """Add one render's screen-space gradients of a key's rows.

        grad2d: [N, 2] dL/dmeans2d in px (None: all zero); radii: [N, 2] screen half extents in px; visible: [N]
        bool. Rows that are invisible, culled (radii 0) or have non-finite gradients do not count. ``renders``: how
        many renders the loss averages over (the gradients are multiplied by it, gsplat's ``n_cameras``).
        """
        n = radii.shape[0]
        if grad2d is None:
            grad2d = torch.zeros(n, 2, device=radii.device)
        if grad2d.shape != (n, 2) or radii.shape != (n, 2) or visible.shape != (n,):
            raise ValueError(f"need grad2d [N,2], radii [N,2], visible [N]; got {tuple(grad2d.shape)}, "
                             f"{tuple(radii.shape)}, {tuple(visible.shape)}")
        s = self._stats(key, n, grad2d.device)
        half = torch.tensor([0.5 * width * renders, 0.5 * height * renders], device=grad2d.device)
        norm = (grad2d.detach().float() * half).norm(dim=-1)  # [N] normalised gradient norm
        vis = visible.bool() & (radii > 0).any(-1) & torch.isfinite(norm)
        s["grad"] += torch.where(vis, norm, torch.zeros_like(norm))
        s["count"] += vis.float()
        frac = radii.detach().float().amax(-1) / float(max(width, height))  # [N]
        s["radius"] = torch.maximum(s["radius"], torch.where(vis, frac, torch.zeros_like(frac)))

    def mean_grad(self, key: str) -> Tensor | None:
        """[N] mean normalised gradient norm of a key's rows since the last refine (0 where never visible)."""
        s = self.stats.get(key)
        return None if s is None else s["grad"] / s["count"].clamp_min(1.0)

    def remap(self, key: str, src: Tensor) -> None:
        """Follow a row change made elsewhere (topology evolution): new row i takes the statistics of old row
        ``src[i]``, or zeros where ``src[i] < 0``."""
        s = self.stats.get(key)
        if s is None:
            return
        src = torch.as_tensor(src, dtype=torch.long, device=s["grad"].device)
        has = src >= 0
        self.stats[key] = {k: torch.where(has, v[src.clamp_min(0)], torch.zeros_like(v[src.clamp_min(0)]))
                           for k, v in s.items()}

    def forget(self, key: str) -> None:
        """Drop a key's statistics (e.g. when its node is removed)."""
        self.stats.pop(key, None)
        self.last.pop(key, None)

    def _stats(self, key: str, n: int, device: torch.device) -> dict[str, Tensor]:
        s = self.stats.get(key)
        if s is not None and s["grad"].shape[0] != n:
            log.warning("densify %r: %d rows but statistics for %d (rows changed without remap); statistics reset",
                        key, n, s["grad"].shape[0])
            s = None
        if s is None:
            s = {k: torch.zeros(n, dtype=torch.float32, device=device) for k in STAT_NAMES}
        elif s["grad"].device != torch.device(device):
            s = {k: v.to(device) for k, v in s.items()}
        self.stats[key] = s
        return s

    # ----------------------------------------------------------------------------------------------------- step
    def step(self, key: str, params: GaussianParams, optimizer: torch.optim.Optimizer | None, iteration: int,
             extent: float | None = None, groups: Tensor | None = None, reset_opacity: bool = True) -> Tensor | None:
        """Refine / reset a key's parameter set at this iteration (call after ``optimizer.step()``).

        extent: the size the scale thresholds are fractions of (default: the scene extent; e.g. an agent's box
        size). groups: [N] long, rows sharing a value form a group for ``min_gaussians_to_keep``.
        Returns ``src`` [N'] long (new row -> old row) when rows changed, else None.
        """
        cfg = self.config
        extent = self.scene_extent if extent is None else float(extent)
        src = None
        with torch.no_grad():
            if cfg.is_refine(iteration):
                src = self._refine(key, params, optimizer, iteration, extent, groups)
            elif (cfg.refine_every > 0 and iteration >= cfg.refine_stop and iteration % cfg.refine_every == 0
                  and cfg.max_scale is not None):
                self._clamp_scales(params, extent)
            if reset_opacity and cfg.is_reset(iteration):
                self.reset_opacity(params, optimizer)
        return src

    def _refine(self, key, params, optimizer, iteration, extent, groups) -> Tensor | None:
        cfg = self.config
        n = len(params)
        if n == 0:
            return None
        device = params.means.device
        s = self._stats(key, n, device)
        mean_grad = s["grad"] / s["count"].clamp_min(1.0)  # [N]
        opacity = torch.sigmoid(params.opacity_logits)  # [N]
        size_on = iteration > cfg.size_prune_start
        if cfg.max_scale is not None and cfg.oversize == "clamp":
            self._clamp_scales(params, extent)
        largest = params.log_scales.exp().amax(-1)  # [N]

        prune = opacity < cfg.prune_opacity
        if size_on and cfg.max_scale is not None and cfg.oversize == "prune":
            prune |= largest > cfg.max_scale * extent
        if size_on and cfg.max_screen_fraction is not None:
            prune |= s["radius"] > cfg.max_screen_fraction
        groups = torch.zeros(n, dtype=torch.long, device=device) if groups is None else \
            torch.as_tensor(groups, dtype=torch.long).to(device)
        if groups.shape != (n,):
            raise ValueError(f"groups must be [{n}], got {tuple(groups.shape)}")
        protected = _top_per_group(groups, ~prune, opacity, cfg.min_gaussians_to_keep)  # [N]
        keep = ~prune | protected
        if int(keep.sum()) > cfg.max_gaussians:  # over the cap already: drop the least opaque, protected last
            score = torch.where(keep, opacity + 2.0 * protected.float(), torch.full_like(opacity, -1.0))
            keep = highest(score, cfg.max_gaussians)

        grow = keep & ~prune & (s["count"] > 0) & (mean_grad > cfg.grad_threshold)
        budget = max(cfg.max_gaussians - int(keep.sum()), 0)
        cand = torch.nonzero(grow).squeeze(-1)  # [C]
        if cand.numel() > budget:  # the cap: only the highest-gradient candidates grow
            best = torch.sort(mean_grad[cand], descending=True, stable=True).indices[:budget]
            cand = torch.sort(cand[best]).values
        is_split = largest[cand] > cfg.split_scale * extent
        clone_idx, split_idx = cand[~is_split], cand[is_split]  # [Nc], [Ns]

        self.stats[key] = {k: torch.zeros_like(v) for k, v in s.items()}
        n_pruned = int((~keep).sum())
        self.last[key] = {"iteration": int(iteration), "cloned": int(clone_idx.numel()),
                          "split": int(split_idx.numel()), "pruned": n_pruned, "before": n}
        if n_pruned == 0 and cand.numel() == 0:
            self.last[key]["after"] = n
            return None
        new = _concat([_rows(params, clone_idx), self._split(params, split_idx)])
        append_rows(params, new, optimizer)
        not_split = torch.ones(n, dtype=torch.bool, device=device)
        not_split[split_idx] = False
        full_keep = torch.cat([keep & not_split, torch.ones(len(new), dtype=torch.bool, device=device)])
        keep_rows(params, full_keep, optimizer)
        src = torch.cat([torch.arange(n, device=device), clone_idx, split_idx, split_idx])[full_keep]
        self.stats[key] = {k: torch.zeros(len(src), dtype=torch.float32, device=device) for k in STAT_NAMES}
        self.last[key]["after"] = len(params)
        return src

    def _split(self, params: GaussianParams, idx: Tensor) -> GaussianParams:
        """Two children per parent row ``idx`` [M]: means sampled from the parent Gaussian, scales / split_shrink.
        Rows [0, M) are the first children, [M, 2M) the second ones."""
        m = idx.numel()
        parent = _rows(params, idx)
        scales = parent.log_scales.exp()  # [M, 3]
        rot = quat_to_rotmat(parent.quats)  # [M, 3, 3]
        noise = torch.randn(2, m, 3, generator=self.generator).to(scales)  # CPU draw: device-independent
        offsets = torch.einsum("mij,kmj->kmi", rot, noise * scales)  # [2, M, 3]
        means = (parent.means.unsqueeze(0) + offsets).reshape(2 * m, 3)
        log_scales = (scales / self.config.split_shrink).log().repeat(2, 1)
        return GaussianParams(means, log_scales, parent.quats.repeat(2, 1), parent.opacity_logits.repeat(2),
                              parent.sh.repeat(2, 1, 1))

    def _clamp_scales(self, params: GaussianParams, extent: float) -> None:
        """Clamp every scale axis to max_scale x extent (in place; the Adam moments are kept)."""
        params.log_scales.clamp_(max=math.log(self.config.max_scale * extent))

    def reset_opacity(self, params: GaussianParams, optimizer: torch.optim.Optimizer | None) -> None:
        """Opacities clamped to 2 x prune_opacity, their Adam moments zeroed (in place)."""
        p = params.opacity_logits
        value = min(2.0 * self.config.prune_opacity, 0.5)
        with torch.no_grad():
            p.clamp_(max=math.log(value / (1.0 - value)))
            state = optimizer.state.get(p) if optimizer is not None else None
            for v in (state or {}).values():
                if torch.is_tensor(v) and v.ndim > 0 and v.shape[:1] == p.shape[:1]:
                    v.zero_()

    # ----------------------------------------------------------------------------------------------- checkpoint
    def state_dict(self) -> dict:
        """Statistics, the split generator's state and the last refine counts (plus the config, for reference)."""
        return {"config": asdict(self.config), "scene_extent": self.scene_extent,
                "generator": self.generator.get_state(),
                "stats": {k: {n: v.detach().clone() for n, v in s.items()} for k, s in self.stats.items()},
                "last": {k: dict(v) for k, v in self.last.items()}}

    def load_state_dict(self, state: dict) -> None:
        """Restore ``state_dict()`` output; the config stays the one this Densifier was built with."""
        self.scene_extent = float(state["scene_extent"])
        self.generator.set_state(state["generator"].detach().cpu().clone())
        self.stats = {k: {n: v.detach().clone().float() for n, v in s.items()} for k, s in state["stats"].items()}
        self.last = {k: dict(v) for k, v in state.get("last", {}).items()}


def _rows(params: GaussianParams, idx: Tensor) -> GaussianParams:
    """A detached GaussianParams holding rows ``idx`` of ``params``."""
    return GaussianParams(*(getattr(params, n).detach()[idx] for n in PARAM_NAMES))


def _concat(sets: list[GaussianParams]) -> GaussianParams:
    return GaussianParams(*(torch.cat([getattr(p, n).detach() for p in sets], 0) for n in PARAM_NAMES))


def _top_per_group(groups: Tensor, kept: Tensor, opacity: Tensor, k: int) -> Tensor:
    """[N] bool: in each group, the first ``k`` rows ordered kept-first, then by decreasing opacity."""
    n = groups.numel()
    if k <= 0 or n == 0:
        return torch.zeros(n, dtype=torch.bool, device=groups.device)
    order = torch.sort(opacity, descending=True, stable=True).indices
    order = order[torch.sort((~kept[order]).to(torch.uint8), stable=True).indices]
    order = order[torch.sort(groups[order], stable=True).indices]
    _, counts = torch.unique_consecutive(groups[order], return_counts=True)
    starts = torch.cumsum(counts, 0) - counts
    rank = torch.arange(n, device=groups.device) - torch.repeat_interleave(starts, counts)
    out = torch.zeros(n, dtype=torch.bool, device=groups.device)
    out[order] = rank < k
    return out
