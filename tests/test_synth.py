"""Tests of the synthetic driving suite (agg/synth): determinism, renderer geometry, every corruption knob, bundle."""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np
import pytest

from agg.synth.corrupt import (NoiseConfig, NoiseConfigError, box_world_pose, boxes_through_cameras, corrupt,
                               missed_order, noisy_boxes, noisy_camera_poses, rotation_angle)
from agg.synth.features import FeatureConfig, FeatureConfigError, attention_maps, class_embeddings, classify
from agg.synth.raycast import (ValueNoise, intersect_boxes, intersect_boxes_dense, pixel_rays, render,
                               render_scene_frame, screen_rects)
from agg.synth.scene import MAT_PAINT, SEM, BoxSet, SceneConfig, SceneConfigError, make_scene, pose, rot_y
from agg.synth.suite import generate, load_gt_extras, render_clip

SMALL = SceneConfig(seed=7, frames=12, width=128, height=64, hfov_deg=80.0)


@pytest.fixture(scope="module")
def gt():
    return render_clip(SMALL)


def _k(width=128, height=96, f=100.0):
    return np.array([[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]])


def _boxes(centres, halves, yaws=None, instances=None):
    n = len(centres)
    yaws = np.zeros(n) if yaws is None else yaws
    return BoxSet(np.stack([pose(rot_y(y), c) for y, c in zip(yaws, centres)]), np.asarray(halves, float),
                  np.full(n, MAT_PAINT), np.full((n, 3), 0.5), np.full(n, SEM["car"]),
                  np.arange(1, n + 1) if instances is None else np.asarray(instances))


# ------------------------------------------------------------------------------------------------ determinism

def test_same_seed_gives_identical_arrays_and_other_seed_differs(gt):
    again = render_clip(SMALL)
    for name in ("rgb", "depth", "instance", "semantic", "world_from_camera", "boxes", "features"):
        np.testing.assert_array_equal(getattr(gt, name), getattr(again, name), err_msg=name)
    other = render_clip(replace(SMALL, seed=8))
    assert not np.array_equal(gt.rgb, other.rgb)
    assert not np.allclose(gt.boxes, other.boxes)
    noise = NoiseConfig(seed=1, camera_translation_max=0.5, missed=1, false=1, depth_rel_sigma=0.1,
                        feature_sigma=0.1)
    a, b = corrupt(gt, noise), corrupt(gt, noise)
    np.testing.assert_array_equal(a.world_from_camera, b.world_from_camera)
    np.testing.assert_array_equal(a.boxes, b.boxes)
    np.testing.assert_array_equal(a.depth, b.depth)
    c = corrupt(gt, replace(noise, seed=2))
    assert not np.allclose(a.world_from_camera, c.world_from_camera)


def test_scene_content_and_conventions(gt):
    assert gt.rgb.shape == (12, 64, 128, 3) and gt.rgb.dtype == np.float32
    assert 0.0 <= gt.rgb.min() and gt.rgb.max() <= 1.0
    np.testing.assert_array_equal(gt.world_from_camera[0], np.eye(4))
    # the camera drives forward (+z) and stays about camera_height above the road
    assert gt.world_from_camera[-1, 2, 3] > 0.5 * SMALL.ego_speed * (SMALL.frames - 1) / SMALL.fps
    present = set(np.unique(gt.semantic).tolist())
    for name in ("sky", "road", "marking", "sidewalk", "building", "car"):
        assert SEM[name] in present, name
    assert gt.agent_classes.count("non-rigid") == SMALL.pedestrians
    assert gt.agent_classes.count("rigid") == SMALL.moving_cars + SMALL.parked_cars
    # instance ids map to the right semantic class
    for k, label in zip(gt.agent_ids, gt.agent_labels):
        sem = gt.semantic[gt.instance == k]
        assert sem.size == 0 or np.all(sem == SEM[label])
    # the box frame follows docs/BUNDLE.md: R_y(yaw), moving cars ahead head along +z (yaw ~ -pi/2) or -z
    moving = [k for k, n in enumerate(gt.agent_names) if n == "moving_car"]
    assert np.all(np.abs(np.abs(gt.boxes[moving, :, 6]) - np.pi / 2) < 0.2)
    np.testing.assert_allclose(gt.world_from_agent[..., :3, :3],
                               np.stack([[rot_y(y) for y in row] for row in gt.boxes[..., 6]]), atol=1e-9)
    # every agent pixel lies inside its 3D box
    k0 = moving[0]
    f = int(np.argmax(gt.pixel_count[k0]))
    rows, cols = np.nonzero(gt.instance[f] == gt.agent_ids[k0])
    rays = np.stack([cols, rows, np.ones(len(rows))], -1) @ np.linalg.inv(gt.K).T
    pts_cam = rays * gt.depth[f][rows, cols][:, None]
    pts_w = pts_cam @ gt.world_from_camera[f][:3, :3].T + gt.world_from_camera[f][:3, 3]
    local = (pts_w - gt.world_from_agent[k0, f, :3, 3]) @ gt.world_from_agent[k0, f, :3, :3]
    half = gt.size_lwh[k0][[0, 2, 1]] / 2
    assert np.all(np.abs(local) <= half + 1e-3)


