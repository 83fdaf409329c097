"""Motion evidence of a planned spawn (adaptive topology evolution): a new agent must be seen to move.

Algorithm 1 takes a spawn's evidence from the background's positional gradients and from agent-like features. With
the built-in features (no DINOv2 weights) that evidence is weak on real video: on the dashcam sample, evolution
spawned 15-19 agents on the guard rail, the road surface and the bushes at the horizon, and NVS PSNR fell
(docs/BENCHMARKS.md, thirty-second session). A car the priors missed differs from those in what the video shows:
it moves against the static world.

So a planned spawn is kept only when its box moves in the video (after the road-contact test of ``topology_spawn``).
Over the frames with gradient statistics (the training frames; held-out frames are never read), the normalised flow
residual of the dynamic-mask prior (``agg.priors.masks.dynamic_masks``: dense optical flow against the rigid flow of
the camera motion and depth, and against the epipolar geometry) is computed at the training resolution (at most
``max_width`` wide, the priors' working width) with the **refined** cameras of the graph (the priors computed theirs
with the noisy prior cameras: at 1.0 m of pose noise on the synthetic suite, 36 % of the static background read as
moving). In each training frame where the spawn's box is valid and in view, its *excess moving share* is the
fraction of the pixels of its projected box (the bounding rectangle of its eight corners, clipped to the image)
whose residual exceeds ``threshold`` and that no prior dynamic mask gives to a known agent, less that fraction over
the whole image (camera error makes some of every frame move: 7 % of the synthetic suite's static background at the
first evolution of seed 0, 3 % of the dashcam sample's). The spawn is kept when the median of that excess over those
frames reaches ``min_share``; the evolution's report lists the excess of each tested spawn under ``moving`` (kept)
or ``static`` (dropped; its Gaussians stay in the background).

Measured (docs/TRAINING.md "Spawns must move"): at the first evolution of the synthetic suite (balanced, 1.0 m), the
missed car's planned box read 0.064-0.309 over seeds 0-8; the spawns planned at the first evolution on the dashcam
sample (fast) read -0.032 to -0.008; over three training seeds there, the tracks the test dropped read at most 0.037
and those it kept 0.045-0.169 (among them the traffic 60-100 m ahead). The residual is the dynamic-mask prior's at
its default settings, with the depth prior's confidence where the bundle has one: without it, one of those tracks
(bushes 100 m away, where monocular depth is poor) read 0.13 at 640 px.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from agg.io.video import intrinsics_at, scale_intrinsics
from agg.priors.masks import MaskConfig, dynamic_masks
from agg.train import topology_track as tt


@dataclass(frozen=True)
class MotionConfig:
    enabled: bool = True  # False: spawns need no motion evidence (the evolution's report then lists none)
    min_share: float = 0.04  # a spawn's box needs this median excess moving share over its training frames
    threshold: float = 1.0  # a pixel moves where its normalised residual exceeds this (MaskConfig.threshold)
    max_width: int = 640  # the residual is computed at most this wide (the priors' working width): wider training
    # frames are shrunk for it (area; their depth, confidence and masks nearest), which bounds its cost per evolution


_CORNERS = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], np.float64)  # [8, 3]


def residuals(images: np.ndarray, K: np.ndarray, camera_from_world: np.ndarray, depth: np.ndarray | None,  # noqa: N803
              frames: np.ndarray, confidence: np.ndarray | None = None) -> dict[int, np.ndarray]:
    """{frame: normalised flow residual [H, W]} of each of ``frames`` against its neighbours among ``frames``.

    images [T, H, W, 3] (uint8, or float in [0, 1]); K [3, 3]; camera_from_world [T, 4, 4] (the refined cameras);
    depth [T, H, W] prior z-depth in the cameras' units (0 = none) or None (then only the epipolar residual);
    confidence [T, H, W] in [0, 1]: the depth prior's confidence (None: 1 where there is depth)."""
    frames = np.asarray(frames, np.int64)
    if len(frames) < 2:
        return {}
    wfc = np.linalg.inv(np.asarray(camera_from_world, np.float64)[frames])  # [F, 4, 4]
    h, w = images.shape[1:3]
    d = np.zeros((len(frames), h, w), np.float32) if depth is None else np.asarray(depth, np.float32)[frames]
    conf = None if confidence is None or depth is None else np.asarray(confidence, np.float32)[frames]
    res = dynamic_masks(np.asarray(images)[frames], np.asarray(K, np.float64), wfc, d, MaskConfig(),
                        depth_confidence=conf).residual
    return {int(t): r for t, r in zip(frames, res)}


