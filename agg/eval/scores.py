"""Segmentation and tracking scores: mask IoU, tracklet recall and precision.

Tracklets are arrays of per-frame centres ``[T, D]`` (D = 2 for pixels, 3 for world metres) with NaN rows where
the track is absent; a set of tracks is ``[N, T, D]`` (or a list of ``[T, D]``).

Matching rule (documented in docs/PRIORS.md): a frame is a *hit* for a (predicted, ground-truth) pair when both
are present and their centres are within ``max_dist`` (same units as the centres). The pair's temporal overlap
is ``hits / |frames where either is present|`` (a temporal IoU of the hit frames). Pairs with overlap
``>= min_overlap`` are candidates, and a one-to-one assignment maximising the total overlap is made with the
Hungarian algorithm. Recall = matched ground-truth tracks / ground-truth tracks; precision = matched predicted
tracks / predicted tracks. With no ground-truth (or no predicted) tracks recall (precision) is 1.0 by convention.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


class ScoreError(ValueError):
    """Bad input to a score (shapes, dtypes)."""


def mask_iou(pred: np.ndarray, gt: np.ndarray, empty_value: float = 1.0) -> np.ndarray:
    """Per-frame IoU of boolean masks ``[T, H, W]`` (or one ``[H, W]``) -> ``[T]``.

    A frame where both masks are empty scores ``empty_value`` (1.0: both agree there is nothing).
    """
    p, g = np.asarray(pred), np.asarray(gt)
    if p.shape != g.shape or p.ndim not in (2, 3):
        raise ScoreError(f"masks must share a [T, H, W] or [H, W] shape, got {p.shape} and {g.shape}")
    p, g = p.astype(bool), g.astype(bool)
    if p.ndim == 2:
        p, g = p[None], g[None]
    inter = (p & g).sum(axis=(1, 2))
    union = (p | g).sum(axis=(1, 2))
    return np.where(union > 0, inter / np.maximum(union, 1), empty_value).astype(float)


def mean_mask_iou(pred: np.ndarray, gt: np.ndarray, empty_value: float = 1.0) -> float:
    """Mean over frames of ``mask_iou``."""
    return float(mask_iou(pred, gt, empty_value).mean())


@dataclass(frozen=True)
class TrackletScores:
    recall: float
    precision: float
    matches: list[tuple[int, int]]  # (predicted index, ground-truth index)
    overlap: np.ndarray  # [P, G] temporal overlap of hit frames

    def as_dict(self) -> dict:
        return {"tracklet_recall": self.recall, "tracklet_precision": self.precision,
                "num_matches": len(self.matches)}


def _stack(tracks, name: str) -> np.ndarray:
    if isinstance(tracks, np.ndarray):
        arr = np.asarray(tracks, float)
    else:
        tracks = list(tracks)
        arr = np.stack([np.asarray(t, float) for t in tracks]) if tracks else np.zeros((0, 0, 0))
    if arr.ndim != 3:
        raise ScoreError(f"{name} tracks must be [N, T, D] (NaN where absent), got shape {arr.shape}")
    return arr


def tracklet_overlap(pred: np.ndarray, gt: np.ndarray, max_dist: float) -> np.ndarray:
    """Temporal overlap of hit frames for every (predicted, ground-truth) pair -> ``[P, G]``."""
    p, g = _stack(pred, "predicted"), _stack(gt, "ground-truth")
    if len(p) == 0 or len(g) == 0:
        return np.zeros((len(p), len(g)))
    if p.shape[1:] != g.shape[1:]:
        raise ScoreError(f"predicted and ground-truth tracks must share [T, D], got {p.shape[1:]} and {g.shape[1:]}")
    pp = ~np.isnan(p).any(-1)  # [P, T] present
    gp = ~np.isnan(g).any(-1)  # [G, T]
    d = np.linalg.norm(p[:, None] - g[None], axis=-1)  # [P, G, T], NaN where either is absent
    hits = (np.nan_to_num(d, nan=np.inf) <= max_dist).sum(-1)
    either = (pp[:, None] | gp[None]).sum(-1)
    return hits / np.maximum(either, 1)


def tracklet_scores(pred, gt, max_dist: float, min_overlap: float = 0.5) -> TrackletScores:
    """Tracklet recall and precision under the module's matching rule."""
    from scipy.optimize import linear_sum_assignment

    if max_dist <= 0 or not 0 < min_overlap <= 1:
        raise ScoreError("max_dist must be > 0 and min_overlap in (0, 1]")
    ov = tracklet_overlap(pred, gt, max_dist)
    n_p, n_g = ov.shape
    matches: list[tuple[int, int]] = []
    if n_p and n_g:
        cand = np.where(ov >= min_overlap, ov, 0.0)
        rows, cols = linear_sum_assignment(-cand)
        matches = [(int(r), int(c)) for r, c in zip(rows, cols) if cand[r, c] > 0]
    return TrackletScores(
        recall=len(matches) / n_g if n_g else 1.0,
        precision=len(matches) / n_p if n_p else 1.0,
        matches=matches,
        overlap=ov,
    )
