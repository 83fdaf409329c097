"""The priors pipeline: fills a scene bundle's missing priors, stage by stage, and says what it did.

Stages, in order (each runs only when its part is missing, or when ``PriorsConfig.recompute`` names it):

1. ``poses``: pycolmap SfM with checks and the VO fallback (``poses.py``); writes poses, per-frame source and
   confidence, refined intrinsics (when they were not given) and the sparse depth from the SfM tracks. When the
   bundle already has poses (given) but no depth, SfM still runs for its points, which are moved into the given
   frame by the orientation-aware Sim(3) alignment of the SfM path onto the given one.
2. ``depth``: the documented densification of the sparse depth, or a local monocular model (``depth.py``).
3. ``masks``: optical flow against the ego-motion flow (``masks.py``).
4. ``tracklets``: connected components lifted to 3D and tracked by a Kalman filter (``tracklets.py``).
5. ``semantics``: per-scene PCA features, channel subsets and the prototype bank (``features.py``).

The result is a ``PriorsSummary`` (also written as ``BUNDLE/priors_summary.json``): per-stage seconds, the
registered fraction, outliers and interpolated frames, mask coverage, tracks, and, where the bundle has a
ground-truth sidecar, the scores against it (ATE after Sim(3), mask IoU, tracklet recall and precision).
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Callable

import numpy as np

from agg.io.bundle import SceneBundle

STAGES = ("poses", "depth", "masks", "tracklets", "semantics")
Progress = Callable[[str, int, int], None]  # (stage, done, total)


@dataclass(frozen=True)
class PriorsConfig:
    """What the pipeline runs and with which settings (each stage module documents its own config)."""

    pose_preset: str = "fast"  # agg.priors.poses.PoseConfig.preset: "fast" (half resolution) or "accurate"
    stages: tuple[str, ...] = STAGES  # stages to run (a stage whose part exists is skipped unless recomputed)
    recompute: tuple[str, ...] = ()  # stages to run even when the bundle has their part
    feature_backend: str = "builtin"  # "builtin" (no weights) or "dino" (needs feature_weights)
    feature_weights: str | None = None  # local DINOv2/v3 checkpoint folder for the dino backend
    prototypes: str | None = None  # prototype bank .npz from ``agg prototypes`` (else built per scene)
    mono_depth_weights: str | None = None  # TorchScript monocular depth model; None: densify the sparse depth
    dist: tuple[float, ...] | None = None  # distortion of the bundle frames, when they were not undistorted

    def __post_init__(self) -> None:
        bad = [s for s in (*self.stages, *self.recompute) if s not in STAGES]
        if bad:
            raise ValueError(f"unknown priors stage(s) {bad}; stages are {list(STAGES)}")


@dataclass
class PriorsSummary:
    bundle: str
    num_frames: int
    width: int
    height: int
    seconds: dict[str, float] = field(default_factory=dict)
    ran: list[str] = field(default_factory=list)
    skipped: dict[str, str] = field(default_factory=dict)
    poses: dict = field(default_factory=dict)
    depth: dict = field(default_factory=dict)
    masks: dict = field(default_factory=dict)
    tracklets: dict = field(default_factory=dict)
    semantics: dict = field(default_factory=dict)
    scores: dict = field(default_factory=dict)

    def as_dict(self) -> dict:
        return _jsonable(asdict(self))


def _jsonable(obj):
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    return obj


class _Stage:
    """Times a stage into the summary and reports progress as (stage, done, total)."""

    def __init__(self, summary: PriorsSummary, name: str, total: int, progress: Progress | None):
        self.summary, self.name, self.total, self.progress = summary, name, total, progress

    def tick(self, i: int) -> None:
        if self.progress:
            self.progress(self.name, i + 1, self.total)

    def __enter__(self) -> "_Stage":
        self.t0 = time.perf_counter()
        if self.progress:
            self.progress(self.name, 0, self.total)
        return self

    def __exit__(self, *exc) -> None:
        self.summary.seconds[self.name] = round(time.perf_counter() - self.t0, 3)
        if exc[0] is None:
            self.summary.ran.append(self.name)
            if self.progress:
                self.progress(self.name, self.total, self.total)


def _wants(bundle: SceneBundle, cfg: PriorsConfig, stage: str, part: str, summary: PriorsSummary) -> bool:
    if stage not in cfg.stages:
        summary.skipped[stage] = "not requested"
        return False
    if bundle.has(part) and stage not in cfg.recompute:
        summary.skipped[stage] = "given"
        return False
    return True


def _frames_uint8(bundle: SceneBundle) -> np.ndarray:
    return bundle.frames.raw  # [T, H, W, 3] uint8 memmap


def run_priors(bundle: SceneBundle, config: PriorsConfig = PriorsConfig(), progress: Progress | None = None
               ) -> PriorsSummary:
    """Estimate the bundle's missing priors in place and return (and write) the summary."""
    from agg.priors import depth as depth_mod
    from agg.priors.poses import PoseConfig, estimate_poses

    cfg = config
    t, h, w = bundle.num_frames, bundle.height, bundle.width
    summary = PriorsSummary(bundle=str(bundle.path), num_frames=t, width=w, height=h)
    frames = _frames_uint8(bundle)  # [T, H, W, 3] uint8 (memory-mapped)
    K = bundle.intrinsics[0]  # noqa: N806  [3, 3]
    depth_cfg = depth_mod.DepthConfig()

    # ---------------------------------------------------------------- 1. poses (+ sparse depth)
    given_poses = bundle.has("poses") and "poses" not in cfg.recompute
    need_points = "depth" in cfg.stages and not bundle.has("depth_sparse") and not bundle.has("depth_dense")
    if "poses" in cfg.stages and (not given_poses or need_points):
        with _Stage(summary, "poses", 1, progress):
            intr_given = bundle.intrinsics_source in ("given", "calibration")
            res = estimate_poses(frames, K if intr_given else None, PoseConfig.preset(cfg.pose_preset), dist=cfg.dist)
            if not intr_given:  # refined focal (default field of view + SfM), or the guess kept when SfM failed
                K = res.intrinsics.K  # noqa: N806
                bundle.write_intrinsics(K, source="sfm" if res.method == "sfm" else bundle.intrinsics_source)
            points = res.points
            if given_poses:  # SfM only for its points: move them into the given frame
                points = _points_into_given_frame(res, bundle.world_from_camera)
                summary.poses = {"source": "given", "sfm_registered_fraction": res.registered_fraction}
            else:
                bundle.write_poses(res.world_from_camera, source=res.source, confidence=res.confidence)
                bundle.set_scale(1.0, metric=False)
                interpolated = [i for i, s in enumerate(res.source) if s == "interpolated"]
                summary.poses = {
                    "method": res.method, "registered_fraction": res.registered_fraction,
                    "registered": int(round(res.registered_fraction * t)), "outliers": res.outliers,
                    "interpolated_frames": interpolated, "intrinsics_source": bundle.intrinsics_source,
                    "fx": float(K[0, 0]), "bend_deg": res.diagnostics.get("bend_deg"),
                    "scale_note": "monocular: scene units, median sparse depth = 1", "timings_s": res.timings_s}
            rows = depth_mod.sparse_depth_rows(points, t, w, h, depth_cfg)
            if len(points.xyz):
                bundle.write_sparse_depth(rows, source="sfm")
            summary.depth["sparse_points_per_frame"] = float(np.mean([len(r) for r in rows]))
    elif given_poses:
        summary.skipped["poses"] = "given"
        summary.poses = {"source": "given"}
    else:
        summary.skipped["poses"] = "not requested"
    if not bundle.has("poses"):
        raise ValueError("the bundle has no poses and the poses stage did not run: nothing else can be estimated")
    world_from_camera = bundle.world_from_camera

    # ---------------------------------------------------------------- 2. dense depth
    if _wants(bundle, cfg, "depth", "depth_dense", summary):
        with _Stage(summary, "depth", t, progress) as st:
            rows = [bundle.sparse_depth(i) for i in range(t)] if bundle.has("depth_sparse") else [np.zeros((0, 4))] * t
            if cfg.mono_depth_weights:
                model = depth_mod.MonoDepthModel(cfg.mono_depth_weights)
                out = [model.predict(frames[i].astype(np.float32) / 255.0, rows[i]) for i in range(t)]
                for i in range(t):
                    st.tick(i)
                dense, conf = np.stack([o[0] for o in out]), np.stack([o[1] for o in out])
                source = "mono"
            else:
                dense, conf = depth_mod.densify_clip(rows, frames, depth_cfg, progress=st.tick)
                source = "sfm+densified"
            bundle.write_dense_depth(dense, confidence=conf, dtype="float16", source=source)
            summary.depth.update(source=source, coverage=float((dense > 0).mean()),
                                 mean_confidence=float(conf[dense > 0].mean()) if (dense > 0).any() else 0.0)
    depth, depth_conf = _dense_depth(bundle)

    # ---------------------------------------------------------------- 3. dynamic masks
    residual = None
    if _wants(bundle, cfg, "masks", "dynamic_masks", summary):
        from agg.priors.masks import MaskConfig, dynamic_masks

        with _Stage(summary, "masks", t, progress) as st:
            mres = dynamic_masks(frames, K, world_from_camera, depth, MaskConfig(), depth_confidence=depth_conf,
                                 progress=st.tick)
            bundle.write_dynamic_masks(mres.masks, source="flow-residual")
            if mres.ego is not None and mres.ego.any():  # left out of training and scoring
                bundle.write_ego_mask(mres.ego, source="flow-residual")
            else:
                bundle.remove("ego_mask")  # a stale one of earlier masks
            kept = mres.residual.astype(np.float16)  # what the bundle keeps
            np.save(bundle.path / "masks" / "flow_residual.npy", kept)
            residual = kept.astype(np.float32)  # later stages read these values, as a re-run from the bundle does
            summary.masks = {"source": "flow-residual", "coverage": float(mres.masks.mean()),
                             "frames_with_mask": int((mres.masks.reshape(t, -1).max(1) > 0).sum()),
                             "ego_share": float(mres.ego.mean()) if mres.ego is not None else 0.0}
    masks = np.asarray(bundle.dynamic_masks) if bundle.has("dynamic_masks") else None
    if residual is None and (bundle.path / "masks" / "flow_residual.npy").is_file():
        residual = np.load(bundle.path / "masks" / "flow_residual.npy").astype(np.float32)

    # ---------------------------------------------------------------- 4. tracklets
    track_result = None
    if masks is not None and _wants(bundle, cfg, "tracklets", "tracklets", summary):
        from agg.priors.tracklets import TrackConfig, filled_entries, track_agents

        with _Stage(summary, "tracklets", t, progress) as st:
            track_result = track_agents(masks, depth, K, world_from_camera, TrackConfig(), frames=frames,
                                        depth_confidence=depth_conf, progress=st.tick)
            tr = track_result.tracklets
            if len(tr.classes):
                bundle.write_tracklets(tr)
            np.save(bundle.path / "masks" / "instances.npy", track_result.instance_masks.astype(np.int32))
            summary.tracklets = {"count": len(tr.classes), "classes": list(tr.classes),
                                 "frames_per_track": tr.valid.sum(1).tolist(),
                                 "filled_per_track": filled_entries(tr).sum(1).tolist()}
    elif masks is None and "tracklets" in cfg.stages:
        summary.skipped["tracklets"] = "no dynamic masks"

    # ---------------------------------------------------------------- 5. semantic features
    if _wants(bundle, cfg, "semantics", "semantics", summary):
        from agg.priors.features import FeatureConfig, build_semantics, load_prototype_bank

        with _Stage(summary, "semantics", t, progress) as st:
            fcfg = FeatureConfig(backend=cfg.feature_backend, weights=cfg.feature_weights)
            bank = load_prototype_bank(cfg.prototypes, backend=cfg.feature_backend) if cfg.prototypes else None
            class_masks = _class_masks(bundle, track_result)
            info: dict = {}
            sem = build_semantics(frames, fcfg, masks=masks, class_masks=class_masks, flow_residual=residual,
                                  prototype_bank=bank, progress=st.tick, info=info)
            bundle.write_semantics(sem)
            summary.semantics = {"backend": cfg.feature_backend, "channels": int(sem.features.shape[-1]),
                                 "size_hw": list(sem.features.shape[1:3]), "C_bg": list(sem.C_bg),
                                 "C_ag": list(sem.C_ag), "prototypes": sorted((sem.prototypes or {}).keys()),
                                 "rules": info}

    summary.scores = score_against_gt(bundle)
    (bundle.path / "priors_summary.json").write_text(json.dumps(summary.as_dict(), indent=1))
    return summary


