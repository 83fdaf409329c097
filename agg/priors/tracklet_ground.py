"""Ground rules of the agent tracklets: the road plane of the depth prior, and where a mask component meets it.

Used by ``agg/priors/tracklet_detections.py``; rules and thresholds (``TrackConfig`` fields) are in docs/PRIORS.md
("Agent tracklets"). An agent stands on the road: the lowest pixel of each image column of a component (its
*contact*) either sits on the road (the depth just below it agrees with the road plane there), or is hidden behind
something nearer (the depth below is clearly nearer than the component's own). A component whose contact is above
the horizon, or rests on an upright surface that is not the road (a hillside, a wall, a tree line behind a
barrier), is not an agent. The road plane is the depth prior's RANSAC plane of inverse depth in image space
(``agg.priors.depth.fit_ground_plane``: ``w = a u + b v + c``, exact for a flat road seen by a pinhole camera).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from agg.priors.depth import clip_ground_plane, fit_ground_plane

FLOATING, UNKNOWN, OCCLUDED, GROUNDED = -1, 0, 1, 2  # column verdicts of ``contact_verdicts``


def ground_planes(depth: np.ndarray, conf: np.ndarray | None, masks: np.ndarray, min_conf: float,
                  max_samples: int = 4000) -> list[np.ndarray | None]:
    """[T] road planes (a, b, c) of inverse depth ``w = a u + b v + c`` (or None: no road found).

    depth [T, H, W] z (0 / non-finite = none); conf [T, H, W] or None; masks [T, H, W] bool (dynamic pixels do
    not vote). Each frame's plane is fitted to its own valid pixels (a pitching camera moves the plane); frames
    without one take the plane fitted to every frame's pixels pooled. Deterministic (strided samples, seeded RANSAC).
    """
    t, h, w = depth.shape
    rows = [road_rows(depth[i], None if conf is None else conf[i], masks[i], min_conf, max_samples)
            for i in range(t)]
    planes: list[np.ndarray | None] = []
    for r in rows:
        planes.append(fit_ground_plane(r[:, :2], 1.0 / r[:, 2], w, h) if len(r) >= 3 else None)
    if any(p is None for p in planes):
        pooled = clip_ground_plane([r[::max(1, t // 4)] for r in rows], w, h) if any(len(r) for r in rows) else None
        planes = [pooled if p is None else p for p in planes]
    return planes


def road_rows(depth: np.ndarray, conf: np.ndarray | None, mask: np.ndarray | None, min_conf: float,
              max_samples: int = 4000) -> np.ndarray:
    """[k, 4] float64 rows (u, v, z, 1) of one frame's depth [H, W] that may vote for its road plane: finite, > 0,
    not dynamic (mask [H, W] bool, or None), confidence >= min_conf (conf [H, W] or None); strided to at most about
    ``max_samples`` (deterministic)."""
    d = np.asarray(depth, np.float64)
    ok = np.isfinite(d) & (d > 0)
    if mask is not None:
        ok &= ~np.asarray(mask, bool)
    if conf is not None:
        ok &= np.asarray(conf, np.float64) >= min_conf
    rr, cc = np.nonzero(ok)
    step = max(1, int(np.ceil(len(rr) / max_samples)))
    rr, cc = rr[::step], cc[::step]
    return np.stack([cc, rr, d[rr, cc], np.ones(len(rr))], 1).astype(np.float64)


def road_inverse_depth(plane: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Inverse depth of the road plane at pixels (u, v); <= 0 at and above the horizon."""
    return plane[0] * u + plane[1] * v + plane[2]


def camera_height(plane: np.ndarray, fy: float) -> float:
    """Camera height over the road in scene units (level camera: ``w = (v - v_horizon) / (fy h)``)."""
    return float(1.0 / (plane[1] * fy))


def height_above_road(plane: np.ndarray, K: np.ndarray, points: np.ndarray) -> np.ndarray:  # noqa: N803
    """[N] signed heights over the road of camera-frame points [N, 3] (scene units; > 0 on the camera's side).

    The image-space plane ``w = a u + b v + c`` of a pinhole camera K is the camera-frame plane ``n . X = 1`` with
    ``n = (a fx, b fy, a cx + b cy + c)``; the camera itself is ``1 / |n|`` above it."""
    a, b, c = np.asarray(plane, np.float64)
    n = np.array([a * K[0, 0], b * K[1, 1], a * K[0, 2] + b * K[1, 2] + c])
    return (1.0 - np.asarray(points, np.float64) @ n) / np.linalg.norm(n)


