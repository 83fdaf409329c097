"""Dynamic-mask prior on synthetic clips with exact poses and depth: moving agents are found (IoU floor), a clip
without moving agents stays (near) empty; rigid flow and Sampson distance on known geometry; the ego-vehicle rule;
input errors."""

import numpy as np
import pytest

from agg.eval.scores import mean_mask_iou
from agg.priors.masks import (
    MaskConfig,
    MaskPriorError,
    dynamic_masks,
    ego_vehicle_region,
    rigid_flow,
    sampson_distance,
)
from agg.synth.scene import SceneConfig
from agg.synth.suite import render_clip


def _clip(**kw):
    gt = render_clip(SceneConfig(frames=12, width=320, height=192, **kw))
    return gt, np.where(gt.depth_valid, gt.depth, 0.0).astype(np.float32)


@pytest.fixture(scope="module")
def busy():
    return _clip(seed=0)


def test_moving_agents_are_masked_with_gt_poses_and_depth(busy):
    gt, depth = busy
    seen = []
    res = dynamic_masks(gt.rgb, gt.K, gt.world_from_camera, depth, progress=seen.append)
    assert res.masks.shape == res.residual.shape == depth.shape and res.masks.dtype == np.uint8
    assert set(np.unique(res.masks)) <= {0, 1} and seen == list(range(len(depth)))
    assert np.isfinite(res.residual).all() and res.residual.min() >= 0
    moving = np.isin(gt.instance, gt.agent_ids[gt.agent_moving])
    iou = mean_mask_iou(res.masks, moving)
    assert iou > 0.2  # measured 0.34 (docs/PRIORS.md "Dynamic masks")
    false_pos = (res.masks > 0) & (gt.instance == 0)
    assert false_pos.mean() < 0.03  # measured 0.012
    assert res.residual[moving].mean() > 3 * res.residual[gt.instance == 0].mean()


def test_clip_without_moving_agents_stays_nearly_empty():
    gt, depth = _clip(seed=3, moving_cars=0, pedestrians=0)
    res = dynamic_masks((gt.rgb * 255).astype(np.uint8), gt.K, gt.world_from_camera, depth)
    assert res.masks.mean() < 0.02  # measured 0.004


def test_rigid_flow_and_sampson_distance_on_known_geometry():
    K = np.array([[100.0, 0, 31.5], [0, 100.0, 23.5], [0, 0, 1]])
    depth = np.full((48, 64), 5.0)
    j_from_i = np.eye(4)
    j_from_i[0, 3] = -0.5  # camera j is 0.5 m to the right of i: points move left by f t / z = 10 px
    flow, has = rigid_flow(K, j_from_i, depth)
    assert has.all()
    np.testing.assert_allclose(flow[..., 0], -10.0)
    np.testing.assert_allclose(flow[..., 1], 0.0, atol=1e-9)
    assert sampson_distance(K, j_from_i, flow).max() < 1e-6  # a static scene satisfies the epipolar geometry
    off = flow.copy()
    off[..., 1] += 3.0  # 3 px across the (horizontal) epipolar lines
    np.testing.assert_allclose(sampson_distance(K, j_from_i, off), 3.0 / np.sqrt(2), rtol=1e-6)
    flow_inf, has_inf = rigid_flow(K, j_from_i, np.zeros((48, 64)))  # no depth: point at infinity, no parallax
    assert not has_inf.any() and np.abs(flow_inf).max() < 1e-9


def test_ego_vehicle_region_is_the_persistent_bottom_band():
    masks = np.zeros((10, 40, 60), np.uint8)
    masks[:, 34:, :] = 1  # bonnet: every frame, bottom rows
    masks[:, 10:20, 25:35] = 1  # an agent that stays put but does not touch the bottom
    masks[::3, 25:30, 5:10] = 1  # an intermittent blob
    region = ego_vehicle_region(masks, MaskConfig())
    assert region[34:].all() and not region[10:20, 25:35].any() and not region[25:30, 5:10].any()
    assert not ego_vehicle_region(masks[:4], MaskConfig()).any()  # too few frames for the rule


def test_a_bonnet_fixed_in_the_image_is_the_ego_mask_and_no_agent(busy):
    gt, depth = busy
    rgb = gt.rgb.copy()
    rng = np.random.default_rng(0)
    bonnet = np.repeat(np.repeat(rng.uniform(0.2, 0.8, (6, 80, 3)), 4, 0), 4, 1)  # [24, 320, 3] coarse texture
    rgb[:, -24:] = bonnet  # the same pixels in every frame, whatever the camera does
    res = dynamic_masks(rgb, gt.K, gt.world_from_camera, depth)
    assert res.ego.shape == depth.shape[1:] and res.ego.dtype == bool
    assert res.ego[-24:].mean() > 0.9 and res.ego[:-40].sum() == 0  # the band and its dilation, nothing above
    assert not res.masks[:, res.ego].any()  # and no agent there
    assert not dynamic_masks(gt.rgb, gt.K, gt.world_from_camera, depth).ego.any()  # the clip itself has none


def test_bad_inputs_raise_clear_errors(busy):
    gt, depth = busy
    rgb, K, poses = gt.rgb[:3], gt.K, gt.world_from_camera[:3]
    with pytest.raises(MaskPriorError, match="at least 2 frames"):
        dynamic_masks(rgb[:1], K, poses[:1], depth[:1])
    with pytest.raises(MaskPriorError, match="K"):
        dynamic_masks(rgb, np.eye(2), poses, depth[:3])
    with pytest.raises(MaskPriorError, match="world_from_camera"):
        dynamic_masks(rgb, K, poses[:2], depth[:3])
    with pytest.raises(MaskPriorError, match="depth must be"):
        dynamic_masks(rgb, K, poses, depth[:3, :10])
    with pytest.raises(MaskPriorError, match="depth_confidence"):
        dynamic_masks(rgb, K, poses, depth[:3], depth_confidence=np.ones((3, 2, 2)))
    with pytest.raises(MaskPriorError, match="frames must be"):
        dynamic_masks(rgb[..., 0], K, poses, depth[:3])
    with pytest.raises(MaskPriorError, match="flow"):
        MaskConfig(flow="raft")