def _dense_depth(bundle: SceneBundle) -> tuple[np.ndarray, np.ndarray | None]:
    """The bundle's dense depth [T, H, W] float32 and confidence (or None); rasterised sparse depth otherwise."""
    t, h, w = bundle.num_frames, bundle.height, bundle.width
    if bundle.has("depth_dense"):
        conf = bundle.dense_depth_confidence
        return (np.asarray(bundle.dense_depth, dtype=np.float32),
                None if conf is None else np.asarray(conf, dtype=np.float32))
    depth = np.zeros((t, h, w), np.float32)
    if bundle.has("depth_sparse"):
        for i in range(t):
            r = bundle.sparse_depth(i)
            u = np.clip(np.rint(r[:, 0]).astype(int), 0, w - 1)
            v = np.clip(np.rint(r[:, 1]).astype(int), 0, h - 1)
            depth[i, v, u] = r[:, 2]
    return depth, None


def _class_masks(bundle: SceneBundle, track_result) -> np.ndarray | None:
    """[T, H, W] uint8: 0 background, 1 rigid agent, 2 non-rigid agent, from this run's track instances, else
    from the ones an earlier run kept in the bundle (``masks/instances.npy`` beside its tracklets); None without."""
    if track_result is not None:
        inst, classes = track_result.instance_masks, track_result.tracklets.classes  # [T, H, W] int32: k + 1
    else:
        path = bundle.path / "masks" / "instances.npy"
        if not (bundle.has("tracklets") and path.is_file()):
            return None
        inst, classes = np.load(path), bundle.tracklets.classes
        if inst.shape != (bundle.num_frames, bundle.height, bundle.width) or inst.max(initial=0) > len(classes):
            return None  # not the instances of these tracklets
    lut = np.zeros(len(classes) + 1, np.uint8)
    for k, c in enumerate(classes):
        lut[k + 1] = 1 if c == "rigid" else 2
    return lut[inst]


