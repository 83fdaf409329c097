"""The sky / far-field node: static Gaussians on a large sphere, created only when the scene has sky.

**Sky rule** (``sky_mask``, ``has_sky``; knobs in ``SkyConfig``). A pixel is sky when all of these hold:

1. *No usable depth*: its dense depth is 0 or non-finite, or its dense-depth confidence is below
   ``min_confidence`` (0.5). ``agg/priors/depth.py`` leaves depth 0 / confidence 0 farther than ``fill_radius``
   x the diagonal from every SfM row above the horizon (and for mono depth beyond ``max_depth_ratio`` x the
   median), and gives nearest-row fills a confidence below ``fill_confidence`` = 0.5: on real clips with few
   SfM rows those fills cover much of the sky, so they count as no depth too. With only sparse depth, the
   ``fill_radius`` rule is applied to the rows directly (pixels farther than it from every row). A bundle
   without depth gives no mask (None). No-depth regions narrower than ``hole_fraction`` x the diagonal (depth
   dropouts, gaps between rows) are removed by a morphological opening.
2. *Not dynamic*: outside the dynamic masks (when the bundle has them).
3. *Above the horizon*: its viewing ray's elevation is above ``-horizon_margin_deg``, with "up" the mean of the
   cameras' -y axes in the world (cameras are mounted about level; without poses each camera's own -y).
4. *Not black, and bright*: its brightest channel exceeds ``black_level`` (a black far field, e.g. a synthetic
   clip with ``SceneConfig(sky=False)``, or a night sky, is not modelled as sky) and ``relative_brightness`` x
   the median over the frame's pixels with depth (dark tree canopies and shadows without depth are not sky).
5. *Smooth*: the mean grey gradient over a window of ``smooth_fraction`` x the diagonal is at most
   ``max_gradient`` per pixel (foliage and facades that SfM missed are textured; sky is not).
6. *Open to the top*: its connected region of such pixels reaches the image's top row (``touch_top``), which
   drops isolated windows, walls and patches of far road.

Rules 4-6 use the image only because depth alone does not separate sky from surfaces SfM missed on real clips
(KITTI). ``has_sky`` holds when at least ``min_fraction`` of the pixels of (up to ``max_frames`` evenly spaced)
frames are sky.

**Node** (``SkyNode``). A ``GaussianParams`` in the world frame (static: ``compose`` returns the activated
Gaussians) holding Gaussians on a sphere centred on the camera path's centre with radius ``radius_factor`` x the
scene extent (the larger of the camera path's diameter and the ``extent_quantile`` of the valid depths). The
directions kept are those of a Fibonacci lattice that are above the horizon (as in rule 3) and inside the view
of at least one sampled camera (image grown by ``view_margin``); the lattice density is chosen so that about
``n`` directions are kept. Each Gaussian is coloured from the pixels it projects to: the mean of the sky pixels
it falls on over the sampled frames; a direction never seen as sky (hidden behind buildings, or just outside the
images) takes the mean colour of the seen directions at its elevation (a clear sky varies mostly with
elevation). Scales are isotropic, ``scale_factor`` x the lattice spacing, with opacity ``opacity``, so the sphere
renders opaque (alpha ~ 1). The SH degree must match the other nodes' (the scene graph concatenates their SH).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from agg.io.bundle import SceneBundle
from agg.nodes.gaussians import PARAM_NAMES, GaussianParams


@dataclass(frozen=True)
class SkyConfig:
    """The sky rule (module docstring) and the sky node's initialisation."""

    min_confidence: float = 0.5  # dense depth below this confidence counts as none (depth.py's nearest-row fills)
    hole_fraction: float = 0.02  # no-depth regions narrower than this x the diagonal are not sky (>= 2 px)
    horizon_margin_deg: float = 3.0  # rays down to this far below the horizon may be sky
    black_level: float = 0.06  # brightest channel (in [0, 1]) at or below this: black, not sky
    relative_brightness: float = 1.0  # brightest channel >= this x its median over the pixels with depth
    max_gradient: float = 0.02  # mean grey gradient (per pixel) over the smoothing window at most this
    smooth_fraction: float = 0.01  # smoothing window radius, fraction of the diagonal (>= 1 px)
    touch_top: bool = True  # keep only sky regions connected to the image's top row
    max_frames: int = 32  # frames (evenly spaced) used by has_sky and SkyNode.from_bundle
    radius_factor: float = 5.0  # sphere radius = this x scene extent
    extent_quantile: float = 0.95  # scene extent: this quantile of the valid depths (or the path diameter)
    view_margin: float = 0.1  # a direction is in view when it projects inside the image grown by this fraction
    scale_factor: float = 0.75  # Gaussian std = this x the lattice spacing
    opacity: float = 0.95

    def __post_init__(self) -> None:
        if not (self.hole_fraction >= 0 and 0 <= self.min_confidence <= 1 and self.max_gradient > 0
                and self.smooth_fraction >= 0 and self.relative_brightness >= 0 and self.max_frames >= 1
                and self.radius_factor > 1 and 0 < self.extent_quantile <= 1 and self.view_margin >= 0
                and self.scale_factor > 0 and 0 < self.opacity < 1):
            raise ValueError(f"SkyConfig out of range: {self}")


