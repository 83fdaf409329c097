"""``agg render SCENE (--frame F | --time S | --pose FILE) -o OUT.png|OUT.mp4``: render a trained scene."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

from agg.eval.interpolate import interpolate_pose
from agg.io.video import intrinsics_at


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("render", help="render a trained scene at frames, times or a given camera pose",
                              description="Render RGB (or depth, alpha, instance ids) of a trained scene. One "
                                          "frame writes a PNG; several (--frame all, 0:50, --time ranges) an MP4.")
    p.add_argument("scene", metavar="SCENE")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--frame", metavar="F", help="frame index, 'A:B[:STEP]' range or 'all'")
    src.add_argument("--time", type=float, metavar="S", help="seconds from the first frame (poses interpolated)")
    src.add_argument("--pose", metavar="FILE",
                     help="text file with a 4x4 (or 3x4) world_from_camera matrix (OpenCV axes), rendered at --at")
    p.add_argument("--at", type=float, default=0.0, metavar="S", help="time (s) of the agents for --pose")
    p.add_argument("--shift", metavar="X,Y,Z", help="move the camera by this offset in its own frame, in metres "
                                                   "(scene units through the scene's metric_scale, an estimate for a "
                                                   "video), e.g. '-3.5,0,0' for one lane to the left")
    p.add_argument("--what", default="rgb", choices=["rgb", "depth", "alpha", "instances"])
    p.add_argument("--fps", type=float, default=10.0, help="MP4 frame rate")
    p.add_argument("--device", default="cpu", help="torch device to render on: cpu (default), cuda, cuda:N")
    p.add_argument("-o", "--output", required=True, metavar="OUT.png|OUT.mp4")
    p.set_defaults(func=run)


def _frames(spec: str, n: int) -> list[int]:
    if spec == "all":
        return list(range(n))
    if ":" in spec:
        parts = [int(x) if x else None for x in spec.split(":")]
        return list(range(n))[slice(*parts)]
    f = int(spec)
    if not 0 <= f < n:
        raise ValueError(f"frame {f} is out of range [0, {n})")
    return [f]


def _image(res: dict, what: str) -> np.ndarray:
    """[H, W, 3] uint8 picture of one output of ``Scene.render``."""
    if what == "rgb":
        return (res["rgb"] * 255 + 0.5).astype(np.uint8)
    if what == "alpha":
        return np.repeat((np.clip(res["alpha"], 0, 1) * 255 + 0.5).astype(np.uint8)[..., None], 3, -1)
    if what == "depth":
        d = res["depth"]
        valid_d = d[d > 0]
        hi = np.percentile(valid_d, 98) if valid_d.size else 1.0
        v = (1.0 - np.clip(d / max(hi, 1e-6), 0, 1)) * (d > 0)
        return np.repeat((v * 255).astype(np.uint8)[..., None], 3, -1)
    ids = res["instance"]  # [H, W] track ids, 0 = none
    rng = np.random.default_rng(7)
    palette = np.vstack([[0, 0, 0], rng.integers(60, 255, (int(ids.max()) if ids.size else 0, 3))]).astype(np.uint8)
    return palette[ids]


def run(args: argparse.Namespace) -> int:
    from agg.device import resolve_device
    from agg.scene import Scene, SceneNotReady, SceneUnreadable

    output = {"rgb": "rgb", "depth": "depth", "alpha": "alpha", "instances": "instance"}[args.what]
    try:
        scene = Scene.load(args.scene, device=resolve_device(args.device))
        n, ts = scene.num_frames, scene.timestamps_us

        def at_time(s: float) -> int:  # timestamp of a time in seconds from the first frame
            return int(round(ts[0] + s * 1e6))

        jobs = []  # (timestamp_us, world_from_camera [4, 4] or None: the refined camera at that time)
        if args.frame is not None:
            jobs = [(int(ts[f]), None) for f in _frames(args.frame, n)]
        elif args.time is not None:
            jobs = [(at_time(args.time), None)]
        else:
            m = np.loadtxt(args.pose, dtype=np.float64).reshape(-1)
            if m.size not in (12, 16) or not np.isfinite(m).all():
                raise ValueError(f"{args.pose}: need 12 or 16 finite numbers (a 3x4 or 4x4 world_from_camera)")
            pose = np.eye(4)
            pose[:3] = m.reshape(-1, 4)[:3]
            jobs = [(at_time(args.at), pose)]
        shift = None
        if args.shift:
            shift = np.array([float(v) for v in args.shift.split(",")])
            if shift.shape != (3,) or not np.isfinite(shift).all():
                raise ValueError("--shift needs three finite numbers X,Y,Z")
            if scene.metres_per_unit is None:
                print("agg render: scene.json has no metric_scale (trained before it was recorded): --shift is read "
                      "in scene units", file=sys.stderr)
            else:
                shift = shift / scene.metres_per_unit  # metres -> scene units
        cams = torch.as_tensor(scene.world_from_camera(), dtype=torch.float32)  # [T, 4, 4]
        images = []
        for t_us, cam in jobs:
            x = scene.frame_at(t_us)
            lo = int(np.floor(x))
            hi = min(lo + 1, n - 1)
            if cam is None:
                cam = (interpolate_pose(cams[lo], cams[hi], x - lo) if hi != lo else cams[lo]).numpy()
            cam = np.array(cam, np.float64)
            if shift is not None:
                cam[:3, 3] += cam[:3, :3] @ shift
            K = intrinsics_at(scene.K, lo)  # noqa: N806
            res = scene.render(t_us, cam, K, scene.width, scene.height, outputs=(output,))
            images.append(_image(res, args.what))
        _write(Path(args.output), images, args.fps)
    except (ValueError, OSError, SceneNotReady, SceneUnreadable) as exc:
        print(f"agg render: error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {args.output} ({len(images)} frame{'s' if len(images) > 1 else ''})")
    return 0


def _write(path: Path, images: list[np.ndarray], fps: float) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix.lower() == ".png":
        if len(images) != 1:
            raise ValueError("a PNG holds one frame: use an .mp4 output for several")
        import cv2

        cv2.imwrite(str(path), cv2.cvtColor(images[0], cv2.COLOR_RGB2BGR))
        return
    if path.suffix.lower() != ".mp4":
        raise ValueError("output must end in .png or .mp4")
    import av

    h, w = images[0].shape[:2]
    with av.open(str(path), "w") as container:
        stream = container.add_stream("libx264", rate=int(round(fps)))
        stream.width, stream.height = w - w % 2, h - h % 2
        stream.pix_fmt = "yuv420p"
        for img in images:
            frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(img[: h - h % 2, : w - w % 2]), format="rgb24")
            container.mux(stream.encode(frame))
        container.mux(stream.encode())