def test_pedestrian_limbs_move_but_box_contains_them():
    scene = make_scene(SceneConfig(seed=3, frames=10))
    ped = next(a for a in scene.agents if a.kind == "non_rigid")
    b0, b5 = ped.boxes(0, 1), ped.boxes(5, 1)
    rel0 = np.linalg.inv(ped.world_from_agent[0]) @ b0.world_from_box
    rel5 = np.linalg.inv(ped.world_from_agent[5]) @ b5.world_from_box
    assert not np.allclose(rel0, rel5)  # limbs swing
    np.testing.assert_allclose(rel0[:2], rel5[:2], atol=1e-9)  # torso and head rigid
    half = ped.size_lwh[[0, 2, 1]] / 2
    for rel, boxes in ((rel0, b0), (rel5, b5)):
        corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
        for r, h in zip(rel, boxes.half_size):
            pts = (corners * h) @ r[:3, :3].T + r[:3, 3]
            assert np.all(np.abs(pts) <= half + 1e-6)


# ------------------------------------------------------------------------------------------------ renderer geometry

def test_ground_plane_depth_matches_analytic():
    k, h = _k(), 1.6
    out = render(k, np.eye(4), 128, 96, BoxSet.empty(), plane=(np.array([0.0, -1.0, 0.0]), -h), sky=True)
    rows = np.arange(96)
    below = rows > k[1, 2]
    expected = h * k[1, 1] / (rows[below] - k[1, 2])  # z = h fy / (v - cy) for every column
    np.testing.assert_allclose(out.depth[below], np.repeat(expected[:, None], 128, 1), rtol=1e-5)
    assert not out.valid[~below].any() and np.isinf(out.depth[~below]).all()
    assert np.all(out.semantic[~below] == SEM["sky"]) and np.all(out.instance == 0)


def test_scene_road_depth_matches_plane_intersection(gt):
    scene = make_scene(SMALL)
    f = 5
    n, d = scene.ground_plane()
    road = (gt.semantic[f] == SEM["road"]) | (gt.semantic[f] == SEM["marking"])
    rows, cols = np.nonzero(road)
    rays_cam = np.stack([cols, rows, np.ones(len(rows))], -1) @ np.linalg.inv(gt.K).T
    w = gt.world_from_camera[f]
    rays_w = rays_cam @ w[:3, :3].T
    t = (d - n @ w[:3, 3]) / (rays_w @ n)
    assert len(t) > 500
    np.testing.assert_allclose(gt.depth[f][rows, cols], t, rtol=1e-5)


def test_box_projection_matches_pinhole():
    k = _k()
    centre, half = np.array([0.0, 0.0, 10.0]), np.array([1.0, 0.8, 0.5])
    out = render(k, np.eye(4), 128, 96, _boxes([centre], [half]), sky=False)
    mask = out.instance == 1
    rows, cols = np.nonzero(mask)
    # silhouette of an axis-aligned box centred on the optical axis = its front face (z = 9.5)
    u_half, v_half = k[0, 0] * half[0] / 9.5, k[1, 1] * half[1] / 9.5
    assert cols.min() == int(np.ceil(k[0, 2] - u_half)) and cols.max() == int(np.floor(k[0, 2] + u_half))
    assert rows.min() == int(np.ceil(k[1, 2] - v_half)) and rows.max() == int(np.floor(k[1, 2] + v_half))
    np.testing.assert_allclose(out.depth[mask], 9.5, rtol=1e-6)
    assert abs(cols.mean() - k[0, 2]) < 0.5 and abs(rows.mean() - k[1, 2]) < 0.5
    # an off-axis rotated box: the pixel at the projection of its centre belongs to it
    c2 = np.array([2.5, -0.7, 12.0])
    out2 = render(k, np.eye(4), 128, 96, _boxes([c2], [[1.5, 0.6, 0.8]], yaws=[0.6]), sky=False)
    u, v = (k @ c2)[:2] / c2[2]
    assert out2.instance[int(round(v)), int(round(u))] == 1
    assert 12.0 - 1.6 < out2.depth[int(round(v)), int(round(u))] < 12.0


