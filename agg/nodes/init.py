"""Initialise a scene graph's Gaussians from a scene bundle's priors.

- **Background**: static points accumulated over frames: pixels with depth (dense where the bundle has it, else
  the sparse rows) outside the dynamic masks and the ego vehicle's mask, back-projected with the frame's pose,
  coloured from the frame, merged on a voxel grid (one point per voxel, averaged), then capped at a budget.
- **Rigid agents**: for each rigid tracklet, the depth pixels of the frames where it is valid, taken into the box
  frame (``inv(world_from_box)``) and kept when inside the box (grown by ``box_margin``); a track with too few
  points is filled with points spread uniformly in its box, with the mean colour of its pixels.
- **Scales** from KNN distances, clamped to ``[min_scale_fraction, max_scale_fraction] x`` the depth at which
  the point was seen (background; a far point may be large, a near one may not cover the view) or the agent's
  box size (agents).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from agg.io.bundle import SceneBundle
from agg.nodes.gaussians import GaussianParams, knn_scales


@dataclass(frozen=True)
class InitConfig:
    background_budget: int = 60_000  # Gaussians at most in the background
    agent_budget: int = 3_000  # per agent
    pixels_per_frame: int = 8_000  # depth pixels sampled per frame
    voxel_fraction: float = 0.005  # background voxel edge, fraction of the median depth
    min_confidence: float = 0.3  # dense-depth confidence below this is ignored
    box_margin: float = 0.1  # agents: keep points within the box grown by this fraction
    min_agent_points: int = 50  # below this, the box is filled with uniform points
    min_scale_fraction: float = 1e-4  # KNN scale clamp, fractions of the depth the point was seen at (or of
    max_scale_fraction: float = 0.02  # the agent's box size): 0.02 is ~1.1 degrees seen from the camera
    sh_degree: int = 1
    opacity: float = 0.1
    fallback_depth: float = 10.0  # scene units: the background shell of a clip without any depth pixel
    seed: int = 0


def box_pose(box: np.ndarray) -> np.ndarray:
    """[4, 4] ``world_from_box`` of a bundle box (cx, cy, cz, l, w, h, yaw): rotation about the world y axis."""
    c, s = np.cos(box[6]), np.sin(box[6])
    p = np.eye(4)
    p[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    p[:3, 3] = box[:3]
    return p


def _frame_points(bundle: SceneBundle, i: int, cfg: InitConfig, rng: np.random.Generator,
                  dense, conf) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Depth pixels of frame i: (u, v) [M, 2], camera-frame xyz [M, 3], rgb [M, 3] in [0, 1]."""
    if dense is not None:
        d = np.asarray(dense[i], np.float32)
        ok = np.isfinite(d) & (d > 0)
        if conf is not None:
            ok &= np.asarray(conf[i], np.float32) >= cfg.min_confidence
        v, u = np.nonzero(ok)
        z = d[v, u]
    elif bundle.has("depth_sparse"):
        rows = bundle.sparse_depth(i)
        u, v, z = rows[:, 0], rows[:, 1], rows[:, 2]
    else:
        return np.zeros((0, 2)), np.zeros((0, 3)), np.zeros((0, 3))
    if len(z) > cfg.pixels_per_frame:
        pick = rng.choice(len(z), cfg.pixels_per_frame, replace=False)
        u, v, z = u[pick], v[pick], z[pick]
    K = bundle.intrinsics[i]  # noqa: N806
    x = (u - K[0, 2]) / K[0, 0] * z
    y = (v - K[1, 2]) / K[1, 1] * z
    ui = np.clip(np.rint(u).astype(int), 0, bundle.width - 1)
    vi = np.clip(np.rint(v).astype(int), 0, bundle.height - 1)
    rgb = np.asarray(bundle.frames.raw[i][vi, ui], np.float32) / 255.0
    return np.stack([ui, vi], -1), np.stack([x, y, z], -1), rgb


