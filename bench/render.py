"""Renderer benchmark: prints exactly one JSON line.

    python bench/render.py --scene FILE.npz [--backend cpu] [--device cuda]
    python bench/render.py --generate OUT.npz --width W --height H --n N --sh D

Scene file keys: means [N,3], quats [N,4] (wxyz), scales [N,3] (linear), opacities [N] (in (0,1)), sh [N,K,3],
viewmat [4,4] (world->camera, OpenCV axes), K [3,3], width, height.

forward_ms: rasterize() under torch.inference_mode (no autograd graph).
forward_backward_ms: L1 on colour against a fixed random target, backward to every parameter and the view matrix.
peak_rss_mb: the process's peak resident set size; peak_gpu_mb: the CUDA allocator's peak (null on CPU).
Times are medians after one warm-up, with 2 torch threads; on a CUDA device each timing waits for the device.
"""

from __future__ import annotations

import argparse
import json
import math
import resource
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from agg.device import synchronize  # noqa: E402
from agg.render import rasterize  # noqa: E402


def generate(path: str, width: int, height: int, n: int, sh_degree: int, seed: int = 0) -> None:
    """The standard scene: N Gaussians filling the frustum at depths 2-30 m.

    Depths are uniform in inverse depth (as a real scene's points are spread over the image) and sizes are set so
    that the summed screen coverage sum_i pi r_i^2 stays about 3x the image area whatever N is.
    """
    rng = np.random.default_rng(seed)
    f = 0.5 * width / math.tan(math.radians(35.0))  # 70 degree horizontal field of view
    K = np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1]], np.float32)
    inv_z = rng.uniform(1 / 30.0, 1 / 2.0, n)
    z = 1.0 / inv_z
    u = rng.uniform(0, width - 1, n)
    v = rng.uniform(0, height - 1, n)
    x = (u - K[0, 2]) / f * z
    y = (v - K[1, 2]) / f * z
    means = np.stack([x, y, z], -1).astype(np.float32)
    # Screen radius r_px = 2 * s * f / z (about 2 sigma visible); choose s so sum(pi r^2) = 3 W H.
    r_px = math.sqrt(3.0 * width * height / (math.pi * n))
    base = r_px * z / (2.0 * f)
    scales = (base[:, None] * rng.uniform(0.5, 1.5, (n, 3))).astype(np.float32)
    quats = rng.normal(size=(n, 4)).astype(np.float32)
    quats /= np.linalg.norm(quats, axis=-1, keepdims=True)
    opacities = rng.uniform(0.1, 0.9, n).astype(np.float32)
    sh = (rng.normal(size=(n, (sh_degree + 1) ** 2, 3)) * 0.2).astype(np.float32)
    sh[:, 0] = rng.uniform(-1.5, 1.5, (n, 3))
    np.savez(path, means=means, quats=quats, scales=scales, opacities=opacities, sh=sh,
             viewmat=np.eye(4, dtype=np.float32), K=K, width=width, height=height)


def bench(path: str, backend: str, repeats: int, device: str = "cpu") -> dict:
    torch.set_num_threads(2)
    dev = torch.device(device)
    data = np.load(path)
    t = {k: torch.from_numpy(np.asarray(data[k])).to(dev)
         for k in ("means", "quats", "scales", "opacities", "sh", "viewmat", "K")}
    width, height = int(data["width"]), int(data["height"])
    kw = dict(K=t["K"], width=width, height=height, backend=backend)

    def forward():
        with torch.inference_mode():
            return rasterize(t["means"], t["quats"], t["scales"], t["opacities"], sh=t["sh"], viewmat=t["viewmat"],
                             **kw)

    target = torch.rand(height, width, 3, generator=torch.Generator().manual_seed(0)).to(dev)

    def forward_backward():
        leaves = {k: v.clone().requires_grad_(True) for k, v in t.items() if k != "K"}
        out = rasterize(leaves["means"], leaves["quats"], leaves["scales"], leaves["opacities"], sh=leaves["sh"],
                        viewmat=leaves["viewmat"], **kw)
        (out.color - target).abs().mean().backward()
        return out

    def timed(fn):
        fn()  # warm-up (also builds the native kernels on first use)
        synchronize(dev)
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            fn()
            synchronize(dev)
            times.append((time.perf_counter() - t0) * 1e3)
        return statistics.median(times)

    fwd = timed(forward)
    fwd_bwd = timed(forward_backward)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    peak_gpu = torch.cuda.max_memory_allocated(dev) / 2**20 if dev.type == "cuda" else None
    out = forward()
    return {
        "scene": Path(path).name,
        "backend": out.meta.backend,
        "device": str(dev),
        "width": width,
        "height": height,
        "n": int(t["means"].shape[0]),
        "sh_degree": int(round(math.sqrt(t["sh"].shape[1]))) - 1,
        "forward_ms": round(fwd, 2),
        "forward_backward_ms": round(fwd_bwd, 2),
        "peak_rss_mb": round(peak, 1),
        "peak_gpu_mb": None if peak_gpu is None else round(peak_gpu, 1),
        "threads": torch.get_num_threads(),
        "repeats": repeats,
    }


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scene", help="scene .npz to benchmark")
    p.add_argument("--backend", default="auto", choices=["auto", "cpu", "cuda", "torch"])
    p.add_argument("--device", default="cpu", help="torch device of the scene tensors (cpu, cuda, cuda:1, ...)")
    p.add_argument("--repeats", type=int, default=7)
    p.add_argument("--generate", metavar="OUT.npz", help="write the standard scene instead of benchmarking")
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=192)
    p.add_argument("--n", type=int, default=200_000)
    p.add_argument("--sh", type=int, default=1, choices=[0, 1, 2, 3])
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args()
    if args.generate:
        generate(args.generate, args.width, args.height, args.n, args.sh, args.seed)
        print(json.dumps({"generated": args.generate, "width": args.width, "height": args.height, "n": args.n,
                          "sh_degree": args.sh}))
        return 0
    if not args.scene:
        p.error("--scene FILE.npz or --generate OUT.npz is required")
    print(json.dumps(bench(args.scene, args.backend, args.repeats, args.device)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