def test_occluded_agent_is_hidden_and_depth_ordered():
    k = _k()
    near = _boxes([[0.0, 0.0, 6.0]], [[1.0, 1.0, 0.5]], instances=[1])
    far = _boxes([[0.5, 0.0, 15.0]], [[1.0, 1.0, 0.5]], instances=[2])
    hidden = render(k, np.eye(4), 128, 96, BoxSet.concat([far, near]), sky=False)
    assert (hidden.instance == 2).sum() == 0  # fully behind the near box
    partial = render(k, np.eye(4), 128, 96, BoxSet.concat([_boxes([[2.0, 0.0, 15.0]], [[1.5, 1.0, 0.5]], instances=[2]),
                                                           near]), sky=False)
    alone = render(k, np.eye(4), 128, 96, _boxes([[2.0, 0.0, 15.0]], [[1.5, 1.0, 0.5]], instances=[2]), sky=False)
    both = (alone.instance == 2) & (render(k, np.eye(4), 128, 96, near, sky=False).instance == 1)
    assert both.sum() > 20 and np.all(partial.instance[both] == 1)
    assert 0 < (partial.instance == 2).sum() < (alone.instance == 2).sum()
    np.testing.assert_allclose(partial.depth[both], 5.5, rtol=1e-6)


def test_tiled_intersection_equals_dense_reference():
    scene = make_scene(SceneConfig(seed=2, width=96, height=64))
    w = scene.world_from_camera[4]
    boxes = scene.boxes_at(4)
    rays = pixel_rays(scene.K, 96, 64) @ w[:3, :3].T
    rects = screen_rects(boxes, np.linalg.inv(w), scene.K, 96, 64)
    fast = intersect_boxes(w[:3, 3], rays, boxes, rects, 96)
    ref = intersect_boxes_dense(w[:3, 3], rays, boxes)
    np.testing.assert_array_equal(fast[1], ref[1])
    np.testing.assert_allclose(fast[0], ref[0], rtol=1e-12)


def test_render_is_fast():
    scene = make_scene(SceneConfig(seed=1, width=160, height=96))
    assert len(scene.agents) >= 10
    noise = ValueNoise(scene.texture_seed)
    times = []
    for _ in range(5):
        t0 = time.perf_counter()
        render_scene_frame(scene, 3, noise)
        times.append(time.perf_counter() - t0)
    assert min(times) < 0.1, times


def test_no_sky_is_black_far_field_with_invalid_depth():
    out = render_clip(replace(SMALL, sky=False, frames=2))
    sky = out.semantic == SEM["sky"]
    assert sky.any()
    assert np.all(out.rgb[sky] == 0.0) and not out.depth_valid[sky].any() and np.isinf(out.depth[sky]).all()


def test_real_agents_never_overlap():
    for cfg in (SceneConfig(seed=11), SceneConfig(seed=12, moving_cars=8, parked_cars=10, pedestrians=8)):
        boxes = render_clip(replace(cfg, frames=6, width=32, height=16), FeatureConfig(factor=4)).boxes
        for f in range(boxes.shape[1]):
            for i in range(len(boxes)):
                for j in range(i + 1, len(boxes)):
                    assert not _footprints_overlap(boxes[i, f], boxes[j, f]), (cfg.seed, f, i, j)


def test_bad_configs_raise_specific_errors():
    with pytest.raises(SceneConfigError):
        make_scene(SceneConfig(frames=1))
    with pytest.raises(FeatureConfigError):
        render_clip(SceneConfig(width=150, frames=2))
    with pytest.raises(NoiseConfigError):
        NoiseConfig(camera_translation_max=-1.0).validate()
    with pytest.raises(NoiseConfigError):
        NoiseConfig(depth_keep_fraction=1.5).validate()


