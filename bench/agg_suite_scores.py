"""How a trained synthetic or real-clip scene scores beyond its held-out PSNR: the missed car's spawned agent and the
false agent (``topology_scores``), the priors' agents' refined poses (``agent_pose_scores``), the cameras against
ground truth before and after the Sim(3) alignment (``camera_scores``, ``sim3_scores``, ``clip_camera_scores``), and
the held-out error split into agent and background pixels (``region_scores``, ``split_regions``,
``prior_mask_scores``). ``bench/agg_suite.py`` writes them into every run's record; the probes import them too."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np


def load_graph(scene_dir: Path):
    """The trained SceneGraph of a scene directory (its model.pt)."""
    import torch

    from agg.graph import SceneGraph

    state = torch.load(scene_dir / "model.pt", map_location="cpu", weights_only=False)
    return SceneGraph.from_state(state["graph"])


def topology_scores(graph, bundle_path: Path, gt_from_est=None) -> dict:
    """Distance of the best spawned agent to the missed car per frame, and whether false agents survived.

    With ``gt_from_est`` (the Sim(3) that aligns the refined training cameras to ground truth, fitted on the cameras
    alone) the match also gets ``within_1m_aligned`` and ``median_aligned_m``: the same distances once the drift of
    the whole reconstruction is taken out, as for the cameras' ``sim3_mean_m``."""
    import torch

    from agg.synth.suite import load_gt_extras

    extras = load_gt_extras(bundle_path)
    index = extras["index"]
    ids = [a["id"] for a in index["agents"]]
    out: dict = {"missed_ids": index["missed_ids"], "false_ids": index["false_ids"]}
    surviving = set(graph.slot_track_ids().tolist())
    out["false_pruned"] = [fid for fid in index["false_ids"] if fid not in surviving]
    prior_ids = {t["id"] for t in index["prior_tracks"]}
    spawned = [tid for tid in surviving if tid not in prior_ids]
    out["spawned"] = spawned
    best = None
    for mid in index["missed_ids"]:
        gt_c = extras["world_from_agent"][ids.index(mid)][:, :3, 3]  # [T, 3]
        vis = extras["pixel_count"][ids.index(mid)] > 0
        for node in graph.agent_nodes():
            for j, tid in enumerate(node.track_ids.tolist()):
                if tid not in spawned:
                    continue
                with torch.no_grad():
                    c = np.stack([node.world_from_box(t)[j, :3, 3].numpy() for t in range(node.num_frames)])
                valid = node.valid[:, j].numpy() & vis
                if not valid.any():
                    continue
                d = np.linalg.norm(c - gt_c, axis=1)[valid]  # [F]
                frac = float((d <= 1.0).mean())
                score = {"track_id": tid, "frames": int(valid.sum()), "visible_frames": int(vis.sum()),
                         "within_1m": frac, "within_1m_of_visible": float((d <= 1.0).sum() / vis.sum()),
                         "median_m": float(np.median(d))}
                if gt_from_est is not None:
                    da = np.linalg.norm(gt_from_est.apply_to_points(c) - gt_c, axis=1)[valid]  # [F]
                    score |= {"within_1m_aligned": float((da <= 1.0).sum() / vis.sum()),
                              "median_aligned_m": float(np.median(da))}
                if best is None or score["within_1m_of_visible"] > best["within_1m_of_visible"]:
                    best = score
    out["missed_match"] = best
    return out


def agent_pose_scores(graph, bundle_path: Path) -> dict | None:
    """How far the refined poses of the priors' true agents end from ground truth: per agent, the median
    box-centre error (m) and rotation error (deg) over its valid frames; then the median over agents."""
    import torch

    from agg.eval.trajectory import rotation_angle_deg
    from agg.synth.suite import load_gt_extras

    extras = load_gt_extras(bundle_path)
    ids = [a["id"] for a in extras["index"]["agents"]]
    per_agent = {}
    for node in graph.agent_nodes():
        for j, tid in enumerate(node.track_ids.tolist()):
            valid = node.valid[:, j].numpy()
            if tid not in ids or not valid.any():
                continue
            gt = extras["world_from_agent"][ids.index(tid)][valid]  # [F, 4, 4]
            with torch.no_grad():
                est = np.stack([node.world_from_box(t)[j].numpy() for t in np.flatnonzero(valid)])  # [F, 4, 4]
            rot = np.swapaxes(est[:, :3, :3], 1, 2) @ gt[:, :3, :3]  # [F, 3, 3] R_est^T R_gt
            per_agent[str(tid)] = {"translation_m": float(np.median(np.linalg.norm(est[:, :3, 3] - gt[:, :3, 3],
                                                                                     axis=1))),
                                   "rotation_deg": float(np.median(rotation_angle_deg(rot)))}
    if not per_agent:
        return None
    return {"translation_m": float(np.median([a["translation_m"] for a in per_agent.values()])),
            "rotation_deg": float(np.median([a["rotation_deg"] for a in per_agent.values()])),
            "per_agent": per_agent}


def _training_cameras(graph, scene_dir: Path, bundle_path: Path):
    """(prior, refined, ground truth) camera-to-world poses [F, 4, 4] of the training frames."""
    import torch

    from agg.io.bundle import SceneBundle

    b = SceneBundle.load(bundle_path)
    frames = json.loads((scene_dir / "scene.json").read_text())["train_frames"]
    with torch.no_grad():
        refined = graph.camera.world_from_camera().numpy()  # [T, 4, 4]
    return (np.asarray(b.world_from_camera, np.float64)[frames], np.asarray(refined, np.float64)[frames],
            np.asarray(b.gt.world_from_camera, np.float64)[frames])


