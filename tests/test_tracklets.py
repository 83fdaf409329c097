"""Agent tracklets (agg/priors/tracklets.py): synthetic clips with exact ground truth and constructed scenes."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from agg.eval.scores import tracklet_scores
from agg.priors.kalman import TrackHistory, relink, smooth_sequence
from agg.priors.tracklet_ground import camera_height, ground_planes
from agg.priors.tracklet_paths import stray_detections
from agg.priors.tracklets import TrackConfig, TrackletInputError, fill_gaps, track_agents
from agg.synth.corrupt import NoiseConfig, corrupt
from agg.synth.scene import SceneConfig
from agg.synth.suite import render_clip


@pytest.fixture(scope="module")
def clip():
    """Seed 0, 20 frames at 160x96: 3 moving cars and 3 pedestrians (one of them only a few pixels tall)."""
    gt = render_clip(SceneConfig(seed=0, frames=20, width=160, height=96))
    moving = np.nonzero(gt.agent_moving)[0]
    masks = np.isin(gt.instance, gt.agent_ids[moving])  # [T, H, W] GT moving-agent masks
    depth = np.where(gt.depth_valid, gt.depth, 0.0).astype(np.float32)  # [T, H, W], 0 = none (sky)
    return gt, moving, masks, depth


def _gt_centres(gt, agents):
    return np.where(gt.visible[agents][..., None], gt.boxes[agents][..., :3], np.nan)  # [G, T, 3]


def _pred_centres(res):
    tr = res.tracklets
    return np.where(tr.valid[..., None], tr.boxes[..., :3], np.nan)  # [K, T, 3]


def _track_of(res, gt, agent, frame):
    """The track id (instance value) covering most pixels of a GT agent in a frame, 0 if none."""
    vals = res.instance_masks[frame][gt.instance[frame] == gt.agent_ids[agent]]
    vals = vals[vals > 0]
    return int(np.bincount(vals).argmax()) if len(vals) else 0


def test_synthetic_moving_agents_get_stable_tracks(clip):
    gt, moving, masks, depth = clip
    res = track_agents(masks, depth, gt.K, gt.world_from_camera, frames=(gt.rgb * 255).astype(np.uint8))
    tr = res.tracklets
    k, t = len(tr.ids), masks.shape[0]
    assert tr.boxes.shape == (k, t, 7) and tr.valid.shape == (k, t) and tr.confidence.shape == (k, t)
    assert res.boxes2d.shape == (k, t, 4) and res.centres2d.shape == (k, t, 2)
    assert res.instance_masks.shape == masks.shape and res.instance_masks.dtype == np.int32
    assert list(tr.ids) == list(range(1, k + 1)) and len(res.detections) == t
    assert np.isnan(tr.boxes[~tr.valid]).all() and np.isfinite(tr.boxes[tr.valid]).all()
    assert np.isnan(res.boxes2d[~tr.valid]).all() and ((tr.confidence >= 0) & (tr.confidence <= 1)).all()
    # instance pixels lie inside the dynamic masks
    assert not np.any((res.instance_masks > 0) & ~masks)
    s = tracklet_scores(_pred_centres(res), _gt_centres(gt, moving), max_dist=1.5)
    assert s.recall >= 0.8 and s.precision >= 0.8, (s.recall, s.precision)
    # every moving car: one track id in every frame it is visible, boxes within 1 m, heading along the road
    for car in moving[:3]:
        ids = {_track_of(res, gt, car, i) for i in range(t) if gt.pixel_count[car, i] >= 30}
        assert len(ids) == 1 and 0 not in ids, (car, ids)
        kk = ids.pop() - 1
        both = tr.valid[kk] & gt.visible[car]
        err = np.linalg.norm(tr.boxes[kk, both, :3] - gt.boxes[car, both, :3], axis=-1)
        assert np.median(err) < 1.0, err
        dyaw = (tr.boxes[kk, both, 6] - gt.boxes[car, both, 6] + np.pi / 2) % np.pi - np.pi / 2
        assert np.abs(np.degrees(dyaw)).max() < 10.0
        assert tr.classes[kk] == "rigid" and (tr.boxes[kk, both, 3] > tr.boxes[kk, both, 4]).all()
    # deterministic
    again = track_agents(masks, depth, gt.K, gt.world_from_camera, frames=(gt.rgb * 255).astype(np.uint8))
    assert np.array_equal(again.tracklets.boxes, tr.boxes, equal_nan=True)


def test_rigid_cars_and_non_rigid_pedestrians(clip):
    gt, moving, masks, depth = clip
    res = track_agents(masks, depth, gt.K, gt.world_from_camera)
    s = tracklet_scores(_pred_centres(res), _gt_centres(gt, moving), max_dist=1.5)
    got = {gt.agent_labels[moving[g]]: [] for _, g in s.matches}
    for p, g in s.matches:
        # a silhouette of a few pixels has no aspect ratio to read: the class is asked of larger ones only
        if np.median(gt.pixel_count[moving[g]]) > 6:
            got[gt.agent_labels[moving[g]]].append(res.tracklets.classes[p])
    assert got["car"] == ["rigid"] * 3
    assert len(got["pedestrian"]) >= 2 and set(got["pedestrian"]) == {"non-rigid"}
    # non-rigid boxes: square footprint, taller than wide
    for k, c in enumerate(res.tracklets.classes):
        b = res.tracklets.boxes[k, res.tracklets.valid[k]]
        if c == "non-rigid":
            assert np.allclose(b[:, 3], b[:, 4]) and np.median(b[:, 5]) > np.median(b[:, 4])


def _hide(gt, masks, car, gap):
    """The masks [T, H, W] with one agent's pixels removed in the frames of ``gap``."""
    occluded = masks.copy()
    for i in gap:
        occluded[i][gt.instance[i] == gt.agent_ids[car]] = False
    return occluded