# ------------------------------------------------------------------------------------------------ corruption knobs

def _many_poses(n=4001, seed=0):
    rng = np.random.default_rng(seed)
    out = np.stack([pose(rot_y(a), t) for a, t in zip(rng.uniform(-1, 1, n), rng.normal(0, 5, (n, 3)))])
    out[0] = np.eye(4)
    return out


def test_zero_noise_priors_equal_ground_truth(gt):
    p = corrupt(gt, NoiseConfig(seed=5))
    np.testing.assert_array_equal(p.world_from_camera, gt.world_from_camera)
    np.testing.assert_array_equal(p.depth[gt.depth_valid], gt.depth[gt.depth_valid])
    assert np.all(p.depth[~gt.depth_valid] == 0)
    np.testing.assert_array_equal(p.boxes, gt.boxes)
    np.testing.assert_array_equal(p.valid, gt.visible)
    np.testing.assert_array_equal(p.track_ids, gt.agent_ids)
    np.testing.assert_array_equal(p.instance, gt.instance)
    np.testing.assert_array_equal(p.features, gt.features)


@pytest.mark.parametrize("bound", [0.25, 0.5, 1.0])
def test_camera_translation_noise_bound_and_distribution(bound):
    poses = _many_poses()
    noisy = noisy_camera_poses(poses, NoiseConfig(seed=3, camera_translation_max=bound))
    np.testing.assert_array_equal(noisy[0], poses[0])  # frame 0 = world origin, exact
    np.testing.assert_array_equal(noisy[:, :3, :3], poses[:, :3, :3])  # rotations untouched
    delta = noisy[1:, :3, 3] - poses[1:, :3, 3]
    mag = np.linalg.norm(delta, axis=1)
    assert mag.max() <= bound + 1e-12
    assert abs(mag.mean() - bound / 2) < 0.03 * bound  # U[0, M]: mean M/2
    assert abs(np.mean(mag < bound / 4) - 0.25) < 0.03  # uniform magnitude
    assert mag.max() > 0.98 * bound
    dirs = delta / mag[:, None]
    assert np.linalg.norm(dirs.mean(0)) < 0.05  # isotropic directions
    np.testing.assert_allclose(np.mean(dirs ** 2, axis=0), 1 / 3, atol=0.03)


def test_camera_rotation_noise_bound(gt):
    poses = _many_poses()
    noisy = noisy_camera_poses(poses, NoiseConfig(seed=4, camera_rotation_max_deg=2.0))
    ang = np.rad2deg(rotation_angle(poses[1:, :3, :3].transpose(0, 2, 1) @ noisy[1:, :3, :3]))
    assert ang.max() <= 2.0 + 1e-9 and abs(ang.mean() - 1.0) < 0.05
    np.testing.assert_array_equal(noisy[:, :3, 3], poses[:, :3, 3])
    np.testing.assert_allclose(noisy[:, :3, :3] @ noisy[:, :3, :3].transpose(0, 2, 1), np.eye(3)[None].repeat(len(poses), 0),
                               atol=1e-12)
    # through the full corrupt() on a real clip
    p = corrupt(gt, NoiseConfig(seed=4, camera_translation_max=0.5, camera_rotation_max_deg=1.0))
    dt = np.linalg.norm(p.world_from_camera[:, :3, 3] - gt.world_from_camera[:, :3, 3], axis=1)
    assert dt[0] == 0 and np.all(dt[1:] <= 0.5) and np.all(dt[1:] > 0)
    rel = gt.world_from_camera[:, :3, :3].transpose(0, 2, 1) @ p.world_from_camera[:, :3, :3]
    assert np.rad2deg(rotation_angle(rel)).max() <= 1.0 + 1e-9


def test_agent_pose_noise_bounds():
    rng = np.random.default_rng(0)
    boxes = np.concatenate([rng.normal(0, 10, (50, 80, 3)), np.full((50, 80, 3), 2.0), rng.uniform(-3, 3, (50, 80, 1))],
                           -1)
    valid = rng.random((50, 80)) < 0.7
    noisy = noisy_boxes(boxes, valid, NoiseConfig(seed=2, agent_translation_max=0.4, agent_yaw_max_deg=6.0))
    d = np.linalg.norm(noisy[..., :3] - boxes[..., :3], axis=-1)
    assert d[valid].max() <= 0.4 + 1e-12 and abs(d[valid].mean() - 0.2) < 0.01
    assert np.all(d[~valid] == 0)
    dyaw = np.rad2deg(noisy[..., 6] - boxes[..., 6])
    assert np.abs(dyaw[valid]).max() <= 6.0 + 1e-9
    assert abs(dyaw[valid].std() - 6.0 / np.sqrt(3)) < 0.15 and abs(dyaw[valid].mean()) < 0.15
    np.testing.assert_array_equal(noisy[..., 3:6], boxes[..., 3:6])


