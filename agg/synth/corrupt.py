"""Corruption knobs: turn the exact ground truth of a synthetic clip into noisy priors, deterministic by seed.

Every knob draws from its own random stream (``default_rng([seed, knob])``), so changing one knob never changes
the draws of another. With every knob at zero the priors equal the ground truth exactly.

Distributions (all i.i.d. over the entries they name):

- Camera translation (``camera_translation_max`` = M metres): frames 1..T-1 each get ``c' = c + m * u`` with ``u``
  uniform on the unit sphere and ``m ~ U[0, M]`` (so |noise| <= M, mean M/2). Frame 0 is left exact: it defines
  the world frame (``world_from_camera[0] = I``), and the paper perturbs camera poses used as priors relative to it.
- Camera rotation (``camera_rotation_max_deg`` = A): frames 1..T-1 get ``R' = R @ exp(a * u)``, axis ``u`` uniform on
  the sphere (camera frame), angle ``a ~ U[0, A]``; the geodesic distance between R and R' is exactly ``a``.
- Agent pose (``agent_translation_max`` = M_a, ``agent_yaw_max_deg`` = Y): every valid tracklet entry (agent, frame)
  gets its box centre moved by ``m * u`` as for cameras (``m ~ U[0, M_a]``) and its yaw changed by ``U[-Y, Y]``.
  Box sizes stay exact.
- Boxes through the cameras (``boxes_follow_cameras``): a tracklet estimated from a video is lifted into the world
  through that video's estimated cameras (``agg.priors.tracklet_detections``), so it carries each frame's camera
  error. With the flag on, every tracklet entry at frame t (the false agents' too) is moved by the noisy camera's
  error, ``world_from_camera'[t] @ inv(world_from_camera[t])``: the box keeps its true place in the frame's view and
  the noisy camera puts it in the world. The yaw takes the error's rotation about y. Off (the default), the boxes
  keep their world poses whatever the cameras' noise, and the camera error is a pure camera error.
- Missed agents (``missed`` = k): k real agents are removed from the prior tracklets, the dynamic masks and the
  prior instance map. They are chosen without randomness, by ``missed_order``: moving cars first, then
  pedestrians, then parked cars; within each group the most visible (total pixels over the clip) first; agents
  never visible come last. So ``--missed 1`` always drops the most visible moving car when there is one.
- False agents (``false`` = k): k static boxes that exist nowhere in the scene, alternating rigid (car-sized) and
  non-rigid (pedestrian-sized), placed on the road (|x| <= 5 m of the road centre line) 8 to 35 m ahead of the last
  camera, heading along the road. Their bird's-eye footprint circles keep a 0.5 m gap to every real agent at every
  frame and to each other. A false box stands for a detector's false positive, which fires on something it sees:
  it is placed only where its silhouette, depth-tested against the real scene, covers at least
  ``FALSE_MIN_PIXELS`` of the image (0.2 %: 123 pixels at 320 x 192) in at least ``FALSE_MIN_FRAMES`` frames (a
  box hidden behind a real car, seen on a few pixels, is no detection anyone would make). Their tracklets are
  valid in the frames where they would be seen (silhouette >= 1 pixel); the silhouette is added to the dynamic
  masks.
- Depth (``depth_rel_sigma`` = s, ``depth_keep_fraction`` = f): every valid pixel gets ``d' = d * max(1 + s * n,
  0.05)``, ``n ~ N(0, 1)`` (so std(d'/d - 1) = s; the clip only matters for s > 0.3); then exactly
  ``round(f * n_valid)`` valid pixels per frame, drawn uniformly without replacement, are kept and the rest set to
  0 ("no depth"). Sky pixels are always 0.
- Features (``feature_sigma`` = s): ``F' = F + s * n`` per element, ``n ~ N(0, 1)``.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from agg.synth.raycast import intersect_boxes, pixel_rays, screen_rects
from agg.synth.scene import MAT_PAINT, SEM, BoxSet, pose, rot_y, yaw_of


class NoiseConfigError(ValueError):
    """A corruption knob is out of range (negative bound, too many missed agents, ...)."""


@dataclass(frozen=True)
class NoiseConfig:
    """Corruption knobs (metres, degrees, fractions); see the module doc for each distribution."""

    seed: int = 0
    camera_translation_max: float = 0.0  # metres, bound of |noise| per frame (frames 1..T-1)
    camera_rotation_max_deg: float = 0.0  # degrees, bound of the rotation angle per frame
    agent_translation_max: float = 0.0  # metres, bound of |centre noise| per valid tracklet entry
    agent_yaw_max_deg: float = 0.0  # degrees, yaw noise ~ U[-Y, Y]
    missed: int = 0  # real agents removed from the priors
    false: int = 0  # false agents added to the priors
    depth_rel_sigma: float = 0.0  # relative (multiplicative) depth noise std
    depth_keep_fraction: float = 1.0  # fraction of valid depth pixels kept
    feature_sigma: float = 0.0  # std of the Gaussian noise added to each feature element
    boxes_follow_cameras: bool = False  # tracklet boxes carry each frame's camera error (lifted through it)

    def validate(self) -> None:
        for name in ("camera_translation_max", "camera_rotation_max_deg", "agent_translation_max",
                     "agent_yaw_max_deg", "depth_rel_sigma", "feature_sigma"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise NoiseConfigError(f"{name} must be a finite value >= 0, got {v}")
        if self.camera_rotation_max_deg > 180 or self.agent_yaw_max_deg > 180:
            raise NoiseConfigError("rotation bounds must be <= 180 degrees")
        if self.missed < 0 or self.false < 0:
            raise NoiseConfigError(f"missed and false must be >= 0, got {self.missed} and {self.false}")
        if not 0.0 <= self.depth_keep_fraction <= 1.0:
            raise NoiseConfigError(f"depth_keep_fraction must be in [0, 1], got {self.depth_keep_fraction}")

    def as_dict(self) -> dict:
        return asdict(self)


NOISE_PRESETS: dict[str, NoiseConfig] = {
    "clean": NoiseConfig(),
    "pose_0.25": NoiseConfig(camera_translation_max=0.25),
    "pose_0.5": NoiseConfig(camera_translation_max=0.5),
    "pose_1.0": NoiseConfig(camera_translation_max=1.0),
    "missed_moving_car": NoiseConfig(missed=1),
    "wild": NoiseConfig(camera_translation_max=0.5, camera_rotation_max_deg=1.0, agent_translation_max=0.5,
                        agent_yaw_max_deg=5.0, missed=1, false=1, depth_rel_sigma=0.1, depth_keep_fraction=0.5,
                        feature_sigma=0.05),
}

FALSE_MIN_PIXELS = 0.002  # fraction of the image a false box covers ...
FALSE_MIN_FRAMES = 3  # ... in at least this many frames
_KNOB = {"cam_t": 1, "cam_r": 2, "agent": 3, "false": 4, "depth": 5, "feature": 6}


@dataclass
class Priors:
    """Noisy priors for a clip (world frame, metres), ready to be written as a scene bundle."""

    world_from_camera: np.ndarray  # [T, 4, 4]
    depth: np.ndarray  # [T, H, W] float32, 0 = no depth
    track_ids: np.ndarray  # [K'] int64 (real agents keep their GT id; false agents get ids > max GT id)
    track_classes: list[str]  # [K'] "rigid" | "non-rigid"
    track_labels: list[str]  # [K'] "car" | "pedestrian" | "false-car" | "false-pedestrian"
    boxes: np.ndarray  # [K', T, 7] (cx, cy, cz, l, w, h, yaw)
    valid: np.ndarray  # [K', T] bool
    gt_index: np.ndarray  # [K'] index into the GT agents, -1 for false agents
    instance: np.ndarray  # [T, H, W] int32 prior instance ids (0 = none)
    features: np.ndarray  # [T, h, w, D] float32
    missed_ids: list[int]  # GT ids removed
    false_ids: list[int]  # ids of the false tracks


def random_unit_vectors(rng: np.random.Generator, n: int) -> np.ndarray:
    """[n, 3] directions uniform on the unit sphere."""
    v = rng.standard_normal((n, 3))
    return v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)


def axis_angle_matrix(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rodrigues: unit axes [n, 3], angles [n] (radians) -> rotations [n, 3, 3]."""
    k = np.zeros((len(axis), 3, 3))
    k[:, 0, 1], k[:, 0, 2], k[:, 1, 2] = -axis[:, 2], axis[:, 1], -axis[:, 0]
    k = k - k.transpose(0, 2, 1)
    s, c = np.sin(angle)[:, None, None], np.cos(angle)[:, None, None]
    return np.eye(3)[None] + s * k + (1 - c) * (k @ k)