def _points_into_given_frame(res, given_world_from_camera: np.ndarray):
    """SfM sparse points (and their depths) moved into the frame and scale of the given poses."""
    from agg.eval.trajectory import align_sim3

    sim = align_sim3(res.world_from_camera, given_world_from_camera)
    pts = res.points
    return replace(pts, xyz=sim.apply_to_points(pts.xyz), obs_depth=sim.scale * pts.obs_depth)


def score_against_gt(bundle: SceneBundle) -> dict:
    """Scores of the bundle's priors against its ``gt/`` sidecar, for whatever both hold."""
    gt = bundle.gt
    if gt is None:
        return {}
    from agg.eval.scores import mean_mask_iou
    from agg.eval.trajectory import evaluate_trajectory

    out: dict = {}
    if bundle.has("poses") and gt.has("poses"):
        m = evaluate_trajectory(bundle.world_from_camera, gt.world_from_camera)
        out["poses"] = {"ate_rmse": m.ate_rmse, "ate_percent_of_path": m.ate_percent_of_path,
                        "rpe_trans_rmse": m.rpe_trans_rmse, "rpe_rot_rmse_deg": m.rpe_rot_rmse_deg,
                        "ate_rot_mean_deg": m.ate_rot_mean_deg, "path_length": m.path_length,
                        "units": "metres" if gt.metric else "gt scene units"}
    if bundle.has("dynamic_masks") and gt.has("dynamic_masks"):
        pred = np.asarray(bundle.dynamic_masks) > 0
        out["masks"] = {"iou_all_agents": mean_mask_iou(pred, np.asarray(gt.dynamic_masks) > 0)}
        moving = _moving_gt_masks(bundle)
        if moving is not None:
            out["masks"]["iou_moving_agents"] = mean_mask_iou(pred, moving)
    if bundle.has("tracklets") and gt.has("tracklets") and bundle.has("poses") and gt.has("poses"):
        out["tracklets"] = _score_tracklets(bundle, gt)
    return out


