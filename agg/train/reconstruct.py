"""``reconstruct``: input (video, image folder, dataset folder or scene bundle) -> a trained scene directory.

Scene directory (docs/SCENE.md):

- ``scene.json``: metadata (frames, timestamps, training size and intrinsics, split, preset, status, timings,
  ``metric_scale``: metres per scene unit, exact or estimated, ``agg.priors.metric_scale``);
- ``bundle/``: the scene bundle, when the input was not a bundle with every prior (ingested, then ``run_priors``);
  ``bundle_gt_poses/`` with ``gt_poses=True``;
- ``checkpoint.pt``: the latest resumable training state (written every ``checkpoint_every`` iterations);
- when done: ``model.pt`` (the graph), ``metrics.json`` (NVS evaluation), ``scene.ply`` (3DGS PLY of frame 0),
  ``graph.json`` (the scene graph).
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from dataclasses import replace
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from agg.graph import SceneGraph
from agg.io.bundle import SceneBundle
from agg.priors.metric_scale import MetricScale, estimate_metric_scale
from agg.train.config import TrainConfig, get_preset
from agg.train.data import load_train_data
from agg.train.trainer import Cancelled, Trainer, seed_everything

PRIOR_PARTS = ("poses", "depth_dense", "dynamic_masks", "tracklets", "semantics")


def _is_bundle(path: Path) -> bool:
    return path.is_dir() and (path / "manifest.json").is_file()


def prepare_bundle(input_path: str | Path, scene_dir: Path, progress: Callable[[dict], None] | None = None,
                   max_frames: int | None = None, intrinsics: str | None = None,
                   should_stop: Callable[[], bool] | None = None) -> SceneBundle:
    """The bundle to train on: the input bundle itself when it has every prior, else ``scene_dir/bundle`` with
    the missing priors estimated (a video or dataset folder is ingested first).

    ``should_stop`` is polled at every priors step (each frame of the per-frame stages, each stage's start and
    end); it raises ``Cancelled`` there. Every finished prior is already in the bundle, so a resumed job skips it."""
    from agg.commands.priors import open_input
    from agg.priors.pipeline import PriorsConfig, run_priors

    src = Path(input_path)
    if not src.exists():
        raise FileNotFoundError(f"{src}: no such file or folder")
    if _is_bundle(src):
        b = SceneBundle.load(src)
        if all(b.has(p) for p in PRIOR_PARTS):
            return b
    out = scene_dir / "bundle"
    if _is_bundle(out):
        bundle = SceneBundle.load(out)  # resumed job: ingest already done (priors skip what exists)
    else:
        args = argparse.Namespace(input=str(src), output=str(out), fps=None, stride=1, start=0.0, end=None,
                                  max_frames=max_frames, width=None, height=None, intrinsics=intrinsics,
                                  overwrite=True)
        bundle = open_input(args)

    def bar(stage: str, done: int, total: int) -> None:
        if should_stop is not None and should_stop():
            raise Cancelled(f"cancelled while estimating priors ({stage} {done}/{total})")
        if progress is not None:
            progress({"stage": "priors", "phase": "priors", "step": stage, "done": done, "total": total})

    run_priors(bundle, PriorsConfig(), progress=bar)
    return bundle


def with_gt_poses(bundle: SceneBundle, out: Path) -> SceneBundle:
    """A copy of ``bundle`` whose camera poses are its ground truth. The other priors were estimated in the frame
    (and scale) of the estimated poses, so they are moved by the Sim(3) that aligns the estimate with the ground
    truth: depth x s, tracklet centres mapped, sizes x s, yaw turned by the alignment's rotation about y."""
    from agg.eval.trajectory import align_sim3
    from agg.io.bundle import Tracklets

    gt = bundle.gt
    if gt is None or not gt.has("poses"):
        raise ValueError(f"{bundle.path} has no ground-truth poses (gt/ sidecar)")
    if out.exists():
        shutil.rmtree(out)
    shutil.copytree(bundle.path, out)
    b = SceneBundle.load(out)
    sim = align_sim3(bundle.world_from_camera, gt.world_from_camera)
    s, r = sim.scale, sim.rotation
    b.write_poses(gt.world_from_camera, source="gt")
    b.set_scale(gt.scale, metric=gt.metric)  # every length below is moved into the ground truth's units
    if b.has("depth_dense"):
        b.write_dense_depth(np.asarray(b.dense_depth, np.float32) * s, b.dense_depth_confidence, dtype="float32",
                            source="sim3-to-gt")
    if b.has("depth_sparse"):
        rows = [b.sparse_depth(i) * np.array([1, 1, s, 1], np.float32) for i in range(b.num_frames)]
        b.write_sparse_depth(rows, source="sim3-to-gt")
    tr = b.tracklets
    if tr is not None:
        boxes = np.array(tr.boxes, np.float64)
        boxes[..., :3] = s * boxes[..., :3] @ r.T + sim.translation
        boxes[..., 3:6] *= s
        boxes[..., 6] += np.arctan2(r[0, 2], r[2, 2])  # yaw about world y
        # "world": the boxes carry the estimated cameras' error, which the camera node's refinement around the
        # ground truth does not follow
        b.write_tracklets(Tracklets(tr.ids, tr.classes, boxes, tr.valid, tr.confidence, tr.labels, anchor="world"))
    return b


