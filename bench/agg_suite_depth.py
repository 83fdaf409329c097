"""Where the background's held-out error lies by distance, and what the agents and the cameras add to it.

    python bench/agg_suite_depth.py SEED SCENE [SCENE ...] [--work bench/out/agg_suite] [--noise 1.0]
                                    [--agent-noise 0] [--pose-fit 60]

SCENE names a folder under WORK/scenes (a run of ``bench/agg_suite.py`` whose scene is still on disk) trained on the
seed's bundle at ``--noise`` (and ``--agent-noise`` for an agent-noise probe). Only pixels outside the ground-truth
agent masks count. For the held-out frames (cameras and agent poses interpolated as ``agg eval`` does) and for the
training frames (their refined cameras), it prints the pooled PSNR of

- the pixels in each band of ground-truth depth (0-5, 5-10, 10-20, 20-40, over 40 m, and no depth: the sky);
- the bottom third of the image (the road nearest the camera) as rendered, rendered without the agents, and on
  the pixels the agents do not cover (agent alpha under 0.05): the background alone;
- the agents' mean alpha outside the agent masks (how much of the background they paint);
- the median signed relative error of the rendered depth on the bottom third where the render is solid (alpha
  over 0.5): below 0, the near road sits nearer than the truth;

and, with ``--pose-fit N``, the held-out PSNR after N Adam steps fit each held-out camera alone to its frame (the
scene frozen), so a difference that survives it is the scene's and not the interpolated camera's.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from agg_suite import ROOT, bundle_dir  # bench/ is the script's folder, so it is on the path
from agg_suite_scores import load_graph

BANDS_M = (0.0, 5.0, 10.0, 20.0, 40.0, float("inf"))


def _fit_camera(graph, frame: int, cam: torch.Tensor, poses: dict, valid: dict, gt: torch.Tensor,
                background: torch.Tensor, steps: int) -> torch.Tensor:
    """The held-out camera [4, 4] after ``steps`` Adam steps on the background pixels' squared error."""
    from kornia.geometry.liegroup import Se3

    xi = torch.zeros(1, 6, requires_grad=True)  # kornia's se(3) tangent: translation, then rotation vector
    opt = torch.optim.Adam([xi], lr=1e-3)
    for _ in range(steps):
        opt.zero_grad()
        out = graph.render(frame, world_from_camera=cam @ Se3.exp(xi).matrix()[0], agent_poses=poses,
                           agent_valid=valid)
        ((out.color - gt) ** 2)[background].mean().backward()
        opt.step()
    return (cam @ Se3.exp(xi).matrix()[0]).detach()


def depth_errors(scene_dir: Path, bundle_path: Path, pose_fit: int = 0) -> dict:
    """{"test": {...}, "train": {...}} of one scene (see the module doc)."""
    from agg.io.bundle import SceneBundle

    meta = json.loads((scene_dir / "scene.json").read_text())
    graph = load_graph(scene_dir)
    graph.eval()
    for p in graph.parameters():
        p.requires_grad_(False)
    return graph_depth_errors(graph, SceneBundle.load(bundle_path), sorted(meta["train_frames"]),
                              list(meta["test_frames"]), pose_fit)


