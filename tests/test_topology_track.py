"""Tracking of topology candidates over the frames: held-out frames neither end a track nor break its run, and the
fragments of one object are joined (``agg.train.topology_track``)."""

from __future__ import annotations

import numpy as np

from agg.priors.kalman import smooth_sequence
from agg.train.topology_track import TrackParams, drop_outliers, longest_run, stitch, track_clusters

T = 20
HELD_OUT = np.arange(T) % 5 == 4  # the NVS split: frames 4, 9, 14, 19 have no gradient statistics


def _path(start, velocity, frames) -> np.ndarray:
    """[T, 3] positions of a constant-velocity object, NaN outside ``frames``."""
    z = np.full((T, 3), np.nan)
    for t in frames:
        z[t] = np.asarray(start, float) + np.asarray(velocity, float) * t
    return z


def _state(z: np.ndarray) -> np.ndarray:
    return smooth_sequence(z, np.tile(np.eye(3) * 0.05 ** 2, (T, 1, 1)), accel_var=0.3 ** 2, init_vel_var=4.0)[0]


def test_a_held_out_frame_neither_counts_nor_breaks_a_run():
    hit = ~HELD_OUT
    assert longest_run(hit) == (4, 0)
    assert longest_run(hit, observed=~HELD_OUT) == (T - 4, 0)
    hit[12] = False  # a real miss still breaks it
    assert longest_run(hit, observed=~HELD_OUT) == (10, 0)  # 0-11 less 4 and 9


def test_a_track_coasts_through_held_out_frames_without_a_miss():
    z = _path([0, 0, 10], [0.8, 0, 0.1], range(T))
    frames = [z[t][None] if not HELD_OUT[t] and t != 5 else np.zeros((0, 3)) for t in range(T)]  # 4 held out, 5 missed
    params = TrackParams(meas_sigma=0.2, accel_sigma=0.3, init_vel_sigma=2.0, max_missed=1)
    assert len([h for h in track_clusters(frames, params) if h.hits > 1]) == 2  # 4 and 5: two misses in a row
    tracks = track_clusters(frames, params, observed=~HELD_OUT)
    assert len(tracks) == 1 and tracks[0].hits == T - 5


def test_fragments_of_one_object_are_stitched_and_other_objects_are_not():
    car = dict(start=[0, 0, 10], velocity=[0.8, 0, 0.1])
    front = _state(_path(**car, frames=range(0, 8)))
    smear = _state(_path([1.2, 0, 10.5], car["velocity"], range(3, 10)))  # a second cluster on the same car
    later = _state(_path(**car, frames=range(11, 18)))  # the track restarts after a 2-frame gap
    neighbour = _state(_path([0, 0, 16], car["velocity"], range(0, 12)))  # the next lane over: 6 m away
    turned = _state(_path([0, 0, 10], [0.8, 0, 1.2], range(11, 18)))  # off the car's path after the gap
    far_later = _state(_path(**car, frames=range(16, 20)))  # the gap from `front` is 8 frames
    states = [front, smear, later, neighbour, turned, far_later]
    groups = stitch(states, [8, 7, 7, 12, 7, 4], merge_dist=2.5, max_gap=2, observed=~HELD_OUT)
    as_sets = sorted(sorted(g) for g in groups)
    assert [0, 1, 2, 5] in as_sets  # far_later joins through `later` (they overlap), not across 8 frames
    assert [3] in as_sets and [4] in as_sets
    assert stitch([front, far_later], [8, 4], merge_dist=2.5, max_gap=2, observed=~HELD_OUT) == [[0], [1]]
    one_hit = stitch([front, smear], [8, 1], merge_dist=2.5, max_gap=2, observed=~HELD_OUT)
    assert one_hit == [[0], [1]]  # one hit says nothing


