"""A track's path in the image: its stray detections are dropped (used by ``agg/priors/tracklets.py``).

The Kalman association works in 3D, where the gate is as wide as the depth is uncertain (a mask blob on the road
beside a car has the road's depth, close to the car's). In the image an agent moves smoothly, so its pixel
centroid, box size and area give a second, sharper test: a detection far off the line through its neighbours'
centroids, or much smaller than they are, is a blob taken where the agent's own mask was missing or small, and
it is dropped. Rules and thresholds (``TrackConfig`` fields ``stray_*``) are in docs/PRIORS.md ("Agent
tracklets").
"""

from __future__ import annotations

import numpy as np
from scipy.stats import theilslopes

from agg.priors.kalman import TrackHistory, smooth_sequence
from agg.priors.tracklet_boxes import uncut
from agg.priors.tracklet_detections import Candidate


def _line_at(frames: np.ndarray, values: np.ndarray, i: int) -> float:
    """The Theil-Sen line of values [n] over frames [n] (n >= 2), evaluated at frame i."""
    slope, intercept = theilslopes(values, frames)[:2]
    return float(intercept + slope * i)


def stray_detections(frames: np.ndarray, centres: np.ndarray, sizes: np.ndarray, areas: np.ndarray, cfg,
                     inner: np.ndarray | None = None) -> np.ndarray:
    """[n] bool: the detections of one track that sit off its path in the image. frames [n] sorted frame indices,
    centres [n, 2] pixel centroids (u, v), sizes [n, 2] box (width, height), areas [n] pixels; inner [n] bool: not
    cut by the image border (None: all). Each inner detection is compared with the track's other inner ones within
    ``stray_window`` frames: it is a stray when its centroid lies more than ``stray_offset`` x their median width
    (u) or height (v) off their Theil-Sen line through time (with at least 2 of them), or its area is below
    ``stray_area_ratio`` x their median area (also with only one). A detection cut by the border shrinks and shifts
    as the agent leaves the image: it is neither judged nor a reference."""
    out = np.zeros(len(frames), bool)
    if cfg.stray_window <= 0:
        return out
    inner = np.ones(len(frames), bool) if inner is None else np.asarray(inner, bool)
    for j, i in enumerate(frames):
        near = np.nonzero((np.abs(frames - i) <= cfg.stray_window) & (frames != i) & inner)[0]
        if not inner[j] or len(near) == 0:
            continue
        if len(near) == 1:  # no line through one centroid, and each of two is as far off the other: area only
            out[j] = bool(areas[j] < cfg.stray_area_ratio * areas[near[0]])
            continue
        scale = np.median(sizes[near], 0)  # [2]
        off = [abs(centres[j, a] - _line_at(frames[near], centres[near, a], i)) for a in range(2)]
        out[j] = bool(off[0] > cfg.stray_offset * scale[0] or off[1] > cfg.stray_offset * scale[1]
                      or areas[j] < cfg.stray_area_ratio * np.median(areas[near]))
    return out


def _track_arrays(hist: TrackHistory, lifted: list[list[Candidate]], shape: tuple[int, int]):
    """Frames [n], centroids [n, 2], box sizes [n, 2], areas [n] and inner [n] of a track's detections."""
    steps = np.nonzero(hist.assoc >= 0)[0]
    cands = [lifted[i][hist.assoc[i]] for i in steps]
    bbox = np.array([c.bbox for c in cands], float).reshape(-1, 4)  # [n, 4]
    centres = np.array([c.centre_px for c in cands], float).reshape(-1, 2)
    areas = np.array([c.area for c in cands], float)
    return steps, centres, bbox[:, 2:] - bbox[:, :2], areas, uncut(bbox, shape)


def _smoothed(assoc: np.ndarray, lifted: list[list[Candidate]], accel_var: float,
              init_vel_var: float) -> TrackHistory:
    """A track history with these associations, its states RTS-smoothed from their visible-surface centres."""
    z = np.full((len(assoc), 3), np.nan)
    r = np.repeat(np.eye(3)[None], len(assoc), 0)
    for i in np.nonzero(assoc >= 0)[0]:
        c = lifted[i][assoc[i]]
        z[i], r[i] = c.centre_world, c.cov_world
    state, cov = smooth_sequence(z, r, accel_var=accel_var, init_vel_var=init_vel_var)
    return TrackHistory(assoc=assoc, state=state, cov=cov, hits=int((assoc >= 0).sum()))


def drop_strays(hist: TrackHistory, lifted: list[list[Candidate]], shape: tuple[int, int], cfg, accel_var: float,
                init_vel_var: float) -> TrackHistory:
    """The track without its stray detections (``stray_detections``), smoothed again without them."""
    steps, centres, sizes, areas, inner = _track_arrays(hist, lifted, shape)
    stray = stray_detections(steps, centres, sizes, areas, cfg, inner)
    if not stray.any():
        return hist
    assoc = hist.assoc.copy()
    assoc[steps[stray]] = -1
    return _smoothed(assoc, lifted, accel_var, init_vel_var)


__all__ = ["stray_detections", "drop_strays"]