def box_rect(world_from_box: np.ndarray, half: np.ndarray, camera_from_world: np.ndarray, K: np.ndarray,  # noqa: N803
             width: int, height: int, near: float) -> tuple[int, int, int, int] | None:
    """The pixel rectangle (u0, v0, u1, v1), inclusive, bounding a box's eight corners in the image, or None when
    a corner is nearer than ``near`` (the box reaches behind the camera) or the rectangle misses the image."""
    corners = (_CORNERS * half) @ world_from_box[:3, :3].T + world_from_box[:3, 3]  # [8, 3] world
    uv, z, _ = tt.project(corners, camera_from_world, K, width, height, near)
    if (z <= near).any():
        return None
    lo = np.floor(uv.min(0) + 0.5).astype(np.int64)
    hi = np.floor(uv.max(0) + 0.5).astype(np.int64)
    u0, v0 = max(int(lo[0]), 0), max(int(lo[1]), 0)
    u1, v1 = min(int(hi[0]), width - 1), min(int(hi[1]), height - 1)
    if u1 < u0 or v1 < v0:
        return None
    return u0, v0, u1, v1


def moving_share(residual: dict[int, np.ndarray], known: np.ndarray | None, poses: np.ndarray, valid: np.ndarray,
                 half: np.ndarray, camera_from_world: np.ndarray, K: np.ndarray, width: int, height: int,  # noqa: N803
                 near: float, threshold: float) -> tuple[float, int]:
    """(median excess moving share of a box over its judged frames, number of judged frames); (0.0, 0) when no
    frame can be judged. A frame is judged when it has a residual, the box is valid there and its rectangle is in
    the image; its excess is the share of moving pixels in the box's rectangle minus that share over the whole
    image (camera noise makes some of every frame move). Pixels of known agents (``known``) never count as moving.
    poses [T, 4, 4] world_from_box, valid [T] bool, half [3]; known [T, H, W] bool prior dynamic masks or None;
    K [T or 1, 3, 3]."""
    shares = []
    for t, r in residual.items():
        if not valid[t]:
            continue
        rect = box_rect(poses[t], half, camera_from_world[t], intrinsics_at(K, t), width, height, near)
        if rect is None:
            continue
        u0, v0, u1, v1 = rect
        moving = r > threshold  # [H, W]
        if known is not None:
            moving &= ~known[t]
        shares.append(float(moving[v0:v1 + 1, u0:u1 + 1].mean()) - float(moving.mean()))
    return (float(np.median(shares)) if shares else 0.0), len(shares)


def spawn_motion(evo, poses: np.ndarray, valid: np.ndarray, half: np.ndarray, camera_from_world: np.ndarray,
                 observed: np.ndarray, cache: dict) -> float | None:
    """The excess moving share (``moving_share``) of a planned spawn's box over the training frames (``observed``:
    the frames with gradient statistics), or None when the test is off or the evolution has no images. ``evo``:
    the ``TopologyEvolution``; ``cache``: one dict per evolution, which keeps the residuals of the refined cameras
    for every spawn planned in it."""
    cfg = evo.config
    if not cfg.motion.enabled or evo.images is None:
        return None
    if "residual" not in cache:
        cache.update(_analysis_inputs(evo, np.flatnonzero(observed), camera_from_world))
    w, h = cache["size"]
    share, _ = moving_share(cache["residual"], cache["known"], poses, valid, half, camera_from_world, cache["K"], w, h,
                            cfg.near_m * evo.unit, cfg.motion.threshold)
    return share


def _analysis_inputs(evo, frames: np.ndarray, camera_from_world: np.ndarray) -> dict:
    """The residuals of ``frames`` at the analysis size (training size, at most ``max_width`` wide), with the
    intrinsics [T or 1, 3, 3], the size (w, h) and the known-agent masks (or None) at that size. The clip's
    intrinsics are taken as constant (the first training frame's) for the flow; boxes use each frame's own."""
    from agg.train.data import resize_depth, resize_images, training_size

    w, h, _ = training_size(evo.width, evo.height, evo.config.motion.max_width)
    images, depth, conf, known, K = evo.images, evo.depth, evo.depth_confidence, evo.dynamic, evo.K  # noqa: N806
    if (w, h) != (evo.width, evo.height):
        images = resize_images(images, w, h).numpy()  # [T, h, w, 3] float in [0, 1]
        depth = None if depth is None else resize_depth(depth, w, h)
        conf = None if conf is None else resize_depth(conf, w, h)
        known = None if known is None else resize_depth(known.astype(np.float32), w, h) > 0.5
        K = np.stack([scale_intrinsics(k, (evo.width, evo.height), (w, h)) for k in K])  # noqa: N806
    res = residuals(images, intrinsics_at(K, frames[0]) if len(frames) else K[0], camera_from_world, depth,
                    frames, conf)
    return {"residual": res, "K": K, "size": (w, h), "known": known}