def test_a_centroid_metres_off_the_steady_path_is_dropped_and_jitter_is_kept():
    rng = np.random.default_rng(0)
    z = _path([0, 0, 10], [0.8, 0, 0.4], range(16)) + rng.normal(0, 0.15, (T, 3))
    z[16:] = np.nan
    z[12] += [0, 0, -3.0]  # a cluster that took in the smear in front of the car
    kept = drop_outliers(z, meas_sigma=0.5, accel_sigma=0.05, init_vel_sigma=2.0, max_residual=1.0)
    assert np.isnan(kept[12, 0])
    assert np.count_nonzero(~np.isnan(kept[:, 0])) == 15


def test_match_boxes_take_the_tracklet_size_not_the_gaussians_spread():
    """A car whose Gaussians spread 6 m (floaters after training) keeps its 4.6 m tracklet box for matching, so a
    missed car 3.5 m beside it stays unmatched; an instance without a sized tracklet keeps the Gaussians' extent."""
    import torch

    from agg.io.bundle_priors import Tracklets
    from agg.nodes.gaussians import GaussianParams
    from agg.nodes.rigid import RigidAgents
    from agg.train.topology import TopologyConfig, TopologyEvolution
    from agg.train.topology_track import tracklet_half_extents

    frames = 3
    boxes = np.zeros((2, frames, 7))
    boxes[0, :, 3:6] = [4.6, 1.8, 1.5]  # l, w, h
    boxes[1, :, 3:6] = np.nan  # centre-only track
    tracks = Tracklets(ids=np.array([1, 2]), classes=["rigid", "rigid"], boxes=boxes,
                       valid=np.ones((2, frames), bool))
    half = tracklet_half_extents(tracks)
    assert set(half) == {1} and np.allclose(half[1], [2.3, 0.75, 0.9])  # box frame: x = l, y = h, z = w

    rng = np.random.default_rng(0)
    pts = np.concatenate([rng.uniform(-1, 1, (200, 3)) * [2.3, 0.75, 0.9],  # the car
                          rng.uniform(-1, 1, (20, 3)) * [6.0, 1.0, 6.0],  # floaters
                          rng.uniform(-1, 1, (50, 3))])  # instance 1
    g = GaussianParams.from_points(pts, np.full((len(pts), 3), 0.5), 0, 0.5, scales=np.full(len(pts), 0.1))
    inst = torch.tensor([0] * 220 + [1] * 50)
    wfb = torch.eye(4).repeat(frames, 2, 1, 1)
    wfb[:, 1, :3, 3] = torch.tensor([0.0, 0.0, 30.0])
    node = RigidAgents(g, inst, wfb, torch.ones(frames, 2, dtype=torch.bool), torch.tensor([1, 2]))

    class Graph:
        def agent_nodes(self):
            return [node]

    cfg = TopologyConfig()
    evo = TopologyEvolution(cfg, None, np.eye(3)[None], 32, 24, box_half=half)
    (box,) = evo._agent_boxes(Graph())
    assert np.allclose(box["half"][0], half[1] * (1 + cfg.match_margin))
    assert box["half"][1][0] > 0.9 * (1 + cfg.match_margin)  # the Gaussians' 98 % quantile, about 1
    missed = np.array([0.0, 0.0, 3.5])  # 3.5 m beside the car's centre, across its width
    assert evo._match([box], 0, missed) is None
    blind = TopologyEvolution(cfg, None, np.eye(3)[None], 32, 24)
    assert blind._match(blind._agent_boxes(Graph()), 0, missed) == (0, 0)  # what the floaters did
    state = evo.state_dict()
    again = TopologyEvolution(cfg, None, np.eye(3)[None], 32, 24)
    again.load_state_dict(state)
    assert np.allclose(again.box_half[1], half[1])