def _ids_around(res, gt, car, gap):
    return _track_of(res, gt, car, gap[0] - 1), _track_of(res, gt, car, gap[-1] + 1)


def test_two_frame_occlusion_keeps_id(clip):
    gt, moving, masks, depth = clip
    car, gap = moving[0], (8, 9)  # the car ahead in the ego lane
    occluded = _hide(gt, masks, car, gap)
    res = track_agents(occluded, depth, gt.K, gt.world_from_camera)
    before, after = _ids_around(res, gt, car, gap)
    assert before > 0 and before == after
    k = before - 1
    tr = res.tracklets
    assert tr.valid[k, [gap[0] - 1, gap[-1] + 1]].all() and (tr.confidence[k, [gap[0] - 1, gap[-1] + 1]] > 0).all()
    # the hidden frames get boxes from the smoothed track (no detection: confidence 0), and those follow the car
    assert tr.valid[k, list(gap)].all() and (tr.confidence[k, list(gap)] == 0).all()
    assert np.isnan(res.boxes2d[k, list(gap)]).all() and not (res.instance_masks[list(gap)] == before).any()
    err = np.linalg.norm(tr.boxes[k, list(gap), :3] - gt.boxes[car, list(gap), :3], axis=-1)
    seen = np.linalg.norm(tr.boxes[k, [gap[0] - 1, gap[-1] + 1], :3] - gt.boxes[car, [gap[0] - 1, gap[-1] + 1], :3],
                          axis=-1)
    assert err.max() < max(0.5, 1.5 * seen.max()), (err, seen)
    dyaw = (tr.boxes[k, list(gap), 6] - gt.boxes[car, list(gap), 6] + np.pi / 2) % np.pi - np.pi / 2
    assert np.abs(np.degrees(dyaw)).max() < 10.0
    assert np.allclose(tr.boxes[k, list(gap), 3:6], tr.boxes[k, gap[0] - 1, 3:6])  # a rigid track: one size
    unfilled = track_agents(occluded, depth, gt.K, gt.world_from_camera, TrackConfig(fill_max_gap=0)).tracklets
    assert not unfilled.valid[k, list(gap)].any() and np.isnan(unfilled.boxes[k, list(gap)]).all()
    assert np.array_equal(unfilled.boxes[k, ~np.isin(np.arange(len(unfilled.valid[k])), gap)],
                          tr.boxes[k, ~np.isin(np.arange(len(tr.valid[k])), gap)], equal_nan=True)
    assert {_track_of(res, gt, car, i) for i in range(masks.shape[0]) if i not in gap} == {before}
    # control: a tracker that forgets after one missed frame (and never re-links) gives a new id after the gap
    short = track_agents(occluded, depth, gt.K, gt.world_from_camera, TrackConfig(max_missed=1, relink_max_gap=0))
    assert len(set(_ids_around(short, gt, car, gap))) == 2