def rotation_angle(r: np.ndarray) -> np.ndarray:
    """Geodesic angle (radians) of rotations [..., 3, 3]."""
    tr = np.trace(r, axis1=-2, axis2=-1)
    return np.arccos(np.clip((tr - 1.0) / 2.0, -1.0, 1.0))


def noisy_camera_poses(world_from_camera: np.ndarray, cfg: NoiseConfig) -> np.ndarray:
    """[T, 4, 4] poses with translation and rotation noise on frames 1..T-1 (frame 0 exact)."""
    out = world_from_camera.copy()
    n = len(out) - 1
    if cfg.camera_translation_max > 0 and n > 0:
        rng = np.random.default_rng([cfg.seed, _KNOB["cam_t"]])
        mag = rng.uniform(0.0, cfg.camera_translation_max, n)
        out[1:, :3, 3] += mag[:, None] * random_unit_vectors(rng, n)
    if cfg.camera_rotation_max_deg > 0 and n > 0:
        rng = np.random.default_rng([cfg.seed, _KNOB["cam_r"]])
        angle = np.deg2rad(rng.uniform(0.0, cfg.camera_rotation_max_deg, n))
        out[1:, :3, :3] = out[1:, :3, :3] @ axis_angle_matrix(random_unit_vectors(rng, n), angle)
    return out