def sample_frames(num_frames: int, max_frames: int) -> np.ndarray:
    """[F] evenly spaced frame indices (all frames when there are at most ``max_frames``)."""
    return np.unique(np.linspace(0, num_frames - 1, min(num_frames, max_frames)).round().astype(np.int64))


def up_vector(bundle: SceneBundle) -> np.ndarray:
    """[3] world "up": the mean of the cameras' -y axes (OpenCV y is down); (0, -1, 0) without poses."""
    if bundle.world_from_camera is None:
        return np.array([0.0, -1.0, 0.0])
    up = -np.asarray(bundle.world_from_camera, np.float64)[:, :3, 1].mean(0)
    return up / max(np.linalg.norm(up), 1e-12)


def _depth_valid(bundle: SceneBundle, i: int, min_confidence: float) -> np.ndarray | None:
    """[H, W] bool: pixels with depth (dense with confidence >= ``min_confidence``; or within depth.py's
    ``fill_radius`` of a sparse row); None without depth."""
    if bundle.has("depth_dense"):
        d = np.asarray(bundle.dense_depth[i], np.float32)
        ok = np.isfinite(d) & (d > 0)
        conf = bundle.dense_depth_confidence
        return ok & (np.asarray(conf[i], np.float32) >= min_confidence) if conf is not None else ok
    if bundle.has("depth_sparse"):
        import cv2

        from agg.priors.depth import DepthConfig

        h, w = bundle.height, bundle.width
        rows = bundle.sparse_depth(i)
        rows = rows[np.isfinite(rows).all(1) & (rows[:, 2] > 0)]
        if not len(rows):
            return np.zeros((h, w), bool)
        far = np.ones((h, w), np.uint8)
        far[np.clip(np.rint(rows[:, 1]).astype(int), 0, h - 1), np.clip(np.rint(rows[:, 0]).astype(int), 0, w - 1)] \
            = 0
        dist = cv2.distanceTransform(far, cv2.DIST_L2, 5)  # [H, W] px to the nearest row
        return dist <= DepthConfig().fill_radius * math.hypot(w, h)
    return None


def _open(mask: np.ndarray, radius: float) -> np.ndarray:
    """Morphological opening of a bool mask [H, W] by a disc of ``radius`` px (distance transforms)."""
    import cv2

    if not mask.any():
        return mask
    dist = cv2.distanceTransform(mask.astype(np.uint8), cv2.DIST_L2, 5)  # to the nearest pixel outside
    core = dist > radius
    if not core.any():
        return np.zeros_like(mask)
    grow = cv2.distanceTransform((~core).astype(np.uint8), cv2.DIST_L2, 5)  # to the nearest core pixel
    return mask & (grow <= radius)