def test_boxes_follow_cameras_keep_their_place_in_each_view(gt):
    """A box lifted through a noisy camera is seen from that camera where the true camera sees the true box."""
    cfg = NoiseConfig(seed=6, camera_translation_max=1.0, missed=1, false=1, boxes_follow_cameras=True)
    p, exact = corrupt(gt, cfg), corrupt(gt, replace(cfg, boxes_follow_cameras=False))
    np.testing.assert_array_equal(p.world_from_camera, exact.world_from_camera)
    np.testing.assert_array_equal(p.valid, exact.valid)
    moved = np.linalg.norm(p.boxes[..., :3] - exact.boxes[..., :3], axis=-1)  # [K, T]
    error = np.linalg.norm(p.world_from_camera[:, :3, 3] - gt.world_from_camera[:, :3, 3], axis=1)  # [T]
    np.testing.assert_allclose(moved[p.valid], np.broadcast_to(error, moved.shape)[p.valid], atol=1e-9)
    assert np.all(moved[~p.valid] == 0) and error[1:].min() > 0
    np.testing.assert_allclose(p.boxes[..., 6], exact.boxes[..., 6], atol=1e-12)  # translation noise: same yaw
    # with rotation noise too: the camera-frame pose of every valid entry is the true one (false agents included)
    cams = noisy_camera_poses(gt.world_from_camera, NoiseConfig(seed=6, camera_translation_max=0.5,
                                                                camera_rotation_max_deg=3.0))
    rng = np.random.default_rng(1)
    t = len(cams)
    boxes = np.concatenate([rng.normal(0, 10, (4, t, 3)), np.full((4, t, 3), 2.0), rng.uniform(-3, 3, (4, t, 1))], -1)
    valid = rng.random((4, t)) < 0.8
    lifted = boxes_through_cameras(boxes, valid, gt.world_from_camera, cams)
    for k, i in zip(*np.nonzero(valid)):
        seen = np.linalg.inv(cams[i]) @ box_world_pose(lifted[k, i])
        truth = np.linalg.inv(gt.world_from_camera[i]) @ box_world_pose(boxes[k, i])
        np.testing.assert_allclose(seen[:3, 3], truth[:3, 3], atol=1e-9)  # the centre exactly
        heading = np.rad2deg(rotation_angle(seen[:3, :3].T @ truth[:3, :3]))
        assert heading <= 3.0 + 1e-6  # yaw-only boxes keep the rotation about y; the tilt (<= 3 deg) is lost
    np.testing.assert_array_equal(lifted[~valid], boxes[~valid])


def test_missed_agents_are_the_documented_ones(gt):
    order = missed_order(gt)
    assert gt.agent_names[order[0]] == "moving_car"
    moving = [k for k, n in enumerate(gt.agent_names) if n == "moving_car" and gt.pixel_count[k].sum() > 0]
    assert order[0] == max(moving, key=lambda k: gt.pixel_count[k].sum())
    for k in (1, 2, 4):
        p = corrupt(gt, NoiseConfig(missed=k))
        dropped = [int(gt.agent_ids[i]) for i in order[:k]]
        assert p.missed_ids == dropped and len(p.track_ids) == len(gt.agent_ids) - k
        assert not set(dropped) & set(p.track_ids.tolist())
        assert not np.isin(p.instance, dropped).any()
        assert np.isin(gt.instance, dropped).any()
    with pytest.raises(NoiseConfigError):
        corrupt(gt, NoiseConfig(missed=len(gt.agent_ids) + 1))