def graph_depth_errors(graph, bundle, train: list[int], test: list[int], pose_fit: int = 0,
                       bands_only: bool = False) -> dict:
    """``depth_errors`` of a graph in memory (e.g. one still training: ``bench/agg_suite_curve.py``);
    ``bands_only`` skips the renders without the agents and of their alpha (the near-road and alpha scores)."""
    from agg.eval.metrics import psnr_from_mse, squared_error
    from agg.eval.nvs import agent_pose_tables, fit_image, held_out_overrides

    masks, depth = bundle.gt.dynamic_masks, bundle.gt.dense_depth
    tables = agent_pose_tables(graph)
    hidden = {tid: False for ids, _, _ in tables for tid in ids}
    out = {}
    for split, frames in (("test", test), ("train", train)):
        acc: dict[str, list[float]] = {}  # key -> [sum of squared errors, values], pooled over the frames

        def add(key: str, pred: torch.Tensor, sel: torch.Tensor) -> None:
            sse, n = squared_error(pred.clamp(0, 1), gt, sel)  # gt: the frame of this loop iteration
            a = acc.setdefault(key, [0.0, 0])
            a[0] += sse
            a[1] += n

        coverage, depth_bias = [], []
        for f in frames:
            cam, poses, valid = held_out_overrides(graph, train, f, tables) if split == "test" else (None, None, None)
            with torch.no_grad():
                full = graph.render(f, world_from_camera=cam, agent_poses=poses, agent_valid=valid)
            h, w = full.color.shape[:2]
            gt = fit_image(torch.as_tensor(np.array(bundle.frame(f), np.float32)), h, w)  # [H, W, 3]
            m = fit_image(torch.as_tensor(np.array(masks[f], bool))[..., None].float(), h, w, "nearest")[..., 0]
            d = fit_image(torch.as_tensor(np.array(depth[f], np.float32))[..., None], h, w, "nearest")[..., 0]
            bg = m < 0.5  # [H, W]
            add("all", full.color, bg)
            for lo, hi in zip(BANDS_M[:-1], BANDS_M[1:]):
                add(f"{lo:g}-{hi:g}m", full.color, bg & (d > lo) & (d <= hi))
            add("no_depth", full.color, bg & (d <= 0))
            near = bg.clone()
            near[: 2 * h // 3] = False
            add("near", full.color, near)
            solid = near & (d > 0) & (full.alpha > 0.5)
            depth_bias.append(((full.depth[solid] - d[solid]) / d[solid]).numpy())  # relative, signed
            if not bands_only:
                with torch.no_grad():
                    alone = graph.render(f, world_from_camera=cam, agent_poses=poses, agent_valid=hidden)
                    agent = (graph.compose(f)["node"] > 0).float()[:, None].repeat(1, 3)  # [N, 3]
                    cover = graph.render(f, world_from_camera=cam, agent_poses=poses, agent_valid=valid,
                                         colors=agent).color[..., 0]  # [H, W] agents' alpha
                add("near_without_agents", alone.color, near)
                add("near_uncovered", full.color, near & (cover < 0.05))
                coverage.append(float(cover[bg].mean()))
            if split == "test" and pose_fit > 0:
                fitted = _fit_camera(graph, f, cam, poses, valid, gt, bg, pose_fit)
                with torch.no_grad():
                    refit = graph.render(f, world_from_camera=fitted, agent_poses=poses, agent_valid=valid)
                add("all_pose_fit", refit.color, bg)
        out[split] = {k: None if n == 0 else round(psnr_from_mse(sse / n), 2) for k, (sse, n) in acc.items()}
        if coverage:
            out[split]["agent_alpha_outside"] = round(float(np.mean(coverage)), 4)
        bias = np.concatenate(depth_bias)
        out[split]["near_depth_bias"] = round(float(np.median(bias)), 4) if bias.size else None
    return out


def add_finished_scene_args(p: argparse.ArgumentParser) -> None:
    """The arguments that name finished suite scenes: the seed, the scenes (folders under WORK/scenes), ``--work``
    and the camera ``--noise`` of their bundle."""
    p.add_argument("seed", type=int)
    p.add_argument("scenes", nargs="+")
    p.add_argument("--work", default=str(ROOT / "bench" / "out" / "agg_suite"))
    p.add_argument("--noise", type=float, default=1.0)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_finished_scene_args(p)
    p.add_argument("--agent-noise", type=float, default=0.0)
    p.add_argument("--pose-fit", type=int, default=0, help="Adam steps of the held-out camera fit (0: none)")
    args = p.parse_args(argv)
    work = Path(args.work)
    bundle = bundle_dir(work, args.seed, args.noise, args.agent_noise)
    if not (bundle / "manifest.json").is_file():
        raise SystemExit(f"no bundle at {bundle}: run bench/agg_suite.py for seed {args.seed} first")
    for name in args.scenes:
        scene = work / "scenes" / name
        if not (scene / "model.pt").is_file():
            raise SystemExit(f"no finished scene at {scene}")
        print(json.dumps({"scene": name, **depth_errors(scene, bundle, args.pose_fit)}), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
