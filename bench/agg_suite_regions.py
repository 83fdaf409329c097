"""Where the held-out error of finished suite scenes lies, split by the missed car's path.

    python bench/agg_suite_regions.py SEED SCENE [SCENE ...] [--work bench/out/agg_suite] [--noise 1.0] [--per-agent]

SCENE names a folder under WORK/scenes (a run of ``bench/agg_suite.py`` whose scene is still on disk) trained on the
seed's bundle at ``--noise`` (an ``--oracle-agents`` probe's scene shows the same frames: its bundle differs only in
the priors). Each held-out frame is rendered as ``agg eval`` renders it (cameras and agent poses interpolated from
the training frames) and its squared error is pooled over four sets of pixels, from the ground truth:

- *missed car*: the pixels of the car that the suite's priors miss;
- *other agents*: the pixels of every other agent;
- *path*: outside the agents, within 2.5 m of the missed car's centre at any frame of the clip (a disc at that
  centre's depth, projected into the frame's true camera): where a background that explains the car leaves it;
- *rest*: every other pixel.

Prints, per scene, the pooled PSNR of each set, its share of the pixels and its share of the squared error;
``--per-agent`` adds each ground-truth agent's pixels ("agent ID", a subset of the two agent sets), and
``--per-frame`` each held-out frame's missed-car PSNR with the mean alpha the spawned agents render over its pixels.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np
import torch

from agg_suite import bundle_dir  # bench/ is the script's folder, so it is on the path
from agg_suite_depth import add_finished_scene_args
from agg_suite_scores import load_graph

PATH_RADIUS_M = 2.5


def path_mask(world_from_agent: np.ndarray, camera_from_world: np.ndarray, K: np.ndarray, width: int,  # noqa: N803
              height: int) -> np.ndarray:
    """[H, W] bool: discs of PATH_RADIUS_M around the agent's centre at every frame (world_from_agent [T, 4, 4]),
    seen by one camera (camera_from_world [4, 4], K [3, 3] at width x height)."""
    out = np.zeros((height, width), np.uint8)
    for pose in world_from_agent:
        p = camera_from_world @ pose[:, 3]  # [4] the centre in the camera
        if p[2] <= 0.5:
            continue
        u, v = K[0, 0] * p[0] / p[2] + K[0, 2], K[1, 1] * p[1] / p[2] + K[1, 2]
        r = max(2, int(K[0, 0] * PATH_RADIUS_M / p[2]))
        if -r < u < width + r and -r < v < height + r:
            cv2.circle(out, (int(u), int(v)), r, 1, -1)
    return out > 0


def region_errors(scene_dir: Path, bundle_path: Path, per_agent: bool = False, frames: list | None = None) -> dict:
    """{set: (pooled MSE, pixels)} over the held-out frames of one scene (sets as in the module doc); with
    ``per_agent`` also one set per ground-truth agent id ("agent ID"), which the two agent sets already hold.
    ``frames``: a list that gets (frame, missed-car MSE, spawned agents' mean alpha on the car) per held-out frame."""
    from agg.eval.nvs import agent_pose_tables, fit_image, held_out_overrides
    from agg.io.bundle import SceneBundle
    from agg.synth.suite import load_gt_extras

    bundle, extras = SceneBundle.load(bundle_path), load_gt_extras(bundle_path)
    ids = [a["id"] for a in extras["index"]["agents"]]
    missed = extras["index"]["missed_ids"][0]
    meta = json.loads((scene_dir / "scene.json").read_text())
    train = meta["train_frames"]
    test = [f for f in range(bundle.num_frames) if f not in train]
    graph = load_graph(scene_dir)
    graph.eval()
    tables = agent_pose_tables(graph)
    spawned = torch.zeros(0)  # [N] 1 on the rows of the agents topology evolution spawned
    if frames is not None and graph.rigid is not None:
        sl, node = graph.node_slices()["rigid"], graph.rigid
        rows = torch.isin(node.track_ids[node.instance], torch.as_tensor(meta["summary"]["agents_spawned"]))
        spawned = torch.zeros(graph.num_gaussians())  # compose order: the rigid rows at node_slices()["rigid"]
        spawned[sl.start:sl.stop] = rows.float()
    acc = {k: [0.0, 0] for k in ("missed car", "other agents", "path", "rest")}
    extra: dict[str, list] = {}  # per-agent sets (overlap the agent sets above)
    for f in test:
        with torch.no_grad():
            cam, poses, valid = held_out_overrides(graph, train, f, tables)
            pred = graph.render(f, world_from_camera=cam, agent_poses=poses, agent_valid=valid).color.clamp(0, 1)
        h, w = pred.shape[:2]
        gt = fit_image(torch.as_tensor(np.asarray(bundle.frame(f), np.float32)), h, w).numpy()
        err = ((pred.numpy() - gt) ** 2).mean(-1)  # [h, w]
        inst = cv2.resize(extras["instance"][f].astype(np.int32), (w, h), interpolation=cv2.INTER_NEAREST)
        k = np.asarray(bundle.gt.intrinsics)[f] * np.array([[w / bundle.width], [h / bundle.height], [1.0]])
        on_car, on_agents = inst == missed, (inst > 0) & (inst != missed)
        on_path = path_mask(extras["world_from_agent"][ids.index(missed)],
                            np.linalg.inv(np.asarray(bundle.gt.world_from_camera)[f]), k, w, h) & (inst == 0)
        for name, m in (("missed car", on_car), ("other agents", on_agents), ("path", on_path),
                        ("rest", ~(on_car | on_agents | on_path))):
            acc[name][0] += float(err[m].sum())
            acc[name][1] += int(m.sum())
        if frames is not None:
            alpha = 0.0
            if spawned.numel():
                with torch.no_grad():
                    alpha = float(graph.render(f, world_from_camera=cam, agent_poses=poses, agent_valid=valid,
                                               colors=spawned[:, None]).color[..., 0].numpy()[on_car].mean())
            frames.append((f, float(err[on_car].mean()), alpha))
        for a in np.unique(inst[inst > 0]) if per_agent else ():
            cell = extra.setdefault(f"agent {a}", [0.0, 0])
            cell[0] += float(err[inst == a].sum())
            cell[1] += int((inst == a).sum())
    acc.update(sorted(extra.items(), key=lambda kv: int(kv[0].split()[1])))
    return {k: (v[0] / max(v[1], 1), v[1]) for k, v in acc.items()}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_finished_scene_args(p)
    p.add_argument("--per-agent", action="store_true", help="also each ground-truth agent's pixels (by id)")
    p.add_argument("--per-frame", action="store_true",
                   help="also each held-out frame's missed-car PSNR and the spawned agents' alpha on it")
    args = p.parse_args(argv)
    work = Path(args.work)
    for name in args.scenes:
        frames = [] if args.per_frame else None
        sets = region_errors(work / "scenes" / name, bundle_dir(work, args.seed, args.noise), args.per_agent, frames)
        disjoint = {k: v for k, v in sets.items() if not k.startswith("agent ")}
        sse, n = sum(m * c for m, c in disjoint.values()), sum(c for _, c in disjoint.values())
        print(f"{name}: pooled {-10 * np.log10(sse / n):.2f} dB;", "; ".join(
            f"{k} {-10 * np.log10(max(m, 1e-12)):.2f} dB ({100 * c / n:.1f} % px, {100 * m * c / sse:.1f} % err)"
            for k, (m, c) in sets.items()), flush=True)
        for f, mse, alpha in frames or ():
            print(f"  frame {f}: missed car {-10 * np.log10(max(mse, 1e-12)):.2f} dB, spawned agents' alpha on it "
                  f"{alpha:.2f}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