def _synth_extra(bundle: SceneBundle, key: str) -> Path | None:
    """Path of a synthetic ground-truth extra (``agg.synth.suite.GT_EXTRAS``), or None when it is absent."""
    from agg.synth.suite import GT_EXTRAS

    path = bundle.path / "gt" / GT_EXTRAS[key]
    return path if path.is_file() else None


def _synth_moving_ids(bundle: SceneBundle) -> list[int] | None:
    """Ids of the GT agents that move (synthetic bundles record it), or None."""
    index = _synth_extra(bundle, "index")
    return None if index is None else [a["id"] for a in json.loads(index.read_text())["agents"] if a.get("moving")]


def _moving_gt_masks(bundle: SceneBundle) -> np.ndarray | None:
    """GT masks of the moving agents only (synthetic bundles record which agents move)."""
    moving, inst = _synth_moving_ids(bundle), _synth_extra(bundle, "instance")
    return None if moving is None or inst is None else np.isin(np.load(inst), moving)


def _score_tracklets(bundle: SceneBundle, gt: SceneBundle, max_dist_m: float = 2.0,
                     min_pixel_fraction: float = 1e-3) -> dict:
    """Recall/precision of predicted track centres against GT centres, in the GT world after aligning the
    estimated camera path to GT (Sim(3)); a hit is a centre within ``max_dist_m``. Synthetic bundles record
    which agents move and how many pixels each covers: the GT tracks are then the moving agents, valid in the
    frames where they cover at least ``min_pixel_fraction`` of the image (0.1 %, 61 px at 320x192: an agent of a
    few pixels cannot be segmented by flow)."""
    from agg.eval.scores import tracklet_scores
    from agg.eval.trajectory import align_sim3

    sim = align_sim3(bundle.world_from_camera, gt.world_from_camera)
    pred_t = bundle.tracklets
    pred = np.where(pred_t.valid[..., None], pred_t.boxes[..., :3], np.nan)  # [K, T, 3]
    pred = sim.apply_to_points(pred)  # [K, T, 3]
    gt_t = gt.tracklets
    valid = np.asarray(gt_t.valid)  # [G, T]
    keep = np.ones(len(gt_t.classes), bool)
    moving, counts = _synth_moving_ids(bundle), _synth_extra(bundle, "pixel_count")
    if moving is not None and counts is not None:
        valid = valid & (np.load(counts) >= min_pixel_fraction * bundle.width * bundle.height)
        keep = np.isin(gt_t.ids, moving) & valid.any(1)
    gtc = np.where(valid[..., None], gt_t.boxes[..., :3], np.nan)[keep]
    max_dist = max_dist_m / gt.scale if gt.metric else max_dist_m
    s = tracklet_scores(pred, gtc, max_dist=max_dist)
    return {**s.as_dict(), "max_dist": max_dist_m, "gt_tracks": int(keep.sum()),
            "min_pixel_fraction": min_pixel_fraction}
