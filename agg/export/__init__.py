"""Exports of a reconstructed scene: 3DGS PLY Gaussians (``ply``) and the scene graph as JSON (``graph_json``)."""

from __future__ import annotations

import json
from pathlib import Path

import torch

from agg.export.graph_json import scene_graph_json
from agg.export.ply import export_graph_ply, read_ply, write_ply


def export_scene(graph, ply_path: str | Path, graph_path: str | Path, timestamps_us, meta: dict | None = None,
                 frame: int = 0) -> dict:
    """Write the world Gaussians at ``frame`` as a 3DGS PLY and the scene graph as JSON; returns the JSON doc."""
    with torch.no_grad():
        export_graph_ply(graph, ply_path, frame=frame)
        doc = scene_graph_json(graph, timestamps_us, meta=meta)
    Path(graph_path).write_text(json.dumps(doc))
    return doc


__all__ = ["export_graph_ply", "export_scene", "read_ply", "scene_graph_json", "write_ply"]
