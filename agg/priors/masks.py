"""Dynamic-mask prior: dense optical flow against the rigid flow of the estimated ego-motion and depth.

For each frame i, one neighbour on each side is used: the nearest frame j (up to ``max_gap`` away) where the
rigid flow of the depth map reaches ``target_parallax_px`` (at its 25 % quantile), so that far agents move
enough. OpenCV dense flow (DIS) i -> j is compared with what a static world would give:

* **Depth residual** (pixels with depth): the rigid flow ``r(p) = pi(K (R_ji d K^-1 p + t_ji)) - p``. A car
  ahead at the ego's speed has ~0 observed flow while the rigid flow of its pixels (depth from the road around
  it) is large, so this residual finds it.
* **Epipolar residual** (every pixel, no depth needed): Sampson distance of the flow correspondence to the
  relative pose's epipolar geometry; it finds motion across the epipolar lines (crossing, turning agents). It is
  skipped when the baseline is too small for an epipolar geometry.

Both are normalised, ``e = |disagreement| / (floor_px * W / 640 + rel * max(|rigid|, |observed|))``, so 1 means
"more than ``rel`` of the motion and more than ``floor_px`` pixels at 640 px width"; for the depth residual
``rel = rel_flow + rel_uncertain * (1 - depth confidence)``. An agent with ~0 observed flow crosses 1 once its
rigid flow exceeds ``floor / (1 - rel)``; a depth error by a factor k crosses 1 when ``1 - 1/k > rel``.
The flow itself is the per-pixel better (photometric error) of a plain flow and a flow computed after warping
frame j by the rigid flow (``_Flow``). A direction's residual is the larger of the two residuals, times a
texture weight (flow means nothing on sky or plain asphalt), and NaN where the forward-backward check fails or
the flow leaves the image. A frame's residual is the minimum over its usable directions (disocclusions
disagree with one side only), 0 where none is usable. Thresholded, it is cleaned by opening, closing, hole
filling and removal of small components; the ego vehicle's bonnet (dynamic at the same pixels in most frames,
touching the bottom border) is removed. Rules and measurements: docs/PRIORS.md "Dynamic masks".
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np


class MaskPriorError(ValueError):
    """Bad input to the dynamic-mask prior (shapes, poses, intrinsics, config)."""


@dataclass(frozen=True)
class MaskConfig:
    """Settings of ``dynamic_masks``. Pixel lengths are at 640 px image width and scale with the width."""

    flow: str = "dis"  # "dis" (cv2.DISOpticalFlow) or "farneback" (cv2.calcOpticalFlowFarneback)
    dis_preset: str = "medium"  # "ultrafast" | "fast" | "medium"
    flow_mode: str = "best"  # "compensated", "direct" or "best" of the two per pixel (see _Flow)
    photo_window: float = 7.0  # window (px at 640 width) of the photometric error that picks the better flow
    photo_margin: float = 0.01  # the direct flow must beat the compensated one by this (grey in [0, 1])
    max_gap: int = 6  # neighbours: per direction the nearest frame (up to max_gap away) whose ...
    target_parallax_px: float = 6.0  # ... rigid flow reaches this (px at 640 width) at the ...
    parallax_quantile: float = 0.25  # ... quantile of the pixels with depth
    floor_px: float = 1.0  # absolute tolerance of the flow disagreement (px at 640 px width)
    rel_flow: float = 0.3  # relative tolerance (x max(|rigid|, |observed|)) with fully confident depth
    rel_uncertain: float = 0.3  # extra relative tolerance at depth confidence 0 (none given: confidence 1)
    epipolar: bool = True  # also use the Sampson (epipolar) residual
    epipolar_rel: float = 0.1  # relative tolerance of the epipolar residual (x |observed flow|)
    epipolar_floor_px: float = 1.5  # absolute tolerance of the epipolar residual (px at 640 px width)
    min_texture: float = 0.3  # residuals x min(1, texture / (this x the frame's median texture)); texture =
    #   smallest eigenvalue of the grey image's structure tensor (cv2.cornerMinEigenVal, window 9 px at 640
    #   width): flow is unreliable without texture (sky, plain asphalt); 0 = off
    min_baseline: float = 1e-3  # epipolar residual only when |t_ji| > this x median depth
    fb_max_px: float = 1.5  # forward-backward flow check: tolerance px (at 640 width) + 0.1 x |flow|
    threshold: float = 1.0  # residual above this is dynamic
    open_radius: float = 2.0  # opening radius (px at 640 width)
    close_radius: float = 10.0  # closing radius (px at 640 width)
    fill_holes: bool = True
    min_area: float = 4e-4  # components smaller than this fraction of the image are removed
    ego_fraction: float = 0.7  # ego-vehicle rule (ego_vehicle_region): dynamic in this fraction of frames ...
    ego_min_frames: int = 8  # ... of a clip this long at least, and touching the bottom border
    keep_flow: bool = False  # return the forward flows (i -> i+1) in MaskResult.flow

    def __post_init__(self) -> None:
        if self.flow_mode not in ("compensated", "direct", "best"):
            raise MaskPriorError(f"MaskConfig.flow_mode must be compensated, direct or best, got {self.flow_mode!r}")
        if self.flow not in ("dis", "farneback"):
            raise MaskPriorError(f"MaskConfig.flow must be 'dis' or 'farneback', got {self.flow!r}")
        if self.dis_preset not in ("ultrafast", "fast", "medium"):
            raise MaskPriorError(f"MaskConfig.dis_preset must be ultrafast, fast or medium, got {self.dis_preset!r}")
        if self.max_gap < 1:
            raise MaskPriorError(f"MaskConfig.max_gap must be >= 1, got {self.max_gap}")
        if self.threshold <= 0 or self.floor_px <= 0 or self.rel_flow < 0 or self.rel_uncertain < 0:
            raise MaskPriorError("MaskConfig threshold and floor_px must be > 0, rel_flow, rel_uncertain >= 0")


@dataclass
class MaskResult:
    masks: np.ndarray  # [T, H, W] uint8 0/1
    residual: np.ndarray  # [T, H, W] float32, normalised residual (dimensionless, threshold 1 by default)
    flow: np.ndarray | None = None  # [T, H, W, 2] float32 forward flow i -> i+1 (last frame zeros), optional
    ego: np.ndarray | None = None  # [H, W] bool, the ego vehicle's pixels (ego_vehicle_region), taken out of the
    # masks; all False where the rule found none (or the clip is shorter than ego_min_frames)


# ------------------------------------------------------------------------------------------------------ flow
def _pixels(h: int, w: int) -> np.ndarray:
    jj, ii = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    return np.stack([jj, ii, np.ones_like(jj)], -1)  # [H, W, 3] homogeneous image points (u, v, 1)


def _project(K: np.ndarray, j_from_i: np.ndarray, pix: np.ndarray, depth: np.ndarray  # noqa: N803
             ) -> tuple[np.ndarray, np.ndarray]:
    """Rigid flow [..., 2] of image points pix [..., 3] with depth [...] (0 = none: point at infinity) and
    whether it comes from the depth [...] bool."""
    rays = pix @ np.linalg.inv(K).T  # [..., 3], z = 1
    x_inf = rays @ j_from_i[:3, :3].T  # direction of a point at infinity in camera j
    xj = x_inf * depth[..., None] + j_from_i[:3, 3]
    has = (depth > 0) & (xj[..., 2] > 1e-9)
    xj = np.where(has[..., None], xj, x_inf)
    z = xj[..., 2:]
    ok = z > 1e-9
    uv = (xj @ K.T)[..., :2] / np.where(ok, z, 1.0)
    return np.where(ok, uv - pix[..., :2], 0.0), has


def rigid_flow(K: np.ndarray, j_from_i: np.ndarray, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # noqa: N803
    """Flow [H, W, 2] that a static world with depth [H, W] (z, 0 = none) gives from frame i to frame j, and
    where it comes from the depth [H, W] bool. Pixels without depth (or behind camera j) get the rotation-only
    flow of a point at infinity."""
    return _project(K, j_from_i, _pixels(*depth.shape), depth)


def _warp(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Sample img at image points uv [H, W, 2] (bilinear, border replicated)."""
    import cv2

    return cv2.remap(img, np.ascontiguousarray(uv[..., 0], np.float32), np.ascontiguousarray(uv[..., 1], np.float32),
                     cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


class _Flow:
    """Dense flow between frames (cached).

    ``compensated``: frame j is first warped onto frame i by the rigid flow r (depth + relative pose), OpenCV flow
    d is computed between frame i and the warped frame, and the total flow is ``d + r(p + d)``. A static world
    then only needs a small correction, which is where dense flow is accurate (the large forward-motion flows of
    the road at the image bottom are not). But an agent whose rigid flow is wrong by many pixels (a car ahead
    at the ego's speed: ~0 observed, large rigid) needs a large correction, which DIS finds only in part.
    ``direct``: plain flow i -> j, right for such agents, wrong on large textureless motion. ``best``: both, and
    per pixel the direct flow where its photometric error (window mean of |I_i(p) - I_j(p + f)|) beats the
    compensated one's by ``photo_margin``; ties (textureless areas) keep the compensated flow.
    """

    def __init__(self, grey: list[np.ndarray], K: np.ndarray, wfc: np.ndarray, depth, config: MaskConfig):  # noqa: N803
        import cv2

        self.cv2, self.grey, self.K, self.config = cv2, grey, K, config
        self.wfc, self.cfw, self.depth = wfc, np.linalg.inv(wfc), depth
        self.cache: dict = {}
        if config.flow == "dis":
            preset = {"ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST, "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
                      "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM}[config.dis_preset]
            self.dis = cv2.DISOpticalFlow_create(preset)

    def j_from_i(self, i: int, j: int) -> np.ndarray:
        return self.cfw[j] @ self.wfc[i]

    def parallax(self, i: int, j: int) -> float:
        """Quantile ``parallax_quantile`` of the rigid-flow magnitude (px) from i to j over pixels with depth (every
        8th row and column)."""
        d = self.depth(i)[::8, ::8]
        if not (d > 0).any():
            return 0.0
        pix = _pixels(*self.depth(i).shape)[::8, ::8]
        flow, has = _project(self.K, self.j_from_i(i, j), pix, d)
        mag = np.linalg.norm(flow[has], axis=-1)
        return float(np.quantile(mag, self.config.parallax_quantile)) if has.any() else 0.0

    def neighbour(self, i: int, step: int) -> int | None:
        """Nearest frame j = i + k step (k = 1..max_gap) whose parallax reaches the target; else the farthest."""
        n = len(self.grey)
        target = self.config.target_parallax_px * self.grey[0].shape[1] / 640.0
        best = None
        for k in range(1, self.config.max_gap + 1):
            j = i + k * step
            if not 0 <= j < n:
                break
            best = j
            if self.parallax(i, j) >= target:
                break
        return best

    def texture(self, i: int) -> np.ndarray:
        """Texture weight [H, W] in [0, 1] of frame i (MaskConfig.min_texture)."""
        key = ("texture", i)
        if key not in self.cache:
            w = self.grey[i].shape[1]
            block = max(3, int(round(9 * w / 640.0)) | 1)
            lam = self.cv2.cornerMinEigenVal(self.grey[i].astype(np.float32) / 255.0, block, 3)
            ref = self.config.min_texture * max(float(np.median(lam)), 1e-12)
            self.cache[key] = np.clip(lam / ref, 0.0, 1.0)
        return self.cache[key]

    def _photo(self, i: int, j: int, pix: np.ndarray, flow: np.ndarray) -> np.ndarray:
        """Window mean of |I_i(p) - I_j(p + flow)| [H, W] (grey in [0, 1])."""
        diff = np.abs(self.grey[i].astype(np.float32) - _warp(self.grey[j].astype(np.float32), pix + flow)) / 255.0
        k = max(3, int(round(self.config.photo_window * self.grey[i].shape[1] / 640.0)) | 1)
        return self.cv2.blur(diff, (k, k))

    def _raw(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        if self.config.flow == "dis":
            return self.dis.calc(a, b, None)
        return self.cv2.calcOpticalFlowFarneback(a, b, None, 0.5, 4, 15, 3, 5, 1.1, 0)

    def __call__(self, i: int, j: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(flow [H, W, 2] float32, rigid flow [H, W, 2], rigid flow from depth [H, W] bool) from i to j."""
        if (i, j) not in self.cache:
            rig, has = rigid_flow(self.K, self.j_from_i(i, j), self.depth(i))
            mode = self.config.flow_mode
            pix = _pixels(*has.shape)[..., :2]
            if mode in ("compensated", "best"):
                warped = _warp(self.grey[j], pix + rig)
                d = self._raw(self.grey[i], warped).astype(np.float64)
                rig_at = np.stack([_warp(rig[..., k].astype(np.float32), pix + d) for k in range(2)], -1)
                flow = d + rig_at
            if mode in ("direct", "best"):
                direct = self._raw(self.grey[i], self.grey[j]).astype(np.float64)
                if mode == "best":
                    better = self._photo(i, j, pix, direct) < self._photo(i, j, pix, flow) - self.config.photo_margin
                    flow = np.where(better[..., None], direct, flow)
                else:
                    flow = direct
            self.cache[(i, j)] = (flow.astype(np.float32), rig, has)
        return self.cache[(i, j)]

    def evict_before(self, i: int) -> None:
        for key in [k for k in self.cache if (k[1] if k[0] == "texture" else max(k)) < i]:
            del self.cache[key]


def _skew(t: np.ndarray) -> np.ndarray:
    return np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])


# -------------------------------------------------------------------------------------------------- residual
def sampson_distance(K: np.ndarray, j_from_i: np.ndarray, flow: np.ndarray) -> np.ndarray:  # noqa: N803
    """Sampson distance (px) [H, W] of the correspondences p -> p + flow to the relative pose's epipolar geometry."""
    kinv = np.linalg.inv(K)
    fmat = kinv.T @ _skew(j_from_i[:3, 3]) @ j_from_i[:3, :3] @ kinv  # x_j^T F x_i = 0
    xi = _pixels(*flow.shape[:2])  # [H, W, 3]
    xj = xi.copy()
    xj[..., :2] += flow
    fx = xi @ fmat.T  # F x_i
    ftx = xj @ fmat  # F^T x_j
    num = (xj * fx).sum(-1) ** 2
    den = fx[..., 0] ** 2 + fx[..., 1] ** 2 + ftx[..., 0] ** 2 + ftx[..., 1] ** 2
    return np.sqrt(num / np.maximum(den, 1e-12))


def _direction_residual(flows: _Flow, i: int, j: int, conf: np.ndarray, median_depth: float, config: MaskConfig
                        ) -> np.ndarray:
    """Normalised residual [H, W] of frame i against neighbour j; NaN where this direction is unusable."""
    flow_ij, rig, has_depth = flows(i, j)
    flow_ji = flows(j, i)[0]
    h, w = has_depth.shape
    s = w / 640.0
    target = _pixels(h, w)[..., :2] + flow_ij  # [H, W, 2]
    inside = (target[..., 0] >= 0) & (target[..., 0] <= w - 1) & (target[..., 1] >= 0) & (target[..., 1] <= h - 1)
    back = _warp(flow_ji, target)  # flow of j at p + f, should be -f
    mag_obs = np.linalg.norm(flow_ij, axis=-1)
    consistent = np.linalg.norm(flow_ij + back, axis=-1) <= config.fb_max_px * s + 0.1 * mag_obs
    mag_rig = np.linalg.norm(rig, axis=-1)
    rel = config.rel_flow + config.rel_uncertain * (1.0 - conf)
    e_depth = np.linalg.norm(flow_ij - rig, axis=-1) / (config.floor_px * s + rel * np.maximum(mag_rig, mag_obs))
    e = np.where(has_depth, e_depth, 0.0)
    j_from_i = flows.j_from_i(i, j)
    if config.epipolar and float(np.linalg.norm(j_from_i[:3, 3])) > config.min_baseline * median_depth:
        d_s = sampson_distance(flows.K, j_from_i, flow_ij)
        e = np.maximum(e, d_s / (config.epipolar_floor_px * s + config.epipolar_rel * mag_obs))
    if config.min_texture > 0:
        e = e * flows.texture(i)
    return np.where(inside & consistent, e, np.nan).astype(np.float32)


# ------------------------------------------------------------------------------------------------ clean-up
def clean_mask(raw: np.ndarray, config: MaskConfig = MaskConfig()) -> np.ndarray:
    """Morphological clean-up of a boolean mask [H, W] -> uint8 0/1 (opening, closing, hole filling, small
    components removed)."""
    import cv2
    from scipy.ndimage import binary_fill_holes

    h, w = raw.shape
    s = w / 640.0
    m = raw.astype(np.uint8)

    def disk(r: float) -> np.ndarray:
        k = max(1, int(round(r * s)))
        return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * k + 1, 2 * k + 1))

    if config.open_radius > 0:
        m = cv2.morphologyEx(m, cv2.MORPH_OPEN, disk(config.open_radius))
    if config.close_radius > 0:
        m = cv2.morphologyEx(m, cv2.MORPH_CLOSE, disk(config.close_radius))
    if config.fill_holes:
        m = binary_fill_holes(m).astype(np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
    small = np.flatnonzero(stats[:, cv2.CC_STAT_AREA] < config.min_area * h * w)
    small = small[small > 0]
    if len(small):
        m[np.isin(labels, small)] = 0
    return m


# ------------------------------------------------------------------------------------------------------- api
def _check_inputs(frames, K, world_from_camera, depth, depth_confidence):
    t = len(frames)
    if t < 2:
        raise MaskPriorError(f"dynamic masks need at least 2 frames, got {t}")
    f0 = np.asarray(frames[0])
    if f0.ndim != 3 or f0.shape[2] != 3:
        raise MaskPriorError(f"frames must be [T, H, W, 3], got frame shape {f0.shape}")
    h, w = f0.shape[:2]
    K = np.asarray(K, np.float64)  # noqa: N806
    if K.shape != (3, 3) or not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise MaskPriorError(f"K must be a finite [3, 3] with positive focal lengths, got {K}")
    wfc = np.asarray(world_from_camera, np.float64)
    if wfc.shape != (t, 4, 4) or not np.isfinite(wfc).all():
        raise MaskPriorError(f"world_from_camera must be finite [{t}, 4, 4], got {wfc.shape}")
    depth = np.asarray(depth)
    if depth.shape != (t, h, w):
        raise MaskPriorError(f"depth must be [{t}, {h}, {w}], got {depth.shape}")
    if depth_confidence is not None and np.asarray(depth_confidence).shape != (t, h, w):
        raise MaskPriorError(f"depth_confidence must be [{t}, {h}, {w}], got {np.asarray(depth_confidence).shape}")
    return t, h, w, K, wfc, depth


def _grey(frame: np.ndarray) -> np.ndarray:
    import cv2

    f = np.asarray(frame)
    if f.dtype != np.uint8:
        f = np.clip(np.asarray(f, np.float32) * 255.0 + 0.5, 0, 255).astype(np.uint8)
    return cv2.cvtColor(f, cv2.COLOR_RGB2GRAY)


def dynamic_masks(frames, K: np.ndarray, world_from_camera: np.ndarray, depth: np.ndarray,  # noqa: N803
                  config: MaskConfig = MaskConfig(), depth_confidence: np.ndarray | None = None,
                  progress: Callable[[int], None] | None = None) -> MaskResult:
    """Dynamic masks of a clip (module docstring).

    frames [T, H, W, 3] (uint8 or float in [0, 1]); K [3, 3]; world_from_camera [T, 4, 4]; depth [T, H, W]
    (z, 0 = none); depth_confidence [T, H, W] in [0, 1] (None: 1 where depth > 0). ``progress(i)`` is called
    after each frame's residual.
    """
    t, h, w, K, wfc, depth = _check_inputs(frames, K, world_from_camera, depth, depth_confidence)  # noqa: N806

    def depth_of(i: int) -> np.ndarray:  # [H, W] float64, 0 = none
        d = np.asarray(depth[i], np.float64)
        return np.where(np.isfinite(d) & (d > 0), d, 0.0)

    flows = _Flow([_grey(frames[i]) for i in range(t)], K, wfc, depth_of, config)
    residual = np.zeros((t, h, w), np.float32)
    fwd = np.zeros((t, h, w, 2), np.float32) if config.keep_flow else None
    for i in range(t):
        d = depth_of(i)
        c = (d > 0).astype(np.float64) if depth_confidence is None else \
            np.clip(np.nan_to_num(np.asarray(depth_confidence[i], np.float64)), 0.0, 1.0)
        median_depth = float(np.median(d[d > 0])) if (d > 0).any() else 1.0
        per_dir = []
        for step in (-1, 1):
            j = flows.neighbour(i, step)
            if j is not None:
                per_dir.append(_direction_residual(flows, i, j, c, median_depth, config))
        if fwd is not None and i + 1 < t:
            fwd[i] = flows(i, i + 1)[0]
        stack = np.stack(per_dir)  # [n_dir, H, W]
        r = np.where(np.isnan(stack), np.inf, stack).min(0)  # [H, W], inf where no direction is usable
        r[np.isinf(r)] = 0.0
        residual[i] = r
        flows.evict_before(i - config.max_gap)
        if progress is not None:
            progress(i)
    masks = np.stack([clean_mask(r > config.threshold, config) for r in residual])
    ego = ego_vehicle_region(masks, config)
    if ego.any():
        residual[:, ego] = 0.0
        masks[:, ego] = 0
        masks = np.stack([clean_mask(m > 0, config) for m in masks])
    return MaskResult(masks=masks, residual=residual, flow=fwd, ego=ego)


def ego_vehicle_region(masks: np.ndarray, config: MaskConfig = MaskConfig()) -> np.ndarray:
    """[H, W] bool: the ego vehicle's bonnet (or dashboard) seen at the image bottom.

    It moves with the camera, so it is "dynamic" at the same pixels in nearly every frame: the connected parts
    of ``mean_t(masks) >= ego_fraction`` that touch the bottom image border, dilated by the closing radius.
    Needs ``ego_min_frames`` frames; an agent that stays in the same pixels at the image bottom for the whole
    clip is removed with it.
    """
    import cv2

    t, h, w = masks.shape
    if t < config.ego_min_frames or config.ego_fraction <= 0:
        return np.zeros((h, w), bool)
    persistent = (masks.mean(0) >= config.ego_fraction).astype(np.uint8)
    n, labels = cv2.connectedComponents(persistent, connectivity=8)
    bottom = np.unique(labels[-1][labels[-1] > 0])
    region = np.isin(labels, bottom).astype(np.uint8)
    if region.any():
        k = max(1, int(round(config.close_radius * w / 640.0)))
        region = cv2.dilate(region, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * k + 1, 2 * k + 1)))
    return region.astype(bool)