def test_false_agents_added_in_free_space(gt):
    p = corrupt(gt, NoiseConfig(seed=9, false=3))
    assert len(p.false_ids) == 3 and len(p.track_ids) == len(gt.agent_ids) + 3
    false = np.isin(p.track_ids, p.false_ids)
    assert np.all(p.gt_index[false] == -1)
    assert [c for c, f in zip(p.track_classes, false) if f] == ["rigid", "non-rigid", "rigid"]
    for j in np.nonzero(false)[0]:
        box = p.boxes[j, 0]
        assert p.valid[j].any() and np.all(p.boxes[j] == box)  # static, seen in some frames
        assert 0.5 < box[3] < 5.0 and 0.4 < box[4] < 2.0 and 1.3 < box[5] < 2.0
        # no overlap with any real agent at any frame (separating-axis test on the bird's-eye footprints)
        for k in range(len(gt.agent_ids)):
            for f in range(len(gt.timestamps_us)):
                assert not _footprints_overlap(box, gt.boxes[k, f])
        # its silhouette is exactly where its box, ray-cast independently, is in front of the real scene
        sil = p.instance == p.track_ids[j]
        assert sil.any() and np.all(p.valid[j] == sil.any((1, 2)))
        f = int(np.argmax(sil.sum((1, 2))))
        w = gt.world_from_camera[f]
        one = BoxSet(box_world_pose(box)[None], 0.5 * box[[3, 5, 4]][None], np.array([MAT_PAINT]), np.ones((1, 3)),
                     np.array([SEM["car"]]), np.array([1]))
        t, _, _, _, _ = intersect_boxes_dense(w[:3, 3], pixel_rays(gt.K, 128, 64) @ w[:3, :3].T, one)
        expected = t.reshape(64, 128) < gt.depth[f]
        others = np.isin(p.instance[f], [i for i in p.false_ids if i != p.track_ids[j]])  # another false box
        np.testing.assert_array_equal(sil[f], expected & ~others)
        assert not np.isin(gt.instance[f][sil[f]], gt.agent_ids).all()  # it covers background, not only agents


def _footprints_overlap(a: np.ndarray, b: np.ndarray) -> bool:
    def corners(box):
        r = rot_y(box[6])
        local = np.array([[sx * box[3] / 2, 0, sz * box[4] / 2] for sx, sz in ((-1, -1), (-1, 1), (1, 1), (1, -1))])
        return (local @ r.T + box[:3])[:, [0, 2]]

    ca, cb = corners(a), corners(b)
    for poly in (ca, cb):
        for i in range(4):
            edge = poly[(i + 1) % 4] - poly[i]
            axis = np.array([-edge[1], edge[0]])
            pa, pb = ca @ axis, cb @ axis
            if pa.max() < pb.min() or pb.max() < pa.min():
                return False
    return True


