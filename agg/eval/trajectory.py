"""Trajectory accuracy: Sim(3) alignment that uses orientations, ATE and RPE.

All poses are camera-to-world 4x4 matrices (``world_from_camera``, OpenCV camera axes). The estimated
trajectory lives in its own world frame and scale (monocular), so it is aligned to ground truth with a
similarity ``gt_world_from_est_world`` = (s, R, t) first. Errors are then in ground-truth units (metres for
KITTI).

Why orientations: on a forward-driving clip the camera centres are nearly collinear, so Umeyama's alignment on
centres alone leaves the rotation about the path axis undetermined (the cross-covariance has rank ~1). Here the
rotation maximises ``tr(R^T C)`` with

    C = (1/N) sum_i (y_i - y_mean)(x_i - x_mean)^T / (sigma_y sigma_x)  +  w (1/N) sum_i R_gt_i R_est_i^T

i.e. the Kabsch/Umeyama term on centres normalised by their RMS spread (so it is scale-free) plus the
orientation term of the chordal least squares ``sum_i ||R_gt_i - R R_est_i||_F^2`` with weight ``w``. For an
exact similarity both terms equal ``R*`` times a positive semi-definite matrix, so ``R*`` is recovered exactly;
on a straight path the orientation term makes ``C`` full rank. Scale and translation then follow in closed form
from the centres given ``R``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


class TrajectoryError(ValueError):
    """Bad trajectory input (shapes, lengths, non-finite values)."""


@dataclass(frozen=True)
class Sim3:
    """Similarity ``y = s * R @ x + t`` (maps estimate-world points to ground-truth-world points)."""

    scale: float
    rotation: np.ndarray  # [3, 3]
    translation: np.ndarray  # [3]

    def apply_to_points(self, points: np.ndarray) -> np.ndarray:
        """Map points [..., 3] into the target world (float64)."""
        return self.scale * np.asarray(points, float) @ self.rotation.T + self.translation

    def apply_to_poses(self, world_from_camera: np.ndarray) -> np.ndarray:
        """Map camera-to-world poses [N, 4, 4] into the target world; rotations stay orthonormal."""
        out = np.array(world_from_camera, float, copy=True)
        out[:, :3, :3] = self.rotation @ out[:, :3, :3]
        out[:, :3, 3] = self.apply_to_points(out[:, :3, 3])
        return out


@dataclass(frozen=True)
class TrajectoryMetrics:
    """ATE/RPE after Sim(3) alignment. Lengths in ground-truth units (m), angles in degrees."""

    ate_rmse: float
    ate_percent_of_path: float
    ate_rot_mean_deg: float  # mean absolute orientation error after alignment
    rpe_trans_rmse: float  # per ``delta`` frames
    rpe_rot_rmse_deg: float
    path_length: float  # ground-truth path length
    delta: int
    alignment: Sim3

    def as_dict(self) -> dict:
        return {
            "ate_rmse_m": self.ate_rmse,
            "ate_percent_of_path": self.ate_percent_of_path,
            "ate_rot_mean_deg": self.ate_rot_mean_deg,
            "rpe_trans_rmse_m": self.rpe_trans_rmse,
            "rpe_rot_rmse_deg": self.rpe_rot_rmse_deg,
            "path_length_m": self.path_length,
            "rpe_delta_frames": self.delta,
            "sim3_scale": self.alignment.scale,
        }


def _check_poses(*arrays: np.ndarray) -> None:
    n = None
    for a in arrays:
        if a.ndim != 3 or a.shape[1:] not in ((4, 4), (3, 4)):
            raise TrajectoryError(f"poses must be [N, 4, 4] or [N, 3, 4], got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise TrajectoryError("poses contain non-finite values")
        if n is not None and a.shape[0] != n:
            raise TrajectoryError(f"pose counts differ: {n} vs {a.shape[0]}")
        n = a.shape[0]
    if n is not None and n < 2:
        raise TrajectoryError("need at least 2 poses")


def _as44(a: np.ndarray) -> np.ndarray:
    a = np.asarray(a, float)
    if a.shape[1:] == (3, 4):
        bottom = np.tile(np.array([[[0.0, 0.0, 0.0, 1.0]]]), (a.shape[0], 1, 1))
        a = np.concatenate([a, bottom], axis=1)
    return a


def rotation_angle_deg(r: np.ndarray) -> np.ndarray:
    """Angle (deg) of rotation matrices [..., 3, 3]: atan2(sin, cos) with |R - R^T|_F = 2 sqrt(2) sin(angle) and
    trace = 1 + 2 cos(angle), exact at every angle (the trace's arccos alone loses about 0.01 deg near zero)."""
    r = np.asarray(r, float)
    cos = (np.trace(r, axis1=-2, axis2=-1) - 1.0) / 2.0  # [...]
    sin = np.linalg.norm(r - np.swapaxes(r, -1, -2), axis=(-2, -1)) / (2.0 * np.sqrt(2.0))  # [...]
    return np.degrees(np.arctan2(sin, cos))


def _project_so3(c: np.ndarray) -> np.ndarray:
    u, _, vt = np.linalg.svd(c)
    d = np.sign(np.linalg.det(u @ vt)) or 1.0
    return u @ np.diag([1.0, 1.0, d]) @ vt


def align_sim3(
    est_world_from_camera: np.ndarray, gt_world_from_camera: np.ndarray, rot_weight: float = 1.0
) -> Sim3:
    """Sim(3) ``gt_world_from_est_world`` from centres and orientations (see module docstring).

    ``rot_weight = 0`` gives classic centre-only Umeyama (ill-posed on straight paths; kept for comparison).
    """
    est, gt = _as44(est_world_from_camera), _as44(gt_world_from_camera)
    _check_poses(est, gt)
    x, y = est[:, :3, 3], gt[:, :3, 3]  # [N, 3] camera centres
    xm, ym = x.mean(0), y.mean(0)
    xc, yc = x - xm, y - ym
    sx, sy = np.sqrt((xc**2).sum(1).mean()), np.sqrt((yc**2).sum(1).mean())
    c = np.zeros((3, 3))
    moving = sx > 1e-12 and sy > 1e-12
    if moving:
        c += (yc / sy).T @ (xc / sx) / len(x)
    if rot_weight > 0:
        c += rot_weight * np.einsum("nij,nkj->ik", gt[:, :3, :3], est[:, :3, :3]) / len(x)
    if not np.any(c):
        raise TrajectoryError("alignment is undetermined: no motion and rot_weight = 0")
    r = _project_so3(c)
    s = float(np.sum(yc * (xc @ r.T)) / np.sum(xc**2)) if moving else 1.0
    if s <= 0:
        raise TrajectoryError("alignment gave a non-positive scale (trajectories disagree in direction)")
    return Sim3(scale=s, rotation=r, translation=ym - s * r @ xm)


def path_length(world_from_camera: np.ndarray) -> float:
    """Sum of distances between consecutive camera centres (world units)."""
    c = _as44(world_from_camera)[:, :3, 3]
    return float(np.linalg.norm(np.diff(c, axis=0), axis=1).sum())


def relative_pose_errors(
    est_world_from_camera: np.ndarray, gt_world_from_camera: np.ndarray, delta: int = 1
) -> tuple[np.ndarray, np.ndarray]:
    """Per-pair RPE for pairs (i, i+delta): translation error [N-delta] (units of the inputs) and rotation
    error [N-delta] (deg). Inputs must already share a scale (align first)."""
    est, gt = _as44(est_world_from_camera), _as44(gt_world_from_camera)
    _check_poses(est, gt)
    if not 1 <= delta < len(est):
        raise TrajectoryError(f"delta must be in [1, {len(est) - 1}], got {delta}")
    rel_est = np.linalg.inv(est[:-delta]) @ est[delta:]  # [M, 4, 4] camera_i_from_camera_{i+delta}
    rel_gt = np.linalg.inv(gt[:-delta]) @ gt[delta:]
    err = np.linalg.inv(rel_gt) @ rel_est
    return np.linalg.norm(err[:, :3, 3], axis=1), rotation_angle_deg(err[:, :3, :3])


def evaluate_trajectory(
    est_world_from_camera: np.ndarray,
    gt_world_from_camera: np.ndarray,
    delta: int = 1,
    rot_weight: float = 1.0,
) -> TrajectoryMetrics:
    """ATE RMSE (and % of the ground-truth path length) and RPE after orientation-aware Sim(3) alignment."""
    est, gt = _as44(est_world_from_camera), _as44(gt_world_from_camera)
    sim = align_sim3(est, gt, rot_weight=rot_weight)
    aligned = sim.apply_to_poses(est)
    d = aligned[:, :3, 3] - gt[:, :3, 3]
    ate = float(np.sqrt((d**2).sum(1).mean()))
    length = path_length(gt)
    rot_err = rotation_angle_deg(np.einsum("nji,njk->nik", gt[:, :3, :3], aligned[:, :3, :3]))
    rpe_t, rpe_r = relative_pose_errors(aligned, gt, delta)
    return TrajectoryMetrics(
        ate_rmse=ate,
        ate_percent_of_path=100.0 * ate / length if length > 0 else float("nan"),
        ate_rot_mean_deg=float(rot_err.mean()),
        rpe_trans_rmse=float(np.sqrt((rpe_t**2).mean())),
        rpe_rot_rmse_deg=float(np.sqrt((rpe_r**2).mean())),
        path_length=length,
        delta=delta,
        alignment=sim,
    )


def read_kitti_poses(path) -> np.ndarray:
    """KITTI pose file (one row-major 3x4 camera-to-world matrix per line) -> [N, 4, 4]."""
    rows = np.loadtxt(path, ndmin=2)
    if rows.shape[1] != 12:
        raise TrajectoryError(f"{path}: expected 12 numbers per line, got {rows.shape[1]}")
    return _as44(rows.reshape(-1, 3, 4))
