"""Depth prior: per-frame sparse depth from the SfM tracks, an image-guided densification, optional mono depth.

* ``sparse_depth_rows``: each frame's SfM observations as rows ``(u, v, z, confidence)``.
* ``densify_depth`` / ``densify_clip``: the default dense prior from the rows and the image: a RANSAC ground plane
  in image space (rows behind it, i.e. agents driving with the ego, are snapped onto it and stood up), a local
  outlier test, linear interpolation of inverse depth over a Delaunay triangulation (exact on planes), ground
  clamp and completion, and a confidence-normalised guided filter. No depth far from rows above the horizon.
* ``MonoDepthModel``: relative inverse depth from a *local* TorchScript file, aligned per frame to the rows.

Depth is camera z in scene units, 0 = none; confidence in [0, 1]. Rules and measurements: docs/PRIORS.md "Depth".
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np


class DepthPriorError(ValueError):
    """Bad input to the depth prior (shapes, sizes, missing model file)."""


@dataclass(frozen=True)
class DepthConfig:
    """Settings of the depth prior. Lengths given as fractions are of the image diagonal unless named otherwise."""

    # sparse rows: confidence = 1 / (1 + (error / error_ref_px)^2) * min(1, (track_length - 1) / (full_track - 1))
    error_ref_px: float = 1.0  # reprojection error (SfM work resolution) at which the error factor is 0.5
    full_track_length: int = 4  # observations at which the track-length factor reaches 1 (2 obs: 1/3)
    max_depth_ratio: float = 100.0  # rows deeper than this x the median depth (clip or frame) are dropped
    # densification
    min_points: int = 6  # fewer usable rows in a frame: no dense depth (zeros, confidence 0)
    ground: bool = True  # use a RANSAC ground plane (fit_ground_plane); rows ...
    ground_margin: float = 1.5  # ... deeper than this x the plane's depth at their pixel are snapped onto it
    upright: bool = True  # and hold up to the horizon (_upright_rows) ...
    upright_band: float = 0.01  # ... unless ground rows lie above them within this x W columns
    ground_tol: float = 0.08  # RANSAC inlier: |w - w_plane| <= ground_tol * w (w = inverse depth)
    ground_min_inliers: int = 12  # and at least this many inliers (and 10 % of the lower-half rows)
    ground_max_height: float = 0.25  # implied camera height (focal ~ max(W, H)) <= this x median row depth
    ground_iterations: int = 300
    ground_clamp_confidence: float = 0.5  # pixels clamped onto the plane get at least this confidence
    ground_fill_confidence: float = 0.2  # bare pixels below the horizon take the plane's depth at this confidence
    outlier_neighbours: int = 8  # image-space neighbours of the local outlier test
    outlier_ratio: float = 2.5  # a row deeper/shallower than this x its neighbours' median is dropped
    max_edge: float = 0.2  # triangles with an edge longer than this (x diagonal) are not interpolated
    fill_radius: float = 0.06  # outside kept triangles, pixels this close (x diagonal) to a row take its depth
    fill_confidence: float = 0.5  # confidence factor of such nearest-row fills
    conf_distance: float = 0.04  # confidence x exp(-0.5 (distance to nearest row / (this x diagonal))^2)
    conf_spread: float = 1.0  # confidence x exp(-log(max/min depth of the triangle) / conf_spread)
    guided_radius: float = 0.012  # guided-filter window radius as a fraction of the image width (0: off)
    guided_eps: float = 1e-3  # guided-filter regularisation (grey image in [0, 1])
    seed: int = 0  # RANSAC
    # mono depth alignment
    mono_min_points: int = 20  # fewer sparse rows: the frame gets no mono depth
    mono_confidence: float = 0.8  # confidence of aligned mono depth, x the inlier fraction of the fit
    mono_inlier_tol: float = 0.15  # relative inverse-depth residual of an inlier of the scale/shift fit

    def __post_init__(self) -> None:
        if min(self.min_points, self.mono_min_points) < 3 or self.full_track_length < 2 or self.error_ref_px <= 0 \
                or min(self.outlier_ratio, self.ground_margin, self.max_depth_ratio) <= 1:
            raise DepthPriorError("DepthConfig: min_points, mono_min_points >= 3, full_track_length >= 2, "
                                  "error_ref_px > 0, outlier_ratio, ground_margin, max_depth_ratio > 1")


# ------------------------------------------------------------------------------------------------ sparse rows
def sparse_depth_rows(points, num_frames: int, width: int, height: int,
                      config: DepthConfig = DepthConfig()) -> list[np.ndarray]:
    """Per frame float32 [k, 4] rows (u, v, depth, confidence) from ``SparsePoints`` (``agg.priors.poses``).

    ``obs_uv`` must be at the training resolution (width x height). Rows outside the image, with depth <= 0 or
    non-finite, or deeper than ``max_depth_ratio`` x the clip's median observation depth are dropped.
    Confidence = ``1 / (1 + (error_px / error_ref_px)^2) * min(1, (n_obs - 1) / (full_track_length - 1))``
    (rows of confidence 0 are dropped too).
    """
    if num_frames < 1 or width < 1 or height < 1:
        raise DepthPriorError(f"num_frames, width and height must be >= 1, got {num_frames}, {width}, {height}")
    try:
        frame = np.asarray(points.obs_frame, np.int64)  # [K]
        pid = np.asarray(points.obs_point, np.int64)  # [K]
        uv = np.asarray(points.obs_uv, np.float64).reshape(-1, 2)  # [K, 2]
        z = np.asarray(points.obs_depth, np.float64).ravel()  # [K]
        err = np.asarray(points.error_px, np.float64).ravel()  # [M]
    except AttributeError as e:
        raise DepthPriorError(f"points must be a SparsePoints (obs_frame, obs_point, obs_uv, obs_depth, "
                              f"error_px): {e}") from None
    if not (len(frame) == len(pid) == len(uv) == len(z)):
        raise DepthPriorError(f"SparsePoints observation arrays differ in length: {len(frame)}, {len(pid)}, "
                              f"{len(uv)}, {len(z)}")
    if len(frame) and (frame.min() < 0 or frame.max() >= num_frames or pid.min() < 0 or pid.max() >= len(err)):
        raise DepthPriorError(f"obs_frame must lie in [0, {num_frames}) and obs_point in [0, {len(err)})")
    track = np.bincount(pid, minlength=len(err))  # [M] observations per point
    e = np.where(np.isfinite(err[pid]), err[pid], np.inf)
    conf = np.clip((track[pid] - 1) / (config.full_track_length - 1), 0.0, 1.0) / (1.0 + (e / config.error_ref_px) ** 2)
    r = np.concatenate([uv, z[:, None], conf[:, None]], 1)  # [K, 4]
    keep = _keep(r, width, height, config)
    return [r[keep & (frame == i)].astype(np.float32) for i in range(num_frames)]


# ------------------------------------------------------------------------------------------- densification
def _rows(rows, w: int, h: int, config: DepthConfig) -> np.ndarray:
    """Usable rows [k, 4] float64 of rows [k, 4] (or [k, 3], confidence 1): finite, inside the image, depth > 0,
    confidence > 0, depth <= ``max_depth_ratio`` x their median."""
    r = np.asarray(rows, np.float64)
    if r.size == 0:
        return np.zeros((0, 4))
    if r.ndim != 2 or r.shape[1] not in (3, 4):
        raise DepthPriorError(f"rows must be [k, 4] (u, v, depth, confidence), got {r.shape}")
    r = r if r.shape[1] == 4 else np.concatenate([r, np.ones((len(r), 1))], 1)
    return r[_keep(r, w, h, config)]


def _keep(r: np.ndarray, w: int, h: int, config: DepthConfig) -> np.ndarray:
    with np.errstate(invalid="ignore"):
        u, v, z, c = r.T
        ok = np.isfinite(r).all(1) & (z > 0) & (c > 0) & (u >= -0.5) & (u < w - 0.5) & (v >= -0.5) & (v < h - 0.5)
    if ok.any():
        ok &= z <= config.max_depth_ratio * np.median(z[ok])
    return ok


def _grey(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image)
    if img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] != 3) or min(img.shape[:2]) < 2:
        raise DepthPriorError(f"image must be [H, W, 3] (or [H, W]), got {img.shape}")
    img = _as_float(img)
    return img.mean(2) if img.ndim == 3 else img  # [H, W]


def fit_ground_plane(uv: np.ndarray, inv_depth: np.ndarray, width: int, height: int,
                     config: DepthConfig = DepthConfig(), iterations: int | None = None) -> np.ndarray | None:
    """RANSAC plane of inverse depth w in image space, ``w = a u + b v + c`` -> (a, b, c) or None.

    A level ground at camera height h gives ``w = (v - v_horizon) / (fy h)``, so no intrinsics are needed. Rows in
    the lower half vote. A candidate needs b > 0 (closer downwards), |a| < b (roll < 45 deg), a horizon row at the
    centre column in (-0.5 H, 0.75 H) and an implied camera height ``1 / (b max(W, H))`` <= ``ground_max_height``
    x the median row depth (rejects fronto-parallel clusters such as the traffic ahead). Inliers
    (``|w - w_plane| <= ground_tol w``) score ``((v - H/2) / (H/2))^2`` (the ground is what is seen lowest); the
    winner needs ``ground_min_inliers`` and 10 % of the voters and is refitted to its inliers.
    """
    low = uv[:, 1] > 0.5 * height
    if low.sum() < max(config.ground_min_inliers, 3):
        return None
    design = np.concatenate([uv[low], np.ones((int(low.sum()), 1))], 1)  # [n, 3]
    a_w = inv_depth[low]  # [n]
    min_b = 1.0 / (config.ground_max_height * float(np.median(1.0 / inv_depth)) * max(width, height))

    def valid(p: np.ndarray) -> np.ndarray:  # [N, 3] -> [N] bool
        horizon = -(p[:, 0] * 0.5 * width + p[:, 2]) / np.where(p[:, 1] > 0, p[:, 1], 1.0)
        return (p[:, 1] > min_b) & (np.abs(p[:, 0]) < p[:, 1]) & (horizon > -0.5 * height) & (horizon < 0.75 * height)

    rng = np.random.default_rng(config.seed)
    n_it = config.ground_iterations if iterations is None else iterations
    idx = np.stack([rng.choice(len(a_w), 3, replace=False) for _ in range(n_it)])  # [N, 3]
    a, y = design[idx], a_w[idx]  # [N, 3, 3], [N, 3]
    ok = np.abs(np.linalg.det(a)) > 1e-12
    if not ok.any():
        return None
    planes = np.linalg.solve(a[ok], y[ok][..., None])[..., 0]  # [N', 3]
    planes = planes[valid(planes)]
    if not len(planes):
        return None
    inliers = np.abs(planes @ design.T - a_w) <= config.ground_tol * a_w  # [N', n]
    lowness = ((design[:, 1] - 0.5 * height) / (0.5 * height)) ** 2  # [n] the ground is what is seen lowest
    k = int(np.argmax(inliers @ lowness))
    best = planes[k]
    if inliers[k].sum() < max(config.ground_min_inliers, 0.1 * len(a_w)):
        return None
    inl = np.abs(design @ best - a_w) <= config.ground_tol * a_w
    p = np.linalg.lstsq(design[inl], a_w[inl], rcond=None)[0]
    return p if valid(p[None])[0] else best


def clip_ground_plane(rows: list[np.ndarray], width: int, height: int, config: DepthConfig = DepthConfig()
                      ) -> np.ndarray | None:
    """One ground plane (a, b, c) for a clip: RANSAC on all frames' rows pooled. The image-space plane depends only
    on the camera's height, pitch and roll over the road, so the road wins over planes that fit one frame."""
    pooled = [r for r in (_rows(x, width, height, config) for x in rows) if len(r)]
    if not pooled:
        return None
    r = np.concatenate(pooled)
    return fit_ground_plane(r[:, :2], 1.0 / r[:, 2], width, height, config, iterations=8 * config.ground_iterations)