def missed_order(gt) -> list[int]:
    """GT agent indices in the order they are dropped by ``missed`` (see the module doc)."""
    seen = gt.pixel_count.sum(1)  # [K]
    group = {"moving_car": 0, "pedestrian": 1, "parked_car": 2}

    def key(k: int):
        return (seen[k] == 0, group.get(gt.agent_names[k], 3), -int(seen[k]), k)

    return sorted(range(len(seen)), key=key)


def noisy_boxes(boxes: np.ndarray, valid: np.ndarray, cfg: NoiseConfig) -> np.ndarray:
    """[K, T, 7] boxes with centre and yaw noise on the valid entries."""
    out = boxes.copy()
    rng = np.random.default_rng([cfg.seed, _KNOB["agent"]])
    shape = boxes.shape[:2]
    n = int(np.prod(shape))
    mag = rng.uniform(0.0, cfg.agent_translation_max, n).reshape(shape) if cfg.agent_translation_max > 0 else None
    dirs = random_unit_vectors(rng, n).reshape(*shape, 3)
    dyaw = rng.uniform(-1.0, 1.0, n).reshape(shape) * np.deg2rad(cfg.agent_yaw_max_deg)
    if mag is not None:
        out[..., :3] += np.where(valid[..., None], mag[..., None] * dirs, 0.0)
    if cfg.agent_yaw_max_deg > 0:
        out[..., 6] = np.where(valid, out[..., 6] + dyaw, out[..., 6])
    return out


def boxes_through_cameras(boxes: np.ndarray, valid: np.ndarray, true_world_from_camera: np.ndarray,
                          world_from_camera: np.ndarray) -> np.ndarray:
    """[K, T, 7] boxes seen from the true cameras [T, 4, 4] and placed in the world by ``world_from_camera``
    [T, 4, 4]: each valid entry moved by ``world_from_camera[t] @ inv(true_world_from_camera[t])``."""
    error = world_from_camera @ np.linalg.inv(true_world_from_camera)  # [T, 4, 4]
    centre = np.einsum("tij,ktj->kti", error[:, :3, :3], boxes[..., :3]) + error[None, :, :3, 3]  # [K, T, 3]
    heading = np.einsum("tij,ktj->kti", error[:, :3, :3], np.stack(  # the box's +z axis under rot_y(yaw)
        [np.sin(boxes[..., 6]), np.zeros(boxes.shape[:2]), np.cos(boxes[..., 6])], -1))  # [K, T, 3]
    out = boxes.copy()
    out[..., :3] = np.where(valid[..., None], centre, boxes[..., :3])
    out[..., 6] = np.where(valid, np.arctan2(heading[..., 0], heading[..., 2]), boxes[..., 6])
    return out


