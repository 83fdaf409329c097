"""``agg demo-render``: fit 3D Gaussians to a frame of the bundled dashcam clip with the CPU renderer.

It shows the renderer training at interactive speed on a CPU: Gaussians start at random depths along random pixel
rays with noisy colours, then Adam fits them to the frame. Writes ``fit.png`` (target | render | depth) and
``metrics.json`` to ``--out``. (``agg demo``, the README's main command, runs the whole service: service/demo.py.)
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

SAMPLE = Path(__file__).resolve().parents[2] / "samples" / "dashcam.mp4"


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo-render", help="fit Gaussians to a frame of the bundled sample clip (renderer demo)",
                       description=__doc__)
    p.add_argument("--video", type=Path, default=SAMPLE, help="video to take the frame from")
    p.add_argument("--frame", type=int, default=0, help="frame index")
    p.add_argument("--width", type=int, default=320, help="training width in px (height keeps the aspect)")
    p.add_argument("--gaussians", type=int, default=20_000)
    p.add_argument("--steps", type=int, default=300)
    p.add_argument("--backend", default="auto", choices=["auto", "cpu", "torch", "cuda"])
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=Path("runs/demo-render"))
    p.set_defaults(func=run)


def read_frame(path: Path, index: int, width: int):
    """One RGB frame as float32 [H, W, 3] in [0, 1], resized to ``width`` (aspect kept)."""
    from agg.io.video import IngestConfig, ingest

    result = ingest(path, IngestConfig(width=width, max_frames=index + 1, min_frames=index + 1))
    return result.frames[index]


def run(args: argparse.Namespace) -> int:
    import numpy as np
    import torch
    from PIL import Image
    from tqdm import tqdm

    from agg.render import rasterize

    torch.manual_seed(args.seed)
    target = torch.from_numpy(read_frame(args.video, args.frame, args.width))  # [H, W, 3]
    H, W = target.shape[:2]
    f = 0.5 * W / math.tan(math.radians(30.0))  # a 60 degree horizontal field of view
    K = torch.tensor([[f, 0, (W - 1) / 2], [0, f, (H - 1) / 2], [0, 0, 1]])
    view = torch.eye(4)

    n = args.gaussians
    g = torch.Generator().manual_seed(args.seed)
    u = torch.rand(n, generator=g) * (W - 1)
    v = torch.rand(n, generator=g) * (H - 1)
    z = 1.0 / torch.empty(n).uniform_(1 / 40.0, 1 / 3.0, generator=g)  # depths 3-40 m, uniform in 1/z
    means = torch.stack([(u - K[0, 2]) / f * z, (v - K[1, 2]) / f * z, z], -1)
    pix = target[v.round().long(), u.round().long()]  # [n, 3]
    noisy = (pix + 0.2 * torch.randn(n, 3, generator=g)).clamp(0.02, 0.98)
    radius_px = math.sqrt(2.0 * W * H / (math.pi * n))
    params = {
        "means": means,
        "quats": torch.randn(n, 4, generator=g),
        "log_scales": torch.log(radius_px * z / f).unsqueeze(-1).repeat(1, 3),
        "opacity_logits": torch.full((n,), 1.0),
        "color_logits": torch.logit(noisy),
    }
    params = {k: t.requires_grad_(True) for k, t in params.items()}
    lrs = {"means": 2e-3, "quats": 1e-2, "log_scales": 1e-2, "opacity_logits": 5e-2, "color_logits": 5e-2}
    opt = torch.optim.Adam([{"params": [params[k]], "lr": lr} for k, lr in lrs.items()])

    def render():
        return rasterize(params["means"], params["quats"], params["log_scales"].exp(),
                         torch.sigmoid(params["opacity_logits"]), torch.sigmoid(params["color_logits"]), K=K,
                         width=W, height=H, viewmat=view, background=torch.zeros(3), backend=args.backend)

    def psnr(img):
        return float(-10 * torch.log10(((img - target) ** 2).mean()))

    t0 = time.perf_counter()
    with tqdm(range(args.steps), desc=f"fitting {n} Gaussians to {W}x{H}", unit="step") as bar:
        for step in bar:
            out = render()
            loss = (out.color - target).abs().mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            if step % 10 == 0 or step == args.steps - 1:
                bar.set_postfix(loss=f"{loss.item():.4f}", psnr=f"{psnr(out.color.detach()):.2f} dB")
    train_s = time.perf_counter() - t0

    with torch.no_grad():
        out = render()
        t1 = time.perf_counter()
        render()
        render_ms = (time.perf_counter() - t1) * 1e3
    final_psnr = psnr(out.color)
    depth = out.depth / out.depth.max().clamp_min(1e-6)
    panel = torch.cat([target, out.color.clamp(0, 1), depth.unsqueeze(-1).expand(-1, -1, 3)], 1)
    args.out.mkdir(parents=True, exist_ok=True)
    Image.fromarray((panel.numpy() * 255).round().astype(np.uint8)).save(args.out / "fit.png")
    metrics = {
        "psnr_db": round(final_psnr, 2),
        "steps": args.steps,
        "gaussians": n,
        "width": W,
        "height": H,
        "backend": out.meta.backend,
        "train_seconds": round(train_s, 2),
        "ms_per_step": round(train_s / max(args.steps, 1) * 1e3, 1),
        "render_ms": round(render_ms, 1),
    }
    (args.out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    print(json.dumps(metrics))
    print(f"wrote {args.out / 'fit.png'} (target | render | depth)")
    return 0
