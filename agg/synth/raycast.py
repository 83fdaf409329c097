"""An independent analytic ray caster for the synthetic suite (numpy, vectorised over pixels).

It intersects one ray per pixel centre with a plane (the road) and oriented boxes (slab test), keeps the nearest
hit, and shades it with procedural textures. It shares no code with AGG's Gaussian renderer, so it can serve as
ground truth for it.

Rays: for pixel (row i, column j) the camera-frame direction is ``K^-1 [j, i, 1]`` (OpenCV pixel-centre
convention), i.e. scaled so that its z component is 1. The ray parameter of a hit is therefore exactly its depth
(z along the camera axis, metres).

Outputs (``RenderOutput``): RGB float32 [H, W, 3] in [0, 1]; depth float32 [H, W] in metres, ``inf`` where the ray
hits nothing (sky / far field) with ``valid`` False there; instance int32 [H, W] (0 = background, k = agent k);
semantic uint8 [H, W] (ids of ``scene.SEMANTIC_CLASSES``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from agg.synth.scene import (MAT_CLOTH, MAT_FACADE, MAT_GLASS, MAT_PAINT, MAT_RUBBER, MAT_SIDEWALK, MAT_SKIN, SEM,
                             BoxSet, Scene)

NEAR = 0.05  # metres; hits closer than this are ignored (boxes that contain the camera are invisible)
SKY_HORIZON = np.array([0.86, 0.89, 0.93])
SKY_ZENITH = np.array([0.33, 0.53, 0.85])


@dataclass
class RenderOutput:
    rgb: np.ndarray  # [H, W, 3] float32 in [0, 1]
    depth: np.ndarray  # [H, W] float32 metres (z), inf where nothing was hit
    valid: np.ndarray  # [H, W] bool, depth is finite
    instance: np.ndarray  # [H, W] int32, 0 = background
    semantic: np.ndarray  # [H, W] uint8


class ValueNoise:
    """Smooth value noise on a periodic 256x256 lattice, deterministic by seed. Output in [0, 1]."""

    def __init__(self, seed: int, size: int = 256):
        self.size = size
        self.table = np.random.default_rng([seed, 0x7E47]).random((size, size))  # [S, S]

    def __call__(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        iu, iv = np.floor(u), np.floor(v)
        fu, fv = u - iu, v - iv
        fu, fv = fu * fu * (3 - 2 * fu), fv * fv * (3 - 2 * fv)
        i0, j0 = iu.astype(np.int64) % self.size, iv.astype(np.int64) % self.size
        i1, j1 = (i0 + 1) % self.size, (j0 + 1) % self.size
        t = self.table
        a = t[i0, j0] * (1 - fu) + t[i1, j0] * fu
        b = t[i0, j1] * (1 - fu) + t[i1, j1] * fu
        return a * (1 - fv) + b * fv

    def fbm(self, u: np.ndarray, v: np.ndarray, scale: float) -> np.ndarray:
        """Two octaves at ``scale`` and ``scale / 4`` metres."""
        return 0.65 * self(u / scale, v / scale) + 0.35 * self(u * 4 / scale + 17.0, v * 4 / scale + 31.0)


def pixel_rays(K: np.ndarray, width: int, height: int) -> np.ndarray:
    """Camera-frame ray directions [H*W, 3] with z = 1, row-major over pixels."""
    jj, ii = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    pix = np.stack([jj.ravel(), ii.ravel(), np.ones(width * height)], -1)  # [P, 3]
    return pix @ np.linalg.inv(K).T


def intersect_plane(origin: np.ndarray, dirs: np.ndarray, normal: np.ndarray, offset: float) -> np.ndarray:
    """Ray parameter [P] of the hit with plane ``normal . x = offset`` from its front (normal) side; inf if none."""
    denom = dirs @ normal  # [P]
    dist = float(normal @ origin) - offset  # > 0: origin on the front side
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -dist / denom
    return np.where((denom < -1e-12) & (dist > 0) & (t > NEAR), t, np.inf)


_CORNER_SIGNS = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float)  # [8, 3]
_EDGES = np.array([(a, b) for a in range(8) for b in range(a + 1, 8)
                   if np.abs(_CORNER_SIGNS[a] - _CORNER_SIGNS[b]).sum() == 2])  # [12, 2] corner pairs


def screen_rects(boxes: BoxSet, camera_from_world: np.ndarray, K: np.ndarray, width: int, height: int) -> np.ndarray:
    """Pixel rectangles [B, 4] (col0, col1, row0, row1, inclusive) bounding each box's image; empty: col0 > col1.

    The box is clipped to the near plane (z = NEAR) first, so boxes reaching behind the camera get a tight rect.
    """
    n_box = len(boxes)
    local = _CORNER_SIGNS[None] * boxes.half_size[:, None]  # [B, 8, 3]
    cam_from_box = camera_from_world[None] @ boxes.world_from_box  # [B, 4, 4]
    pts = np.einsum("bij,bkj->bki", cam_from_box[:, :3, :3], local) + cam_from_box[:, None, :3, 3]  # [B, 8, 3]
    a, b = pts[:, _EDGES[:, 0]], pts[:, _EDGES[:, 1]]  # [B, 12, 3]
    za, zb = a[..., 2], b[..., 2]
    crossing = (za - NEAR) * (zb - NEAR) < 0  # [B, 12]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(crossing, (NEAR - za) / (zb - za), 0.0)
    cut = a + s[..., None] * (b - a)  # [B, 12, 3], on the near plane where crossing
    cand = np.concatenate([pts, cut], 1)  # [B, 20, 3]
    ok = np.concatenate([pts[..., 2] >= NEAR, crossing], 1)  # [B, 20]
    z = np.maximum(cand[..., 2], NEAR)
    u = K[0, 0] * cand[..., 0] / z + K[0, 1] * cand[..., 1] / z + K[0, 2]
    v = K[1, 1] * cand[..., 1] / z + K[1, 2]
    big = 1e9
    u0 = np.where(ok, u, big).min(1)
    u1 = np.where(ok, u, -big).max(1)
    v0 = np.where(ok, v, big).min(1)
    v1 = np.where(ok, v, -big).max(1)
    rect = np.stack([np.floor(np.clip(u0, -1, width)), np.ceil(np.clip(u1, -1, width)),
                     np.floor(np.clip(v0, -1, height)), np.ceil(np.clip(v1, -1, height))], -1).astype(np.int64)
    rect[:, [0, 2]] = np.maximum(rect[:, [0, 2]], 0)
    rect[:, 1] = np.minimum(rect[:, 1], width - 1)
    rect[:, 3] = np.minimum(rect[:, 3], height - 1)
    empty = ~ok.any(1) | (rect[:, 0] > rect[:, 1]) | (rect[:, 2] > rect[:, 3])
    rect[empty] = [1, 0, 1, 0]
    return rect.reshape(n_box, 4)


def _slab(o_b: np.ndarray, d_b: np.ndarray, half: np.ndarray):
    """Slab test in box frames: o_b [..., 3], d_b [..., 3], half [..., 3] -> (t [...], axis [...])."""
    d_safe = np.where(np.abs(d_b) < 1e-12, 1e-12, d_b)
    inv = 1.0 / d_safe
    t1 = (-half - o_b) * inv
    t2 = (half - o_b) * inv
    tmin = np.minimum(t1, t2)
    t_near = tmin.max(-1)
    t_far = np.maximum(t1, t2).min(-1)
    return np.where((t_near <= t_far) & (t_near > NEAR), t_near, np.inf), tmin.argmax(-1)


def _finish(origin, dirs, boxes, t_best, idx):
    n_rays = len(dirs)
    if not len(boxes):
        return t_best, idx, np.zeros((n_rays, 3)), np.zeros(n_rays, int), np.ones(n_rays)
    hit = np.isfinite(t_best)
    safe = np.where(hit, idx, 0)
    rot = boxes.world_from_box[safe, :3, :3]  # [P, 3, 3]
    d_hit = np.einsum("pji,pj->pi", rot, dirs)  # [P, 3] box frame
    o_hit = np.einsum("pji,pj->pi", rot, origin[None] - boxes.world_from_box[safe, :3, 3])
    local = o_hit + np.where(hit, t_best, 0.0)[:, None] * d_hit
    # face axis: the coordinate that lies on the box surface (largest relative coordinate)
    axis = (np.abs(local) / boxes.half_size[safe]).argmax(-1)
    sign = np.sign(local[np.arange(n_rays), axis])
    return t_best, np.where(hit, idx, -1), local, axis, np.where(sign == 0, 1.0, sign)


def intersect_boxes_dense(origin: np.ndarray, dirs: np.ndarray, boxes: BoxSet):
    """Reference version of ``intersect_boxes``: every ray against every box ([P, B] arrays)."""
    n_rays = len(dirs)
    if not len(boxes):
        return _finish(origin, dirs, BoxSet.empty(), np.full(n_rays, np.inf), np.full(n_rays, -1))
    rot = boxes.world_from_box[:, :3, :3]  # [B, 3, 3]
    o_b = np.einsum("bji,bj->bi", rot, origin[None] - boxes.world_from_box[:, :3, 3])  # [B, 3]
    d_b = np.einsum("bji,pj->pbi", rot, dirs)  # [P, B, 3]
    t, _ = _slab(o_b[None], d_b, boxes.half_size[None])  # [P, B]
    idx = t.argmin(1)
    return _finish(origin, dirs, boxes, t[np.arange(n_rays), idx], idx)


def intersect_boxes(origin: np.ndarray, dirs: np.ndarray, boxes: BoxSet, rects: np.ndarray, width: int):
    """Nearest box hit per pixel ray, testing each box only on the pixels of its screen rectangle.

    origin [3] and dirs [H*W, 3] (row-major pixels) are in the world frame; rects [B, 4] from ``screen_rects``.
    Returns (t [P] (inf if none), index [P] (-1 if none), local_point [P, 3] in the hit box's frame,
    local_axis [P] (0..2, the face's normal axis), local_sign [P] (+-1, the face's side)).
    """
    n_rays = len(dirs)
    t_best = np.full(n_rays, np.inf)
    idx = np.full(n_rays, -1)
    if not len(boxes):
        return _finish(origin, dirs, BoxSet.empty(), t_best, idx)
    rot = boxes.world_from_box[:, :3, :3]  # [B, 3, 3]
    o_b = np.einsum("bji,bj->bi", rot, origin[None] - boxes.world_from_box[:, :3, 3])  # [B, 3]
    for b in np.nonzero((rects[:, 0] <= rects[:, 1]) & (rects[:, 2] <= rects[:, 3]))[0]:
        c0, c1, r0, r1 = rects[b]
        pix = (np.arange(r0, r1 + 1)[:, None] * width + np.arange(c0, c1 + 1)[None]).ravel()  # [M]
        t, _ = _slab(o_b[b][None], dirs[pix] @ rot[b], boxes.half_size[b][None])  # [M]
        closer = t < t_best[pix]
        t_best[pix[closer]] = t[closer]
        idx[pix[closer]] = b
    return _finish(origin, dirs, boxes, t_best, idx)


# ---------------------------------------------------------------------------------------------------------------
# procedural materials: each returns RGB [M, 3] for the M pixels given


def _face_uv(local: np.ndarray, axis: np.ndarray, half: np.ndarray):
    """Face coordinates (metres): u horizontal along the face, h = height above the box bottom (y is down)."""
    u = np.where(axis == 0, local[:, 2], local[:, 0])
    u = np.where(axis == 1, local[:, 0] + local[:, 2], u)
    h = half[:, 1] - local[:, 1]
    return u, h


def _facade(noise, colour, local, axis, half):
    u, h = _face_uv(local, axis, half)
    u = u + half[:, 0] + half[:, 2]  # start each face near 0 so windows line up per building
    floor_h, bay = 3.2, 2.8
    window = ((h % floor_h) > 1.0) & ((h % floor_h) < 2.4) & ((u % bay) > 0.6) & ((u % bay) < 1.9)
    window &= (h < 2 * half[:, 1] - 1.0) & (h > 0.8) & (axis != 1)
    row = np.floor(h / 0.25)
    ub = u + 0.25 * (row % 2)
    mortar = ((h % 0.25) < 0.035) | ((ub % 0.5) < 0.035)
    brick_var = 0.85 + 0.3 * noise(np.floor(ub / 0.5) * 7.3, row * 3.1)
    rgb = colour * brick_var[:, None] * (0.9 + 0.2 * noise.fbm(u, h, 2.0))[:, None]
    rgb = np.where(mortar[:, None], 0.8 * colour + 0.15, rgb)
    glass = np.array([0.16, 0.21, 0.29]) + 0.12 * noise(u * 0.3 + 5.0, h * 0.3)[:, None]
    return np.where(window[:, None], glass, rgb)


def _road(noise, road_xz):
    """Asphalt albedo [M, 3]; road_xz [M, 2] in the road frame (metres)."""
    x, z = road_xz[:, 0], road_xz[:, 1]
    grey = 0.25 + 0.1 * noise.fbm(x, z, 1.5)
    return np.stack([grey, grey, grey * 1.04], -1)


def _markings(x: np.ndarray, z: np.ndarray, lane_width: float) -> np.ndarray:
    """Lane markings (road frame, metres): dashed lines between lanes, solid lines at the outer lane edges."""
    dashed = (np.abs(np.abs(x) - 0.5 * lane_width) < 0.08) & ((z % 6.0) < 3.0)
    solid = np.abs(np.abs(x) - 1.5 * lane_width) < 0.1
    return dashed | solid


def shade(noise: ValueNoise, material, colour, local, axis, half, world_point) -> np.ndarray:
    """RGB [M, 3] (unlit albedo) of M hits of one material (box materials only)."""
    m = len(material)
    u, h = _face_uv(local, axis, half)
    if material[0] == MAT_FACADE:
        return _facade(noise, colour, local, axis, half)
    if material[0] == MAT_SIDEWALK:
        tile = ((np.abs(local[:, 0]) % 1.0) < 0.04) | ((np.abs(local[:, 2]) % 1.0) < 0.04)
        base = colour * (0.9 + 0.2 * noise.fbm(world_point[:, 0], world_point[:, 2], 0.8))[:, None]
        return np.where(tile[:, None], 0.7 * colour, base)
    if material[0] == MAT_GLASS:
        grad = np.clip(0.5 + 0.6 * (local[:, 1] / np.maximum(half[:, 1], 1e-6)), 0, 1)
        return 0.55 * colour + 0.1 + 0.15 * grad[:, None] * np.array([0.6, 0.7, 0.9])
    if material[0] in (MAT_PAINT, MAT_CLOTH, MAT_SKIN):
        amp = {MAT_PAINT: 0.06, MAT_CLOTH: 0.15, MAT_SKIN: 0.05}[int(material[0])]
        return colour * (1 - amp + 2 * amp * noise.fbm(u + 3.0 * axis, h, 0.4))[:, None]
    if material[0] == MAT_RUBBER:
        return colour + 0.05 * noise(u * 8, h * 8)[:, None]
    return np.repeat(np.array([[1.0, 0.0, 1.0]]), m, 0)  # unknown material: loud magenta


def render(K: np.ndarray, world_from_camera: np.ndarray, width: int, height: int, boxes: BoxSet,
           plane: tuple[np.ndarray, float] | None = None, road_from_world: np.ndarray | None = None,
           sky: bool = True, noise: ValueNoise | None = None, lane_width: float = 3.5) -> RenderOutput:
    """Ray-cast one frame.

    K [3, 3]; world_from_camera [4, 4]; boxes in the world frame; plane = (n [3], d) with n the up normal of the
    road (``n . x = d``); road_from_world [4, 4] gives the road frame for the road texture and the sky's up
    direction (identity if omitted).
    """
    noise = noise or ValueNoise(0)
    road_from_world = np.eye(4) if road_from_world is None else road_from_world
    camera_from_world = np.linalg.inv(world_from_camera)
    origin = world_from_camera[:3, 3]
    dirs = pixel_rays(K, width, height) @ world_from_camera[:3, :3].T  # [P, 3] world, camera z = 1
    n_pix = len(dirs)
    rects = screen_rects(boxes, camera_from_world, K, width, height) if len(boxes) else np.zeros((0, 4), int)
    t_box, idx, local, axis, sign = intersect_boxes(origin, dirs, boxes, rects, width)
    t_plane = intersect_plane(origin, dirs, *plane) if plane is not None else np.full(n_pix, np.inf)
    on_box = t_box <= t_plane
    t = np.minimum(t_box, t_plane)
    hit = np.isfinite(t)
    rgb = np.zeros((n_pix, 3))
    semantic = np.full(n_pix, SEM["sky"], np.uint8)
    instance = np.zeros(n_pix, np.int32)
    normal = np.zeros((n_pix, 3))
    world_point = origin[None] + np.where(hit, t, 0.0)[:, None] * dirs

    box_pix = np.nonzero(hit & on_box)[0]
    if len(box_pix):
        b = idx[box_pix]
        semantic[box_pix] = boxes.semantic[b]
        instance[box_pix] = boxes.instance[b]
        n_local = np.zeros((len(box_pix), 3))
        n_local[np.arange(len(box_pix)), axis[box_pix]] = sign[box_pix]
        normal[box_pix] = np.einsum("pij,pj->pi", boxes.world_from_box[b, :3, :3], n_local)
        mats = boxes.material[b]
        for mat in np.unique(mats):
            sel = mats == mat
            p = box_pix[sel]
            rgb[p] = shade(noise, mats[sel], boxes.colour[b[sel]], local[p], axis[p], boxes.half_size[b[sel]],
                           world_point[p])
    plane_pix = np.nonzero(hit & ~on_box)[0]
    if len(plane_pix):
        road_pt = world_point[plane_pix] @ road_from_world[:3, :3].T + road_from_world[:3, 3]
        rgb[plane_pix] = _road(noise, road_pt[:, [0, 2]])
        mark = _markings(road_pt[:, 0], road_pt[:, 2], lane_width)
        rgb[plane_pix[mark]] = 0.92
        semantic[plane_pix] = np.where(mark, SEM["marking"], SEM["road"])
        normal[plane_pix] = plane[0]
    # lighting: ambient + Lambert with a fixed sun (road frame: up, slightly right and from behind)
    up = road_from_world[:3, :3].T @ np.array([0.0, -1.0, 0.0])  # world
    sun = road_from_world[:3, :3].T @ np.array([0.35, -1.0, -0.45])
    sun /= np.linalg.norm(sun)
    lit = 0.55 + 0.45 * np.clip(normal @ sun, 0.0, 1.0)
    rgb *= lit[:, None]
    miss = ~hit
    if sky:
        d = dirs[miss] / np.linalg.norm(dirs[miss], axis=1, keepdims=True)
        e = np.clip(2.0 * (d @ up), 0.0, 1.0)[:, None]
        rgb[miss] = (1 - e) * SKY_HORIZON + e * SKY_ZENITH
    depth = np.where(hit, t, np.inf)
    return RenderOutput(np.clip(rgb, 0, 1).reshape(height, width, 3).astype(np.float32),
                        depth.reshape(height, width).astype(np.float32), hit.reshape(height, width),
                        instance.reshape(height, width), semantic.reshape(height, width))


def render_scene_frame(scene: Scene, frame: int, noise: ValueNoise | None = None) -> RenderOutput:
    """Render frame ``frame`` of a generated scene with its road plane, textures and sky setting."""
    cfg = scene.config
    return render(scene.K, scene.world_from_camera[frame], cfg.width, cfg.height, scene.boxes_at(frame),
                  plane=scene.ground_plane(), road_from_world=np.linalg.inv(scene.world_from_road), sky=cfg.sky,
                  noise=noise or ValueNoise(scene.texture_seed), lane_width=cfg.lane_width)