def refined_alignment(graph, scene_dir: Path, bundle_path: Path):
    """The Sim(3) ground-truth-from-estimate world that aligns the refined training cameras to ground truth."""
    from agg.eval.trajectory import align_sim3

    _, refined, gt = _training_cameras(graph, scene_dir, bundle_path)
    return align_sim3(refined, gt)


def camera_scores(graph, scene_dir: Path, bundle_path: Path) -> dict:
    """Camera-centre error against ground truth (metres) of the priors and of the refined cameras, over the
    training frames: mean, median, max, and ``sim3_mean_m`` after the Sim(3) alignment of the training cameras
    to ground truth (what is left once a drift of the whole trajectory and map together is taken out), whose scale
    (ground truth per scene unit) is ``sim3_scale``; ``sim3_max_m`` and ``sim3_rotation_deg`` (the mean angle
    between aligned and true orientations, ``evaluate_trajectory``'s ``ate_rot_mean_deg``) go with it."""
    prior, refined, gt = _training_cameras(graph, scene_dir, bundle_path)
    out = {}
    for name, p in (("prior", prior), ("refined", refined)):
        e = np.linalg.norm(p[:, :3, 3] - gt[:, :3, 3], axis=1)  # [F]
        out[name] = {"mean_m": float(e.mean()), "median_m": float(np.median(e)), "max_m": float(e.max()),
                     **sim3_scores(p, gt)}
    return out


def sim3_scores(cams: np.ndarray, gt: np.ndarray) -> dict:
    """Centre error (metres, mean and max), mean rotation error (degrees) and scale of camera-to-world poses
    ``cams`` [F, 4, 4] after their Sim(3) alignment to ``gt`` [F, 4, 4]."""
    from agg.eval.trajectory import evaluate_trajectory

    m = evaluate_trajectory(cams, gt)
    ea = np.linalg.norm(m.alignment.apply_to_poses(cams)[:, :3, 3] - gt[:, :3, 3], axis=1)  # [F]
    return {"sim3_mean_m": float(ea.mean()), "sim3_max_m": float(ea.max()),
            "sim3_rotation_deg": m.ate_rot_mean_deg, "sim3_scale": float(m.alignment.scale)}


def clip_camera_scores(scene_dir: Path) -> dict | None:
    """``camera_scores`` of a KITTI or real-clip scene against the bundle it trained on, as ``reconstruct`` keeps it
    in the scene (the ground-truth-pose copy for a ``--gt-poses`` run); None when that bundle has no ground-truth
    cameras."""
    from agg.io.bundle import SceneBundle

    for name in ("bundle_gt_poses", "bundle"):
        if (scene_dir / name).is_dir():
            if SceneBundle.load(scene_dir / name).gt is None:
                return None
            return camera_scores(load_graph(scene_dir), scene_dir, scene_dir / name)
    return None


def region_scores(scene_dir: Path) -> dict | None:
    """Where the held-out error lies, from metrics.json's per-frame rows: the PSNR of the pixels outside the agent
    masks (pooled over the test frames), the share of pixels that are agent pixels and the share of the squared
    error they carry. Exact: each frame's full-image MSE is split into its agent and non-agent parts."""
    path = scene_dir / "metrics.json"
    if not path.is_file():
        return None
    rows = json.loads(path.read_text())["per_frame"]
    if not rows or any(r["agent_pixels"] is None for r in rows):
        return None
    meta = json.loads((scene_dir / "scene.json").read_text())
    return split_regions(rows, meta["width"] * meta["height"])


def split_regions(rows: list[dict], n: int) -> dict:
    """PSNR outside the agent masks, and the agents' shares of pixels and squared error, from ``evaluate``'s
    per-frame rows of ``n``-pixel frames (each frame's MSE split into its agent and non-agent parts; a row's
    ``pixels``, where it has them, are the pixels it scored: the ego vehicle's are not)."""
    sse = sse_ag = n_ag = n_all = 0.0
    for r in rows:
        scored = r.get("pixels", n)
        sse += 10.0 ** (-r["psnr"] / 10.0) * scored  # per-value MSE x pixels (the 3 channels cancel in the ratios)
        n_all += scored
        if r["agent_pixels"]:
            sse_ag += 10.0 ** (-r["psnr_agents"] / 10.0) * r["agent_pixels"]
            n_ag += r["agent_pixels"]
    n_bg = n_all - n_ag
    return {"psnr_background": float(-10.0 * np.log10(max(sse - sse_ag, 1e-12) / n_bg)),
            "agent_pixel_share": n_ag / n_all, "agent_error_share": sse_ag / sse}


def prior_mask_scores(scene_dir: Path) -> dict:
    """A real clip's held-out metrics with its priors' dynamic masks as the agent regions (it has no ground truth):
    the same pixels for every variant, whatever agents each one ends with. Also the PSNR outside them."""
    from agg.eval.nvs import evaluate
    from agg.io.bundle import SceneBundle
    from agg.scene import Scene
    from agg.train.data import resize_images

    scene = Scene.load(scene_dir)
    bundle = SceneBundle.load(scene.meta["bundle"])
    graph = scene.graph
    metrics = evaluate(graph, bundle, sorted(set(scene.meta["test_frames"])), scene.meta["train_frames"],
                       images=resize_images(bundle.frames[:], graph.width, graph.height),
                       agent_masks=np.asarray(bundle.dynamic_masks[:]) > 0)
    split = split_regions(metrics["per_frame"], graph.width * graph.height)
    return {"psnr": metrics["psnr"], "psnr_agents": metrics["psnr_agents"], "ssim_agents": metrics["ssim_agents"],
            "psnr_background": split["psnr_background"], "agent_pixel_share": split["agent_pixel_share"]}
