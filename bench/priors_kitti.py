"""Benchmark the camera-pose prior on the real KITTI clip (kitti06_51) without using its GT poses.

Prints one JSON line: registered fraction, ATE RMSE (m and % of path) and RPE after orientation-aware Sim(3)
alignment to GT, the refined focal length, and seconds per stage (feature extraction, matching, mapping,
checks). Usage::

    python bench/priors_kitti.py [--data /work/shared/data/kitti06_51] [--preset accurate|fast]
                                 [--frames N] [--default-intrinsics] [--vo]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from agg.eval.trajectory import evaluate_trajectory, read_kitti_poses
from agg.priors.intrinsics import default_intrinsics, read_kitti_calib
from agg.priors.poses import estimate_poses, PoseConfig

DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "kitti06_51"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA)
    ap.add_argument("--preset", default="accurate", choices=["accurate", "fast"])
    ap.add_argument("--frames", type=int, default=0, help="use the first N frames (0: all)")
    ap.add_argument("--default-intrinsics", action="store_true", help="ignore calib.txt: 60 deg FOV, refined")
    ap.add_argument("--vo", action="store_true", help="OpenCV visual odometry only (the fallback)")
    args = ap.parse_args(argv)
    paths = sorted((args.data / "image_l").glob("*.png"))
    if not paths:
        print(f"no frames under {args.data / 'image_l'}", file=sys.stderr)
        return 1
    if args.frames:
        paths = paths[: args.frames]
    import cv2

    h, w = cv2.imread(str(paths[0]), cv2.IMREAD_GRAYSCALE).shape
    intr = default_intrinsics(w, h) if args.default_intrinsics else read_kitti_calib(args.data / "calib.txt", w, h)
    cfg = PoseConfig.preset(args.preset)
    if args.vo:
        cfg = PoseConfig(**{**cfg.__dict__, "use_sfm": False})
    res = estimate_poses(paths, intr, cfg)
    gt = read_kitti_poses(args.data / "poses.txt")[: len(paths)]  # used for scoring only
    m = evaluate_trajectory(res.world_from_camera, gt)
    m_centre = evaluate_trajectory(res.world_from_camera, gt, rot_weight=0.0)  # classic Umeyama, for comparison
    out = {
        "clip": args.data.name, "frames": len(paths), "preset": args.preset, "method": res.method,
        "intrinsics": res.intrinsics.source, "fx_refined": round(res.intrinsics.fx, 2),
        "registered_fraction": res.registered_fraction, "outliers": res.outliers,
        "sources": {s: res.source.count(s) for s in sorted(set(res.source))},
        "ate_rmse_m": m.ate_rmse, "ate_percent_of_path": m.ate_percent_of_path,
        "rpe_trans_rmse_m": m.rpe_trans_rmse, "rpe_rot_rmse_deg": m.rpe_rot_rmse_deg,
        "ate_rot_mean_deg": m.ate_rot_mean_deg, "ate_percent_centre_only_umeyama": m_centre.ate_percent_of_path, "path_length_m": m.path_length,
        "bend_deg": res.diagnostics.get("bend_deg"), "num_points": int(len(res.points.xyz)),
        "seconds": {k: round(v, 2) for k, v in res.timings_s.items()},
    }
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
