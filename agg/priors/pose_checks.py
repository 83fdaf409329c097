"""Checks and repairs of a camera path, and the two-view geometry they rest on (used by ``agg.priors.poses``).

``epipolar_check`` (check (a)): each consecutive pair's SfM motion against an OpenCV essential matrix on LK tracks,
on rotation and on the direction of travel, per pair and as a clip-level "bend". ``find_pose_outliers`` (check
(b)): smoothness against slerp/lerp of the neighbours. ``interpolate_poses`` fills rejected and unregistered
frames: slerp/lerp inside, constant velocity beyond the ends. Thresholds: ``PoseConfig``; details: docs/PRIORS.md.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from agg.eval.trajectory import rotation_angle_deg as _angle_deg

if TYPE_CHECKING:
    from agg.priors.poses import PoseConfig


class PoseEstimationError(ValueError):
    """Bad input to pose estimation (no frames, inconsistent sizes, unreadable paths)."""


def _config(config: "PoseConfig | None") -> "PoseConfig":
    from agg.priors.poses import PoseConfig

    return config if config is not None else PoseConfig()


# ----------------------------------------------------------------------------------------------- rotations
def _slerp(ra: np.ndarray, rb: np.ndarray, f: float) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    rel = Rotation.from_matrix(ra.T @ rb).as_rotvec()
    return ra @ Rotation.from_rotvec(f * rel).as_matrix()


def interpolate_poses(world_from_camera: np.ndarray, valid: np.ndarray, velocity_span: int = 3) -> np.ndarray:
    """Fill invalid frames [T] from valid ones: linear centre and slerp rotation between valid frames; beyond the
    ends, constant velocity (centre and rotation rate) measured over the last ``velocity_span`` valid steps, the
    rotation extrapolated by at most three such spans. A single valid frame is copied."""
    out = np.array(world_from_camera, float, copy=True)
    idx = np.flatnonzero(valid)
    if len(idx) == 0:
        raise PoseEstimationError("no valid pose to interpolate from")
    for i in np.flatnonzero(~np.asarray(valid)):
        k = np.searchsorted(idx, i)
        if k == 0 or k == len(idx):
            a = idx[0] if k == 0 else idx[-1]
            b = idx[min(velocity_span, len(idx) - 1)] if k == 0 else idx[max(len(idx) - 1 - velocity_span, 0)]
            out[i] = out[a]
            if a != b:
                f = (i - a) / (a - b)  # > 0: steps of (a - b) beyond a, away from b
                out[i, :3, :3] = _slerp(out[a, :3, :3], out[b, :3, :3], -min(f, 3.0))
                out[i, :3, 3] = out[a, :3, 3] + f * (out[a, :3, 3] - out[b, :3, 3])
            continue
        p, n = idx[k - 1], idx[k]
        f = (i - p) / (n - p)
        out[i] = np.eye(4)
        out[i, :3, :3] = _slerp(out[p, :3, :3], out[n, :3, :3], f)
        out[i, :3, 3] = (1 - f) * out[p, :3, 3] + f * out[n, :3, 3]
    return out


def find_pose_outliers(
    world_from_camera: np.ndarray, valid: np.ndarray, config: "PoseConfig | None" = None, depth_ref: float = 0.0
) -> list[int]:
    """Frames whose pose breaks the smoothness of their valid neighbours (see module docstring, check (b)).

    ``depth_ref`` (world units, e.g. median scene depth) floors the translation threshold so a stationary
    camera's jitter is not flagged.
    """
    config = _config(config)
    valid = np.array(valid, bool, copy=True)
    r, c = world_from_camera[:, :3, :3], world_from_camera[:, :3, 3]
    outliers: list[int] = []
    while valid.sum() >= 4:
        idx = np.flatnonzero(valid)
        gaps = np.diff(idx)
        step_rot = _angle_deg(np.einsum("nji,njk->nik", r[idx[:-1]], r[idx[1:]])) / gaps
        step_t = np.linalg.norm(np.diff(c[idx], axis=0), axis=1) / gaps
        rot_thr = max(config.outlier_min_deg, config.outlier_k * float(np.median(step_rot)))
        t_thr = config.outlier_k * max(float(np.median(step_t)), 0.004 * depth_ref, 1e-9)
        score = np.zeros(len(idx))
        for k, i in enumerate(idx):
            if 0 < k < len(idx) - 1:
                p, n = idx[k - 1], idx[k + 1]
                f = (i - p) / (n - p)
                r_pred, c_pred = _slerp(r[p], r[n], f), (1 - f) * c[p] + f * c[n]
                g = min(i - p, n - i)
            else:  # an end: constant-velocity extrapolation from the two nearest valid frames
                a, b = (idx[1], idx[2]) if k == 0 else (idx[-2], idx[-3])
                f = (i - a) / (a - b)
                r_pred = _slerp(r[a], r[b], -f) if abs(f) <= 3 else r[a]
                c_pred = c[a] + f * (c[a] - c[b])
                g = abs(i - a)
            rot_err = float(_angle_deg(r_pred.T @ r[i]))
            score[k] = max(rot_err / (rot_thr * max(1, g)), np.linalg.norm(c[i] - c_pred) / (t_thr * max(1, g)))
        worst = int(np.argmax(score))
        if score[worst] <= 1.0:
            break
        valid[idx[worst]] = False
        outliers.append(int(idx[worst]))
    return sorted(outliers)


# ------------------------------------------------------------------------------------- two-view geometry
def track_corners(gray_a, others, K, dist, max_corners):  # noqa: N803
    """Corners of ``gray_a`` tracked (LK, forward-backward checked) into every image of ``others``.

    Returns (pa [n, 2], [pb [n, 2] per other]) in undistorted pixel coordinates, kept where all tracks held.
    """
    import cv2

    empty = (np.zeros((0, 2)), [np.zeros((0, 2)) for _ in others])
    pa = cv2.goodFeaturesToTrack(gray_a, maxCorners=max_corners, qualityLevel=0.01, minDistance=7)
    if pa is None or len(pa) < 8:
        return empty
    lk = dict(winSize=(21, 21), maxLevel=4, criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01))
    ok = np.ones(len(pa), bool)
    pbs = []
    for gray_b in others:
        pb, st, _ = cv2.calcOpticalFlowPyrLK(gray_a, gray_b, pa, None, **lk)
        pa2, st2, _ = cv2.calcOpticalFlowPyrLK(gray_b, gray_a, pb, None, **lk)
        ok &= (st[:, 0] == 1) & (st2[:, 0] == 1) & (np.linalg.norm((pa2 - pa)[:, 0], axis=1) < 0.5)
        pbs.append(pb)
    out = []
    for p in [pa, *pbs]:
        p = p[ok].reshape(-1, 1, 2).astype(np.float64)
        if dist is not None and np.any(dist) and len(p):
            p = cv2.undistortPoints(p, K, dist, P=K)
        out.append(p.reshape(-1, 2))
    return out[0], out[1:]


def two_view_motion(gray_a, gray_b, K, dist=None, max_corners: int = 2000) -> dict:  # noqa: N803
    """Relative motion ``b_from_a`` (R [3,3], unit t [3]) from an OpenCV essential matrix on LK tracks.

    Also returns the tracks (pixels, undistorted), the inlier mask, and the median flow (px). OpenCV's RANSAC
    draws from a process-wide generator; it is reseeded here so a pair's answer does not depend on what ran
    before it in the process.
    """
    import cv2

    pa, (pb,) = track_corners(gray_a, [gray_b], K, dist, max_corners)
    res = {"R": np.eye(3), "t": np.zeros(3), "inliers": 0, "flow": 0.0, "pa": pa, "pb": pb,
           "mask": np.zeros(len(pa), bool), "ok": False}
    if len(pa) < 8:
        return res
    res["flow"] = float(np.median(np.linalg.norm(pb - pa, axis=1)))
    cv2.setRNGSeed(0)
    E, mask = cv2.findEssentialMat(pa, pb, K, method=cv2.RANSAC, prob=0.999, threshold=1.0)  # noqa: N806
    if E is None or E.shape != (3, 3):
        return res
    n, R, t, mask2 = cv2.recoverPose(E, pa, pb, K, mask=mask.copy())  # noqa: N806
    res.update(R=R, t=t.reshape(3), inliers=int(n), mask=mask2.reshape(-1) > 0, ok=n >= 8)
    return res


def epipolar_check(grays, world_from_camera, valid, K, dist=None,  # noqa: N803
                   config: "PoseConfig | None" = None) -> dict:
    """Compare the SfM motion of consecutive valid frames with the essential matrix's (check (a)).

    A pair disagrees when the rotations differ by more than ``epipolar_max_deg``, or, where the pair's median flow
    is at least ``epipolar_min_flow_px`` (a defined direction of travel), when the SfM step and the essential
    matrix's translation point more than ``epipolar_max_t_deg`` apart: a frame registered a step too far and
    turned 2 deg away passes the rotation and smoothness checks but travels 65-78 deg off.
    Returns per-pair rotation and direction disagreement ``pair_deg``, ``pair_t_deg`` [T-1] (NaN where not
    checked), ``bad_pairs`` [T-1], frame outliers (disagree with both neighbours, or the only neighbour), and
    ``bend_deg``: the angle between the chained essential-matrix rotations and SfM's rotation over the longest run
    of consecutive valid frames.
    """
    config = _config(config)
    n = len(grays)
    pair, pair_t = np.full(n - 1, np.nan), np.full(n - 1, np.nan)
    r_sfm_chain, r_e_chain = np.eye(3), np.eye(3)
    run, best_run, best_bend = 0, 0, 0.0
    for i in range(n - 1):
        if not (valid[i] and valid[i + 1]):
            r_sfm_chain, r_e_chain, run = np.eye(3), np.eye(3), 0
            continue
        m = two_view_motion(grays[i], grays[i + 1], K, dist, config.vo_max_corners)
        b_from_a = np.linalg.inv(world_from_camera[i + 1]) @ world_from_camera[i]  # cam_{i+1}_from_cam_i
        r_sfm = b_from_a[:3, :3]
        if not m["ok"]:
            continue
        pair[i] = float(_angle_deg(m["R"].T @ r_sfm))
        step = np.linalg.norm(b_from_a[:3, 3])
        if m["flow"] >= config.epipolar_min_flow_px and step > 0:
            pair_t[i] = float(np.degrees(np.arccos(np.clip(b_from_a[:3, 3] @ m["t"] / step, -1.0, 1.0))))
        r_sfm_chain, r_e_chain, run = r_sfm @ r_sfm_chain, m["R"] @ r_e_chain, run + 1
        if run >= best_run:
            best_run, best_bend = run, float(_angle_deg(r_e_chain.T @ r_sfm_chain))
    bad = (np.nan_to_num(pair, nan=0.0) > config.epipolar_max_deg) | (
        np.nan_to_num(pair_t, nan=0.0) > config.epipolar_max_t_deg)
    checked = ~np.isnan(pair)
    outliers = []
    for i in range(n):
        left = bad[i - 1] if i > 0 and checked[i - 1] else None
        right = bad[i] if i < n - 1 and checked[i] else None
        votes = [v for v in (left, right) if v is not None]
        if valid[i] and votes and all(votes) and (len(votes) == 2 or n <= 2 or i in (0, n - 1)):
            outliers.append(i)
    return {"pair_deg": pair, "pair_t_deg": pair_t, "outliers": outliers, "bend_deg": best_bend, "bad_pairs": bad}
