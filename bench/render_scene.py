"""Serving speed of a trained scene: ``Scene.render`` at every frame of the clip, as the gRPC server renders it.
Prints exactly one JSON line.

    python bench/render_scene.py SCENE [--device cuda] [--scale 4] [--outputs rgb|all] [--compare cpu]

Each render composes the graph at the frame's time (agents posed, non-rigid agents deformed), rasterises it from
the frame's refined camera and copies the requested outputs to host arrays: the whole cost of one served view.
``--scale S`` renders at S times the training resolution (intrinsics scaled about pixel centres), e.g. the
video's own resolution. ``--compare DEVICE`` renders the same views on a second device and reports the PSNR between
the two (rgb), which checks that backends agree on a trained scene. Times: median and p90 over all frames of
``--repeats`` passes, after one warm-up render; on CUDA each render ends with the copy to the host, so no extra
synchronisation is needed.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from agg.device import resolve_device  # noqa: E402
from agg.eval.metrics import psnr  # noqa: E402
from agg.render.rasterize import _choose_backend  # noqa: E402
from agg.scene import Scene  # noqa: E402


def scaled_K(K: np.ndarray, s: float) -> np.ndarray:  # noqa: N802
    """[3, 3] intrinsics of an image s times larger (pixel (i, j) sampled at (j, i), OpenCV)."""
    k = K.copy()
    k[0, 0], k[1, 1] = K[0, 0] * s, K[1, 1] * s
    k[0, 2], k[1, 2] = (K[0, 2] + 0.5) * s - 0.5, (K[1, 2] + 0.5) * s - 0.5
    return k


def views(scene: Scene, s: float) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """(timestamp_us, world_from_camera [4, 4], K [3, 3]) of every frame of the clip."""
    cams, Ks = scene.world_from_camera(), scene.K  # noqa: N806
    return [(int(scene.timestamps_us[f]), cams[f], scaled_K(Ks[min(f, len(Ks) - 1)], s))
            for f in range(scene.num_frames)]


def render_all(scene: Scene, jobs, width: int, height: int, outputs) -> tuple[list[float], list[dict]]:
    times, results = [], []
    for t_us, cam, K in jobs:  # noqa: N806
        t0 = time.perf_counter()
        res = scene.render(t_us, cam, K, width, height, outputs=outputs)
        times.append((time.perf_counter() - t0) * 1e3)
        results.append(res)
    return times, results


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scene", help="scene folder written by agg reconstruct (model.pt and scene.json are read)")
    p.add_argument("--device", default="cpu")
    p.add_argument("--scale", type=float, default=1.0, help="render at this multiple of the training resolution")
    p.add_argument("--outputs", default="rgb", choices=["rgb", "all"])
    p.add_argument("--repeats", type=int, default=3, help="passes over the clip")
    p.add_argument("--compare", metavar="DEVICE", help="also render on DEVICE and report the rgb PSNR between them")
    p.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    outputs = ("rgb",) if a.outputs == "rgb" else ("rgb", "depth", "alpha", "instance")
    scene = Scene.load(a.scene, device=resolve_device(a.device))
    width, height = int(round(scene.width * a.scale)), int(round(scene.height * a.scale))
    jobs = views(scene, a.scale)
    render_all(scene, jobs[:1], width, height, outputs)  # warm-up (kernel builds, allocator)
    times, results = [], []
    for _ in range(a.repeats):
        t, results = render_all(scene, jobs, width, height, outputs)
        times += t
    with torch.no_grad():
        n = int(scene.graph.compose(0)["means"].shape[0])
    row = {
        "scene": Path(a.scene).name,
        "device": str(scene.device),
        "backend": _choose_backend("auto", scene.graph.K),
        "width": width,
        "height": height,
        "frames": len(jobs),
        "n_gaussians": n,
        "outputs": a.outputs,
        "render_ms_median": round(statistics.median(times), 2),
        "render_ms_p90": round(float(np.percentile(times, 90)), 2),
        "fps": round(1e3 / statistics.median(times), 1),
        "peak_gpu_mb": round(torch.cuda.max_memory_allocated(scene.device) / 2**20, 1)
        if scene.device.type == "cuda" else None,
        "threads": torch.get_num_threads(),
        "repeats": a.repeats,
    }
    if a.compare:
        other = Scene.load(a.scene, device=resolve_device(a.compare))
        _, ref = render_all(other, jobs, width, height, ("rgb",))
        values = [psnr(x["rgb"], y["rgb"]) for x, y in zip(results, ref)]
        row.update({"compare_device": a.compare, "compare_psnr_min": round(min(values), 2),
                    "compare_psnr_mean": round(float(np.mean(values)), 2)})
    print(json.dumps(row))
    return 0


if __name__ == "__main__":
    sys.exit(main())