def _local_gradient(grey: np.ndarray, radius: int) -> np.ndarray:
    """[H, W] mean gradient magnitude (per pixel, grey in [0, 1]) over a (2 radius + 1)^2 box."""
    import cv2

    gx = cv2.Sobel(grey, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(grey, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    return cv2.blur(np.hypot(gx, gy), (2 * radius + 1, 2 * radius + 1))


def _touching_top(mask: np.ndarray) -> np.ndarray:
    """The connected components (8-connected) of a bool mask [H, W] that reach the image's top row."""
    import cv2

    if not mask[0].any():
        return np.zeros_like(mask)
    _, labels = cv2.connectedComponents(mask.astype(np.uint8), connectivity=8)
    top = np.unique(labels[0][mask[0]])
    return np.isin(labels, top) & mask


def _sin_elevation(K: np.ndarray, world_from_camera: np.ndarray | None, up: np.ndarray, h: int, w: int
                   ) -> np.ndarray:
    """[H, W] sine of each pixel ray's elevation above the horizon."""
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)  # [H, W, 3]
    rot = np.eye(3) if world_from_camera is None else np.asarray(world_from_camera, np.float64)[:3, :3]
    return (rays @ (rot.T @ up)) / np.linalg.norm(rays, axis=-1)


def frame_sky_mask(bundle: SceneBundle, i: int, config: SkyConfig = SkyConfig(),
                   up: np.ndarray | None = None) -> np.ndarray | None:
    """[H, W] bool sky pixels of frame i by the module's rule; None when the bundle has no depth."""
    valid = _depth_valid(bundle, i, config.min_confidence)
    if valid is None:
        return None
    image = np.asarray(bundle.frame(i), np.float32)  # [H, W, 3] in [0, 1]
    h, w = valid.shape
    radius = max(2.0, config.hole_fraction * math.hypot(w, h))
    sky = _open(~valid, radius)
    if bundle.dynamic_masks is not None:
        sky &= np.asarray(bundle.dynamic_masks[i]) == 0
    poses = bundle.world_from_camera
    up = up_vector(bundle) if up is None else up
    sin_el = _sin_elevation(bundle.intrinsics[i], None if poses is None else poses[i], up, h, w)
    sky &= sin_el > -math.sin(math.radians(config.horizon_margin_deg))
    bright = image.max(-1)  # [H, W]
    ref = float(np.median(bright[valid])) if valid.any() else 0.0  # the surfaces' typical brightness
    sky &= (bright > config.black_level) & (bright >= config.relative_brightness * ref)
    sky &= _local_gradient(image.mean(-1), max(1, round(config.smooth_fraction * math.hypot(w, h)))) \
        <= config.max_gradient
    return _touching_top(sky) if config.touch_top else sky


def sky_mask(bundle: SceneBundle, config: SkyConfig = SkyConfig(), frames=None) -> np.ndarray | None:
    """[F, H, W] bool sky pixels (module docstring) of ``frames`` (default all T); None without depth."""
    frames = np.arange(bundle.num_frames) if frames is None else np.asarray(frames, np.int64).reshape(-1)
    up = up_vector(bundle)
    out = np.zeros((len(frames), bundle.height, bundle.width), bool)
    for j, i in enumerate(frames):
        m = frame_sky_mask(bundle, int(i), config, up)
        if m is None:
            return None
        out[j] = m
    return out


def has_sky(bundle: SceneBundle, min_fraction: float = 0.01, config: SkyConfig = SkyConfig()) -> bool:
    """Whether at least ``min_fraction`` of the pixels of up to ``config.max_frames`` frames are sky."""
    mask = sky_mask(bundle, config, sample_frames(bundle.num_frames, config.max_frames))
    return mask is not None and float(mask.mean()) >= min_fraction


def fibonacci_sphere(n: int) -> np.ndarray:
    """[n, 3] unit vectors spread evenly over the sphere (golden-angle spiral)."""
    k = np.arange(n, dtype=np.float64) + 0.5
    z = 1.0 - 2.0 * k / n
    r = np.sqrt(np.clip(1.0 - z * z, 0.0, 1.0))
    phi = math.pi * (3.0 - math.sqrt(5.0)) * k
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], -1)