def test_track_lost_longer_than_max_missed_is_relinked(clip):
    gt, moving, masks, depth = clip
    car, gap = moving[0], range(7, 12)  # 5 frames: longer than max_missed = 3, the filter's track ends
    occluded = _hide(gt, masks, car, gap)
    res = track_agents(occluded, depth, gt.K, gt.world_from_camera)
    before, after = _ids_around(res, gt, car, gap)
    assert before > 0 and before == after
    filled = res.tracklets.valid[before - 1, list(gap)], res.tracklets.confidence[before - 1, list(gap)]
    assert filled[0].all() and (filled[1] == 0).all()
    short = track_agents(occluded, depth, gt.K, gt.world_from_camera, TrackConfig(fill_max_gap=4)).tracklets
    assert not short.valid[before - 1, list(gap)].any()  # 5 frames: longer than the gaps it fills
    # the other moving cars are not joined to it, and without re-linking the car gets a new id after the gap
    assert all(_track_of(res, gt, c, 15) != before for c in moving[1:3])
    plain = track_agents(occluded, depth, gt.K, gt.world_from_camera, TrackConfig(relink_max_gap=0))
    assert len(set(_ids_around(plain, gt, car, gap))) == 2


def test_stray_detections_are_the_ones_off_the_tracks_image_path():
    frames = np.arange(12)
    centres = np.stack([300.0 + 40.0 * frames, 200.0 + 5.0 * frames], 1)  # [12, 2] fast, steady motion
    sizes = np.tile([150.0, 160.0], (12, 1))  # [12, 2]
    areas = np.full(12, 20000.0)
    cfg = TrackConfig()
    assert not stray_detections(frames, centres, sizes, areas, cfg).any()  # the ends too (one-sided windows)
    centres[4, 0] += 90.0  # 0.6 widths to the side: a blob beside the agent
    areas[8] = 3000.0  # a small blob taken instead of the agent
    assert np.nonzero(stray_detections(frames, centres, sizes, areas, cfg))[0].tolist() == [4, 8]
    centres[4, 0] -= 30.0  # 0.4 widths: kept
    assert np.nonzero(stray_detections(frames, centres, sizes, areas, cfg))[0].tolist() == [8]
    assert not stray_detections(frames, centres, sizes, areas, TrackConfig(stray_window=0)).any()
    # a detection with no other within the window is not judged
    assert not stray_detections(np.array([0, 5, 10]), centres[:3], sizes[:3], areas[:3] * [1, 0.01, 1], cfg).any()
    # with one other, only by its area (each of two centroids is as far off the other)
    two = np.array([0, 2])
    assert stray_detections(two, centres[:2], sizes[:2], areas[:2] * [0.1, 1], cfg).tolist() == [True, False]
    assert not stray_detections(two, centres[:2] + [[0, 0], [400, 0]], sizes[:2], areas[:2], cfg).any()