def box_world_pose(box: np.ndarray) -> np.ndarray:
    """world_from_box [4, 4] of a (cx, cy, cz, l, w, h, yaw) box."""
    return pose(rot_y(box[6]), box[:3])


def _footprint_radius(size_lwh: np.ndarray) -> np.ndarray:
    return 0.5 * np.hypot(size_lwh[..., 0], size_lwh[..., 1])


def false_agents(gt, cfg: NoiseConfig) -> tuple[np.ndarray, list[str], np.ndarray]:
    """Place ``cfg.false`` static false boxes: (boxes [k, 7], classes [k], silhouettes [k, T, H, W] bool)."""
    rng = np.random.default_rng([cfg.seed, _KNOB["false"]])
    road_from_world = np.linalg.inv(gt.world_from_road)
    last_road = road_from_world @ gt.world_from_camera[-1]  # road_from_camera of the last frame
    boxes, classes, masks = [], [], []
    real_xz = gt.boxes[..., [0, 2]]  # [K, T, 2]
    real_r = _footprint_radius(gt.boxes[..., 3:5])  # [K, T]
    for i in range(cfg.false):
        rigid = i % 2 == 0
        for _attempt in range(500):
            size = (np.array([rng.uniform(3.8, 4.6), rng.uniform(1.7, 1.9), rng.uniform(1.4, 1.6)]) if rigid
                    else np.array([rng.uniform(0.6, 0.9), rng.uniform(0.5, 0.7), rng.uniform(1.6, 1.85)]))
            x = rng.uniform(-5.0, 5.0)
            z = last_road[2, 3] + rng.uniform(8.0, 35.0)
            heading = rng.choice([0.0, np.pi]) + rng.uniform(-0.1, 0.1)
            road_from_box = pose(rot_y(heading - 0.5 * np.pi), [x, -0.5 * size[2], z])
            world_from_box = gt.world_from_road @ road_from_box
            box = np.concatenate([world_from_box[:3, 3], size, [yaw_of(world_from_box)]])
            r = _footprint_radius(size)
            gap = np.linalg.norm(real_xz - box[[0, 2]], axis=-1) - real_r - r  # [K, T]
            if gap.size and gap.min() < 0.5:
                continue
            if any(np.linalg.norm(b[[0, 2]] - box[[0, 2]]) < _footprint_radius(b[3:5]) + r + 0.5 for b in boxes):
                continue
            sil = silhouettes(gt, box)
            seen = sil.sum((1, 2)) >= max(1.0, FALSE_MIN_PIXELS * sil[0].size)  # [T]
            if seen.sum() >= min(FALSE_MIN_FRAMES, len(sil)):
                break
        else:
            raise NoiseConfigError(f"could not place false agent {i + 1} of {cfg.false} in free, visible space")
        boxes.append(box)
        classes.append("rigid" if rigid else "non-rigid")
        masks.append(sil)
    shape = (0, *gt.instance.shape)
    return (np.array(boxes).reshape(-1, 7), classes, np.array(masks, bool).reshape(-1, *shape[1:]) if masks
            else np.zeros(shape, bool))


