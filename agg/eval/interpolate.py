"""Novel-view split and pose interpolation for held-out frames.

The split holds out every ``every``-th frame counting from 1: frames ``i`` with ``i % every == every - 1`` (4, 9,
14, ... for ``every = 5``) are test frames, all others train. Frame 0 therefore always trains, so the gauge (world =
first camera) is fixed by an optimised frame.

A held-out frame was never optimised, so its camera and agent poses come from the nearest train frames before and
after it: the rotation is slerped (kornia's shortest-arc quaternion slerp), the translation linearly interpolated,
with weight ``w = (frame - before) / (after - before)``. Past either end of the train frames the nearest one is
held. An agent exists at a held-out frame when it is valid at one of the neighbours used; when it is valid at only
one of them that neighbour's pose is held.
"""

from __future__ import annotations

import bisect
from collections.abc import Sequence

import torch
from kornia.geometry.quaternion import Quaternion
from torch import Tensor


def split_frames(num_frames: int, every: int = 5) -> tuple[list[int], list[int]]:
    """(train, test) frame lists of a clip of ``num_frames``: test = frames with ``i % every == every - 1``."""
    if every < 2:
        raise ValueError(f"every must be >= 2, got {every}")
    test = [i for i in range(num_frames) if i % every == every - 1]
    train = [i for i in range(num_frames) if i % every != every - 1]
    return train, test


def interpolate_pose(a: Tensor, b: Tensor, w: float) -> Tensor:
    """[4, 4] rigid pose between ``a`` (w = 0) and ``b`` (w = 1): slerp of the rotations, lerp of the translations."""
    a, b = torch.as_tensor(a, dtype=torch.float32), torch.as_tensor(b, dtype=torch.float32)
    w = float(w)
    if w == 0.0:
        return a.clone()
    if w == 1.0:
        return b.clone()
    qa = Quaternion.from_matrix(a[None, :3, :3].double())
    qb = Quaternion.from_matrix(b[None, :3, :3].double())
    out = torch.eye(4, dtype=torch.float32, device=a.device)
    out[:3, :3] = qa.slerp(qb, w).matrix()[0].to(a)
    out[:3, 3] = (1.0 - w) * a[:3, 3] + w * b[:3, 3]
    return out


def neighbours(train_frames: Sequence[int], frame: int) -> tuple[int, int, float]:
    """(before, after, w): the nearest train frames around ``frame`` and its weight between them.

    A train frame is its own neighbour (w = 0); before the first / after the last train frame both neighbours are
    that end frame."""
    train = sorted(int(f) for f in train_frames)
    if not train:
        raise ValueError("no train frames to interpolate from")
    j = bisect.bisect_left(train, frame)
    if j < len(train) and train[j] == frame:
        return frame, frame, 0.0
    if j == 0:
        return train[0], train[0], 0.0
    if j == len(train):
        return train[-1], train[-1], 0.0
    lo, hi = train[j - 1], train[j]
    return lo, hi, (frame - lo) / (hi - lo)


def interpolate_camera(world_from_camera: Tensor, train_frames: Sequence[int], frame: int) -> Tensor:
    """[4, 4] camera pose at ``frame`` from the poses [T, 4, 4] of its neighbouring train frames."""
    lo, hi, w = neighbours(train_frames, frame)
    return interpolate_pose(world_from_camera[lo], world_from_camera[hi], w)


def interpolate_agents(world_from_box: Tensor, valid: Tensor, train_frames: Sequence[int],
                       frame: int) -> tuple[Tensor, Tensor]:
    """Agent poses [K, 4, 4] and validity [K] at ``frame`` from ``world_from_box`` [T, K, 4, 4], ``valid`` [T, K].

    Valid at both neighbours: interpolated; at one: that pose held; at neither: invalid (identity pose)."""
    world_from_box = torch.as_tensor(world_from_box, dtype=torch.float32)
    valid = torch.as_tensor(valid, dtype=torch.bool)
    lo, hi, w = neighbours(train_frames, frame)
    k = world_from_box.shape[1]
    poses = torch.eye(4, device=world_from_box.device).repeat(k, 1, 1)  # [K, 4, 4]
    ok = valid[lo] | valid[hi]  # [K]
    for j in range(k):
        if valid[lo, j] and valid[hi, j]:
            poses[j] = interpolate_pose(world_from_box[lo, j], world_from_box[hi, j], w)
        elif valid[lo, j]:
            poses[j] = world_from_box[lo, j]
        elif valid[hi, j]:
            poses[j] = world_from_box[hi, j]
    return poses, ok
