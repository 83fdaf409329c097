"""``agg reconstruct INPUT -o SCENE --preset P [--ablate ...] [--gt-poses]``: train a scene graph."""

from __future__ import annotations

import argparse
import json
import sys

from agg.train.config import ABLATIONS, AGENT_ANCHORS, CAMERA_TRACKING, PRESETS


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "reconstruct", help="train a 4D Gaussian scene graph from a video, dataset folder or scene bundle",
        description="Estimate the priors INPUT lacks (like 'agg priors'), train the AGG scene graph with the "
                    "preset, evaluate novel views on every 5th frame and write SCENE/ (model.pt, checkpoint.pt, "
                    "metrics.json, scene.ply, graph.json, scene.json). Re-running resumes from the checkpoint.")
    p.add_argument("input", metavar="INPUT", help="video file, image folder, KITTI/nerfstudio/COLMAP folder or bundle")
    p.add_argument("-o", "--output", required=True, metavar="SCENE", help="scene folder")
    p.add_argument("--preset", default="fast", choices=[k for k in PRESETS if k != "tiny"] + ["tiny"],
                   help="speed/accuracy trade (docs/BENCHMARKS.md): fast, balanced, quality, paper")
    p.add_argument("--ablate", default="", metavar="LIST",
                   help=f"switch components off: comma-separated {','.join(ABLATIONS)}; 'all' = fixed-topology "
                        "GSG baseline")
    p.add_argument("--gt-poses", action="store_true",
                   help="use the bundle's ground-truth camera poses (gt/ sidecar) instead of the estimates")
    p.add_argument("--iterations", type=int, help="override the preset's iteration count")
    p.add_argument("--semantic-min-contrast", type=_contrast, metavar="RATIO|none",
                   help="train without the semantic loss when the attention maps separate the priors' dynamic masks "
                        "by less than RATIO (default 1.5); 'none' keeps it on whatever the maps (the paper's rule)")
    p.add_argument("--agent-anchor", choices=AGENT_ANCHORS,
                   help="camera: the priors' agents move with the camera's refinement, as tracklets lifted through "
                        "the estimated cameras do; world: they keep their world poses; auto (default): what the "
                        "bundle's tracklets were measured against (camera for agg priors; docs/TRAINING.md)")
    p.add_argument("--camera-tracking", choices=CAMERA_TRACKING,
                   help="the camera-tracking rounds (pose-only refinement against the map at a few milestones): "
                        "on (the default but for fast), off, or auto (fast's): on unless every camera prior is an "
                        "SfM registration (docs/TRAINING.md)")
    p.add_argument("--max-frames", type=int, metavar="N", help="keep at most N frames of a video")
    p.add_argument("--intrinsics", metavar="FILE|fx,fy,cx,cy", help="camera intrinsics (see agg priors)")
    p.add_argument("--no-resume", action="store_true", help="start over even if SCENE has a checkpoint")
    p.add_argument("--no-eval", action="store_true", help="skip the novel-view evaluation")
    p.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    p.add_argument("--device", default="cpu", help="torch device training runs on: cpu (default), cuda, cuda:N "
                                                   "(the priors run on the CPU)")
    p.set_defaults(func=run)


def _contrast(text: str) -> float | str:
    """``--semantic-min-contrast``: a ratio > 0, or "none" (the loss always on)."""
    if text.lower() == "none":
        return "none"
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a ratio or 'none', got {text!r}") from None
    if not value > 0:
        raise argparse.ArgumentTypeError(f"the ratio must be > 0, got {text!r}")
    return value


