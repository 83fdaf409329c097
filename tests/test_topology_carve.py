"""Free-space carving of a spawned agent's swept box (agg.train.topology_carve): the trail inside goes, the road
under it, a wall beside it and whatever lies past its valid frames stay."""

from __future__ import annotations

import numpy as np

from agg.train.topology_carve import carve_rows

ROAD = 1.5  # camera-frame road height (y down), the camera at the world origin in every frame
K = np.array([[200.0, 0, 160], [0, 200.0, 96], [0, 0, 1]])
HALF = np.array([2.25, 0.8, 0.9])  # box half extents: x = length, y = height (down), z = width


def _road_plane() -> np.ndarray:
    """The road y = ROAD as an image-space plane of inverse depth w = a u + b v + c."""
    return np.array([0.0, 1.0 / (K[1, 1] * ROAD), -K[1, 2] / (K[1, 1] * ROAD)])


def _poses(frames: int, sink: float = 0.0) -> np.ndarray:
    """A car 4 m to the right driving away along +z from 10 m to 19.5 m, 0.5 m per frame (box x along +z)."""
    rot = np.array([[0.0, 0, -1], [0, 1, 0], [1, 0, 0]])  # columns: box x -> +z, box y -> +y (down), box z -> -x
    poses = np.tile(np.eye(4), (frames, 1, 1))
    poses[:, :3, :3] = rot
    poses[:, :3, 3] = [[4.0, ROAD - HALF[1] + sink, 10.0 + 0.5 * t] for t in range(frames)]
    return poses


def _carve(points, poses, valid, planes="road", shrink=0.8, clearance=0.3):
    frames = len(poses)
    plane = [_road_plane()] * frames if planes == "road" else planes
    return carve_rows(points, poses, valid, HALF, np.tile(np.eye(4), (frames, 1, 1)), K[None], plane, shrink,
                      clearance)


def test_the_trail_inside_the_swept_box_goes_and_the_road_wall_and_unseen_path_stay():
    rng = np.random.default_rng(0)
    frames = 20
    poses, valid = _poses(frames), np.ones(frames, bool)
    valid[15:] = False  # the car is valid up to 17 m
    # the trail: points in the box at frames 0..14, inside the shrunk length / width and above the clearance
    t = rng.integers(0, 15, 500)
    local = rng.uniform(-1, 1, (500, 3)) * [0.75 * HALF[0], HALF[1], 0.75 * HALF[2]]
    local[:, 1] = np.minimum(local[:, 1], HALF[1] - 0.35)
    trail = np.einsum("nij,nj->ni", poses[t, :3, :3], local) + poses[t, :3, 3]
    # the road under the path, a wall 1 m beside the lane's centre line (past the box's 0.9 m half width) and
    # the lane's last metres, which the car reaches only at frames it is not valid
    z = rng.uniform(9, 17, 300)
    road = np.stack([rng.uniform(3.2, 4.8, 300), ROAD - rng.uniform(0, 0.25, 300), z], 1)
    wall = np.stack([np.full(300, 5.0), rng.uniform(0, ROAD - 0.4, 300), z], 1)
    unseen = np.stack([rng.uniform(3.5, 4.5, 300), rng.uniform(0.5, 1.0, 300), rng.uniform(20.5, 21.5, 300)], 1)
    carved = _carve(np.concatenate([trail, road, wall, unseen]), poses, valid)
    n = 500
    assert carved[:n].all()
    assert not carved[n:].any(), [int(carved[n + 300 * i:n + 300 * (i + 1)].sum()) for i in range(3)]


def test_the_shrink_keeps_what_the_full_box_edge_holds():
    poses, valid = _poses(10), np.ones(10, bool)
    # 0.8 m beside the centre line: inside the full box (0.9 m), outside the shrunk one (0.72 m)
    edge = poses[0, :3, 3] + poses[0, :3, :3] @ np.array([0.0, 0.0, 0.8])
    assert not _carve(edge[None], poses, valid)[0]
    assert _carve(edge[None], poses, valid, shrink=1.0)[0]


def test_the_road_plane_keeps_the_road_under_a_box_that_sinks_into_it():
    # a box placed 0.5 m too low reaches 0.5 m under the road: its bottom clearance alone would carve the road
    poses, valid = _poses(10, sink=0.5), np.ones(10, bool)
    road = np.array([[4.0, ROAD - 0.1, 10.0], [4.5, ROAD, 10.5]])
    body = np.array([[4.0, ROAD - 0.6, 10.0]])  # 0.6 m above the road, inside the box
    assert not _carve(road, poses, valid).any()
    assert _carve(road, poses, valid, planes=None).all()
    assert _carve(body, poses, valid).all()


def test_an_agent_that_does_not_travel_half_its_length_carves_nothing():
    # a parked car: the background rows in its box that the clusters did not hand over are its own surface
    poses = np.repeat(_poses(1), 10, 0)
    poses[:, 2, 3] += np.linspace(0.0, 1.0, 10)  # 1 m of jitter and creep, under its 2.25 m half length
    body = poses[0, :3, 3][None]
    assert not _carve(body, poses, np.ones(10, bool)).any()
    assert _carve(body, _poses(10), np.ones(10, bool)).all()  # 4.5 m of travel