def _project(points: np.ndarray, world_from_camera: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World points [N, 3] -> (pixels uv [N, 2], camera z [N])."""
    cam = (points - world_from_camera[:3, 3]) @ world_from_camera[:3, :3]  # [N, 3]
    z = cam[:, 2]
    uv = (cam[:, :2] / np.where(z > 1e-9, z, 1e-9)[:, None]) * K[[0, 1], [0, 1]] + K[:2, 2]
    return uv, z


def _in_view(dirs: np.ndarray, centre: np.ndarray, radius: float, poses: np.ndarray, Ks: np.ndarray,  # noqa: N803
             w: int, h: int, margin: float) -> np.ndarray:
    """[N] bool: directions whose sphere point projects into at least one camera (image grown by margin)."""
    seen = np.zeros(len(dirs), bool)
    mu, mv = margin * w, margin * h
    for pose, K in zip(poses, Ks):  # noqa: N806
        uv, z = _project(centre + radius * dirs, pose, K)
        seen |= (z > 0) & (uv[:, 0] >= -0.5 - mu) & (uv[:, 0] < w - 0.5 + mu) & (uv[:, 1] >= -0.5 - mv) \
            & (uv[:, 1] < h - 0.5 + mv)
    return seen


def _colour_by_elevation(sin_el: np.ndarray, rgb: np.ndarray, seen: np.ndarray, bins: int = 64) -> np.ndarray:
    """Colours [M', 3] of the unseen directions: the mean colour of the seen ones at the same elevation (binned;
    interpolated between bins, clamped beyond them), as a clear sky varies mostly with elevation."""
    el = np.arcsin(np.clip(sin_el, -1.0, 1.0))  # [M]
    edges = np.linspace(el.min(), el.max() + 1e-9, bins + 1)
    counts, _ = np.histogram(el[seen], edges)
    ok = counts > 0
    centres = 0.5 * (edges[1:] + edges[:-1])[ok]
    out = np.empty((int((~seen).sum()), 3))
    for c in range(3):
        sums, _ = np.histogram(el[seen], edges, weights=rgb[seen, c])
        out[:, c] = np.interp(el[~seen], centres, sums[ok] / counts[ok])
    return out


class SkyNode(GaussianParams):
    """World-frame sky Gaussians on a sphere (``centre`` [3], ``radius``); static, see the module docstring."""

    def __init__(self, means: Tensor, log_scales: Tensor, quats: Tensor, opacity_logits: Tensor, sh: Tensor,
                 centre: Tensor | None = None, radius: float | Tensor = 1.0):
        super().__init__(means, log_scales, quats, opacity_logits, sh)
        self.register_buffer("centre", torch.zeros(3) if centre is None
                             else torch.as_tensor(centre, dtype=torch.float32).reshape(3).clone())  # [3]
        self.register_buffer("radius", torch.as_tensor(float(radius), dtype=torch.float32))  # []

    def compose(self, frame: int | None = None, t: float | None = None) -> dict[str, Tensor]:
        """World Gaussians (the same at every frame and time): ``activated()``."""
        return self.activated()

    def state(self) -> dict[str, Tensor]:
        out = super().state()
        out.update(centre=self.centre.clone(), radius=self.radius.clone())
        return out

    @classmethod
    def from_state(cls, state: dict[str, Tensor]) -> "SkyNode":
        return cls(*(torch.as_tensor(state[n]) for n in PARAM_NAMES), centre=state["centre"],
                   radius=float(state["radius"]))

    @classmethod
    def from_bundle(cls, bundle: SceneBundle, n: int = 20_000, sh_degree: int = 1,
                    config: SkyConfig = SkyConfig()) -> "SkyNode":
        """About ``n`` sky Gaussians initialised from the bundle's frames, poses and sky pixels (module doc).
        Raises ValueError without poses, without depth or without any sky pixel (see ``has_sky``)."""
        if bundle.world_from_camera is None:
            raise ValueError("the sky node needs camera poses")
        frames = sample_frames(bundle.num_frames, config.max_frames)
        masks = sky_mask(bundle, config, frames)  # [F, H, W]
        if masks is None or not masks.any():
            raise ValueError("the bundle has no sky pixels (has_sky is False)")
        poses = np.asarray(bundle.world_from_camera, np.float64)[frames]  # [F, 4, 4]
        Ks = np.asarray(bundle.intrinsics, np.float64)[frames]  # noqa: N806  [F, 3, 3]
        w, h = bundle.width, bundle.height
        centres = poses[:, :3, 3]
        centre = centres.mean(0)
        extent = max(float(np.linalg.norm(np.ptp(centres, axis=0))), _depth_extent(bundle, frames, config), 1e-3)
        radius = config.radius_factor * extent
        up = up_vector(bundle)
        min_sin = -math.sin(math.radians(config.horizon_margin_deg))

        def kept(total: int) -> np.ndarray:
            d = fibonacci_sphere(total)
            d = d[d @ up > min_sin]
            return d[_in_view(d, centre, radius, poses, Ks, w, h, config.view_margin)]

        probe = 16_384
        frac = len(kept(probe)) / probe
        if frac == 0:
            raise ValueError("no direction above the horizon is in view of the cameras")
        total = int(math.ceil(n / frac))
        dirs = kept(total)  # [M, 3]
        xyz = centre + radius * dirs
        acc, wsum = np.zeros((len(dirs), 3)), np.zeros(len(dirs))
        for j, i in enumerate(frames):  # mean colour of the sky pixels each direction projects to
            if not masks[j].any():
                continue
            uv, z = _project(xyz, poses[j], Ks[j])
            ui, vi = np.rint(uv[:, 0]).astype(np.int64), np.rint(uv[:, 1]).astype(np.int64)
            hit = np.flatnonzero((z > 0) & (ui >= 0) & (ui < w) & (vi >= 0) & (vi < h))
            hit = hit[masks[j][vi[hit], ui[hit]]]
            acc[hit] += np.asarray(bundle.frame(int(i)), np.float32)[vi[hit], ui[hit]]
            wsum[hit] += 1.0
        seen = wsum > 0
        if not seen.any():
            raise ValueError("no sky pixel falls on the sky sphere's directions")
        rgb = acc / np.maximum(wsum, 1.0)[:, None]
        rgb[~seen] = _colour_by_elevation(dirs @ up, rgb, seen)
        spacing = radius * math.sqrt(4.0 * math.pi / total)
        g = GaussianParams.from_points(xyz, np.clip(rgb, 0, 1), sh_degree, config.opacity,
                                       scales=np.full(len(xyz), config.scale_factor * spacing))
        return cls(*(getattr(g, k) for k in PARAM_NAMES), centre=torch.as_tensor(centre, dtype=torch.float32),
                   radius=radius)


def _depth_extent(bundle: SceneBundle, frames: np.ndarray, config: SkyConfig) -> float:
    """The ``extent_quantile`` of the valid depths of ``frames`` (dense, else sparse rows); 0 without depth."""
    if bundle.has("depth_dense"):
        d = np.concatenate([np.asarray(bundle.dense_depth[int(i)], np.float32).ravel() for i in frames])
    elif bundle.has("depth_sparse"):
        d = np.concatenate([bundle.sparse_depth(int(i))[:, 2] for i in frames])
    else:
        return 0.0
    d = d[np.isfinite(d) & (d > 0)]
    return float(np.quantile(d, config.extent_quantile)) if len(d) else 0.0