def silhouettes(gt, box: np.ndarray) -> np.ndarray:
    """[T, H, W] bool: pixels where the box would be seen, in front of the real scene (depth test)."""
    t_count, height, width = gt.instance.shape
    bs = BoxSet(box_world_pose(box)[None], 0.5 * box[[3, 5, 4]][None], np.array([MAT_PAINT]), np.ones((1, 3)),
                np.array([SEM["car"]]), np.array([1]))
    rays = pixel_rays(gt.K, width, height)
    out = np.zeros((t_count, height, width), bool)
    for i in range(t_count):
        w_from_c = gt.world_from_camera[i]
        rects = screen_rects(bs, np.linalg.inv(w_from_c), gt.K, width, height)
        t, _, _, _, _ = intersect_boxes(w_from_c[:3, 3], rays @ w_from_c[:3, :3].T, bs, rects, width)
        out[i] = (t.reshape(height, width) < gt.depth[i])
    return out


def corrupt(gt, cfg: NoiseConfig) -> Priors:
    """Noisy priors from a ``suite.GroundTruth`` (see the module doc for every knob)."""
    cfg.validate()
    n_agents = len(gt.agent_ids)
    if cfg.missed > n_agents:
        raise NoiseConfigError(f"missed={cfg.missed} but the scene has only {n_agents} agents")
    poses = noisy_camera_poses(gt.world_from_camera, cfg)
    # depth
    depth = np.where(gt.depth_valid, gt.depth, 0.0).astype(np.float32)
    if cfg.depth_rel_sigma > 0:
        rng = np.random.default_rng([cfg.seed, _KNOB["depth"]])
        factor = np.maximum(1.0 + cfg.depth_rel_sigma * rng.standard_normal(depth.shape), 0.05)
        depth = np.where(gt.depth_valid, depth * factor, 0.0).astype(np.float32)
    if cfg.depth_keep_fraction < 1.0:
        rng = np.random.default_rng([cfg.seed, _KNOB["depth"] + 100])
        for i in range(len(depth)):
            idx = np.flatnonzero(gt.depth_valid[i])
            keep = rng.choice(idx, size=int(round(cfg.depth_keep_fraction * len(idx))), replace=False)
            frame = np.zeros(depth[i].size, np.float32)
            frame[keep] = depth[i].ravel()[keep]
            depth[i] = frame.reshape(depth[i].shape)
    # agents
    dropped = missed_order(gt)[:cfg.missed]
    kept = [k for k in range(n_agents) if k not in dropped]
    boxes = noisy_boxes(gt.boxes, gt.visible, cfg)[kept]
    valid = gt.visible[kept]
    ids = [int(gt.agent_ids[k]) for k in kept]
    classes = [gt.agent_classes[k] for k in kept]
    labels = [gt.agent_labels[k] for k in kept]
    instance = np.where(np.isin(gt.instance, [gt.agent_ids[k] for k in dropped]), 0, gt.instance).astype(np.int32)
    fboxes, fclasses, fsil = false_agents(gt, cfg)
    next_id = int(gt.agent_ids.max(initial=0)) + 1
    false_ids = list(range(next_id, next_id + len(fboxes)))
    for j in range(len(fboxes)):
        instance = np.where(fsil[j], false_ids[j], instance)
    fvalid = fsil.any((2, 3))  # [k, T]
    all_boxes = np.concatenate([boxes, np.repeat(fboxes[:, None], len(gt.depth), 1)]) if len(fboxes) else boxes
    all_valid = np.concatenate([valid, fvalid]).astype(bool)
    if cfg.boxes_follow_cameras:
        all_boxes = boxes_through_cameras(all_boxes, all_valid, gt.world_from_camera, poses)
    # features
    features = gt.features.copy()
    if cfg.feature_sigma > 0:
        rng = np.random.default_rng([cfg.seed, _KNOB["feature"]])
        features = (features + cfg.feature_sigma * rng.standard_normal(features.shape)).astype(np.float32)
    return Priors(
        world_from_camera=poses, depth=depth,
        track_ids=np.array(ids + false_ids, np.int64), track_classes=classes + fclasses,
        track_labels=labels + ["false-car" if c == "rigid" else "false-pedestrian" for c in fclasses],
        boxes=all_boxes.reshape(-1, len(gt.depth), 7), valid=all_valid,
        gt_index=np.array(kept + [-1] * len(fboxes), np.int64), instance=instance, features=features,
        missed_ids=[int(gt.agent_ids[k]) for k in dropped], false_ids=false_ids)
