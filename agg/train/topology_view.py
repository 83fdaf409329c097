"""Where a spawned agent's box can be seen, and whether the features see an agent there: the ``in_view`` and
``evidence`` tests that decide how far a spawned agent's validity extends past its track
(``topology_track.trajectory_poses``).

A box is in view in a frame when its centre projects into the image, or when part of it does and the features
there look like an agent: a car that the camera overtakes leaves at the image edge with its centre already
outside while its front still covers hundreds of pixels (seed 7 of the synthetic suite: the centre leaves at
frame 8, the car at frame 21). The evidence reads the feature cells in a square around the centre's pixel (a
side of the box height there) cut to the part of the box that the image holds; with the centre outside, the
square moves to the nearest point of that part.
"""

from __future__ import annotations

import numpy as np

from agg.io.video import intrinsics_at
from agg.train import topology_track as tt


def box_grid(world_from_box: np.ndarray, half: np.ndarray, n: int = 9) -> np.ndarray:
    """[n^3, 3] world points on an n x n x n grid through the box ``world_from_box`` [4, 4] of half extents
    ``half`` [3] (corners included)."""
    axis = np.linspace(-1.0, 1.0, n)
    local = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3) * half  # [n^3, 3]
    return local @ world_from_box[:3, :3].T + world_from_box[:3, 3]


def box_image_rect(world_from_box: np.ndarray, half: np.ndarray, camera_from_world: np.ndarray,
                   K: np.ndarray, width: int, height: int, near: float  # noqa: N803
                   ) -> tuple[np.ndarray, np.ndarray] | None:
    """Pixel bounds (lo [2], hi [2]) of the box's grid points that the image holds (in front of ``near`` and
    inside it): the part of the box the frame shows. None when it shows none."""
    uv, _, vis = tt.project(box_grid(world_from_box, half), camera_from_world, K, width, height, near)
    if not vis.any():
        return None
    return uv[vis].min(0), uv[vis].max(0)


def region_agent_fraction(features: np.ndarray, bank: dict, tau_sem: float, uv: np.ndarray, radius: float,
                          width: int, height: int, exclude: np.ndarray | None = None,
                          within: tuple[np.ndarray, np.ndarray] | None = None) -> float:
    """Fraction of agent-like cells of a low-resolution feature map [h, w, C] in the square of half side
    ``radius`` pixels around ``uv`` [2] (training-resolution pixels), cut to the pixel bounds ``within``
    (lo [2], hi [2]) when given; cells whose centre falls on ``exclude`` [height, width] (e.g. the prior dynamic
    masks: pixels already explained by another agent) are skipped. 0 when no cell is left."""
    h, w = features.shape[:2]
    lo_px, hi_px = uv - radius, uv + radius
    if within is not None:
        lo_px, hi_px = np.maximum(lo_px, within[0]), np.minimum(hi_px, within[1])
        if np.any(lo_px > hi_px):
            return 0.0
    lo = np.floor((lo_px + 0.5) * np.array([w / width, h / height]))  # cells holding the region's corners
    hi = np.floor((hi_px + 0.5) * np.array([w / width, h / height]))
    (x0, y0), (x1, y1) = np.clip(lo, 0, [w - 1, h - 1]), np.clip(hi, 0, [w - 1, h - 1])
    ys, xs = np.mgrid[int(y0):int(y1) + 1, int(x0):int(x1) + 1]  # cell indices
    ys, xs = ys.ravel(), xs.ravel()
    if exclude is not None:
        px, py = tt.cell_centre_pixels(xs, ys, w, h, width, height)
        free = ~np.asarray(exclude, bool)[py, px]
        ys, xs = ys[free], xs[free]
    if len(xs) == 0:
        return 0.0
    ag, _ = tt.agent_like(np.asarray(features, np.float32)[ys, xs], bank, tau_sem)
    return float(ag.mean())


def box_visibility(evo, camera_from_world: np.ndarray, half: np.ndarray):
    """(``in_view``, ``evidence``) for ``trajectory_poses`` of a spawned box of half extents ``half`` [3] (scene
    units), seen by the cameras ``camera_from_world`` [T, 4, 4]; ``evo``: the ``TopologyEvolution`` (config,
    scene unit, intrinsics, image size, prototype bank, features and prior dynamic masks). ``evidence(frame,
    world_from_box)``: the agent-like share of the feature cells in the box's square (module docstring), off the
    pixels the prior dynamic masks give to other agents, reaches ``extend_agent_fraction``. ``in_view(frame,
    world_from_box)``: the box centre is in the image, or the image holds part of the box and it has evidence."""
    cfg = evo.config
    near = cfg.near_m * evo.unit

    memo: dict[tuple[int, bytes], bool] = {}  # by (frame, pose): in_view and then trajectory_poses may ask

    def evidence(i: int, pose: np.ndarray) -> bool:
        key = (i, np.ascontiguousarray(pose).tobytes())
        if key not in memo:
            memo[key] = read_evidence(i, pose)
        return memo[key]

    def read_evidence(i: int, pose: np.ndarray) -> bool:
        if evo.bank is None:
            return False
        k = intrinsics_at(evo.K, i)
        rect = box_image_rect(pose, half, camera_from_world[i], k, evo.width, evo.height, near)
        if rect is None:
            return False
        uv, z, _ = tt.project(pose[None, :3, 3], camera_from_world[i], k, evo.width, evo.height, near)
        centre = np.clip(uv[0], *rect) if z[0] > near else 0.5 * (rect[0] + rect[1])  # [2]
        frac = region_agent_fraction(evo.semantics.features[i], evo.bank, cfg.tau_sem, centre,
                                     k[0, 0] * half[1] / max(float(z[0]), near), evo.width, evo.height,
                                     None if evo.dynamic is None else evo.dynamic[i], rect)
        return frac >= cfg.extend_agent_fraction

    def in_view(i: int, pose: np.ndarray) -> bool:
        k = intrinsics_at(evo.K, i)
        centre_in = tt.project(pose[None, :3, 3], camera_from_world[i], k, evo.width, evo.height, near)[2][0]
        return bool(centre_in) or evidence(i, pose)

    return in_view, evidence
