"""``agg render SCENE (--frame F | --time S | --pose FILE) -o OUT.png|OUT.mp4``: render a trained scene."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch


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
    p.add_argument("--shift", metavar="X,Y,Z", help="move the camera by this offset in its own frame (metres "
                                                   "of the scene), e.g. '-3.5,0,0' for one lane to the left")
    p.add_argument("--what", default="rgb", choices=["rgb", "depth", "alpha", "instances"])
    p.add_argument("--fps", type=float, default=10.0, help="MP4 frame rate")
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


def _image(out, what: str, graph, frame, cam, poses, valid) -> np.ndarray:
    if what == "rgb":
        return (out.color.clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8)
    if what == "alpha":
        return np.repeat((out.alpha.clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8)[..., None], 3, -1)
    if what == "depth":
        d = out.depth.numpy()
        valid_d = d[d > 0]
        hi = np.percentile(valid_d, 98) if valid_d.size else 1.0
        v = (1.0 - np.clip(d / max(hi, 1e-6), 0, 1)) * (d > 0)
        return np.repeat((v * 255).astype(np.uint8)[..., None], 3, -1)
    g = graph.compose(frame, agent_poses=poses, agent_valid=valid)
    onehot = torch.nn.functional.one_hot(g["node"], int(g["node"].max()) + 1).float()
    ids = graph.render(frame, world_from_camera=cam, agent_poses=poses, agent_valid=valid, colors=onehot)
    slot = ids.color.argmax(-1).numpy()
    rng = np.random.default_rng(7)
    palette = np.vstack([[0, 0, 0], rng.integers(60, 255, (max(int(slot.max()), 1), 3))]).astype(np.uint8)
    return palette[np.where(ids.alpha.numpy() > 0.5, slot, 0)]


def run(args: argparse.Namespace) -> int:
    from agg.commands._scene import open_scene
    from agg.eval.interpolate import interpolate_pose

    try:
        meta, graph = open_scene(args.scene)
        n = graph.num_frames
        ts = np.asarray(meta["timestamps_us"], np.float64)
        cams = graph.camera.world_from_camera().detach()  # [T, 4, 4]

        def at_time(s: float) -> float:
            t_us = ts[0] + s * 1e6
            if not ts[0] <= t_us <= ts[-1]:
                raise ValueError(f"time {s} s is outside the clip [0, {(ts[-1] - ts[0]) / 1e6:.3f}] s")
            return float(np.interp(t_us, ts, np.arange(n)))

        jobs = []  # (frame index for the agents, fractional frame, camera pose or None)
        if args.frame is not None:
            jobs = [(f, float(f), None) for f in _frames(args.frame, n)]
        elif args.time is not None:
            x = at_time(args.time)
            jobs = [(int(round(x)), x, None)]
        else:
            m = np.loadtxt(args.pose, dtype=np.float64).reshape(-1)
            if m.size not in (12, 16) or not np.isfinite(m).all():
                raise ValueError(f"{args.pose}: need 12 or 16 finite numbers (a 3x4 or 4x4 world_from_camera)")
            pose = np.eye(4)
            pose[:3] = m.reshape(-1, 4)[:3]
            x = at_time(args.at)
            jobs = [(int(round(x)), x, torch.as_tensor(pose, dtype=torch.float32))]
        shift = None
        if args.shift:
            shift = torch.tensor([float(v) for v in args.shift.split(",")], dtype=torch.float32)
            if shift.shape != (3,):
                raise ValueError("--shift needs three numbers X,Y,Z")
        images = []
        with torch.no_grad():
            for frame, x, cam in jobs:
                lo, hi = int(np.floor(x)), min(int(np.floor(x)) + 1, n - 1)
                if cam is None:
                    cam = interpolate_pose(cams[lo], cams[hi], x - lo) if hi != lo else cams[lo]
                cam = cam.clone()
                if shift is not None:
                    cam[:3, 3] += cam[:3, :3] @ shift
                out = graph.render(frame, world_from_camera=cam)
                images.append(_image(out, args.what, graph, frame, cam, None, None))
        _write(Path(args.output), images, args.fps)
    except (ValueError, OSError) as exc:
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
