"""``agg export SCENE [--ply PATH] [--graph PATH] [--frame F]``: a 3DGS PLY and the scene-graph JSON."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path



def add_parser(subparsers) -> None:
    p = subparsers.add_parser("export", help="export a trained scene: 3DGS PLY and scene-graph JSON",
                              description="Write the world Gaussians at a frame as a standard 3DGS PLY (opens in "
                                          "common splat viewers) and the scene graph (nodes, classes, per-frame "
                                          "poses and validity, cameras, time range) as JSON (docs/SCENE.md).")
    p.add_argument("scene", metavar="SCENE")
    p.add_argument("--ply", metavar="PATH", help="PLY path (default SCENE/scene.ply)")
    p.add_argument("--graph", metavar="PATH", help="JSON path (default SCENE/graph.json)")
    p.add_argument("--frame", type=int, default=0, help="frame whose agent poses the PLY uses (default 0)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from agg.export import export_scene
    from agg.scene import Scene, SceneNotReady, SceneUnreadable

    try:
        scene = Scene.load(args.scene)
        meta, graph = scene.meta, scene.graph
        if not 0 <= args.frame < graph.num_frames:
            raise ValueError(f"frame {args.frame} is out of range [0, {graph.num_frames})")
        ply = Path(args.ply or Path(args.scene) / "scene.ply")
        out = Path(args.graph or Path(args.scene) / "graph.json")
        doc = export_scene(graph, ply, out, meta["timestamps_us"], meta={"preset": meta.get("preset"),
                                                                           "metric_scale": meta.get("metric_scale")},
                           frame=args.frame)
    except (ValueError, OSError, SceneNotReady, SceneUnreadable) as exc:
        print(f"agg export: error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {ply} ({graph.num_gaussians()} Gaussians) and {out} ({len(doc.get('nodes', []))} nodes)")
    return 0