def agent_anchor_for(cfg: TrainConfig, bundle: SceneBundle) -> str:
    """The anchor ("world" or "camera") of the priors' agents: the config's, with "auto" read from the bundle's
    tracklets (what their boxes were measured against; "world" without tracklets)."""
    if cfg.agent_anchor != "auto":
        return cfg.agent_anchor
    tracks = bundle.tracklets
    return tracks.anchor if tracks is not None else "world"


def camera_tracking_for(cfg: TrainConfig, bundle: SceneBundle) -> tuple[str, str]:
    """("on" or "off", why) for the camera-tracking rounds: the config's, with "auto" (the fast preset's) read from
    the bundle's pose sources. The rounds pull cameras that start up to a metre off onto the map. Cameras that the
    priors' SfM registered (and its checks kept) start centimetres off; on both real clips measured, training
    without the rounds moved the held-out PSNR by −0.04 to +0.10 dB and took a quarter to two fifths less time
    (docs/TRAINING.md, "Tracking rounds only where the poses need them")."""
    if cfg.tracking is None:
        return "off", "no tracking settings"
    if cfg.camera_tracking != "auto":
        return cfg.camera_tracking, "the config's choice"
    sources = bundle.pose_source or []
    if sources and all(s == "sfm" for s in sources):
        return "off", "every camera's prior is an SfM registration"
    other = sorted({s for s in sources if s != "sfm"}) or ["none"]
    return "on", f"camera priors not all from SfM ({', '.join(other)})"


def _graph_for(bundle: SceneBundle, cfg: TrainConfig, metric: MetricScale) -> SceneGraph:
    """The graph of the bundle's priors; the deformation network's position scale (metres) in scene units."""
    from agg.nodes.nonrigid import DeformConfig

    deform = DeformConfig()
    graph = SceneGraph.from_bundle(bundle, cfg.init,
                                   deform=replace(deform, pos_scale=deform.pos_scale * metric.units_per_metre))
    for node in graph.agent_nodes():  # the priors' tracklets; agents spawned later keep their world tracks
        node.anchored.fill_(agent_anchor_for(cfg, bundle) == "camera")
    return graph


