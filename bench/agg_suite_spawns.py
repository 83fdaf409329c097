"""What the agents that topology evolution spawned render in finished scenes.

    python bench/agg_suite_spawns.py SCENE_DIR [SCENE_DIR ...]

For each scene (a finished ``agg reconstruct`` folder whose bundle is still where scene.json says): every agent
instance's Gaussian count, valid frames, box half extents and the median / 90 % distance of its canonical
Gaussians from its box origin (metres, by the run's metric scale); then the held-out frames (rendered as ``agg
eval`` renders them) with and without the spawned instances, the squared error pooled over the frames inside the
priors' dynamic masks, outside them and over the whole image; and each spawned instance's rendered alpha summed
inside and outside the masks (the pixels it covers).
"""
import sys
from pathlib import Path

import numpy as np
import torch

from agg.eval.nvs import agent_pose_tables, fit_image, held_out_overrides
from agg.io.bundle import SceneBundle
from agg.scene import Scene
from agg.train.data import resize_images


def main(d) -> None:
    d = Path(d)
    scene = Scene.load(d)
    meta = scene.meta
    graph = scene.graph
    graph.eval()
    bundle = SceneBundle.load(meta["bundle"])
    summ = meta["summary"]
    spawned = set(int(t) for t in summ["agents_spawned"])
    node = graph.rigid
    ids = node.track_ids.tolist() if node is not None else []
    live = [t for t in ids if t in spawned]
    scale = meta.get("metric_scale", {}).get("metres_per_unit") if isinstance(meta.get("metric_scale"), dict) else None
    print("spawned", sorted(spawned), "alive", live, "metric", meta.get("metric_scale"))
    if node is not None:
        inst = node.instance.cpu().numpy()
        means = node.gaussians.means.detach().cpu().numpy()
        for k, tid in enumerate(ids):
            m = means[inst == k]
            r = np.linalg.norm(m, axis=1) if len(m) else np.zeros(1)
            extra = ""
            if scale:
                extra = f" r50 {np.median(r) * scale:.1f} m r90 {np.quantile(r, 0.9) * scale:.1f} m"
            print(f"  track {tid} {'spawn' if tid in spawned else 'prior'}: {len(m)} gaussians, "
                  f"valid {int(node.valid[:, k].sum())} frames, half {node.half_extents[k].tolist()}{extra}")
    test = sorted(set(meta["test_frames"]))
    train = meta["train_frames"]
    images = resize_images(bundle.frames[:], graph.width, graph.height)
    masks = np.asarray(bundle.dynamic_masks[:]) > 0
    tables = agent_pose_tables(graph)
    spawn_rows = torch.zeros(graph.compose(test[0])["means"].shape[0], max(len(live), 1))
    sl = graph.node_slices()["rigid"]
    for c, tid in enumerate(live):
        spawn_rows[sl.start:sl.stop, c] = (node.instance == ids.index(tid)).float()
    acc = {"with": [0.0, 0.0, 0.0], "without": [0.0, 0.0, 0.0]}  # sse all, sse in, sse out
    n_in = n_all = 0
    cov_in = np.zeros(max(len(live), 1))
    cov_out = np.zeros(max(len(live), 1))
    with torch.no_grad():
        for f in test:
            cam, poses, valid = held_out_overrides(graph, train, f, tables)
            gt = images[f]  # [H, W, 3]
            m = fit_image(torch.as_tensor(masks[f])[..., None], graph.height, graph.width, "nearest")[..., 0] > 0
            for name in acc:
                v = dict(valid)
                if name == "without":
                    v.update({t: False for t in live})
                out = graph.render(f, world_from_camera=cam, agent_poses=poses, agent_valid=v)
                err = ((out.color.clamp(0, 1) - gt) ** 2).sum(-1)  # [H, W]
                acc[name][0] += float(err.sum())
                acc[name][1] += float(err[m].sum())
                acc[name][2] += float(err[~m].sum())
            cov = graph.render(f, world_from_camera=cam, agent_poses=poses, agent_valid=valid,
                               colors=spawn_rows).color  # [H, W, S]
            cov_in += cov[m].sum(0).numpy()
            cov_out += cov[~m].sum(0).numpy()
            n_in += int(m.sum())
            n_all += m.numel()
    for name, (a, i, o) in acc.items():
        def p(s, n):
            return -10 * np.log10(s / (3 * n))
        print(f"{name:8s}: full {p(a, n_all):.3f} in {p(i, n_in):.3f} out {p(o, n_all - n_in):.3f}")
    for c, tid in enumerate(live):
        print(f"  spawn {tid}: pixels covered in masks {cov_in[c]:.0f} ({cov_in[c] / n_in:.4f}), "
              f"outside {cov_out[c]:.0f} ({cov_out[c] / (n_all - n_in):.4f})")


if __name__ == "__main__":
    for d in sys.argv[1:]:
        print("==", d)
        main(d)