def test_a_blob_beside_a_hidden_car_is_not_taken_as_the_car(clip):
    gt, moving, masks, depth = clip
    car, f = moving[0], 10  # the car ahead: in frame 10 its mask is gone and a road blob lies beside it
    own = gt.instance[f] == gt.agent_ids[car]
    rows, cols = np.nonzero(own)
    blob = np.zeros_like(own)
    blob[rows.max() - 2:rows.max() + 2, cols.min() - 6:cols.min() - 1] = True
    m = masks.copy()
    m[f] = (m[f] & ~own) | blob
    res = track_agents(m, depth, gt.K, gt.world_from_camera)
    k = _track_of(res, gt, car, f - 1) - 1
    tr = res.tracklets
    assert k >= 0 and _track_of(res, gt, car, f + 1) == k + 1
    # frame 10 is filled from the track (confidence 0, no 2D box, no instance pixels) and the box follows the car
    assert tr.valid[k, f] and tr.confidence[k, f] == 0 and np.isnan(res.boxes2d[k, f]).all()
    assert not (res.instance_masks[f][blob] == k + 1).any()
    assert np.linalg.norm(tr.boxes[k, f, :3] - gt.boxes[car, f, :3]) < 1.0
    # control: without the check the track takes the blob
    taken = track_agents(m, depth, gt.K, gt.world_from_camera, TrackConfig(stray_window=0))
    assert taken.tracklets.confidence[k, f] > 0 and (taken.instance_masks[f][blob] == k + 1).all()
    # on the clean masks the check drops nothing
    clean = track_agents(masks, depth, gt.K, gt.world_from_camera)
    unchecked = track_agents(masks, depth, gt.K, gt.world_from_camera, TrackConfig(stray_window=0))
    assert np.array_equal(clean.tracklets.boxes, unchecked.tracklets.boxes, equal_nan=True)


def _blob_at(shape, rows, cols):
    blob = np.zeros(shape, bool)
    blob[max(rows[0], 0):rows[1], max(cols[0], 0):cols[1]] = True
    return blob


def test_a_lost_car_is_not_relinked_to_a_blob_far_off_in_the_image(clip):
    gt, moving, masks, depth = clip
    car = moving[0]
    m = _hide(gt, masks, car, range(7, masks.shape[0]))  # the car ahead is lost from frame 7 on
    blobs = {}
    for f in range(12, 15):  # a car-sized blob on the road 50 px (a third of the image) to its left
        rows, cols = np.nonzero(gt.instance[f] == gt.agent_ids[car])
        blobs[f] = _blob_at(m[f].shape, (rows.max() - 6, rows.max()), (cols.min() - 50, cols.min() - 38))
        m[f] |= blobs[f]
    res = track_agents(m, depth, gt.K, gt.world_from_camera)
    k = _track_of(res, gt, car, 6)
    # the 3D gate of a track lost for 5 frames is wide; in the image the blob is nowhere near where the car went
    assert k > 0 and np.nonzero(res.tracklets.valid[k - 1])[0].tolist() == list(range(7))
    assert not any((res.instance_masks[f][b] == k).any() for f, b in blobs.items())
    # control: without the image gate the track takes the blob, and its boxes sweep across the image to it
    joined = track_agents(m, depth, gt.K, gt.world_from_camera, TrackConfig(gate_box_margin=-1))
    assert all((joined.instance_masks[f][b] == k).all() for f, b in blobs.items())


def _history(steps, t=12):
    """A track measured at ``steps`` on x = step (1 unit per frame), RTS-smoothed."""
    z = np.full((t, 3), np.nan)
    z[steps] = np.stack([np.asarray(steps, float), np.zeros(len(steps)), np.full(len(steps), 10.0)], 1)
    state, cov = smooth_sequence(z, np.repeat(0.01 * np.eye(3)[None], t, 0), accel_var=1e-3, init_vel_var=1.0)
    assoc = np.full(t, -1)
    assoc[steps] = 0
    return TrackHistory(assoc=assoc, state=state, cov=cov, hits=len(steps))


def test_relink_joins_where_the_motion_predicts_and_the_extra_gate_agrees():
    a, b = _history([0, 1, 2, 3, 4]), _history([9, 10, 11])  # lost for 4 frames, found where it would be
    empty = TrackHistory(assoc=np.full(12, -1), state=np.full((12, 6), np.nan), cov=np.full((12, 6, 6), np.nan),
                         hits=0)  # a track whose every detection was a stray
    joined = relink([a, empty, b], max_gap=8, gate=16.27, accel_var=1e-3)
    assert len(joined) == 2 and joined[0].hits == 8 and joined[1].hits == 0
    assert np.flatnonzero(joined[0].assoc >= 0).tolist() == [0, 1, 2, 3, 4, 9, 10, 11]
    seen = []

    def refuse(step, x):  # the image gate's signature: (step, predicted position [3]) -> [N] bool
        seen.append((step, x.copy()))
        return np.zeros(1, bool)

    assert len(relink([a, b], max_gap=8, gate=16.27, accel_var=1e-3, extra_gate=refuse)) == 2
    assert seen[0][0] == 9 and abs(seen[0][1][0] - 9.0) < 0.1  # asked at B's first step, for A's prediction
    assert len(relink([a, b], max_gap=8, gate=16.27, accel_var=1e-3,
                      extra_gate=lambda step, x: np.ones(1, bool))) == 1
    assert len(relink([a, b], max_gap=3, gate=16.27, accel_var=1e-3)) == 2  # a gap of 5 is longer than allowed