def reconstruct(input_path: str | Path, scene_dir: str | Path, preset: str | TrainConfig = "fast", *,
                progress: Callable[[dict], None] | None = None, should_stop: Callable[[], bool] | None = None,
                resume: bool = True, checkpoint_every: int | None = None, overrides: dict | None = None,
                ablate: str | None = None, gt_poses: bool = False, evaluate: bool = True,
                max_frames: int | None = None, intrinsics: str | None = None,
                checkpoint_ok: Callable[[], bool] | None = None, device: str | torch.device = "cpu") -> dict:
    """Train a scene graph on ``input_path`` into ``scene_dir`` and return the summary (also in scene.json).

    Raises ``Cancelled`` when ``should_stop()`` turns True, in the priors or in training (the checkpoint keeps the
    progress; calling again with ``resume=True`` continues from it). ``checkpoint_ok()`` is asked before each
    checkpoint write and False skips the write: a worker passes "I still hold this job's lease". ``device``: where
    training runs ("cpu", "cuda", "cuda:N"; ``agg.device.resolve_device``); the priors always run on the CPU, and a
    checkpoint resumes on any device."""
    from agg.device import resolve_device

    dev = resolve_device(device)
    scene_dir = Path(scene_dir)
    scene_dir.mkdir(parents=True, exist_ok=True)
    cfg = preset if isinstance(preset, TrainConfig) else get_preset(preset)
    cfg = cfg.override(overrides)
    if ablate is not None:
        cfg = cfg.with_ablation(ablate)
    t0 = time.perf_counter()
    bundle = prepare_bundle(input_path, scene_dir, progress, max_frames, intrinsics, should_stop)
    if gt_poses:
        bundle = with_gt_poses(bundle, scene_dir / "bundle_gt_poses")
    tracking, tracking_reason = camera_tracking_for(cfg, bundle)
    cfg = replace(cfg, agent_anchor=agent_anchor_for(cfg, bundle), camera_tracking=tracking,  # what "auto" became
                  tracking=cfg.tracking if tracking == "on" else None)
    t_priors = time.perf_counter() - t0
    seed_everything(cfg.seed)
    data = load_train_data(bundle, cfg.max_width, cfg.attention_norm, cfg.eval_every,
                           cfg.semantic_min_contrast).to(dev)
    if data.semantic is not None and not cfg.semantic:
        data.semantic = {**data.semantic, "active": False, "reason": "ablated (--ablate semantic)"}
    metric = estimate_metric_scale(bundle)  # metres per scene unit (agg/priors/metric_scale.py)
    ckpt = scene_dir / "checkpoint.pt"
    meta = {"version": 1, "scene_id": scene_dir.name, "bundle": str(Path(bundle.path).resolve()),
            "num_frames": bundle.num_frames, "timestamps_us": [int(t) for t in bundle.timestamps_us],
            "width": data.width, "height": data.height, "K": data.K.tolist(), "train_frames": data.train_frames,
            "test_frames": data.test_frames, "preset": cfg.name, "ablate": sorted(cfg.ablate),
            "gt_poses": bool(gt_poses), "config": cfg.as_dict(), "metric_scale": metric.as_dict(),
            "device": str(dev), "semantic": data.semantic,
            "camera_tracking": {"active": tracking == "on", "reason": tracking_reason}, "status": "training"}
    (scene_dir / "scene.json").write_text(json.dumps(meta, indent=1))
    kwargs = {"progress": progress, "should_stop": should_stop, "checkpoint_ok": checkpoint_ok, "metric": metric}
    if resume and ckpt.is_file():
        trainer = Trainer.resume(ckpt, data, cfg, bundle, **kwargs)
    else:
        trainer = Trainer(_graph_for(bundle, cfg, metric), data, cfg, bundle, **kwargs)
    initial = {"n_gaussians": trainer.graph.num_gaussians(), "n_agents": trainer.graph.num_agents,
               "nodes": _node_names(trainer.graph)}
    t1 = time.perf_counter()
    trainer.run(ckpt, checkpoint_every)
    t_train = time.perf_counter() - t1
    graph = trainer.graph
    torch.save({"graph": graph.state(), "iteration": trainer.iteration, "history": trainer.history},
               scene_dir / "model.pt")
    summary = {"iterations": trainer.iteration, "device": str(dev), "seconds_priors": round(t_priors, 2),
               "seconds_train": round(t_train, 2), "initial": initial, "n_gaussians": graph.num_gaussians(),
               "n_agents": graph.num_agents, "nodes": _node_names(graph), "agents_spawned": trainer.spawned,
               "agents_pruned": trainer.pruned, "topology": trainer.topology_log,
               "reanchored": trainer.reanchored, "semantic": data.semantic, "agent_anchor": cfg.agent_anchor,
               "camera_tracking": meta["camera_tracking"], "tracking": trainer.tracking_log,
               "final_train_psnr": _recent_psnr(trainer.history)}
    from agg.export import export_scene

    export_scene(graph, scene_dir / "scene.ply", scene_dir / "graph.json", bundle.timestamps_us,
                 meta={"preset": meta["preset"], "metric_scale": meta["metric_scale"]})
    if evaluate:
        if progress is not None:
            progress({"stage": "eval", "phase": "eval"})
        from agg.eval.nvs import evaluate as nvs_evaluate

        metrics = nvs_evaluate(graph, bundle, data.test_frames, data.train_frames, images=data.images.cpu())
        (scene_dir / "metrics.json").write_text(json.dumps(metrics, indent=1))
        summary["metrics"] = {k: v for k, v in metrics.items() if k != "per_frame"}
    summary["seconds_total"] = round(time.perf_counter() - t0, 2)
    meta.update(status="done", summary=summary)
    (scene_dir / "scene.json").write_text(json.dumps(meta, indent=1))
    return summary


def _node_names(graph: SceneGraph) -> list[str]:
    return ["camera", "background"] + [n for n in ("sky", "rigid", "nonrigid") if getattr(graph, n) is not None]


def _recent_psnr(history: list[dict], n: int = 50) -> float | None:
    vals = [r["psnr"] for r in history[-n:] if np.isfinite(r["psnr"])]
    return float(np.mean(vals)) if vals else None


__all__ = ["reconstruct", "prepare_bundle", "with_gt_poses", "Cancelled"]
