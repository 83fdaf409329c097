"""Trajectory alignment/ATE/RPE and mask/tracklet scores on hand-made cases with known answers."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from agg.eval.scores import ScoreError, mask_iou, mean_mask_iou, tracklet_scores
from agg.eval.trajectory import (
    Sim3,
    TrajectoryError,
    align_sim3,
    evaluate_trajectory,
    path_length,
    relative_pose_errors,
    rotation_angle_deg,
)


def _poses(centres, rotations=None):
    n = len(centres)
    p = np.tile(np.eye(4), (n, 1, 1))
    p[:, :3, 3] = centres
    if rotations is not None:
        p[:, :3, :3] = rotations
    return p


def _straight_path(n=30, step=1.2, rng=None):
    """Forward driving along +z with small yaw/pitch jitter of the camera (not of the path)."""
    rng = rng or np.random.default_rng(0)
    centres = np.c_[np.zeros(n), np.zeros(n), step * np.arange(n)]
    rots = Rotation.from_euler("yxz", rng.normal(0, 0.5, (n, 3)), degrees=True).as_matrix()
    return _poses(centres, rots)


KNOWN = Sim3(scale=3.7, rotation=Rotation.from_rotvec([0.3, -1.1, 0.6]).as_matrix(), translation=np.array([5.0, -2.0, 9.0]))


def _inverse(sim: Sim3) -> Sim3:
    r_inv = sim.rotation.T
    return Sim3(1.0 / sim.scale, r_inv, -(r_inv @ sim.translation) / sim.scale)


def test_sim3_recovers_known_similarity_on_exactly_straight_path():
    gt = _straight_path()
    est = _inverse(KNOWN).apply_to_poses(gt)  # est world = KNOWN^-1 (gt world)
    xc = est[:, :3, 3] - est[:, :3, 3].mean(0)
    assert np.linalg.matrix_rank(xc, tol=1e-9) == 1  # centres collinear: centre-only Umeyama is degenerate
    sim = align_sim3(est, gt)
    assert sim.scale == pytest.approx(KNOWN.scale, rel=1e-9)
    np.testing.assert_allclose(sim.rotation, KNOWN.rotation, atol=1e-9)
    np.testing.assert_allclose(sim.translation, KNOWN.translation, atol=1e-8)
    m = evaluate_trajectory(est, gt)
    assert m.ate_rmse < 1e-9 and m.ate_rot_mean_deg < 1e-6 and m.rpe_rot_rmse_deg < 1e-6


def test_orientations_fix_roll_that_centre_only_umeyama_gets_wrong():
    # Nearly straight path: a 1 cm lateral wiggle in x. The estimate's wiggle is in y instead (noise), so
    # centre-only alignment rolls the estimate 90 deg about the path to fit the wiggle; orientations pin it.
    gt = _straight_path()
    wiggle = 0.01 * np.tile([1.0, -1.0, -1.0, 1.0], 8)[: len(gt)]
    gt[:, 0, 3] = wiggle
    est_in_gt = gt.copy()
    est_in_gt[:, 0, 3], est_in_gt[:, 1, 3] = 0.0, wiggle
    est = _inverse(KNOWN).apply_to_poses(est_in_gt)
    centre_only = align_sim3(est, gt, rot_weight=0.0)
    with_rot = align_sim3(est, gt)
    err_centre = rotation_angle_deg(centre_only.rotation.T @ KNOWN.rotation)
    err_rot = rotation_angle_deg(with_rot.rotation.T @ KNOWN.rotation)
    assert err_centre > 80.0
    assert err_rot < 0.1
    assert evaluate_trajectory(est, gt).ate_rot_mean_deg < 0.1
    assert evaluate_trajectory(est, gt, rot_weight=0.0).ate_rot_mean_deg > 80.0


def test_ate_and_rpe_known_perturbations():
    gt = _straight_path(n=32)
    # zero-mean lateral offsets orthogonal to the path and to its ramp: R = I, scale and ATE in closed form
    d = 0.05
    pattern = d * np.tile([1.0, -1.0, -1.0, 1.0], 8)
    est = gt.copy()
    est[:, 0, 3] += pattern
    m = evaluate_trajectory(est, gt)
    yc = gt[:, :3, 3] - gt[:, :3, 3].mean(0)
    s = (yc**2).sum() / ((yc**2).sum() + len(gt) * d**2)
    expected = np.sqrt(np.mean((1 - s) ** 2 * (yc**2).sum(1) + s**2 * d**2))
    assert m.alignment.scale == pytest.approx(s, rel=1e-6)
    assert m.ate_rmse == pytest.approx(expected, rel=1e-4)
    assert m.ate_percent_of_path == pytest.approx(100 * expected / path_length(gt), rel=1e-4)
    assert path_length(gt) == pytest.approx(1.2 * 31)

    # RPE on already-aligned inputs: steps 10 % too long and 1 deg extra yaw per step
    n = 10
    gt2 = _poses(np.c_[np.zeros(n), np.zeros(n), np.arange(n, dtype=float)])
    est2 = np.tile(np.eye(4), (n, 1, 1))
    for i in range(1, n):
        step = np.eye(4)
        step[:3, :3] = Rotation.from_euler("y", 1.0, degrees=True).as_matrix()
        step[:3, 3] = [0, 0, 1.1]
        est2[i] = est2[i - 1] @ step
    t_err, r_err = relative_pose_errors(est2, gt2, delta=1)
    np.testing.assert_allclose(r_err, 1.0, atol=1e-6)
    np.testing.assert_allclose(t_err, 0.1, atol=1e-9)
    t3, r3 = relative_pose_errors(est2, gt2, delta=3)
    np.testing.assert_allclose(r3, 3.0, atol=1e-6)
    assert np.all(t3 > 0.3)  # 3 steps of +10 % plus the lateral drift from turning


def test_trajectory_bad_input():
    with pytest.raises(TrajectoryError):
        align_sim3(np.zeros((5, 4, 4)), np.zeros((4, 4, 4)))
    with pytest.raises(TrajectoryError):
        evaluate_trajectory(np.full((3, 4, 4), np.nan), np.zeros((3, 4, 4)))


def test_mask_iou_hand_made():
    pred = np.zeros((3, 4, 4), bool)
    gt = np.zeros((3, 4, 4), bool)
    pred[0, :2, :2] = True  # 4 px
    gt[0, :2, :3] = True  # 6 px, 4 shared -> 4/6
    pred[1, 0, 0] = True  # disjoint -> 0
    gt[1, 3, 3] = True
    # frame 2: both empty -> 1 by convention
    np.testing.assert_allclose(mask_iou(pred, gt), [4 / 6, 0.0, 1.0])
    assert mean_mask_iou(pred, gt) == pytest.approx((4 / 6 + 1.0) / 3)
    assert mask_iou(pred, gt, empty_value=0.0)[2] == 0.0
    with pytest.raises(ScoreError):
        mask_iou(pred, gt[:2])


def test_tracklet_recall_precision_hand_made():
    t = 10
    nan = np.full((t, 2), np.nan)
    g0 = np.c_[np.arange(t) * 10.0, np.zeros(t)]  # car moving right
    g1 = np.c_[np.full(t, 100.0), np.arange(t) * 5.0]  # car moving down
    g2 = nan.copy()
    g2[:4] = [[300.0, 300.0]] * 4  # short track, missed
    p0 = g0 + 2.0  # within 5 px every frame -> overlap 1
    p1 = g1.copy()
    p1[6:] = np.nan  # present 6 of 10 frames -> overlap 0.6
    p2 = np.c_[np.full(t, 500.0), np.full(t, 500.0)]  # false positive
    p3 = g0 + 1.0  # duplicate of g0: one-to-one matching leaves it unmatched
    s = tracklet_scores([p0, p1, p2, p3], [g0, g1, g2], max_dist=5.0, min_overlap=0.5)
    assert s.recall == pytest.approx(2 / 3)
    assert s.precision == pytest.approx(2 / 4)
    assert sorted(c for _, c in s.matches) == [0, 1]
    assert s.overlap[1, 1] == pytest.approx(0.6)
    # stricter overlap drops the partial track
    s2 = tracklet_scores([p0, p1, p2, p3], [g0, g1, g2], max_dist=5.0, min_overlap=0.7)
    assert s2.recall == pytest.approx(1 / 3)
    # empty sets follow the documented convention
    empty = tracklet_scores(np.zeros((0, t, 2)), [g0], max_dist=5.0)
    assert empty.recall == 0.0 and empty.precision == 1.0
