"""Benchmark the whole priors pipeline on the synthetic suite: estimate every prior from the frames alone.

For each seed a synthetic clip is rendered (agg.synth, exact ground truth in ``gt/``), every prior is removed
from the bundle (only frames, timestamps and the true K stay), and ``agg.priors.pipeline.run_priors`` estimates
them again. Prints one JSON line per seed and a final line with the means: ATE (% of path, after Sim(3) with
orientations), mask IoU on the moving agents and on all agents, tracklet recall and precision (world centres
within 2 m, moving GT agents), and seconds per stage.

    python bench/priors_suite.py [--seeds 0,1,2] [--frames 24] [--width 320] [--height 192] [--given poses,depth]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np


def run_seed(seed: int, frames: int, width: int, height: int, root: Path, given: tuple[str, ...] = ()) -> dict:
    from agg.io.bundle import SceneBundle
    from agg.priors.pipeline import PriorsConfig, run_priors
    from agg.synth.corrupt import NoiseConfig
    from agg.synth.scene import SceneConfig
    from agg.synth.suite import generate, write_bundle

    cfg = SceneConfig(seed=seed, frames=frames, width=width, height=height)
    gt, priors = generate(cfg, NoiseConfig())
    path = root / f"seed{seed}"
    write_bundle(path, gt, priors, NoiseConfig(), overwrite=True)
    bundle = SceneBundle.load(path)
    keep = {"poses": ("poses",), "depth": ("depth_dense",), "masks": ("dynamic_masks",)}
    kept = {part for g in given for part in keep[g]}
    for part in ("poses", "depth_dense", "depth_sparse", "dynamic_masks", "tracklets", "semantics"):
        if part not in kept:
            bundle.remove(part)
    if "masks" in given:  # the exact masks of the MOVING agents (what a flow-based prior is asked to find)
        bundle.write_dynamic_masks(np.isin(gt.instance, gt.agent_ids[gt.agent_moving]), source="gt")
    summary = run_priors(bundle, PriorsConfig())
    s = summary.scores
    return {
        "seed": seed, "frames": frames, "size": [width, height],
        "moving_agents": int(gt.agent_moving.sum()), "agents": len(gt.agent_ids),
        "registered_fraction": summary.poses.get("registered_fraction"),
        "ate_percent_of_path": s.get("poses", {}).get("ate_percent_of_path"),
        "mask_iou_moving": s.get("masks", {}).get("iou_moving_agents"),
        "mask_iou_all": s.get("masks", {}).get("iou_all_agents"),
        "tracklet_recall": s.get("tracklets", {}).get("tracklet_recall", 0.0 if not bundle.has("tracklets") else None),
        "tracklet_precision": s.get("tracklets", {}).get("tracklet_precision"),
        "tracks": summary.tracklets.get("count", 0),
        "seconds": summary.seconds,
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--frames", type=int, default=24)
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=192)
    ap.add_argument("--keep", type=Path, help="write the bundles here (kept) instead of a temporary folder")
    ap.add_argument("--given", default="", help="exact priors to keep instead of estimating them (isolates a "
                    "stage): comma-separated subset of poses, depth, masks (masks: the moving agents' GT masks)")
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory(prefix="agg_priors_suite_") as tmp:
        for seed in (int(s) for s in args.seeds.split(",")):
            given = tuple(g for g in args.given.split(",") if g)
            row = run_seed(seed, args.frames, args.width, args.height, args.keep or Path(tmp), given)
            row["given"] = list(given)
            rows.append(row)
            print(json.dumps(row), flush=True)
    keys = ("registered_fraction", "ate_percent_of_path", "mask_iou_moving", "mask_iou_all", "tracklet_recall",
            "tracklet_precision")
    mean = {k: float(np.mean([r[k] for r in rows if r[k] is not None])) if any(r[k] is not None for r in rows)
            else None for k in keys}
    print(json.dumps({"mean": mean, "seeds": [r["seed"] for r in rows]}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
