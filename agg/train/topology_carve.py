"""Free space of spawned agents: the background Gaussians a spawned agent's box sweeps through are carved away.

A missed moving car is in no prior dynamic mask, so the background is initialised from its pixels in every frame:
a trail of car-coloured points along its path. Spawning moves the trail's high-gradient, agent-like rows (the
clusters) to the new agent and leaves the rest, which keeps drawing the car where it no longer is. On seed 0 of
the benchmark the 2.5 m band around the missed car's path held 26 % of the held-out pixels, and AGG's error there
stayed within 1 dB of the baseline's while exact agent priors gained 5 dB (docs/BENCHMARKS.md, seventeenth
session). A rigid body fills its box at every frame it is valid, and no static surface lies where a car drove:
the volume its box sweeps over its valid frames is free space for the background, down to the road it stands on.

``carve_rows`` marks the background means inside that volume: inside the box shrunk to ``shrink`` of its length
and width (a spawned box is placed to within a few tenths of a metre, ``topology_anchor``; the shrink keeps a
kerb, a parked car or a wall beside the lane), and ``clearance`` above both the box's bottom and, where the depth
prior has one, the frame's road plane (the road under the car stays). ``TopologyEvolution.evolve`` removes them,
for the agents it spawns and again for earlier spawns at each later evolution (their boxes re-anchored, and
densification may have grown the trail back). Prior agents are left alone: the background never saw their
pixels (the dynamic masks kept them out), and a false prior box over a building must not cut the building. So
are agents that travel less than half their length over their valid frames: a static object leaves no trail, and
the background rows in its box that the clusters did not hand over are still its own surface.
"""

from __future__ import annotations

import numpy as np

from agg.priors.tracklet_ground import height_above_road


def carve_rows(means: np.ndarray, poses: np.ndarray, valid: np.ndarray, half: np.ndarray,
               camera_from_world: np.ndarray, K: np.ndarray, planes: list | None, shrink: float,  # noqa: N803
               clearance: float) -> np.ndarray:
    """[N] bool: background means [N, 3] in the free space of one agent, whose box ``poses`` [T, 4, 4]
    (world_from_box; box axes x = length, y = down, z = width) of half extents ``half`` [3] is valid at ``valid``
    [T]. ``camera_from_world`` [T, 4, 4], ``K`` [T or 1, 3, 3] and ``planes`` ([T] road planes of inverse depth,
    ``tracklet_ground.ground_planes``; None entries or None: no plane) are read for the road test; ``shrink``
    scales the box's length and width, ``clearance`` (scene units) is the height over the box bottom and over the
    road plane below which nothing is carved. Nothing for an agent whose valid centres lie within half its length
    (``half[0]``) of each other."""
    half = np.asarray(half, np.float64)
    out = np.zeros(len(means), bool)
    centres = poses[np.asarray(valid, bool), :3, 3]  # [V, 3]
    if len(centres) < 2 or np.linalg.norm(centres[:, None] - centres[None], axis=-1).max() < half[0]:
        return out  # static: no trail
    reach = float(np.linalg.norm(half))
    lateral = np.array([shrink * half[0], shrink * half[2]])
    for t in np.flatnonzero(valid):
        pose = poses[t]
        near = np.flatnonzero(np.linalg.norm(means - pose[:3, 3], axis=1) <= reach)  # [M] the box's bounding ball
        if len(near) == 0:
            continue
        local = (means[near] - pose[:3, 3]) @ pose[:3, :3]  # [M, 3] R^T (p - c)
        inside = ((np.abs(local[:, 0]) <= lateral[0]) & (np.abs(local[:, 2]) <= lateral[1])
                  & (local[:, 1] >= -half[1]) & (local[:, 1] <= half[1] - clearance))
        if planes is not None and planes[t] is not None and inside.any():
            rows = near[inside]
            pc = means[rows] @ camera_from_world[t, :3, :3].T + camera_from_world[t, :3, 3]  # [m, 3]
            h = height_above_road(planes[t], K[min(t, len(K) - 1)], pc)  # [m]
            inside[np.flatnonzero(inside)[h <= clearance]] = False
        out[near[inside]] = True
    return out