def test_a_track_that_starts_on_a_stray_is_relinked_to_the_car(clip):
    gt, moving, masks, depth = clip
    car, gap, f = moving[0], range(7, 12), 12
    m = _hide(gt, masks, car, gap)
    own = gt.instance[f] == gt.agent_ids[car]  # after the gap the car's mask is missing one more frame, and a
    rows, cols = np.nonzero(own)               # small road blob beside it starts the track that goes on with it
    blob = _blob_at(own.shape, (rows.max() - 2, rows.max() + 2), (cols.max() + 4, cols.max() + 10))
    m[f] = (m[f] & ~own) | blob
    res = track_agents(m, depth, gt.K, gt.world_from_camera)
    before, after = _ids_around(res, gt, car, range(7, 13))
    assert before > 0 and before == after and not (res.instance_masks[f][blob] > 0).any()
    # control: the blob-led track is refused by the image gate, and without the stray check it stays a new id
    plain = track_agents(m, depth, gt.K, gt.world_from_camera, TrackConfig(stray_window=0))
    assert len(set(_ids_around(plain, gt, car, range(7, 13)))) == 2


def test_fill_gaps_interpolates_boxes_inside_a_track_only():
    t = 12
    boxes = np.full((t, 7), np.nan)
    valid = np.zeros(t, bool)
    for i in (1, 2, 6, 8, 11):  # gaps of 3 frames (3-5), 1 frame (7) and 2 frames (9-10)
        boxes[i] = (i, 0.0, 2.0 * i, 4.5, 1.8, 1.5, np.pi - 0.05 if i < 7 else -np.pi + 0.05)
        valid[i] = True
    b = boxes.copy()
    filled = fill_gaps(b, valid, None, max_gap=2)
    assert filled.tolist() == [7, 9, 10]  # the 3-frame gap is longer than max_gap; nothing before or after
    assert np.isnan(b[[0, 3, 4, 5]]).all() and np.array_equal(b[valid], boxes[valid])
    assert np.allclose(b[[9, 10], :3], [[9, 0, 18], [10, 0, 20]]) and np.allclose(b[filled, 3:6], [4.5, 1.8, 1.5])
    # the yaw goes the short way round through pi (not through 0)
    assert np.allclose(np.cos(b[7, 6]), -1.0) and np.allclose(b[[9, 10], 6], -np.pi + 0.05)
    # with a smoothed track, its centres are taken where it has them
    centres = np.full((t, 3), np.nan)
    centres[7] = (7.2, 0.1, 13.9)
    b2 = boxes.copy()
    fill_gaps(b2, valid, centres, max_gap=2)
    assert np.allclose(b2[7, :3], (7.2, 0.1, 13.9)) and np.allclose(b2[9, :3], (9, 0, 18))
    assert fill_gaps(boxes.copy(), valid, None, max_gap=0).size == 0


def test_cars_tracked_with_noisy_depth_and_poses(clip):
    gt, moving, masks, _ = clip
    pr = corrupt(gt, NoiseConfig(seed=0, depth_rel_sigma=0.1, depth_keep_fraction=0.5, camera_translation_max=0.25))
    res = track_agents(masks, pr.depth, gt.K, pr.world_from_camera)
    cars = moving[:3]
    s = tracklet_scores(_pred_centres(res), _gt_centres(gt, cars), max_dist=2.0)
    assert s.recall == 1.0


