"""Demotion of false agents (the pruning half of Algorithm 1 for agents that do not die out).

The paper prunes an agent "whose opacity dies out". A false agent placed on empty road does not die: its Gaussians
are initialised from the road points inside its box, and they keep explaining the road, so their opacity stays
high (measured on the synthetic suite: the planted false car kept a 0.9-quantile opacity near 1). What gives it
away is that it is an agent only in name: it never moves, and what it renders does not look like an agent.

An instance is **demoted** when both hold over its valid frames:

- **static**: its refined box centre stays within ``static_m`` metres of its median position (a moving car can
  never be demoted, whatever its features say);
- **not agent-like**: of its Gaussians in view (in the image of the refined camera and, where there is prior depth,
  not behind the observed surface by more than ``surface_tolerance``, so a Gaussian hidden behind another object
  reads no feature), fewer than ``agent_fraction`` read an agent-like feature (``topology_track.agent_like``, the
  same test that selects spawn candidates). Only frames where those Gaussians cover at least ``min_cells`` cells of
  the low-resolution feature map count: a far or mostly hidden car covers a cell or two whose features are blended
  with its surroundings (measured: a parked car showing 7 pixels read 0 % agent-like), which is no evidence either
  way. An instance with no such frame is kept.

A demoted instance's Gaussians are not deleted: they move to the background in world coordinates (composed at its
middle valid frame), so the pixels it explained keep rendering and only the graph's topology changes. A parked
car with agent-like features stays an agent; a parked car with weak features would become background, which
renders the same because it does not move.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from agg.nodes.gaussians import GaussianParams
from agg.train import topology_track as tt


@dataclass(frozen=True)
class DemoteConfig:
    enabled: bool = True
    static_m: float = 1.0  # metres: max distance of the box centre to its median over the valid frames
    agent_fraction: float = 0.25  # demoted below this fraction of agent-like visible Gaussians
    min_cells: int = 6  # a frame is evidence when the visible Gaussians cover this many feature cells


def static_instances(centres: np.ndarray, valid: np.ndarray, radius: float) -> np.ndarray:
    """centres [T, K, 3] (box centres), valid [T, K] -> [K] bool: within ``radius`` of the median over the valid
    frames (an instance with no valid frame is not static: there is nothing to judge)."""
    out = np.zeros(centres.shape[1], bool)
    for k in range(centres.shape[1]):
        c = centres[valid[:, k], k]  # [V, 3]
        if len(c):
            out[k] = bool(np.linalg.norm(c - np.median(c, 0), axis=1).max() <= radius)
    return out


def agent_like_fraction(means_by_frame: list[np.ndarray], camera_from_world: np.ndarray, K: np.ndarray,  # noqa: N803
                        features: np.ndarray, bank: dict, tau_sem: float, width: int, height: int, near: float,
                        depth: np.ndarray | None, surface_tolerance: float, min_cells: int) -> tuple[float, int]:
    """(fraction of agent-like samples, number of frames judged) of one instance over its valid frames; a frame
    is judged when its visible samples cover at least ``min_cells`` feature cells.

    means_by_frame[i]: world means [N, 3] of the instance at frame ``frames[i]``; camera_from_world [F, 4, 4],
    K [F, 3, 3], features [F, h, w, C] and depth [F, H, W] (or None) of the same frames."""
    hits, total, judged = 0, 0, 0
    h, w = features.shape[1:3]
    for i, means in enumerate(means_by_frame):
        uv, z, vis = tt.project(means, camera_from_world[i], K[i], width, height, near)
        if depth is not None:
            d = tt.depth_at(depth[i], uv, width, height)
            vis &= (d <= 0) | (z <= d * (1 + surface_tolerance))  # not hidden behind the observed surface
        cells = np.unique(np.floor((uv[vis] + 0.5) * np.array([w / width, h / height])).astype(np.int64), axis=0)
        if len(cells) < min_cells:
            continue
        feats = tt.sample_features(features[i], uv[vis], width, height)
        ag, _ = tt.agent_like(feats, bank, tau_sem)
        hits, total, judged = hits + int(ag.sum()), total + int(vis.sum()), judged + 1
    return (hits / total if total else 1.0), judged


def composed(node, instance: int, frame: int) -> dict:
    """One instance's Gaussians composed in world coordinates at ``frame`` (activated values, no gradient)."""
    with torch.no_grad():
        g = node.compose(frame, valid=torch.ones(node.num_instances, dtype=torch.bool))
    sel = node.instance == instance  # [N]
    return {k: v[sel] for k, v in g.items()}


def world_rows(node, instance: int, frame: int) -> GaussianParams:
    """The raw parameters of one instance's Gaussians composed in world coordinates at ``frame`` (background
    rows: means, log-scales, quaternions, opacity logits, SH)."""
    g = composed(node, instance, frame)
    opac = g["opacities"].clamp(1e-6, 1 - 1e-6)
    return GaussianParams(g["means"], torch.log(g["scales"]), g["quats"], torch.log(opac / (1 - opac)), g["sh"])


def world_means_at(node, instance: int, frames: list[int]) -> list[np.ndarray]:
    """World means [N, 3] of one instance at each of ``frames``."""
    return [composed(node, instance, t)["means"].cpu().numpy().astype(np.float64) for t in frames]
