"""Shared by ``agg eval`` / ``agg render`` / ``agg export``: open a scene directory written by ``agg reconstruct``."""

from __future__ import annotations

import json
from pathlib import Path

import torch


def open_scene(path: str | Path):
    """(meta dict from scene.json, SceneGraph) of a scene folder: model.pt, else the latest checkpoint.pt."""
    from agg.graph import SceneGraph

    root = Path(path)
    if not (root / "scene.json").is_file():
        raise FileNotFoundError(f"{root}: not a scene folder (no scene.json; run agg reconstruct first)")
    meta = json.loads((root / "scene.json").read_text())
    for name in ("model.pt", "checkpoint.pt"):
        if (root / name).is_file():
            state = torch.load(root / name, map_location="cpu", weights_only=False)
            graph = SceneGraph.from_state(state["graph"])
            graph.eval()
            return meta, graph
    raise FileNotFoundError(f"{root}: no model.pt or checkpoint.pt yet")