def _crossing_scene(t: int = 30, w: int = 120, h: int = 80):
    """Static camera; a near box (z = 10, red) drives right and a far box (z = 20, blue) drives left behind it.

    Returns masks, depth, rgb, K, poses and the per-frame pixel masks of each box."""
    K = np.array([[100.0, 0, (w - 1) / 2], [0, 100.0, (h - 1) / 2], [0, 0, 1]])
    rows, cols = np.mgrid[0:h, 0:w]
    depth = np.zeros((t, h, w), np.float32)
    rgb = np.zeros((t, h, w, 3), np.uint8)
    own = np.zeros((2, t, h, w), bool)
    for i in range(t):
        boxes = [(20.0, 6.0 - 0.4 * i, (30, 30, 200)), (10.0, -3.0 + 0.2 * i, (200, 30, 30))]  # (z, x, colour)
        for a, (z, x, colour) in enumerate(boxes):
            u0, u1 = K[0, 0] * (x - 0.9) / z + K[0, 2], K[0, 0] * (x + 0.9) / z + K[0, 2]  # 1.8 m wide
            v0, v1 = K[1, 1] * (0.0 - 0.75) / z + K[1, 2], K[1, 1] * (0.0 + 0.75) / z + K[1, 2]  # 1.5 m tall
            box = (cols >= u0) & (cols < u1) & (rows >= v0) & (rows < v1)
            depth[i][box] = z  # the far box is drawn first, the near one over it
            rgb[i][box] = colour
            own[:, i][:, box] = False
            own[a, i][box] = True
    return depth > 0, depth, rgb, K, np.repeat(np.eye(4)[None], t, 0), own


def test_crossing_agents_keep_distinct_ids():
    masks, depth, rgb, K, poses, own = _crossing_scene()
    # the two boxes form one connected component while they overlap
    from cv2 import connectedComponents

    assert min(connectedComponents(m.astype(np.uint8))[0] - 1 for m in masks) == 1
    res = track_agents(masks, depth, K, poses, frames=rgb)
    assert len(res.tracklets.ids) == 2
    for a in range(2):
        ids = set()
        for i in range(masks.shape[0]):
            vals = res.instance_masks[i][own[a, i]]
            if own[a, i].sum() >= 6:
                ids.add(int(np.bincount(vals).argmax()))
        assert len(ids) == 1 and 0 not in ids, (a, ids)
    # each track moves in its own direction along world x at its own depth
    for k in range(2):
        b = res.tracklets.boxes[k, res.tracklets.valid[k]]
        direction = np.sign(b[-1, 0] - b[0, 0])
        far = np.median(b[:, 2]) > 15
        assert direction == (-1 if far else 1)


def test_empty_masks_and_no_depth_give_no_tracks(clip):
    gt, _, masks, depth = clip
    res = track_agents(np.zeros_like(masks), depth, gt.K, gt.world_from_camera)
    assert res.tracklets.boxes.shape == (0, masks.shape[0], 7) and res.tracklets.valid.shape == (0, masks.shape[0])
    assert res.tracklets.classes == [] and not res.instance_masks.any()
    assert all(len(d) == 0 for d in res.detections)
    nodepth = track_agents(masks, np.zeros_like(depth), gt.K, gt.world_from_camera)
    assert len(nodepth.tracklets.ids) == 0 and any(len(d) for d in nodepth.detections)
    assert all(np.isnan(d.centre_world).all() for ds in nodepth.detections for d in ds)
    # a blank frame in the middle (with RGB frames for the appearance cue): nothing is detected there, and the
    # tracks through it are filled from their smoothed paths (confidence 0)
    blank = masks.copy()
    blank[5] = False
    res = track_agents(blank, depth, gt.K, gt.world_from_camera, frames=(gt.rgb * 255).astype(np.uint8))
    tr = res.tracklets
    assert len(tr.ids) > 0 and tr.valid[:, 6].any() and not (res.instance_masks[5] > 0).any()
    through = tr.valid[:, 4] & tr.valid[:, 6]
    assert through.any() and np.array_equal(tr.valid[:, 5], through) and (tr.confidence[:, 5] == 0).all()


