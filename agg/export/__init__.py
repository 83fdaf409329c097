"""Exports of a reconstructed scene: 3DGS PLY Gaussians (``ply``) and the scene graph as JSON (``graph_json``)."""

from agg.export.graph_json import scene_graph_json
from agg.export.ply import export_graph_ply, read_ply, write_ply

__all__ = ["export_graph_ply", "read_ply", "scene_graph_json", "write_ply"]