def _refine_plane(uv: np.ndarray, inv_depth: np.ndarray, plane: np.ndarray, config: DepthConfig) -> np.ndarray:
    """Least-squares refit of a clip plane to one frame's inliers (kept when enough and similar), else the plane."""
    design = np.concatenate([uv, np.ones((len(uv), 1))], 1)
    inl = np.abs(design @ plane - inv_depth) <= config.ground_tol * inv_depth
    if inl.sum() < config.ground_min_inliers:
        return plane
    p = np.linalg.lstsq(design[inl], inv_depth[inl], rcond=None)[0]
    return p if 0.5 * plane[1] < p[1] < 2.0 * plane[1] and abs(p[0]) < p[1] else plane


def _clean_rows(r: np.ndarray, w: int, h: int, config: DepthConfig, ground_plane: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray | None]:
    """Rows [k, 4] -> (cleaned rows [k', 4], ground plane or None): rows behind the ground plane are snapped onto
    it and stood up, then rows disagreeing with their image neighbours are dropped."""
    from scipy.spatial import cKDTree

    r = r.copy()
    plane = None
    if config.ground and ground_plane is not None:
        plane = _refine_plane(r[:, :2], 1.0 / r[:, 2], np.asarray(ground_plane, np.float64), config)
    elif config.ground:
        plane = fit_ground_plane(r[:, :2], 1.0 / r[:, 2], w, h, config)
    if plane is not None:
        wg = r[:, :2] @ plane[:2] + plane[2]  # ground inverse depth at each row's pixel
        behind = (wg > 0) & (1.0 / r[:, 2] < wg / config.ground_margin)
        r[behind, 2] = 1.0 / wg[behind]
        r = np.concatenate([r, _upright_rows(r, behind, wg, plane, w, config)])
    k = min(config.outlier_neighbours, len(r) - 1)
    if k >= 2:
        _, nn = cKDTree(r[:, :2]).query(r[:, :2], k + 1)  # [n, k+1], first column = self
        logz = np.log(r[:, 2])
        med = np.median(logz[nn[:, 1:]], axis=1)
        r = r[np.abs(logz - med) <= math.log(config.outlier_ratio)]
    return r, plane