def test_bad_inputs_raise_clear_errors(clip):
    gt, _, masks, depth = clip
    P, K = gt.world_from_camera, gt.K
    bad = [
        dict(masks=masks[0]),
        dict(depth=depth[:, :-1]),
        dict(K=np.eye(2)),
        dict(K=np.diag([0.0, 1.0, 1.0])),
        dict(world_from_camera=P[:-1]),
        dict(world_from_camera=np.where(np.eye(4, dtype=bool), np.nan, P)),
        dict(frames=np.zeros((3, 4, 5, 3), np.uint8)),
        dict(depth_confidence=np.ones((2, 2, 2))),
        dict(config=TrackConfig(max_missed=-1)),
        dict(config=TrackConfig(gate_probability=1.0)),
        dict(config=TrackConfig(contact_ratio=1.0)),
        dict(config=TrackConfig(min_track_fraction=1.5)),
    ]
    for override in bad:
        args = dict(masks=masks, depth=depth, K=K, world_from_camera=P) | override
        with pytest.raises(TrackletInputError):
            track_agents(**args)
    assert issubclass(TrackletInputError, ValueError)


def test_result_writes_to_a_bundle(clip, tmp_path):
    from agg.io.bundle import SceneBundle

    gt, _, masks, depth = clip
    res = track_agents(masks, depth, gt.K, gt.world_from_camera)
    b = SceneBundle.create(tmp_path / "scene", (gt.rgb * 255).astype(np.uint8), gt.timestamps_us, gt.K)
    b.write_tracklets(res.tracklets)
    back = SceneBundle.load(tmp_path / "scene").tracklets
    assert list(back.ids) == list(res.tracklets.ids) and back.classes == res.tracklets.classes
    assert np.array_equal(np.asarray(back.valid), res.tracklets.valid)
    assert res.tracklets.anchor == back.anchor == "camera"  # lifted through world_from_camera (TrainConfig.agent_anchor)


# --------------------------------------------------------------------------------------------------------------
# ground rule, neck cut, merge across a gap, track confirmation


def test_road_plane_gives_the_camera_height(clip):
    gt, _, masks, depth = clip
    planes = ground_planes(depth, None, masks, 0.5)
    heights = [camera_height(p, gt.K[1, 1]) for p in planes]
    assert np.allclose(heights, 1.6, rtol=0.05), heights  # SceneConfig.camera_height


def test_static_blob_above_the_horizon_is_not_tracked(clip):
    gt, moving, masks, depth = clip
    blob = np.zeros_like(masks)
    blob[:, 20:32, 10:22] = True  # a building facade above the horizon (row ~47) in every frame
    assert (gt.semantic[:, 20:32, 10:22] == 4).all()
    res = track_agents(masks | blob, depth, gt.K, gt.world_from_camera)
    assert not res.instance_masks[blob].any()
    on_blob = [d for ds in res.detections for d in ds if d.bbox[1] == 20 and d.bbox[0] == 10]
    assert len(on_blob) == masks.shape[0] and all(d.on_ground is False for d in on_blob)
    s = tracklet_scores(_pred_centres(res), _gt_centres(gt, moving), max_dist=1.5)
    assert s.recall >= 0.8 and s.precision >= 0.8, (s.recall, s.precision)
    # control: without the ground rule the static blob (it has depth) becomes a track
    off = track_agents(masks | blob, depth, gt.K, gt.world_from_camera, TrackConfig(ground_rule=False))
    assert off.instance_masks[blob].any()


