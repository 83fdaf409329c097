"""Glue of the synthetic suite: generate a clip with exact ground truth, corrupt it, write a scene bundle.

``render_clip(SceneConfig)`` returns a ``GroundTruth`` (pure numpy); ``corrupt.corrupt(gt, NoiseConfig)`` turns it
into ``Priors``; ``write_bundle`` writes the priors as a normal scene bundle (``agg.io.bundle.SceneBundle``) and the
exact ground truth into its ``gt/`` sidecar. What the bundle format has no part for (instance and semantic maps,
per-frame agent poses, the list of missed / false agents) goes to ``gt/synth/`` as ``.npy`` / JSON files listed in
``gt/synth/index.json`` and in the scene manifest's ``meta["synth"]["gt_extras"]``. All lengths are metres
(``scale = 1``, ``metric = true``).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from agg.synth.corrupt import NoiseConfig, Priors, corrupt
from agg.synth.features import ClassEmbeddings, FeatureConfig, class_embeddings, feature_maps, feature_size
from agg.synth.raycast import ValueNoise, render_scene_frame
from agg.synth.scene import SEMANTIC_CLASSES, SceneConfig, make_scene, yaw_of

GT_EXTRAS = {
    "instance": "synth/instance.npy",  # int32 [T, H, W], 0 = background, k = GT agent id k
    "semantic": "synth/semantic.npy",  # uint8 [T, H, W], ids of semantic_classes
    "world_from_agent": "synth/world_from_agent.npy",  # float64 [K, T, 4, 4], metres
    "pixel_count": "synth/pixel_count.npy",  # int64 [K, T], visible pixels of each agent
    "prior_instance": "synth/prior_instance.npy",  # int32 [T, H, W], instance ids of the priors' tracks
    "class_embeddings": "synth/class_embeddings.npy",  # float32 [n_classes, D]
    "world_from_road": "synth/world_from_road.npy",  # float64 [4, 4]
    "index": "synth/index.json",  # agents, prior tracks, missed / false ids, classes
}


@dataclass
class GroundTruth:
    """Exact ground truth of a synthetic clip (world = first camera, metres, OpenCV camera axes)."""

    config: SceneConfig
    K: np.ndarray  # [3, 3]
    timestamps_us: np.ndarray  # [T] int64
    world_from_camera: np.ndarray  # [T, 4, 4]
    world_from_road: np.ndarray  # [4, 4]
    rgb: np.ndarray  # [T, H, W, 3] float32 in [0, 1]
    depth: np.ndarray  # [T, H, W] float32 z-depth, inf where nothing is hit (sky)
    depth_valid: np.ndarray  # [T, H, W] bool
    instance: np.ndarray  # [T, H, W] int32, 0 = background, k = agent id
    semantic: np.ndarray  # [T, H, W] uint8
    agent_ids: np.ndarray  # [K] int64 = instance ids 1..K
    agent_classes: list[str]  # [K] "rigid" | "non-rigid"
    agent_labels: list[str]  # [K] "car" | "pedestrian"
    agent_names: list[str]  # [K] "moving_car" | "parked_car" | "pedestrian"
    agent_moving: np.ndarray  # [K] bool
    world_from_agent: np.ndarray  # [K, T, 4, 4] box frame (docs/BUNDLE.md tracklet axes)
    size_lwh: np.ndarray  # [K, 3]
    boxes: np.ndarray  # [K, T, 7] (cx, cy, cz, l, w, h, yaw), every frame
    in_scene: np.ndarray  # [K, T] bool (agents exist for the whole clip)
    visible: np.ndarray  # [K, T] bool, >= 1 pixel in the instance map; the tracklets' validity
    pixel_count: np.ndarray  # [K, T] int64
    features: np.ndarray  # [T, h, w, D] float32, noise-free
    embeddings: ClassEmbeddings


def render_clip(cfg: SceneConfig, feature_cfg: FeatureConfig = FeatureConfig()) -> GroundTruth:
    """Generate and ray-cast a clip; identical configs give identical arrays."""
    feature_size(cfg.width, cfg.height, feature_cfg.factor)  # fail early on a bad size
    scene = make_scene(cfg)
    noise = ValueNoise(scene.texture_seed)
    outs = [render_scene_frame(scene, i, noise) for i in range(scene.frames)]
    instance = np.stack([o.instance for o in outs])
    n_agents = len(scene.agents)
    ids = np.arange(1, n_agents + 1, dtype=np.int64)
    counts = np.stack([(instance == k).sum((1, 2)) for k in ids]).astype(np.int64) if n_agents else \
        np.zeros((0, scene.frames), np.int64)
    w_from_a = np.stack([a.world_from_agent for a in scene.agents]) if n_agents else np.zeros((0, scene.frames, 4, 4))
    sizes = np.stack([a.size_lwh for a in scene.agents]) if n_agents else np.zeros((0, 3))
    boxes = np.concatenate([w_from_a[..., :3, 3], np.repeat(sizes[:, None], scene.frames, 1),
                            yaw_of(w_from_a)[..., None]], -1)  # [K, T, 7]
    semantic = np.stack([o.semantic for o in outs])
    emb = class_embeddings(feature_cfg)
    return GroundTruth(
        config=cfg, K=scene.K, timestamps_us=scene.timestamps_us, world_from_camera=scene.world_from_camera,
        world_from_road=scene.world_from_road, rgb=np.stack([o.rgb for o in outs]),
        depth=np.stack([o.depth for o in outs]), depth_valid=np.stack([o.valid for o in outs]), instance=instance,
        semantic=semantic, agent_ids=ids, agent_classes=[a.kind.replace("_", "-") for a in scene.agents],
        agent_labels=[SEMANTIC_CLASSES[a.semantic] for a in scene.agents], agent_names=[a.name for a in scene.agents],
        agent_moving=np.array([a.moving for a in scene.agents], bool), world_from_agent=w_from_a, size_lwh=sizes,
        boxes=boxes, in_scene=np.ones((n_agents, scene.frames), bool), visible=counts > 0, pixel_count=counts,
        features=feature_maps(semantic, emb, feature_cfg.factor), embeddings=emb)


def generate(cfg: SceneConfig, noise: NoiseConfig = NoiseConfig(),
             feature_cfg: FeatureConfig = FeatureConfig()) -> tuple[GroundTruth, Priors]:
    """Ground truth and noisy priors of one clip."""
    gt = render_clip(cfg, feature_cfg)
    return gt, corrupt(gt, noise)


def _sparse_points(depth: np.ndarray) -> list[np.ndarray]:
    out = []
    for d in depth:
        rows, cols = np.nonzero(d > 0)
        out.append(np.stack([cols, rows, d[rows, cols], np.ones(len(rows))], -1).astype(np.float32))
    return out


def write_bundle(path: str | Path, gt: GroundTruth, priors: Priors, noise: NoiseConfig,
                 feature_cfg: FeatureConfig = FeatureConfig(), *, depth_format: str = "dense",
                 overwrite: bool = False):
    """Write the priors as a scene bundle at ``path`` and the exact ground truth in ``path/gt``.

    depth_format: "dense" (``depth/dense.npy``, float32, 0 = none), "sparse" (``depth/sparse_points.npy``, one row
    per kept pixel, confidence 1) or "none". Returns the written ``SceneBundle``.
    """
    from agg.io.bundle import SceneBundle, SemanticFeatures, Tracklets

    if depth_format not in ("dense", "sparse", "none"):
        raise ValueError(f"depth_format must be dense, sparse or none, got {depth_format!r}")
    t_count = len(gt.timestamps_us)
    meta = {"synth": {"generator": "agg.synth", "scene_config": asdict(gt.config), "noise": noise.as_dict(),
                      "feature_config": asdict(feature_cfg), "semantic_classes": list(SEMANTIC_CLASSES),
                      "missed_ids": priors.missed_ids, "false_ids": priors.false_ids,
                      "gt_extras": {k: "gt/" + v for k, v in GT_EXTRAS.items()}}}
    bundle = SceneBundle.create(path, gt.rgb, gt.timestamps_us, gt.K,
                                frame_names=[f"synth_{i:06d}" for i in range(t_count)], intrinsics_source="given",
                                scale=1.0, metric=True, meta=meta, overwrite=overwrite)
    exact_poses = bool(np.array_equal(priors.world_from_camera, gt.world_from_camera))
    bundle.write_poses(priors.world_from_camera, source="gt" if exact_poses else "synthetic-noisy")
    depth_source = "gt" if noise.depth_rel_sigma == 0 else "synthetic-noisy"
    if depth_format == "dense":
        bundle.write_dense_depth(priors.depth, dtype="float32", source=depth_source)
    elif depth_format == "sparse":
        bundle.write_sparse_depth(_sparse_points(priors.depth), source=depth_source)
    bundle.write_dynamic_masks(priors.instance > 0, source="synthetic")
    bundle.write_tracklets(Tracklets(priors.track_ids, list(priors.track_classes), priors.boxes, priors.valid,
                                     labels=list(priors.track_labels),
                                     anchor="camera" if noise.boxes_follow_cameras else "world"))
    emb = gt.embeddings
    bundle.write_semantics(SemanticFeatures(priors.features.astype(np.float16), emb.C_bg, emb.C_ag,
                                            prototypes=emb.prototypes, prototype_space="pca"))
    g = bundle.create_gt()
    g.set_scale(1.0, metric=True)
    g.write_poses(gt.world_from_camera, source="gt")
    g.write_dense_depth(np.where(gt.depth_valid, gt.depth, 0.0), dtype="float32", source="gt")
    g.write_dynamic_masks(gt.instance > 0, source="gt")
    g.write_tracklets(Tracklets(gt.agent_ids, list(gt.agent_classes), gt.boxes, gt.visible,
                                labels=list(gt.agent_labels)))
    g.write_semantics(SemanticFeatures(gt.features.astype(np.float16), emb.C_bg, emb.C_ag,
                                       prototypes=emb.prototypes, prototype_space="pca"))
    root = Path(path) / "gt"
    (root / "synth").mkdir(exist_ok=True)
    arrays = {"instance": gt.instance.astype(np.int32), "semantic": gt.semantic.astype(np.uint8),
              "world_from_agent": gt.world_from_agent, "pixel_count": gt.pixel_count,
              "prior_instance": priors.instance.astype(np.int32),
              "class_embeddings": emb.vectors.astype(np.float32), "world_from_road": gt.world_from_road}
    for key, arr in arrays.items():
        np.save(root / GT_EXTRAS[key], arr)
    index = {
        "semantic_classes": list(SEMANTIC_CLASSES),
        "agents": [{"id": int(gt.agent_ids[k]), "class": gt.agent_classes[k], "label": gt.agent_labels[k],
                    "name": gt.agent_names[k], "moving": bool(gt.agent_moving[k]),
                    "size_lwh": [float(v) for v in gt.size_lwh[k]]} for k in range(len(gt.agent_ids))],
        "prior_tracks": [{"id": int(i), "gt_id": int(gt.agent_ids[j]) if j >= 0 else None}
                         for i, j in zip(priors.track_ids, priors.gt_index)],
        "missed_ids": priors.missed_ids, "false_ids": priors.false_ids,
        "noise": noise.as_dict(), "scene_config": asdict(gt.config),
    }
    (root / GT_EXTRAS["index"]).write_text(json.dumps(index, indent=1))
    return bundle


def load_gt_extras(bundle_path: str | Path) -> dict:
    """The ``gt/synth`` extras of a bundle written by ``write_bundle``: arrays by key plus ``index`` (dict)."""
    root = Path(bundle_path) / "gt"
    out: dict = {k: np.load(root / rel) for k, rel in GT_EXTRAS.items() if rel.endswith(".npy")}
    out["index"] = json.loads((root / GT_EXTRAS["index"]).read_text())
    return out