def column_bottoms(rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Lower envelope of a pixel group: its columns [m] (sorted), their lowest row [m], and each pixel's column
    index [n]."""
    ucol, inv = np.unique(cols, return_inverse=True)
    bottom = np.full(len(ucol), -1, np.int64)
    np.maximum.at(bottom, inv, rows)
    return ucol, bottom, inv


def column_medians(values: np.ndarray, index: np.ndarray, keep: np.ndarray, m: int) -> np.ndarray:
    """[m] median of values[keep] grouped by index (NaN for a group without kept values)."""
    out = np.full(m, np.nan)
    if keep.any():
        groups = np.unique(index[keep])
        out[groups] = ndimage.median(values[keep], labels=index[keep], index=groups)
    return out


def _row_nanmedian(x: np.ndarray) -> np.ndarray:
    """[m] median of the finite values of each row of x [m, k] (NaN for a row without any)."""
    s = np.sort(x, 1)  # NaN sorts last
    n = np.isfinite(x).sum(1)
    r = np.arange(len(x))
    lo, hi = s[r, np.maximum(n - 1, 0) // 2], s[r, np.minimum(n // 2, x.shape[1] - 1)]  # the middle pair
    return np.where(n > 0, 0.5 * (lo + hi), np.nan)


def contact_verdicts(ucol: np.ndarray, bottom: np.ndarray, own_depth: np.ndarray, depth: np.ndarray,
                     ok_map: np.ndarray, plane: np.ndarray, cfg) -> np.ndarray:
    """[m] verdict per column (FLOATING, UNKNOWN, OCCLUDED, GROUNDED) of a component's lower envelope.

    ucol, bottom [m]: its columns and their lowest rows; own_depth [m]: the component's depth near its contact
    (NaN: unknown; such a column takes the component's median); depth, ok_map [H, W]: the depth prior and where
    it counts. The prior is read in the ``contact_rows`` x H (>= 3) rows below the contact (their median):
    GROUNDED when it agrees with the road's depth there within ``contact_ratio``; OCCLUDED when it is nearer than
    the component by ``occlusion_ratio`` (the contact is hidden behind an occluder); FLOATING otherwise (the
    surface below is neither road nor in front). No depth below (image border, holes): UNKNOWN. A contact at or
    above the horizon: FLOATING."""
    h = depth.shape[0]
    k = max(3, int(round(cfg.contact_rows * h)))
    vb = bottom[:, None] + np.arange(1, k + 1)[None]  # [m, k] rows below the contact
    inside = vb < h
    vb_c = np.minimum(vb, h - 1)
    uu = np.broadcast_to(ucol[:, None], vb.shape)
    d = np.where(inside & ok_map[vb_c, uu], depth[vb_c, uu], np.nan).astype(np.float64)  # [m, k]
    with np.errstate(all="ignore"):
        w_road = road_inverse_depth(plane, uu.astype(np.float64), vb_c.astype(np.float64))  # [m, k]
        below = _row_nanmedian(d)  # [m] the prior just below the contact
        w_below = _row_nanmedian(np.where(np.isfinite(d), w_road, np.nan))  # [m] the road's inverse depth there
        grounded = (w_below > 0) & (np.abs(np.log(below * w_below)) <= np.log(cfg.contact_ratio))
        fin = np.isfinite(own_depth)
        own = np.where(fin, own_depth, np.median(own_depth[fin]) if fin.any() else np.nan)  # none: the median
        occluded = below < own / cfg.occlusion_ratio
    out = np.full(len(ucol), UNKNOWN, np.int64)
    has = np.isfinite(below)
    out[has] = FLOATING
    out[has & occluded] = OCCLUDED
    out[has & grounded] = GROUNDED
    above = road_inverse_depth(plane, ucol.astype(np.float64), bottom + 0.5) <= 0  # [m] contact at/above horizon
    out[above] = FLOATING
    return out


__all__ = ["ground_planes", "road_rows", "road_inverse_depth", "camera_height", "height_above_road", "column_bottoms",
           "column_medians", "contact_verdicts", "FLOATING", "UNKNOWN", "OCCLUDED", "GROUNDED"]