def _fallback_points(bundle: SceneBundle, cfg: InitConfig, rng: np.random.Generator
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Points at a constant depth (``fallback_depth`` scene units) on a pixel grid of every frame, coloured from
    the frame: (xyz [M, 3], rgb + depth [M, 4]). Used only when no frame has a single usable depth pixel."""
    poses = bundle.world_from_camera
    step = max(4, int(np.sqrt(bundle.width * bundle.height / max(cfg.pixels_per_frame // 4, 1))))
    v, u = np.mgrid[step // 2:bundle.height:step, step // 2:bundle.width:step]
    u, v = u.reshape(-1).astype(float), v.reshape(-1).astype(float)
    z = np.full(len(u), cfg.fallback_depth)
    xyz, extra = [], []
    for i in range(bundle.num_frames):
        K = bundle.intrinsics[i]  # noqa: N806
        cam = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], -1)
        xyz.append(cam @ poses[i, :3, :3].T + poses[i, :3, 3])
        rgb = np.asarray(bundle.frames.raw[i][v.astype(int), u.astype(int)], np.float32) / 255.0
        extra.append(np.c_[rgb, z])
    return np.concatenate(xyz), np.concatenate(extra)


def _voxel_merge(xyz: np.ndarray, extra: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray]:
    """One point per occupied voxel: the mean position [M, 3] and the mean of ``extra`` [M, E] of its points."""
    keys = np.floor(xyz / voxel).astype(np.int64)
    _, inv, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    out_xyz = np.zeros((len(counts), 3))
    out_extra = np.zeros((len(counts), extra.shape[1]))
    np.add.at(out_xyz, inv, xyz)
    np.add.at(out_extra, inv, extra)
    return out_xyz / counts[:, None], out_extra / counts[:, None]


def init_from_bundle(bundle: SceneBundle, config: InitConfig = InitConfig()) -> dict:
    """Initial Gaussians: {"background": GaussianParams, "rigid" / "non-rigid": (GaussianParams, instance [N],
    track rows [K]) or None}. Needs poses and some depth."""
    cfg = config
    if not bundle.has("poses"):
        raise ValueError("initialisation needs camera poses (run agg priors first)")
    if not (bundle.has("depth_dense") or bundle.has("depth_sparse")):
        raise ValueError("initialisation needs depth (dense or sparse) in the bundle")
    rng = np.random.default_rng(cfg.seed)
    poses = bundle.world_from_camera  # [T, 4, 4]
    dense = bundle.dense_depth if bundle.has("depth_dense") else None
    conf = bundle.dense_depth_confidence if dense is not None else None
    masks = bundle.dynamic_masks
    ego = bundle.ego_mask  # [H, W] bool or None
    tracks = bundle.tracklets
    agent_rows = list(range(len(tracks.classes))) if tracks else []  # every agent track, rigid or not
    bg_xyz, bg_rgb = [], []
    ag = {k: ([], []) for k in agent_rows}
    for i in range(bundle.num_frames):
        uv, cam, rgb = _frame_points(bundle, i, cfg, rng, dense, conf)
        world = cam @ poses[i, :3, :3].T + poses[i, :3, 3]  # [M, 3]
        static = np.ones(len(uv), bool) if masks is None else np.asarray(masks[i])[uv[:, 1], uv[:, 0]] == 0
        if ego is not None:
            static &= ~ego[uv[:, 1], uv[:, 0]]  # the ego vehicle's pixels are no part of the scene
        bg_xyz.append(world[static])
        bg_rgb.append(np.c_[rgb[static], cam[static, 2]])  # colour and the depth it was seen at
        for k in agent_rows:
            if not tracks.valid[k, i]:
                continue
            box = np.asarray(tracks.boxes[k, i], float)
            half = 0.5 * np.array([box[3], box[5], box[4]]) * (1 + cfg.box_margin)  # box axes: l, h, w
            if not np.isfinite(half).all():
                continue
            local = (world - box[:3]) @ box_pose(box)[:3, :3]  # [M, 3] in the box frame
            inside = np.all(np.abs(local) <= half, axis=1)
            ag[k][0].append(local[inside])
            ag[k][1].append(rgb[inside])
    xyz, rgbz = np.concatenate(bg_xyz), np.concatenate(bg_rgb)
    if len(xyz) == 0:  # a textureless clip (e.g. black frames): no depth anywhere; start from a fronto-parallel
        xyz, rgbz = _fallback_points(bundle, cfg, rng)  # shell so that training still has something to fit
    depth_med = float(np.median(rgbz[:, 3]))
    xyz, rgbz = _voxel_merge(xyz, rgbz, cfg.voxel_fraction * depth_med)
    if len(xyz) > cfg.background_budget:
        pick = rng.choice(len(xyz), cfg.background_budget, replace=False)
        xyz, rgbz = xyz[pick], rgbz[pick]
    seen = rgbz[:, 3]  # [M] depth each point was seen at
    scales = np.clip(knn_scales(xyz), cfg.min_scale_fraction * seen, cfg.max_scale_fraction * seen)
    background = GaussianParams.from_points(xyz, rgbz[:, :3], cfg.sh_degree, cfg.opacity, scales=scales)
    out = {"background": background, "rigid": None, "non-rigid": None}
    for cls in ("rigid", "non-rigid"):
        rows = [k for k in agent_rows if tracks.classes[k] == cls]
        if rows:
            out[cls] = _agent_gaussians(rows, ag, tracks, cfg, rng, depth_med)
    return out


def _agent_gaussians(rows: list[int], ag: dict, tracks, cfg: InitConfig, rng: np.random.Generator,
                     depth_med: float) -> tuple[GaussianParams, np.ndarray, list[int]]:
    """Canonical Gaussians of the given track rows from their box-frame points (uniform box fill when too few)."""
    pts, cols, inst, sc = [], [], [], []
    for j, k in enumerate(rows):
        p = np.concatenate(ag[k][0]) if ag[k][0] else np.zeros((0, 3))
        c = np.concatenate(ag[k][1]) if ag[k][1] else np.zeros((0, 3))
        if len(p) < cfg.min_agent_points:  # fill the (median) box with uniform points
            sizes = tracks.box_size(k)
            sizes = np.where(np.isfinite(sizes), sizes, 0.05 * depth_med)
            p = (rng.random((cfg.min_agent_points * 4, 3)) - 0.5) * sizes
            c = np.broadcast_to(c.mean(0) if len(c) else np.full(3, 0.5), p.shape)
        if len(p) > cfg.agent_budget:
            pick = rng.choice(len(p), cfg.agent_budget, replace=False)
            p, c = p[pick], c[pick]
        size = float(np.ptp(p, axis=0).max()) if len(p) > 1 else 1.0
        sc.append(np.clip(knn_scales(p), cfg.min_scale_fraction * size, cfg.max_scale_fraction * 5 * size))
        pts.append(p)
        cols.append(c)
        inst.append(np.full(len(p), j))
    p, c = np.concatenate(pts), np.concatenate(cols)
    g = GaussianParams.from_points(p, c, cfg.sh_degree, cfg.opacity, scales=np.concatenate(sc))
    return g, np.concatenate(inst), rows
