"""``agg priors``: turn a video, an image folder, a dataset folder or a bundle into a scene bundle of priors.

Stable interface: ``agg priors INPUT -o BUNDLE [--intrinsics ...] [--max-frames ...] [--poses-out POSES.txt]``.
``--poses-out`` writes the estimated ``world_from_camera`` of every input frame in KITTI format (one row-major
3x4 matrix per line, input order); frames that could not be registered are interpolated and listed in the
summary. See docs/PRIORS.md.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from agg.priors.pipeline import STAGES


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "priors", help="estimate camera poses, depth, dynamic masks, tracklets and features (a scene bundle)",
        description="Ingest INPUT (a video file; an image folder; a KITTI odometry, nerfstudio or COLMAP folder; "
                    "or a scene bundle) and estimate the priors it lacks. Writes BUNDLE/priors_summary.json and "
                    "PNG previews in BUNDLE/previews/.")
    p.add_argument("input", metavar="INPUT", help="video file, image folder, dataset folder or scene bundle")
    p.add_argument("-o", "--output", required=True, metavar="BUNDLE", help="output bundle folder")
    p.add_argument("--intrinsics", metavar="FILE|fx,fy,cx,cy",
                   help="OpenCV YAML/XML (K, dist, image_size), KITTI calib.txt (P0), a text file with the 9 "
                        "numbers of K, or 'fx,fy,cx,cy' in source pixels (default: 60 deg field of view, refined)")
    g = p.add_argument_group("sampling (videos and image folders)")
    g.add_argument("--max-frames", type=int, metavar="N", help="keep at most N frames")
    g.add_argument("--fps", type=float, help="target frame rate")
    g.add_argument("--stride", type=int, default=1, help="keep every N-th frame (default 1)")
    g.add_argument("--start", type=float, default=0.0, metavar="S", help="first second kept")
    g.add_argument("--end", type=float, metavar="S", help="second where sampling stops")
    g.add_argument("--width", type=int, help="training width in pixels (default: the source's)")
    g.add_argument("--height", type=int, help="training height in pixels (default: keep the aspect ratio)")
    g = p.add_argument_group("priors")
    g.add_argument("--preset", default="fast", choices=["fast", "accurate"],
                   help="pose estimation: fast = SfM at half resolution (default), accurate = full resolution")
    g.add_argument("--poses", metavar="POSES.txt", help="given camera-to-world poses (KITTI format): not estimated")
    g.add_argument("--poses-out", metavar="POSES.txt", help="also write the poses of every frame in KITTI format")
    g.add_argument("--features", default="builtin", choices=["builtin", "dino"], help="semantic feature backend")
    g.add_argument("--weights", metavar="PATH", help="local DINOv2/v3 checkpoint folder (with --features dino)")
    g.add_argument("--prototypes", metavar="BANK.npz", help="prototype bank from 'agg prototypes'")
    g.add_argument("--mono-depth", metavar="MODEL.pt", help="local TorchScript monocular depth model")
    g.add_argument("--stages", default=",".join(STAGES), help=f"comma-separated subset of {','.join(STAGES)}")
    g.add_argument("--recompute", default="", help="stages to run even when the input already has their part")
    p.add_argument("--no-previews", action="store_true", help="skip the PNG previews")
    p.add_argument("--overwrite", action="store_true", help="replace BUNDLE if it exists")
    p.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    p.set_defaults(func=run)


def parse_intrinsics(spec: str) -> tuple[np.ndarray, np.ndarray | None, tuple[int, int] | None]:
    """(K [3, 3], dist [5] or None, calibration size (W, H) or None) from the --intrinsics value."""
    from agg.io.errors import CalibrationError
    from agg.io.importers.kitti import read_calib
    from agg.io.video import load_opencv_calibration

    path = Path(spec)
    if path.suffix.lower() in (".yml", ".yaml", ".xml", ".json") and path.is_file():
        K, dist, size = load_opencv_calibration(path)  # noqa: N806
        return K, dist, size
    if path.is_file():
        text = path.read_text()
        if "P0" in text:
            return read_calib(path)["P0"][:, :3], None, None
        vals = np.array(text.split(), float)
        if vals.size != 9:
            raise CalibrationError(f"{path}: expected the 9 numbers of K (row-major) or a KITTI calib.txt")
        return vals.reshape(3, 3), None, None
    try:
        fx, fy, cx, cy = (float(v) for v in spec.split(","))
    except ValueError:
        raise CalibrationError(f"--intrinsics {spec!r}: not a file and not 'fx,fy,cx,cy'") from None
    return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]]), None, None


def open_input(args) -> "SceneBundle":  # noqa: F821
    """Ingest or import INPUT into the output bundle (see the command's description)."""
    from agg.io.bundle import SceneBundle
    from agg.io.importers import import_colmap, import_kitti, import_nerfstudio
    from agg.io.video import IngestConfig, ingest_to_bundle

    src, out = Path(args.input), Path(args.output)
    if not src.exists():
        raise FileNotFoundError(f"{src}: no such file or folder")
    cfg = IngestConfig(fps=args.fps, stride=args.stride, start_s=args.start, end_s=args.end,
                       max_frames=args.max_frames, width=args.width, height=args.height, dtype="uint8")
    if args.intrinsics:
        K, dist, size = parse_intrinsics(args.intrinsics)  # noqa: N806
        cfg = replace(cfg, K=K.tolist(), dist=None if dist is None else dist.tolist(), calib_size=size)
    if src.is_dir() and (src / "manifest.json").is_file():
        if src.resolve() != out.resolve():
            if out.exists() and not args.overwrite:
                raise FileExistsError(f"{out} exists (pass --overwrite to replace it)")
            shutil.rmtree(out, ignore_errors=True)
            shutil.copytree(src, out)
        return SceneBundle.load(out)
    if src.is_dir() and (src / "calib.txt").is_file() and any((src / d).is_dir() for d in ("image_l", "image_0")):
        # KITTI odometry: calib.txt gives the intrinsics; poses.txt, if any, goes to the gt/ sidecar only
        return import_kitti(src, out, with_poses=False, gt_poses=(src / "poses.txt").is_file(), config=cfg,
                            overwrite=args.overwrite)
    if src.is_dir() and (src / "transforms.json").is_file() or src.name == "transforms.json":
        return import_nerfstudio(src, out, config=cfg, overwrite=args.overwrite)
    if src.is_dir() and (src / "sparse" / "0").is_dir() and (src / "images").is_dir():
        return import_colmap(src / "sparse" / "0", src / "images", out, config=cfg, overwrite=args.overwrite)
    return ingest_to_bundle(src, out, cfg, overwrite=args.overwrite)


class _Bars:
    """One tqdm bar per stage, fed by the pipeline's (stage, done, total) callback."""

    def __init__(self):
        self.bar, self.stage = None, None

    def __call__(self, stage: str, done: int, total: int) -> None:
        from tqdm import tqdm

        if stage != self.stage:
            self.close()
            self.stage = stage
            self.bar = tqdm(total=total, desc=f"{stage:>10}", unit="frame" if total > 1 else "step",
                            file=sys.stderr, dynamic_ncols=True)
        self.bar.n = done
        self.bar.refresh()

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None


def run(args: argparse.Namespace) -> int:
    from agg.priors.pipeline import PriorsConfig, run_priors
    from agg.priors.poses import write_kitti_poses
    from agg.priors.previews import write_previews

    stages = tuple(s for s in args.stages.split(",") if s)
    recompute = tuple(s for s in args.recompute.split(",") if s)
    try:
        config = PriorsConfig(pose_preset=args.preset, stages=stages, recompute=recompute,
                              feature_backend=args.features, feature_weights=args.weights,
                              prototypes=args.prototypes, mono_depth_weights=args.mono_depth)
        if args.features == "dino" and not args.weights:
            raise ValueError("--features dino needs --weights PATH (a local DINOv2/v3 checkpoint; docs/PRIORS.md)")
        bundle = open_input(args)
        if args.poses:
            from agg.io.importers.kitti import read_poses

            given = read_poses(args.poses)
            if len(given) != bundle.num_frames:
                raise ValueError(f"{args.poses} has {len(given)} poses for {bundle.num_frames} frames")
            bundle.write_poses(given, source="given", rebase=True)
        bars = _Bars()
        try:
            summary = run_priors(bundle, config, progress=bars)
        finally:
            bars.close()
    except (ValueError, OSError) as exc:  # every agg input error is a ValueError; missing/existing paths OSError
        print(f"agg priors: error: {exc}", file=sys.stderr)
        return 2
    if args.poses_out:
        write_kitti_poses(args.poses_out, bundle.world_from_camera)
    previews = [] if args.no_previews else write_previews(bundle, bundle.path / "previews")
    out = summary.as_dict()
    out["previews"] = [str(p) for p in previews]
    if args.poses_out:
        out["poses_out"] = str(args.poses_out)
    (bundle.path / "priors_summary.json").write_text(json.dumps(out, indent=1))
    print(json.dumps(out) if args.json else format_summary(out))
    return 0


def format_summary(s: dict) -> str:
    """A few human lines from the summary dict."""
    lines = [f"bundle {s['bundle']}: {s['num_frames']} frames at {s['width']}x{s['height']}"]
    p = s.get("poses") or {}
    if "registered_fraction" in p:
        interp = p.get("interpolated_frames") or []
        lines.append(f"poses: {p['method']}, registered {p['registered']}/{s['num_frames']} "
                     f"({100 * p['registered_fraction']:.0f} %), outliers {p['outliers']}, "
                     f"interpolated frames {interp if interp else 'none'}")
    elif p:
        lines.append(f"poses: {p.get('source')}")
    if s.get("depth"):
        lines.append("depth: " + ", ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}"
                                           for k, v in s["depth"].items()))
    if s.get("masks"):
        m = s["masks"]
        ego = f", ego vehicle {100 * m['ego_share']:.1f} % of the image (not trained or scored)" \
            if m.get("ego_share") else ""
        lines.append(f"masks: {100 * m['coverage']:.2f} % of pixels, {m['frames_with_mask']} frames with a mask{ego}")
    if s.get("tracklets"):
        t = s["tracklets"]
        filled = t.get("filled_per_track") or []
        lines.append(f"tracklets: {t['count']} ({', '.join(t['classes']) or '-'}), frames {t['frames_per_track']}"
                     + (f" ({filled} filled across gaps)" if any(filled) else ""))
    if s.get("semantics"):
        m = s["semantics"]
        lines.append(f"semantics: {m['backend']}, {m['channels']} channels at {m['size_hw']}, "
                     f"|C_bg| {len(m['C_bg'])}, |C_ag| {len(m['C_ag'])}, prototypes {m['prototypes']}")
    for k, v in (s.get("skipped") or {}).items():
        lines.append(f"skipped {k}: {v}")
    if s.get("scores"):
        lines.append("scores vs gt/: " + json.dumps(s["scores"]))
    lines.append("seconds: " + ", ".join(f"{k} {v:.1f}" for k, v in s["seconds"].items()))
    if s.get("previews"):
        lines.append("previews: " + ", ".join(s["previews"]))
    return "\n".join(lines)
