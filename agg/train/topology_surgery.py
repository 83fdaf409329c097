"""Graph surgery of topology evolution (``agg/train/topology.py``): reassigned background rows move into the agents
they belong to, planned spawns become new rigid agents, and the background shrinks by every row that left it.

Rows leave the background in world coordinates and enter an agent in its canonical (box) frame, each through the
``world_from_box`` pose of the frame it was matched or clustered in. The optimiser state follows the rows: moved
rows start with zero moments in their new node (``nodes.gaussians.append_rows`` / ``keep_rows``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from agg.nodes.gaussians import PARAM_NAMES, GaussianParams, append_rows, keep_rows
from agg.nodes.rigid import RigidAgents, matrix_to_quat, quat_multiply


@dataclass
class Surgery:
    """What ``operate`` changed."""

    keep: Tensor  # [N_bg] bool: background rows that stayed (on the background's device)
    rows_changed: set[str] = field(default_factory=set)  # nodes whose rows changed: "background", "rigid", ...
    reassigned: int = 0  # rows moved into existing agents
    spawned: list[int] = field(default_factory=list)  # track ids of the new agents, in ``spawn`` order
    new_nodes: list[str] = field(default_factory=list)  # nodes created ("rigid" when the graph had none)


def rows_of(params: GaussianParams, idx: np.ndarray) -> dict[str, Tensor]:
    """Detached copies of rows ``idx`` [M] of every parameter."""
    i = torch.as_tensor(idx, dtype=torch.long, device=params.means.device)
    return {n: getattr(params, n).detach()[i].clone() for n in PARAM_NAMES}


def to_canonical(rows: dict[str, Tensor], world_from_box: np.ndarray) -> GaussianParams:
    """Background rows -> GaussianParams in the box frames world_from_box [M, 4, 4] (one pose per row)."""
    dev = rows["means"].device
    wfb = torch.as_tensor(world_from_box, dtype=torch.float32, device=dev)
    rt = wfb[:, :3, :3].transpose(1, 2)  # [M, 3, 3] box_from_world rotation
    means = (rt @ (rows["means"] - wfb[:, :3, 3])[..., None])[..., 0]
    quats = quat_multiply(matrix_to_quat(rt), rows["quats"])
    return GaussianParams(means, rows["log_scales"], quats, rows["opacity_logits"], rows["sh"])


def append_to_instances(node, params: GaussianParams, instance: np.ndarray, optimizer) -> None:
    """Append Gaussians (canonical frame) to existing instances [M] of an agent node."""
    inst = torch.as_tensor(instance, dtype=torch.long, device=node.instance.device)
    if hasattr(node, "append_gaussians"):
        node.append_gaussians(params, inst, optimizer)
        return
    append_rows(node.gaussians, params, optimizer)
    node.instance = torch.cat([node.instance, inst])


def operate(graph, optimizer, target: np.ndarray, target_frame: np.ndarray, boxes: list[dict], spawn: list[dict],
            next_id: int) -> Surgery:
    """Move reassigned rows to their agents, spawn the new agents (ids ``next_id``, ``next_id + 1``, ...) and
    shrink the background.

    target [N_bg, 2]: (box index into ``boxes``, instance) of each background row, -1 where it stays;
    target_frame [N_bg]: the frame whose box pose takes it into the canonical frame. ``boxes``: the agent boxes
    (``node``, ``poses`` [T, K, 4, 4]); ``spawn``: the planned spawns (``topology_spawn.plan_spawns``)."""
    bg = graph.background
    moved = target[:, 0] >= 0
    names = {id(graph.rigid): "rigid", id(getattr(graph, "nonrigid", None)): "nonrigid"}
    # gather every moved row's parameters before the background shrinks
    reassign = []
    for a, box in enumerate(boxes):
        sel = np.flatnonzero(target[:, 0] == a)
        if len(sel):
            poses = box["poses"][target_frame[sel], target[sel, 1]]  # [M, 4, 4]
            reassign.append((box["node"], to_canonical(rows_of(bg, sel), poses), target[sel, 1]))
    spawned = []
    for plan in spawn:
        poses = plan["poses"][plan["frame_of"]]
        spawned.append(to_canonical(rows_of(bg, plan["rows"]), poses))
        moved[plan["rows"]] = True
    done = Surgery(keep=torch.as_tensor(~moved, device=bg.means.device))
    if moved.any():
        keep_rows(bg, done.keep, optimizer)
        done.rows_changed.add("background")
    for node, params, inst in reassign:
        append_to_instances(node, params, inst, optimizer)
        done.reassigned += len(params)
        done.rows_changed.add(names.get(id(node), "agent"))
    if spawned:
        ids = list(range(next_id, next_id + len(spawned)))
        wfb = torch.as_tensor(np.stack([p["poses"] for p in spawn], 1), dtype=torch.float32)  # [T, k, 4, 4]
        valid = torch.as_tensor(np.stack([p["valid"] for p in spawn], 1))  # [T, k]
        # local instance index of every row, counted before the sets are concatenated into spawned[0]
        instance = torch.cat([torch.full((len(g),), j, dtype=torch.long) for j, g in enumerate(spawned)])
        params = spawned[0]
        for extra in spawned[1:]:
            append_rows(params, extra)
        # the box the node confines each spawn to: its size guessed, grown for where it is placed (None: free)
        boxes_half = torch.as_tensor(np.stack([np.full(3, np.inf) if p.get("box") is None else p["box"]
                                               for p in spawn]), dtype=torch.float32)  # [k, 3]
        if graph.rigid is None:
            dev = bg.means.device
            graph.rigid = RigidAgents(params, instance, wfb, valid, torch.as_tensor(ids), boxes_half).to(dev)
            graph.rigid.speed_free.fill_(True)  # its track's speed is an estimate: trained (nodes/rigid.py)
            done.new_nodes.append("rigid")
        else:
            graph.rigid.add_instances(params, instance, wfb, valid,
                                      torch.as_tensor(ids, device=graph.rigid.track_ids.device), optimizer,
                                      half_extents=boxes_half, speed_free=True)
        k = graph.rigid.num_instances
        # each spawn into its box, unmargined (spawn_box_rows="all" leaves rows outside it); unboxed ones stay free
        graph.rigid.confine(0.0, torch.arange(k - len(spawn), k))
        done.rows_changed.add("rigid")
        done.spawned = ids
    return done