def _road_scene(t: int = 12, w: int = 120, h: int = 80, gap_depth: float | None = None, neck: bool = False,
                marking: bool = False, flicker: bool = False):
    """Static camera 1.5 m over a flat road (fy = 100); two 1.8 x 1.5 m boxes side by side at the same depth
    (z = 10 + 0.2 i) with a 0.2 m gap. gap_depth: a pole in the gap at that depth (not in the mask); neck: a
    2-px strip of mask on the road joins the boxes; marking: a mask blob on the road near the camera in every
    frame; flicker: a third box (x = -5 m) in 3 frames only. Returns masks, depth, K, poses, the box masks."""
    K = np.array([[100.0, 0, (w - 1) / 2], [0, 100.0, (h - 1) / 2], [0, 0, 1]])
    rows, cols = np.mgrid[0:h, 0:w]
    road = np.where(rows > K[1, 2], 150.0 / np.maximum(rows - K[1, 2], 1e-9), 80.0)  # z = fy h / (v - cy); far wall
    depth = np.repeat(road[None], t, 0).astype(np.float32)
    masks = np.zeros((t, h, w), bool)
    own = np.zeros((2, t, h, w), bool)
    for i in range(t):
        z = 10.0 + 0.2 * i
        v0, v1 = K[1, 2], K[1, 2] + 100.0 * 1.5 / z  # top at camera height, bottom on the road
        boxes = [(-1.0, 0), (1.0, 1)] + ([(-5.0, 2)] if flicker and i in (3, 4, 5) else [])
        for x, a in boxes:
            u0, u1 = K[0, 2] + 100.0 * (x - 0.9) / z, K[0, 2] + 100.0 * (x + 0.9) / z
            box = (cols >= u0) & (cols < u1) & (rows >= v0) & (rows < v1)
            depth[i][box], masks[i][box] = z, True
            if a < 2:
                own[a, i] = box
        gap = ~masks[i] & (cols >= K[0, 2] - 100.0 * 0.1 / z) & (cols < K[0, 2] + 100.0 * 0.1 / z)
        if gap_depth is not None:
            depth[i][gap & (rows >= v0) & (rows < v1)] = gap_depth
        if neck:
            masks[i][gap & (rows >= v1 - 2) & (rows < v1)] = True
        if marking:
            masks[i, 72:76, 20:32] = True  # flat on the road, ~4.4 m ahead
    return masks, depth, K, np.repeat(np.eye(4)[None], t, 0), own


def _ids_per_box(res, own):
    return [{int(np.bincount(res.instance_masks[i][own[a, i]]).argmax()) for i in range(own.shape[1])}
            for a in range(2)]


def test_side_by_side_agents_are_not_joined_by_a_road_gap_or_a_mask_strip():
    masks, depth, K, poses, own = _road_scene()
    res = track_agents(masks, depth, K, poses)  # the gap shows the road behind: no occluder, no merge
    ids = _ids_per_box(res, own)
    assert len(res.tracklets.ids) == 2 and ids[0] != ids[1] and all(len(s) == 1 and 0 not in s for s in ids)
    # a pole in front fills the gap: the parts are merged as one object cut by an occluder
    masks, depth, K, poses, own = _road_scene(gap_depth=5.0)
    res = track_agents(masks, depth, K, poses)
    assert len(res.tracklets.ids) == 1 and _ids_per_box(res, own) == [{1}, {1}]
    # a thin strip of mask on the road joins the boxes into one component: cut at the neck
    masks, depth, K, poses, own = _road_scene(neck=True)
    assert max(cv2.connectedComponents(m.astype(np.uint8))[0] - 1 for m in masks) == 1
    ids = _ids_per_box(track_agents(masks, depth, K, poses), own)
    assert ids[0] != ids[1] and all(len(s) == 1 and 0 not in s for s in ids)
    assert len(track_agents(masks, depth, K, poses, TrackConfig(split_neck_ratio=0)).tracklets.ids) == 1


def test_short_lived_and_flat_road_blobs_are_not_tracks():
    masks, depth, K, poses, _ = _road_scene(t=20, marking=True, flicker=True)  # a track needs 4 hits
    res = track_agents(masks, depth, K, poses)
    assert len(res.tracklets.ids) == 2 and not res.instance_masks[:, 72:76, 20:32].any()
    marking = [d for ds in res.detections for d in ds if d.bbox[1] == 72]
    assert len(marking) == masks.shape[0] and all(d.on_ground and d.ground_area < 0.1 for d in marking)
    # controls: the marking is tracked without the area rule, the 3-frame box without the clip-fraction rule
    assert len(track_agents(masks, depth, K, poses, TrackConfig(min_ground_area=0)).tracklets.ids) == 3
    assert len(track_agents(masks, depth, K, poses, TrackConfig(min_track_fraction=0)).tracklets.ids) == 3
