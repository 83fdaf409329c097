"""The scene graph as JSON: nodes, agent classes, refined per-frame poses, validity, cameras and time range.

The schema is documented in docs/SCENE.md. Every number is finite (a non-finite value, which would be a bug
upstream, is written as ``null`` and listed under ``warnings``), so the output passes
``json.dumps(..., allow_nan=False)``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch

from agg.io.video import intrinsics_at

SCHEMA = "agg.scene_graph"
VERSION = 1

CONVENTIONS = {
    "world": "the first camera's frame (OpenCV axes: x right, y down, z forward)",
    "camera": "OpenCV (x right, y down, z forward); intrinsics are pixel-unit 3x3 K",
    "units": "scene units (metres when the bundle's scale is metric), radians",
    "pose": "4x4 row-major rigid transforms named a_from_b: world_from_camera maps camera to world points, "
            "world_from_box maps box-frame points to world points",
    "box_frame": "origin at the box centre; x along the length, y along the height (down), z along the width",
    "quaternions": "wxyz",
    "time": "timestamps_us are integer microseconds; frame i in [0, num_frames)",
    "invalid_frames": "world_from_box is null at frames where the agent is absent (valid false)",
}


class _Clean:
    """Turns tensors/arrays into JSON lists, replacing non-finite numbers with None (and noting where)."""

    def __init__(self):
        self.warnings: list[str] = []

    def __call__(self, x, where: str):
        a = x.detach().cpu().double().numpy() if isinstance(x, torch.Tensor) else np.asarray(x, np.float64)
        if np.isfinite(a).all():
            return a.tolist()
        self.warnings.append(f"non-finite values in {where} written as null")
        return _nan_to_none(a.tolist())


def _nan_to_none(v):
    if isinstance(v, list):
        return [_nan_to_none(x) for x in v]
    return None if isinstance(v, float) and not math.isfinite(v) else v


def _count(node) -> int:
    g = getattr(node, "gaussians", node)
    return len(g)


def agent_entries(graph, clean: _Clean) -> list[dict]:
    """One node entry per agent instance (rigid instances first, then non-rigid), in ``compose`` slot order."""
    out, slot = [], 1
    with torch.no_grad():
        for node in graph.agent_nodes():
            cls = "non-rigid" if node is getattr(graph, "nonrigid", None) else "rigid"
            t = node.num_frames
            poses = torch.stack([node.world_from_box(i).detach() for i in range(t)])  # [T, K, 4, 4]
            valid = node.valid.cpu()  # [T, K]
            means = node.gaussians.means.detach()  # [N, 3] canonical (box frame)
            for j, tid in enumerate(node.track_ids.tolist()):
                rows = node.instance == j
                frames = torch.nonzero(valid[:, j]).reshape(-1).tolist()
                where = f"agent {tid}"
                wfb = [clean(poses[i, j], where) if valid[i, j] else None for i in range(t)]
                aabb = None
                if bool(rows.any()):
                    m = means[rows]
                    aabb = [clean(m.min(0).values, where), clean(m.max(0).values, where)]
                out.append({"id": f"agent/{tid}", "type": "agent", "track_id": int(tid), "class": cls,
                            "slot": slot, "n_gaussians": int(rows.sum()),
                            "first_frame": frames[0] if frames else None,
                            "last_frame": frames[-1] if frames else None,
                            "valid": [bool(v) for v in valid[:, j].tolist()],
                            "world_from_box": wfb, "canonical_aabb": aabb})
                slot += 1
    return out


def scene_graph_json(graph, timestamps_us: Sequence[int], meta: dict | None = None) -> dict:
    """JSON-ready dict of ``graph`` (see docs/SCENE.md); ``timestamps_us`` [T] integer microseconds per frame."""
    ts = [int(t) for t in np.asarray(timestamps_us).reshape(-1)]
    t = graph.num_frames
    if len(ts) != t:
        raise ValueError(f"timestamps_us has {len(ts)} entries, the graph {t} frames")
    clean = _Clean()
    with torch.no_grad():
        cams = graph.camera.world_from_camera().detach()  # [T, 4, 4]
    K = graph.K.detach().cpu()  # noqa: N806  [T or 1, 3, 3]
    intrinsics = [clean(intrinsics_at(K, i), "intrinsics") for i in range(t)]
    nodes = [{"id": "camera", "type": "camera", "num_frames": t},
             {"id": "background", "type": "background", "n_gaussians": len(graph.background)}]
    if getattr(graph, "sky", None) is not None:
        nodes.append({"id": "sky", "type": "sky", "n_gaussians": _count(graph.sky)})
    agents = agent_entries(graph, clean)
    nodes += agents
    out = {
        "schema": SCHEMA,
        "version": VERSION,
        "conventions": CONVENTIONS,
        "time_range": {"first_timestamp_us": ts[0] if ts else None, "last_timestamp_us": ts[-1] if ts else None,
                       "num_frames": t},
        "timestamps_us": ts,
        "cameras": {"width": int(graph.width), "height": int(graph.height),
                    "world_from_camera": [clean(cams[i], "world_from_camera") for i in range(t)],
                    "intrinsics": intrinsics},
        "nodes": nodes,
        "counts": {"nodes": len(nodes), "agents": len(agents),
                   "rigid": sum(a["class"] == "rigid" for a in agents),
                   "non_rigid": sum(a["class"] == "non-rigid" for a in agents),
                   "n_gaussians": int(len(graph.background) + sum(_count(n) for n in graph.agent_nodes())
                                      + (_count(graph.sky) if getattr(graph, "sky", None) is not None else 0))},
        "meta": dict(meta or {}),
    }
    if clean.warnings:
        out["warnings"] = sorted(set(clean.warnings))
    return out