def _upright_rows(r: np.ndarray, behind: np.ndarray, wg: np.ndarray, plane: np.ndarray, w: int,
                  config: DepthConfig) -> np.ndarray:
    """Virtual rows [m, 4] standing the snapped rows up: an agent seen behind the ground stands on it, so its depth
    holds up to about the horizon (cars are about as tall as a dashcam is high). Each snapped row gets a copy at
    the horizon row of its column, or just below the nearest ground row above it within ``upright_band`` x W
    columns (so the ego bonnet, with road right above it, does not stand up)."""
    if not config.upright or not behind.any():
        return np.zeros((0, 4))
    on_ground = ~behind & (wg > 0) & (np.abs(1.0 / r[:, 2] - wg) <= config.ground_tol / r[:, 2])
    gu, gv = r[on_ground, 0], r[on_ground, 1]
    out = []
    for u, v, z, c in r[behind]:
        top = -(plane[0] * u + plane[2]) / plane[1] + 1.0  # horizon row of this column (+1 px)
        near = (np.abs(gu - u) <= config.upright_band * w) & (gv < v) & (gv > top)
        if near.any():
            top = gv[near].max() + 1.0
        if v - top > 1.0:
            out.append((u, top, z, c))
    return np.array(out, np.float64).reshape(-1, 4)