def test_project_and_backproject_are_inverse():
    from agg.train.topology_track import backproject, project

    rng = np.random.default_rng(1)
    K = np.array([[200.0, 0, 160], [0, 210, 96], [0, 0, 1]])  # noqa: N806
    a = np.deg2rad(10)
    cfw = np.eye(4)
    cfw[:3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
    cfw[:3, 3] = [0.5, -0.2, 1.0]
    pts = rng.uniform([-3, -1, 8], [3, 1, 30], (50, 3))
    uv, z, _ = project(pts, cfw, K, 320, 192, 0.1)
    assert np.allclose(backproject(uv, z, cfw, K), pts, atol=1e-9)


def test_a_smeared_cluster_is_placed_where_the_frame_sees_it():
    """Background Gaussians smeared 1.5 m along the viewing ray behind and in front of a car's surface (all on the
    observed surface within the 10 % tolerance at 20 m) are placed at the prior depth of their pixels, so the
    centre does not lag the car; rows without depth keep their means."""
    from types import SimpleNamespace

    from agg.priors.prototypes import CLASS_NAMES
    from agg.train.topology import TopologyConfig, TopologyEvolution

    w, h, c = 64, 48, 4
    K = np.array([[60.0, 0, 32], [0, 60, 24], [0, 0, 1]])  # noqa: N806
    car = np.array([2.0, 0.0, 0.0, 0.0])  # an agent-like feature everywhere; the bank tells car from road
    feats = np.tile(car, (1, 8, 8, 1)).astype(np.float32)
    axis = {"background": 3, "rigid": 0, "non-rigid": 1}  # one feature axis per prototype
    protos = {k: np.eye(c)[axis[k]][None] for k in CLASS_NAMES}
    sem = SimpleNamespace(features=feats, prototypes=protos, prototype_space="pca")
    depth = np.full((1, h, w), 20.0, np.float32)
    depth[0, :, :8] = 0  # no depth on the left edge
    evo = TopologyEvolution(TopologyConfig(), sem, K[None], w, h, depth=depth, num_frames=1)
    rng = np.random.default_rng(0)
    px = np.stack([rng.uniform(12, 52, 200), rng.uniform(10, 38, 200)], 1)
    z = 20.0 + rng.uniform(-1.5, 1.5, 200)
    means = np.concatenate([(px - [32, 24]) / 60 * z[:, None], z[:, None]], 1)
    means = np.concatenate([means, [[(4 - 32) / 60 * 19.0, 0.0, 19.0]]])  # a row at u = 4, where there is no depth
    grad = np.ones(len(means))
    grad[::4] = 10.0  # a quarter of them stand out (the last row too)
    idx, _, surface, seen, _ = evo._candidates(0, means, grad, np.eye(4))
    assert len(idx) == 51 and surface.all()
    assert np.allclose(seen[:-1, 2], 20.0, atol=1e-5) and np.allclose(seen[-1], means[-1])
    assert np.ptp(means[idx[:-1], 2]) > 2.5  # the smear the means would have averaged


# a 160 x 96 camera at the origin looking along +z, and a car's half extents (l, h, w), for the surface-model tests
CAM_W, CAM_H = 160, 96
CAM_K = np.array([[80.0, 0, 79.5], [0, 80, 47.5], [0, 0, 1]])
CAR_HALF = np.array([2.1, 0.8, 0.9])


def _in_image(points: np.ndarray) -> np.ndarray:
    """Which world points [P, 3] that camera's image holds."""
    from agg.train.topology_track import project

    return project(points, np.eye(4), CAM_K, CAM_W, CAM_H, 0.3)[2]


def _box_samples(centre: np.ndarray, yaw: float, n: int = 400_000) -> np.ndarray:
    """World points [P, 3] where rays spread uniformly over the sphere of directions (a Fibonacci lattice, so by
    solid angle) hit a car's box, keeping the rays inside the image of the camera above:
    how densified Gaussians sample a surface (module doc of ``visible_surface_offset``). Ray-cast with the
    synthetic renderer's slab test."""
    from agg.synth.raycast import intersect_boxes_dense
    from agg.synth.scene import BoxSet
    from agg.train.topology_track import pose_from_yaw, project

    i = np.arange(n) + 0.5
    polar, azimuth = np.arccos(1 - 2 * i / n), np.pi * (1 + 5 ** 0.5) * i
    rays = np.stack([np.cos(azimuth) * np.sin(polar), np.sin(azimuth) * np.sin(polar), np.cos(polar)], 1)
    rays = rays[project(rays, np.eye(4), CAM_K, CAM_W, CAM_H, 1e-3)[2]]
    boxes = BoxSet(pose_from_yaw(centre, yaw)[None], CAR_HALF[None], np.zeros(1, int), np.zeros((1, 3)),
                   np.zeros(1, int), np.ones(1, int))
    t, idx, *_ = intersect_boxes_dense(np.zeros(3), rays, boxes)
    return rays[idx >= 0] * t[idx >= 0, None]


def test_the_visible_surface_model_matches_a_box_sampled_by_solid_angle_also_at_the_image_edge():
    """The centroid of a box's surface sampled by solid angle, only the part in view, is what ``visible_centroid``
    predicts, for a car 7 m ahead seen in full and for one half out of the image at the right edge; leaving the
    image edge out would miss the second by more than half a metre."""
    from agg.train.topology_track import visible_centroid

    yaw = 0.3
    for centre in (np.array([1.0, 0.7, 7.0]), np.array([6.5, 0.7, 7.5])):
        seen = _box_samples(centre, yaw).mean(0)
        assert np.linalg.norm(visible_centroid(centre, yaw, CAR_HALF, np.zeros(3), _in_image) - seen) < 0.05
    assert np.linalg.norm(visible_centroid(centre, yaw, CAR_HALF, np.zeros(3)) - seen) > 0.5  # the cut-off car


def test_a_car_leaving_at_the_image_edge_is_placed_by_its_track():
    """A car drives 0.6 m per frame to the right until half of it has left the image. Read from the centroid of
    its surface with the whole box assumed visible, its centre drifts ahead of it as it leaves; with the image
    edges in the model (Gauss-Newton passes) it stays within 0.2 m on every frame."""
    from agg.train.topology_track import spawn_trajectory, yaw_from_heading

    n = 12
    truth = np.array([[1.0 + 0.6 * i, 0.7, 8.0] for i in range(n)])  # [T, 3]
    yaw = yaw_from_heading(1.0, 0.0)
    centroids = {i: _box_samples(truth[i], yaw).mean(0) for i in range(n)}
    state, _ = smooth_sequence(np.stack([centroids[i] for i in range(n)]), np.tile(np.eye(3) * 0.25, (n, 1, 1)),
                               accel_var=0.3 ** 2, init_vel_var=4.0)
    kw = {"meas_sigma": 0.5, "accel_sigma": 0.05, "init_vel_sigma": 2.0, "min_speed": 0.05, "extend": 2}
    args = (state, centroids, np.zeros((n, 3)), CAR_HALF, lambda t, c: True, 0.0)
    without = np.linalg.norm(spawn_trajectory(*args, **kw)[0][:, :3, 3] - truth, axis=1)
    with_edges = spawn_trajectory(*args, **kw, in_image=lambda t, p: _in_image(p))[0][:, :3, 3]
    with_edges = np.linalg.norm(with_edges - truth, axis=1)
    assert with_edges.max() < 0.2, with_edges
    assert without.max() > 0.5, without


def test_a_clusters_centre_skips_members_seen_on_known_agents():
    """Members whose pixel lies in the prior dynamic masks are seen on a known agent (a prior car beside or in
    front of the missed one): the centre leaves them out while enough others remain, then falls back."""
    from agg.train.topology_track import cluster_centre

    seen = np.concatenate([np.tile([0.0, 0.0, 10.0], (30, 1)), np.tile([3.0, 0.0, 12.0], (20, 1))])  # [50, 3]
    opacity = np.full(50, 0.8)
    surface = np.ones(50, bool)
    known = np.arange(50) >= 30  # the last 20 project onto a prior car
    assert np.allclose(cluster_centre(seen, opacity, surface, known, 25), [0.0, 0.0, 10.0])
    assert np.allclose(cluster_centre(seen, opacity, surface, known, 40), [1.2, 0.0, 10.8])  # too few: all count
    off = np.arange(50) < 10  # ten members off the observed surface
    assert np.allclose(cluster_centre(seen, opacity, ~off, np.zeros(50, bool), 25), [1.5, 0.0, 11.0])
