"""Where the background Gaussians that topology evolution reassigns to existing agents lie: in the agent's own box
or only in the matching box (grown by ``match_margin``), and how high above the road.

    python bench/agg_suite_reassign.py BUNDLE OUT.json [--preset fast] [--seed 0] [--evolutions 4] [--work DIR]

Trains BUNDLE (a scene bundle with every prior, e.g. ``agg priors samples/dashcam.mp4 -o B``) as ``agg
reconstruct`` would, and stops after ``--evolutions`` evolutions. At each, every row the evolution is about to move
into an agent is recorded before the move: its box-frame coordinates over the box's own half extents (|x| <= 1 on
every axis: inside the box itself; y points down), its height in metres above the depth prior's road plane of the
frame it was matched in (``agg.priors.tracklet_ground.height_above_road``), its depth and the agent's track id.
The training run is the reconstruct run's up to that point: the recording reads the graph and changes nothing.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from agg.priors.tracklet_ground import height_above_road
from agg.train import topology
from agg.train.reconstruct import Cancelled, reconstruct


def reassigned_rows(evo, graph, target: np.ndarray, target_frame: np.ndarray, boxes: list[dict]) -> list[dict]:
    """One record per background row with a target agent (``target`` [N, 2]: node, instance; -1 for none)."""
    means = graph.background.means.detach().cpu().numpy().astype(np.float64)  # [N, 3]
    cfw = graph.camera.camera_from_world().detach().cpu().numpy().astype(np.float64)  # [T, 4, 4]
    planes = evo.road_planes()
    out = []
    for a, box in enumerate(boxes):
        for r in np.flatnonzero(target[:, 0] == a):
            t, k = int(target_frame[r]), int(target[r, 1])
            pose = box["poses"][t, k]  # world_from_box [4, 4]
            own = box["half"][k] / (1.0 + evo.config.match_margin)  # [3] the box itself
            local = (means[r] - pose[:3, 3]) @ pose[:3, :3] / own
            pc = cfw[t, :3, :3] @ means[r] + cfw[t, :3, 3]
            height = None
            if planes is not None and planes[t] is not None:
                height = float(height_above_road(planes[t], evo.K[min(t, len(evo.K) - 1)], pc[None])[0]) / evo.unit
            out.append({"evolution": evo.evolutions, "track": int(box["node"].track_ids[k]), "frame": t,
                        "local": local.round(4).tolist(), "height_m": height, "depth_m": float(pc[2] / evo.unit)})
    return out


def summarise(rows: list[dict]) -> dict:
    local = np.array([r["local"] for r in rows], np.float64).reshape(-1, 3)
    height = np.array([np.nan if r["height_m"] is None else r["height_m"] for r in rows], np.float64)
    known = height[np.isfinite(height)]
    return {"rows": len(rows), "inside_own_box": int((np.abs(local) <= 1).all(1).sum()),
            "below_own_box": int((local[:, 1] > 1).sum()),
            "bottom_quarter": int(((local[:, 1] > 0.5) & (local[:, 1] <= 1)).sum()),
            "height_m_quantiles_10_25_50_75_90": np.quantile(known, [0.1, 0.25, 0.5, 0.75, 0.9]).round(3).tolist()
            if len(known) else None,
            "under_0.2_m": int((known < 0.2).sum()), "under_0.3_m": int((known < 0.3).sum())}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("bundle")
    p.add_argument("out")
    p.add_argument("--preset", default="fast")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--evolutions", type=int, default=4)
    p.add_argument("--work", default="/tmp/agg_reassign")
    args = p.parse_args(argv)
    rows: list[dict] = []
    seen = {"n": 0}
    apply = topology.TopologyEvolution._apply

    def recording_apply(self, graph, optimizer, report, target, target_frame, boxes, spawn):
        rows.extend(reassigned_rows(self, graph, target, target_frame, boxes))
        seen["n"] += 1
        return apply(self, graph, optimizer, report, target, target_frame, boxes, spawn)

    topology.TopologyEvolution._apply = recording_apply
    try:
        reconstruct(args.bundle, Path(args.work) / f"seed{args.seed}", args.preset, overrides={"seed": args.seed},
                    evaluate=False, resume=False, should_stop=lambda: seen["n"] >= args.evolutions)
    except Cancelled:
        pass
    finally:
        topology.TopologyEvolution._apply = apply
    result = {"bundle": str(args.bundle), "preset": args.preset, "seed": args.seed, "evolutions": seen["n"],
              "summary": summarise(rows), "rows": rows}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result))
    print(json.dumps(result["summary"]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