def _guided_filter(guide: np.ndarray, src: np.ndarray, radius: int, eps: float) -> np.ndarray:
    """Grey-guide guided filter (He et al. 2010) with box means; guide, src [H, W] float32."""
    import cv2

    def box(x):
        return cv2.boxFilter(x, -1, (2 * radius + 1, 2 * radius + 1), borderType=cv2.BORDER_REFLECT)

    mean_i, mean_p = box(guide), box(src)
    a = (box(guide * src) - mean_i * mean_p) / (box(guide * guide) - mean_i * mean_i + eps)
    b = mean_p - a * mean_i
    return box(a) * guide + box(b)


def densify_depth(rows: np.ndarray, image: np.ndarray, config: DepthConfig = DepthConfig(),
                  ground_plane: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Dense depth from sparse rows [k, 4] (u, v, depth, conf) and the image [H, W, 3] (module docstring).

    ``ground_plane``: (a, b, c) of ``clip_ground_plane``, refined on this frame; None: fitted on this frame alone.
    Returns (depth [H, W] float32, 0 = none; confidence [H, W] float32 in [0, 1]). Fewer than ``min_points``
    usable rows give zeros.
    """
    import cv2

    grey = _grey(image)  # [H, W]
    h, w = grey.shape
    depth, conf = np.zeros((h, w), np.float32), np.zeros((h, w), np.float32)
    r = _rows(rows, w, h, config)
    if len(r) < config.min_points:
        return depth, conf
    r, plane = _clean_rows(r, w, h, config, ground_plane)
    if len(r) < config.min_points:
        return depth, conf
    uv, inv, pc = r[:, :2], 1.0 / r[:, 2], np.clip(r[:, 3], 0.0, 1.0)
    diag = math.hypot(w, h)
    jj, ii = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    pix = np.stack([jj.ravel(), ii.ravel()], 1)  # [H*W, 2] image points (u, v)
    inv_d, conf_d, covered = _interpolate(uv, inv, pc, pix, config.max_edge * diag, config.conf_spread)
    # distance to, and index of, the nearest row (OpenCV distance transform with pixel labels)
    seeds = np.ones((h, w), np.uint8)
    ui, vi = np.clip(np.round(uv[:, 0]).astype(int), 0, w - 1), np.clip(np.round(uv[:, 1]).astype(int), 0, h - 1)
    seeds[vi, ui] = 0
    dist, labels = cv2.distanceTransformWithLabels(seeds, cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL)
    label_to_row = np.zeros(labels.max() + 1, np.int64)
    label_to_row[labels[vi, ui]] = np.arange(len(uv))
    nearest, dist = label_to_row[labels.ravel()], dist.ravel().astype(np.float64)  # [H*W]
    fill = ~covered & (dist <= config.fill_radius * diag)
    inv_d[fill] = inv[nearest[fill]]
    conf_d[fill] = pc[nearest[fill]] * config.fill_confidence
    conf_d *= np.exp(-0.5 * (dist / (config.conf_distance * diag)) ** 2)
    support = covered | fill
    if plane is not None:  # nothing static is seen behind the ground: clamp; and complete the bare ground
        wg = pix @ plane[:2] + plane[2]  # [H*W]
        below = wg > 0
        behind = support & below & (inv_d < wg)  # [H*W]
        inv_d[behind] = wg[behind]
        conf_d[behind] = np.maximum(conf_d[behind], config.ground_clamp_confidence)
        bare = ~support & below & (wg >= inv.min())
        inv_d[bare], conf_d[bare] = wg[bare], config.ground_fill_confidence
        support |= bare
    support = support.reshape(h, w)
    inv_map, conf_map = inv_d.reshape(h, w).astype(np.float32), conf_d.reshape(h, w).astype(np.float32)
    rad = int(round(config.guided_radius * w))
    if rad >= 1 and support.any():
        wt = np.where(support, np.maximum(conf_map, 1e-3), 0.0).astype(np.float32)
        num = _guided_filter(grey, wt * inv_map, rad, config.guided_eps)
        den = _guided_filter(grey, wt, rad, config.guided_eps)
        ok = support & (den > 0.25 * np.maximum(wt, 1e-3))
        inv_map = np.where(ok, num / np.where(ok, den, 1.0), inv_map)
        inv_map = np.clip(inv_map, inv.min(), max(inv.max(), float(inv_d.max())))
    depth = np.where(support & (inv_map > 0), 1.0 / np.maximum(inv_map, 1e-12), 0.0).astype(np.float32)
    conf = np.where(depth > 0, np.clip(conf_map, 0.0, 1.0), 0.0).astype(np.float32)
    return depth, conf


def _interpolate(uv: np.ndarray, inv: np.ndarray, pc: np.ndarray, pix: np.ndarray, max_edge: float,
                 conf_spread: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Linear interpolation over a Delaunay triangulation of uv [k, 2] at pix [P, 2], skipping triangles with an
    edge longer than max_edge px -> (inverse depth [P], confidence [P], covered [P] bool)."""
    from scipy.spatial import Delaunay, QhullError

    inv_d, conf_d, covered = np.zeros(len(pix)), np.zeros(len(pix)), np.zeros(len(pix), bool)
    try:
        tri = Delaunay(uv)
    except (QhullError, ValueError):  # all rows on a line, or duplicates only
        return inv_d, conf_d, covered
    s = tri.find_simplex(pix)  # [P], -1 outside the hull
    verts = tri.simplices  # [S, 3]
    edges = np.linalg.norm(uv[verts] - uv[np.roll(verts, 1, 1)], axis=2).max(1)  # [S]
    zv = 1.0 / inv[verts]
    spread = np.log(zv.max(1) / zv.min(1))  # [S]
    good = np.flatnonzero(s >= 0)
    good = good[edges[s[good]] <= max_edge]
    sg, tr = s[good], tri.transform[s[good]]  # [n], [n, 3, 2]
    b = np.einsum("nij,nj->ni", tr[:, :2], pix[good] - tr[:, 2])
    bary = np.concatenate([b, 1 - b.sum(1, keepdims=True)], 1).clip(0, 1)  # [n, 3]
    bary /= bary.sum(1, keepdims=True)
    inv_d[good] = (bary * inv[verts[sg]]).sum(1)
    conf_d[good] = (bary * pc[verts[sg]]).sum(1) * np.exp(-spread[sg] / conf_spread)
    covered[good] = True
    return inv_d, conf_d, covered


def _as_float(img: np.ndarray) -> np.ndarray:
    img = np.asarray(img)
    return np.ascontiguousarray(img, np.float32) / (255.0 if img.dtype == np.uint8 else 1.0)


def densify_clip(rows: list[np.ndarray], frames, config: DepthConfig = DepthConfig(),
                 progress: Callable[[int], None] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``densify_depth`` for every frame with one ``clip_ground_plane``: frames [T, H, W, 3] (uint8 or float in
    [0, 1]) -> (depth [T, H, W] float32, confidence [T, H, W] float32). ``progress(i)`` is called after each
    frame."""
    t = len(frames)
    if len(rows) != t:
        raise DepthPriorError(f"got {len(rows)} row sets for {t} frames")
    if t == 0:
        raise DepthPriorError("no frames")
    h, w = np.asarray(frames[0]).shape[:2]
    plane = clip_ground_plane(rows, w, h, config) if config.ground else None
    depth, conf = np.zeros((t, h, w), np.float32), np.zeros((t, h, w), np.float32)
    for i in range(t):
        depth[i], conf[i] = densify_depth(rows[i], _as_float(frames[i]), config, plane)
        if progress is not None:
            progress(i)
    return depth, conf


# ------------------------------------------------------------------------------------------------ mono depth
def align_scale_shift(pred: np.ndarray, target: np.ndarray, weight: np.ndarray, tol: float, seed: int = 0
                      ) -> tuple[float, float, np.ndarray]:
    """Robust ``target ~ s pred + t`` over [n] values: RANSAC on pairs (inlier: relative residual <= tol), then
    weighted least squares iterated on the inliers -> (s, t, inliers [n] bool)."""
    n = len(pred)
    rng = np.random.default_rng(seed)
    i, j = rng.integers(0, n, (2, 200))
    i, j = i[pred[i] != pred[j]], j[pred[i] != pred[j]]
    if not len(i):
        return 0.0, 0.0, np.zeros(n, bool)
    s = (target[i] - target[j]) / (pred[i] - pred[j])  # [N] candidate scales and shifts
    t = target[i] - s * pred[i]
    inl = np.abs(s[:, None] * pred + t[:, None] - target) <= tol * np.abs(target)  # [N, n]
    inl = inl[int(np.argmax(inl.sum(1)))]
    a = np.stack([pred, np.ones_like(pred)], 1)  # [n, 2]
    s1 = t1 = 0.0
    for _ in range(10):
        if inl.sum() < 2:
            break
        sw = np.sqrt(weight[inl])
        s1, t1 = np.linalg.lstsq(a[inl] * sw[:, None], target[inl] * sw, rcond=None)[0]
        new = np.abs(s1 * pred + t1 - target) <= tol * np.abs(target)
        if np.array_equal(new, inl):
            break
        inl = new
    return float(s1), float(t1), inl


class MonoDepthModel:
    """Dense depth from a LOCAL TorchScript monocular model, aligned to the sparse rows (docs/PRIORS.md "Depth").

    The file maps [1, 3, H, W] float RGB in [0, 1] to [1, H', W'] (or [1, 1, H', W']) relative inverse depth
    (MiDaS / Depth-Anything style, larger = closer), resized to the image. Per frame ``align_scale_shift`` fits a
    scale + shift in inverse depth to the sparse rows; frames with fewer than ``mono_min_points`` rows (or half as
    many inliers, or a scale <= 0) get no mono depth. Confidence = ``mono_confidence`` x inlier fraction.
    """

    def __init__(self, path: str | Path, device: str = "cpu", config: DepthConfig = DepthConfig()):
        import torch

        self.path, self.device, self.config = Path(path), device, config
        if not self.path.is_file():
            raise DepthPriorError(f"mono depth model file not found: {self.path}")
        try:
            with warnings.catch_warnings():  # torch 2.x deprecates TorchScript; loading still works
                warnings.simplefilter("ignore", DeprecationWarning)
                self.model = torch.jit.load(str(self.path), map_location="cpu").to(device).eval()
        except (RuntimeError, ValueError) as e:
            raise DepthPriorError(f"{self.path} is not a TorchScript file: {e}") from None

    def relative_inverse_depth(self, image: np.ndarray) -> np.ndarray:
        """Model output resized to the image [H, W] float32; image [H, W, 3] uint8 or float in [0, 1]."""
        import torch
        import torch.nn.functional as F  # noqa: N812

        img = np.asarray(image)
        if img.ndim != 3 or img.shape[2] != 3:
            raise DepthPriorError(f"image must be [H, W, 3], got {img.shape}")
        x = torch.from_numpy(_as_float(img)).permute(2, 0, 1)[None].to(self.device)  # [1, 3, H, W]
        with torch.no_grad():
            y = self.model(x)
        y = y[0] if isinstance(y, (tuple, list)) else y
        y = y[:, None] if y.ndim == 3 else y
        if y.ndim != 4 or y.shape[:2] != (1, 1):
            raise DepthPriorError(f"model output must be [1, H, W] or [1, 1, H, W], got {tuple(y.shape)}")
        if tuple(y.shape[-2:]) != img.shape[:2]:
            y = F.interpolate(y.float(), size=img.shape[:2], mode="bilinear", align_corners=False)
        return y[0, 0].float().cpu().numpy()

    def predict(self, image: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(depth [H, W] float32, 0 = none; confidence [H, W] float32), like ``densify_depth``."""
        cfg = self.config
        rel = self.relative_inverse_depth(image).astype(np.float64)  # [H, W]
        h, w = rel.shape
        depth, conf = np.zeros((h, w), np.float32), np.zeros((h, w), np.float32)
        r = _rows(rows, w, h, cfg)
        if len(r) < cfg.mono_min_points:
            return depth, conf
        ui, vi = np.clip(np.round(r[:, 0]).astype(int), 0, w - 1), np.clip(np.round(r[:, 1]).astype(int), 0, h - 1)
        s, t, inl = align_scale_shift(rel[vi, ui], 1.0 / r[:, 2], np.clip(r[:, 3], 1e-3, 1), cfg.mono_inlier_tol)
        if not s > 0 or inl.sum() < cfg.mono_min_points // 2:
            return depth, conf
        inv = s * rel + t
        ok = inv > 1.0 / (cfg.max_depth_ratio * float(np.median(r[:, 2])))  # farther: no depth (sky)
        depth[ok] = 1.0 / inv[ok]
        conf[ok] = cfg.mono_confidence * float(inl.mean())
        return depth, conf
