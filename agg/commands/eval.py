"""``agg eval SCENE [--json]``: novel-view metrics on the held-out frames (every 5th) of a trained scene."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("eval", help="novel-view metrics of a trained scene (held-out every 5th frame)",
                              description="Render the held-out frames through interpolated camera and agent poses "
                                          "and compare with the video: PSNR, SSIM, LPIPS (only with local weights, "
                                          "AGG_LPIPS_WEIGHTS), agent-region metrics, render FPS.")
    p.add_argument("scene", metavar="SCENE", help="scene folder written by agg reconstruct")
    p.add_argument("--max-frames", type=int, metavar="N", help="evaluate at most N held-out frames")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--device", default="cpu", help="torch device to render on: cpu (default), cuda, cuda:N "
                                                   "(gsplat's rasteriser when it is installed)")
    p.set_defaults(func=run)


KEYS = ("psnr", "ssim", "lpips", "psnr_agents", "ssim_agents", "split", "n_test_frames", "render_fps",
        "n_gaussians", "n_agents")


def run(args: argparse.Namespace) -> int:
    from agg.device import resolve_device
    from agg.scene import Scene, SceneNotReady, SceneUnreadable
    from agg.eval.nvs import evaluate
    from agg.io.bundle import SceneBundle
    from agg.train.data import resize_images

    try:
        scene = Scene.load(args.scene, device=resolve_device(args.device))
        meta, graph = scene.meta, scene.graph
        bundle = SceneBundle.load(meta["bundle"])
        frames = sorted(set(meta["test_frames"]))
        images = resize_images(bundle.frames[:], graph.width, graph.height)
        metrics = evaluate(graph, bundle, frames, meta["train_frames"], images=images, max_frames=args.max_frames)
    except (ValueError, OSError, SceneNotReady, SceneUnreadable) as exc:
        print(f"agg eval: error: {exc}", file=sys.stderr)
        return 2
    (Path(args.scene) / "metrics.json").write_text(json.dumps(metrics, indent=1))
    if args.json:
        out = {k: metrics.get(k) for k in KEYS}
        out.update({k: v for k, v in metrics.items() if k not in KEYS and k != "per_frame"})
        print(json.dumps(out))
    else:
        for k in KEYS:
            print(f"{k:>14}: {metrics.get(k)}")
        if metrics.get("ego_pixel_share"):
            print(f"{'ego_pixels':>14}: {100 * metrics['ego_pixel_share']:.1f} % of the image, not scored")
    return 0
