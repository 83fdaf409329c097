"""Class, yaw and amodal boxes of the agent tracklets (used by ``agg/priors/tracklets.py``).

Rules and thresholds (``TrackConfig`` fields, passed as ``cfg``) are in docs/PRIORS.md ("Agent tracklets"):
rigid / non-rigid from the image aspect of a track's detections, yaw from the RTS-smoothed world velocity, and
amodal boxes completed behind the visible faces with a class-dependent size prior.
"""

from __future__ import annotations

import numpy as np

from agg.priors.tracklet_detections import Candidate


def _aspect(c: Candidate, K: np.ndarray) -> float:
    """3D height / width of a detection from its pixel box: (bh / fy) / (bw / fx)."""
    x0, y0, x1, y1 = c.bbox
    return float(((y1 - y0) / K[1, 1]) / max((x1 - x0) / K[0, 0], 1e-9))


def uncut(bbox: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """[n] bool: pixel boxes [n, 4] (x0, y0, x1, y1, inclusive-exclusive) that do not touch the border of an image
    of shape (H, W)."""
    h, w = shape
    return (bbox[:, 0] > 0) & (bbox[:, 1] > 0) & (bbox[:, 2] < w) & (bbox[:, 3] < h)


def _inner(cands: dict, shape: tuple[int, int]) -> list[int]:
    """Frames whose detection does not touch the image border (all frames when every one does)."""
    frames = list(cands)
    ok = uncut(np.array([cands[i].bbox for i in frames], float).reshape(-1, 4), shape)
    return [i for i, o in zip(frames, ok) if o] or frames


def classify(cands: dict, K: np.ndarray, shape: tuple[int, int], cfg) -> str:
    """Non-rigid when the median aspect of the detections not cut by the image border is tall (a person)."""
    ratios = [_aspect(cands[i], K) for i in _inner(cands, shape)]
    return "non-rigid" if float(np.median(ratios)) > cfg.nonrigid_min_aspect else "rigid"


def _heading_yaw(v: np.ndarray) -> float:
    """Yaw of a box whose x axis points along the horizontal (world x, z) direction of v: atan2(-vz, vx)."""
    return float(np.arctan2(-v[2], v[0]))


def track_yaws(state: np.ndarray, cov: np.ndarray, valid: np.ndarray, world_from_camera: np.ndarray,
               cfg) -> np.ndarray:
    """[T] yaw per valid frame: smoothed velocity where significant, else the nearest significant frame's, else
    the camera's heading (road-aligned assumption for an agent that never visibly moves). NaN where invalid."""
    n = len(valid)
    yaw = np.full(n, np.nan)
    for i in np.nonzero(valid)[0]:
        v = state[i, 3:]
        speed = float(np.hypot(v[0], v[2]))
        if speed <= 0 or not np.isfinite(speed):
            continue
        u = np.array([v[0], 0.0, v[2]]) / speed
        sigma = float(np.sqrt(max(u @ cov[i, 3:, 3:] @ u, 0.0)))
        if speed > cfg.yaw_min_speed_sigmas * sigma:
            yaw[i] = _heading_yaw(v)
    have = np.nonzero(np.isfinite(yaw))[0]
    for i in np.nonzero(valid & ~np.isfinite(yaw))[0]:
        if len(have):
            yaw[i] = yaw[have[np.argmin(np.abs(have - i))]]
        else:
            yaw[i] = _heading_yaw(world_from_camera[i, :3, 2])
    return yaw


def _box_extents(points: np.ndarray, yaw: float, camera: np.ndarray, cfg) -> np.ndarray:
    """[3, 3] rows (mid, extent, camera coordinate) of visible world points [n, 3] along the box axes x, y, z.

    Robust extents: the ``extent_percentiles`` range scaled to the full range of a uniform spread."""
    axes = np.array([[np.cos(yaw), 0.0, -np.sin(yaw)], [0.0, 1.0, 0.0], [np.sin(yaw), 0.0, np.cos(yaw)]])  # [3, 3]
    lo_p, hi_p = cfg.extent_percentiles
    s = points @ axes.T  # [n, 3]
    a, b = np.percentile(s, [lo_p, hi_p], axis=0)  # [3], [3]
    return np.stack([0.5 * (a + b), (b - a) / ((hi_p - lo_p) / 100.0), axes @ camera], 1)


def _rigid_size(ext: np.ndarray, cfg) -> np.ndarray:
    """(l, w, h) of one frame from visible extents [3] (x, y, z): l >= r w and w >= l / r (the class prior)."""
    r = cfg.rigid_length_width_ratio
    return np.array([max(ext[0], r * ext[2]), max(ext[2], ext[0] / r), ext[1]])


def _place(mid: float, ext: float, size: float, cam: float) -> float:
    """Centre along one axis of a box of ``size`` whose visible part spans ``ext`` around ``mid``: it grows away
    from the camera (the visible points are its near face) unless the camera lies within the visible range."""
    lo, hi = mid - 0.5 * ext, mid + 0.5 * ext
    if cam < lo:
        return lo + 0.5 * size
    if cam > hi:
        return hi - 0.5 * size
    return mid


def track_boxes(cands: dict, yaw: np.ndarray, world_from_camera: np.ndarray, rigid: bool, shape: tuple[int, int],
                 cfg) -> dict:
    """Amodal boxes (cx, cy, cz, l, w, h, yaw) of one track, frame -> [7].

    Sizes come from the detections not cut by the image border (all when every one is).
    Rigid: one size for the track, the median of the per-frame sizes (visible extents along the box axes,
    completed by the l / w ratio prior), and per frame the box placed behind its visible faces (``_place``).
    Non-rigid: a square footprint, l = w = the track's median visible lateral extent (measured across the
    viewing ray from pixel widths, reliable even with noisy depth), h per frame; the centre is the visible-surface
    centre pushed w / 2 away from the camera along the horizontal viewing direction."""
    ext = {i: _box_extents(c.points_world, yaw[i], world_from_camera[i, :3, 3], cfg) for i, c in cands.items()}
    inner = _inner(cands, shape)  # sizes from detections not cut by the image border
    out = {}
    if rigid:
        size = np.median([_rigid_size(ext[i][:, 1], cfg) for i in inner], axis=0)  # [3] l, w, h
        for i, e in ext.items():
            ax = np.array([[np.cos(yaw[i]), 0.0, -np.sin(yaw[i])], [0.0, 1.0, 0.0],
                           [np.sin(yaw[i]), 0.0, np.cos(yaw[i])]])
            centre = (_place(e[0, 0], e[0, 1], size[0], e[0, 2]) * ax[0] + e[1, 0] * ax[1]
                      + _place(e[2, 0], e[2, 1], size[1], e[2, 2]) * ax[2])
            out[i] = np.array([*centre, *size, yaw[i]])
        return out
    foot = float(np.median([cands[i].size[1] for i in inner]))
    for i, c in cands.items():
        view = c.centre_world - world_from_camera[i, :3, 3]
        view = np.array([view[0], 0.0, view[2]]) / max(np.hypot(view[0], view[2]), 1e-12)
        centre = c.centre_world + 0.5 * foot * view
        centre[1] = ext[i][1, 0]
        out[i] = np.array([*centre, foot, foot, ext[i][1, 1], yaw[i]])
    return out

__all__ = ["classify", "track_yaws", "track_boxes", "uncut"]
