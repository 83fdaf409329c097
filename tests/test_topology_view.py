"""Where a spawned agent's box can be seen (``agg.train.topology_view``): a car the camera overtakes leaves at the
image edge with its centre already outside the image."""

from types import SimpleNamespace

import numpy as np

from agg.train.topology import TopologyConfig
from agg.train.topology_track import pose_from_yaw
from agg.train.topology_view import box_image_rect, box_visibility

W, H = 160, 80
K = np.array([[100.0, 0.0, 80.0], [0.0, 100.0, 40.0], [0.0, 0.0, 1.0]])
HALF = np.array([2.3, 0.8, 0.9])  # l, h, w half extents (box x along the heading)
BANK = {"background": np.array([[1.0, 0, 0]]), "rigid": np.array([[0, 1.0, 0]]),
        "non-rigid": np.array([[0, 0, 1.0]])}


def _evo(features: np.ndarray, dynamic=None) -> SimpleNamespace:
    """What ``box_visibility`` reads of a ``TopologyEvolution``: one frame, a camera at the origin looking down +z."""
    return SimpleNamespace(config=TopologyConfig(), unit=1.0, K=K[None], width=W, height=H, bank=BANK,
                           semantics=SimpleNamespace(features=features[None]), dynamic=dynamic)


def _features(car_cells: bool) -> np.ndarray:
    """[10, 20, 3] cells of 8 x 8 pixels: background, with rigid-agent cells at x >= 14 (pixels 112..159), rows
    2..7, when ``car_cells``."""
    feats = np.zeros((10, 20, 3), np.float32)
    feats[..., 0] = 1.0
    if car_cells:
        feats[2:8, 14:] = [0, 1.0, 0]
    return feats


def test_a_box_whose_centre_left_the_image_is_in_view_where_the_features_see_its_visible_part():
    cam = np.eye(4)[None]  # [1, 4, 4] camera_from_world
    leaving = pose_from_yaw(np.array([4.0, 0.0, 4.0]), 0.0)  # centre at u = 180 (outside); its left end inside
    lo, hi = box_image_rect(leaving, HALF, cam[0], K, W, H, 0.3)
    assert 110.0 < lo[0] < 120.0 and hi[0] > 150.0  # the image holds the box from u ~ 115 to its right edge
    in_view, evidence = box_visibility(_evo(_features(True)), cam, HALF)
    assert evidence(0, leaving) and in_view(0, leaving)
    in_view, evidence = box_visibility(_evo(_features(False)), cam, HALF)  # the road there: no agent to extend to
    assert not evidence(0, leaving) and not in_view(0, leaving)
    others = np.zeros((H, W), bool)
    others[:, 100:] = True  # another agent's prior mask covers that part: no evidence for this one
    in_view, evidence = box_visibility(_evo(_features(True), others[None]), cam, HALF)
    assert not in_view(0, leaving)


def test_a_box_in_view_by_its_centre_needs_no_features_and_a_box_outside_the_image_is_never_in_view():
    cam = np.eye(4)[None]
    centred = pose_from_yaw(np.array([0.0, 0.0, 8.0]), 0.0)
    gone = pose_from_yaw(np.array([40.0, 0.0, 4.0]), 0.0)  # every grid point right of the image
    behind = pose_from_yaw(np.array([0.0, 0.0, -6.0]), 0.0)
    in_view, evidence = box_visibility(_evo(_features(False)), cam, HALF)
    assert in_view(0, centred) and not evidence(0, centred)
    in_view, evidence = box_visibility(_evo(_features(True)), cam, HALF)
    for pose in (gone, behind):
        assert box_image_rect(pose, HALF, cam[0], K, W, H, 0.3) is None
        assert not in_view(0, pose) and not evidence(0, pose)
