"""Where a spawned agent is in one frame, read off its semantic silhouette (``topology_spawn``).

A track of unmatched clusters says that an agent moves there, but its cluster centroids are a poor sample of the
agent's visible surface: the clusters are the background Gaussians with the highest positional gradients, and on
a moving car those crowd its leading edge. The spawned box then led the car along its heading (seed 2 of the
synthetic suite at 1.0 m of camera noise: 0.6-1.1 m, within 1 m of the truth on 0.62 of its frames), and no
render can move it back (the box origin and its Gaussians shift together; ``topology_anchor``).

The feature map shows the whole visible agent, not just where the gradients are. In frame t, from the pixel of
the cluster centroid:

- the agent-like cells of the low-resolution feature map (``topology_track.agent_like``: the prototype bank) that
  are 8-connected to that pixel's cell form the silhouette; cells on the prior dynamic masks (other agents) are
  left out, and so is every cell whose point lies farther from the centroid than the box's diagonal (a
  neighbouring agent-like object, or the background behind a boundary cell);
- each cell's point is its centre pixel back-projected at the median prior depth of the pixels it covers;
- the centroid weighs every cell by ``cos^3`` of its ray's angle off the optical axis (pixel counts -> solid
  angle), which is how ``topology_track.visible_surface_offset`` models the visible surface that
  ``box_centre_from_surface`` inverts.

Without features, a prototype bank or depth, or with fewer than ``min_cells`` cells, the cluster centroid stays.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from agg.train import topology_track as tt

_EIGHT = np.ones((3, 3), bool)  # 8-connectivity


def cell_points(depth: np.ndarray, h: int, w: int, camera_from_world: np.ndarray, K: np.ndarray  # noqa: N803
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per cell of an [h, w] grid over a [H, W] depth map: world points [h, w, 3] of the cell centres at the median
    depth of the pixels the cell covers, their depth [h, w] (0: no depth there) and ``cos^3`` of the rays' angle
    off the optical axis [h, w]."""
    height, width = depth.shape
    if height % h == 0 and width % w == 0:  # the usual case: whole blocks of pixels per cell
        blocks = np.where(depth > 0, depth, np.nan).reshape(h, height // h, w, width // w)
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # a block without depth: all-NaN
            z = np.nan_to_num(np.nanmedian(blocks, axis=(1, 3)), nan=0.0)
    else:
        ys = np.minimum((np.arange(h + 1) * height) // h, height)  # rows of cell row i: ys[i]:ys[i+1]
        xs = np.minimum((np.arange(w + 1) * width) // w, width)
        z = np.zeros((h, w))
        for i in range(h):
            for j in range(w):
                block = depth[ys[i]:max(ys[i + 1], ys[i] + 1), xs[j]:max(xs[j + 1], xs[j] + 1)]
                block = block[block > 0]
                z[i, j] = np.median(block) if len(block) else 0.0
    jj, ii = np.meshgrid(np.arange(w), np.arange(h))
    uv = np.stack([(jj + 0.5) * width / w - 0.5, (ii + 0.5) * height / h - 0.5], -1).reshape(-1, 2)  # [h*w, 2]
    cos3 = tt.ray_cos3(uv, K).reshape(h, w)
    points = tt.backproject(uv, z.reshape(-1), camera_from_world, K).reshape(h, w, 3)
    return points, z, cos3


@dataclass(frozen=True)
class FrameCells:
    """What a frame's feature map says about agents, whatever the seed: which cells may belong to a silhouette
    (agent-like, with depth, off the excluded pixels) [h, w] bool, their points [h, w, 3] and ``cos^3``
    weights [h, w] (``cell_points``), and the training resolution they map to."""
    candidate: np.ndarray
    points: np.ndarray
    cos3: np.ndarray
    width: int
    height: int


def frame_cells(features: np.ndarray, bank: dict, tau_sem: float, depth: np.ndarray, camera_from_world: np.ndarray,
                K: np.ndarray, exclude: np.ndarray | None = None) -> FrameCells:  # noqa: N803
    """The ``FrameCells`` of one frame: its feature map [h, w, C], the prior z-depth [H, W] at the training
    resolution (0 = none) and optionally the pixels [H, W] bool explained by other agents (the prior dynamic
    masks). Computed once per frame; every seed of that frame reads it (``silhouette_centroid``)."""
    height, width = depth.shape
    h, w = features.shape[:2]
    ag, _ = tt.agent_like(np.asarray(features, np.float32).reshape(h * w, -1), bank, tau_sem)
    points, z, cos3 = cell_points(np.asarray(depth, np.float64), h, w, camera_from_world, K)
    candidate = ag.reshape(h, w) & (z > 0)
    if exclude is not None:
        jj, ii = np.meshgrid(np.arange(w), np.arange(h))
        px, py = tt.cell_centre_pixels(jj, ii, w, h, width, height)
        candidate &= ~np.asarray(exclude, bool)[py, px]
    return FrameCells(candidate, points, cos3, width, height)


def silhouette_centroid(seed: np.ndarray, cells: FrameCells, camera_from_world: np.ndarray, K: np.ndarray,  # noqa: N803
                        reach: float, min_cells: int = 4, near: float = 0.0) -> tuple[np.ndarray, int] | None:
    """(world centroid [3] of the visible surface of the agent at ``seed`` [3] (a world point on it), number of
    cells) from one frame's ``FrameCells`` (module doc), or None when the seed is out of view or the silhouette
    has fewer than ``min_cells`` cells. reach: the largest distance from the seed a point of the agent can have
    (its box diagonal)."""
    h, w = cells.candidate.shape
    uv, _, vis = tt.project(np.asarray(seed, np.float64)[None], camera_from_world, K, cells.width, cells.height, near)
    if not vis[0]:
        return None
    mask = cells.candidate & (np.linalg.norm(cells.points - seed, axis=-1) <= reach)
    labels, _ = ndimage.label(mask, structure=_EIGHT)  # [h, w], 0 = not in a component
    ci = int(np.clip((uv[0, 1] + 0.5) * h / cells.height, 0, h - 1))
    cj = int(np.clip((uv[0, 0] + 0.5) * w / cells.width, 0, w - 1))
    near_cells = labels[max(ci - 1, 0):ci + 2, max(cj - 1, 0):cj + 2]  # the seed's cell or one next to it
    if labels[ci, cj] > 0:
        label = labels[ci, cj]
    elif (near_cells > 0).any():
        label = np.bincount(near_cells[near_cells > 0]).argmax()
    else:
        return None
    part = labels == label
    n = int(part.sum())
    if n < min_cells:
        return None
    wts = cells.cos3[part]
    return (cells.points[part] * wts[:, None]).sum(0) / wts.sum(), n