def test_depth_noise_and_sparsification(gt):
    p = corrupt(gt, NoiseConfig(seed=1, depth_rel_sigma=0.1))
    v = gt.depth_valid
    rel = p.depth[v] / gt.depth[v] - 1.0
    assert abs(rel.std() - 0.1) < 0.005 and abs(rel.mean()) < 0.005
    assert np.all(p.depth[~v] == 0)
    q = corrupt(gt, NoiseConfig(seed=1, depth_keep_fraction=0.3))
    for i in range(len(gt.depth)):
        assert (q.depth[i] > 0).sum() == int(round(0.3 * v[i].sum()))
    kept = q.depth > 0
    np.testing.assert_array_equal(q.depth[kept], gt.depth[kept])  # sparsification alone adds no noise
    # kept pixels are spread uniformly: kept fraction in the top and bottom halves of the valid pixels agree
    top = kept[:, : kept.shape[1] // 2].sum() / v[:, : v.shape[1] // 2].sum()
    bottom = kept[:, kept.shape[1] // 2:].sum() / v[:, v.shape[1] // 2:].sum()
    assert abs(top - 0.3) < 0.03 and abs(bottom - 0.3) < 0.03


def test_feature_noise_std_and_feature_semantics(gt):
    p = corrupt(gt, NoiseConfig(seed=1, feature_sigma=0.2))
    diff = p.features - gt.features
    assert abs(diff.std() - 0.2) < 0.004 and abs(diff.mean()) < 0.004
    emb = class_embeddings(FeatureConfig())
    assert sorted(emb.C_bg + emb.C_ag) == list(range(64)) and len(emb.C_ag) == 16
    np.testing.assert_allclose(np.linalg.norm(emb.vectors, axis=1), 1.0)
    # pure cells (one class over the whole 4x4 block) classify to the right prototype; agents light up M_ag
    t, h, w = gt.features.shape[:3]
    blocks = gt.semantic.reshape(t, h, 4, w, 4)
    pure = (blocks == blocks[:, :, :1, :, :1]).all((2, 4))
    cls = blocks[:, :, 0, :, 0]
    expected = np.where(cls == SEM["car"], 1, np.where(cls == SEM["pedestrian"], 2, 0))
    pred = classify(gt.features, emb)
    assert np.all(pred[pure] == expected[pure]) and (expected[pure] == 1).sum() > 10
    m_bg, m_ag = attention_maps(gt.features, emb)
    agent = pure & (expected > 0)
    back = pure & (expected == 0)
    assert m_ag[agent].min() > m_ag[back].max() and m_bg[back].min() > m_bg[agent].max()


# ------------------------------------------------------------------------------------------------ command + bundle

def test_command_writes_bundle_and_gt_that_load_back(tmp_path):
    from agg.cli import main
    from agg.io.bundle import SceneBundle

    out = tmp_path / "synth"
    argv = ["synth", "--seed", "3", "--frames", "8", "--width", "96", "--height", "64", "--noise-translation", "0.5",
            "--missed", "1", "--false", "1", "--depth-noise", "0.05", "--feature-noise", "0.1", "-o", str(out)]
    assert main(argv) == 0
    b = SceneBundle.load(out)
    assert (len(b), b.width, b.height) == (8, 96, 64) and b.metric and b.scale == 1.0
    assert b.gt is not None and b.gt.kind == "gt"
    gt_poses, prior_poses = b.gt.world_from_camera, b.world_from_camera
    np.testing.assert_array_equal(prior_poses[0], np.eye(4))
    dt = np.linalg.norm(prior_poses[:, :3, 3] - gt_poses[:, :3, 3], axis=1)
    assert np.all(dt[1:] <= 0.5) and np.all(dt[1:] > 0)
    # the gt sidecar matches an in-memory regeneration
    ref, pri = generate(SceneConfig(seed=3, frames=8, width=96, height=64),
                        NoiseConfig(seed=3, camera_translation_max=0.5, missed=1, false=1, depth_rel_sigma=0.05,
                                    feature_sigma=0.1))
    np.testing.assert_array_equal(gt_poses, ref.world_from_camera)
    np.testing.assert_array_equal(b.frames.raw[:], np.rint(ref.rgb * 255).astype(np.uint8))
    np.testing.assert_allclose(b.gt.dense_depth[:], np.where(ref.depth_valid, ref.depth, 0))
    gtr, prt = b.gt.tracklets, b.tracklets
    assert len(gtr.classes) == len(ref.agent_ids) and len(prt.classes) == len(ref.agent_ids)  # -1 missed +1 false
    meta = b.meta["synth"]
    assert meta["missed_ids"] == pri.missed_ids and meta["false_ids"] == pri.false_ids
    assert not set(meta["missed_ids"]) & set(prt.ids.tolist()) and set(meta["false_ids"]) <= set(prt.ids.tolist())
    assert b.semantics.features.shape == (8, 16, 24, 64) and set(b.semantics.prototypes) == {"rigid", "non-rigid",
                                                                                              "background"}
    ex = load_gt_extras(out)
    np.testing.assert_array_equal(ex["instance"], ref.instance)
    np.testing.assert_array_equal(ex["world_from_agent"], ref.world_from_agent)
    np.testing.assert_array_equal(b.dynamic_masks[:], (pri.instance > 0).astype(np.uint8))
    assert ex["index"]["missed_ids"] == pri.missed_ids
    # an existing bundle is not overwritten without --overwrite
    assert main(argv) == 2
    assert main(argv + ["--overwrite", "--depth-format", "sparse"]) == 0
    assert SceneBundle.load(out).has("depth_sparse")
    # --boxes-follow-cameras: the same priors with each box lifted through its frame's noisy camera
    assert main(argv + ["--overwrite", "--boxes-follow-cameras"]) == 0
    lifted = SceneBundle.load(out)
    assert lifted.meta["synth"]["noise"]["boxes_follow_cameras"] is True
    np.testing.assert_array_equal(lifted.world_from_camera, prior_poses)
    np.testing.assert_allclose(lifted.tracklets.boxes, boxes_through_cameras(prt.boxes, prt.valid, gt_poses,
                                                                             prior_poses), equal_nan=True)