class _Bar:
    """tqdm bars for the priors stages and the training iterations."""

    def __init__(self):
        from tqdm import tqdm

        self.tqdm, self.bar, self.key = tqdm, None, None

    def __call__(self, e: dict) -> None:
        if e.get("stage") == "priors":
            key = ("priors", e.get("step"))
            total = e.get("total") or 1
            if key != self.key:
                self.close()
                self.bar, self.key = self.tqdm(total=total, desc=f"priors: {e.get('step')}", leave=False), key
            self.bar.n = e.get("done", 0)
            self.bar.refresh()
        elif e.get("stage") == "train":
            if self.key != "train":
                self.close()
                self.bar, self.key = self.tqdm(total=e["total"], desc="train", unit="it"), "train"
            self.bar.n = e["iteration"]
            self.bar.set_postfix(phase=e["phase"], psnr=f"{e['psnr']:.2f}", gaussians=e["n_gaussians"],
                                 agents=f"+{e['agents_spawned']}/-{e['agents_pruned']}", refresh=False)
            self.bar.refresh()
        elif e.get("event") == "topology" and self.bar is not None:
            self.bar.write(f"topology: {json.dumps(e['report'])}")
        elif e.get("event") == "reanchor" and self.bar is not None:
            self.bar.write(f"spawned boxes re-anchored (offset in m, box frame): {json.dumps(e['reanchored'])}")
        elif e.get("event") == "tracking" and self.bar is not None:
            r = e["report"]
            losses = ", ".join(f"1/{lv['level']}: {lv['loss_first']:.4f} -> {lv['loss_last']:.4f}"
                               for lv in r["levels"])
            self.bar.write(f"camera tracking at iteration {r['iteration']} ({r['seconds']:.0f} s): {losses}")

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar, self.key = None, None


def run(args: argparse.Namespace) -> int:
    from agg.train import reconstruct

    bar = _Bar()
    try:
        overrides = {"iterations": args.iterations} if args.iterations else {}
        given = args.semantic_min_contrast
        if given is not None:
            overrides["semantic_min_contrast"] = None if given == "none" else given
        if args.agent_anchor:
            overrides["agent_anchor"] = args.agent_anchor
        if args.camera_tracking:
            overrides["camera_tracking"] = args.camera_tracking
        summary = reconstruct(args.input, args.output, args.preset, progress=bar, resume=not args.no_resume,
                              overrides=overrides, ablate=args.ablate or None, gt_poses=args.gt_poses,
                              evaluate=not args.no_eval, max_frames=args.max_frames, intrinsics=args.intrinsics,
                              device=args.device)
    except (ValueError, OSError) as exc:
        bar.close()
        print(f"agg reconstruct: error: {exc}", file=sys.stderr)
        return 2
    bar.close()
    if args.json:
        print(json.dumps(summary))
    else:
        m = summary.get("metrics") or {}
        print(f"scene: {args.output}  nodes: {', '.join(summary['nodes'])}  gaussians: {summary['n_gaussians']}  "
              f"agents: {summary['n_agents']} (+{len(summary['agents_spawned'])} spawned, "
              f"-{len(summary['agents_pruned'])} pruned)  train: {summary['seconds_train']:.0f} s")
        gate = summary.get("semantic") or {}
        if gate.get("active") is False:
            print(f"semantic loss: off, {gate['reason']}")
        tracking = summary.get("camera_tracking") or {}
        if tracking.get("active") is False:
            print(f"camera tracking rounds: off, {tracking['reason']}")
        if summary.get("agent_anchor") == "camera" and summary["initial"]["n_agents"]:
            print("agents: the priors' boxes move with the camera's refinement (their tracklets were lifted through "
                  "the estimated cameras; --agent-anchor world keeps them in place)")
        if m:
            agents = "n/a" if m.get("psnr_agents") is None else f"{m['psnr_agents']:.2f} dB"
            ego = f" (the ego vehicle's {100 * m['ego_pixel_share']:.1f} % of the image not scored)" \
                if m.get("ego_pixel_share") else ""
            print(f"NVS ({m['n_test_frames']} held-out frames): PSNR {m['psnr']:.2f} dB  SSIM {m['ssim']:.3f}  "
                  f"agents PSNR {agents}  render {m['render_fps']:.1f} FPS{ego}")
    return 0
