"""Depth prior: sparse rows from SfM points, image-guided densification (planes, outliers, empty input, agents
behind the ground), the local mono-depth path with a scripted TorchScript module, and input errors."""

import warnings

import numpy as np
import pytest

from agg.priors.depth import (
    DepthConfig,
    DepthPriorError,
    MonoDepthModel,
    align_scale_shift,
    clip_ground_plane,
    densify_clip,
    densify_depth,
    fit_ground_plane,
    sparse_depth_rows,
)
from agg.priors.poses import SparsePoints

W, H = 160, 96
F = 120.0  # focal length (px) of the synthetic camera
CAM_HEIGHT = 1.5


def _texture(seed=0):
    rng = np.random.default_rng(seed)
    return rng.uniform(0, 1, (H, W, 3)).astype(np.float32)


def _ground_inv_depth(u, v, horizon=30.0, roll=0.0):
    """Inverse depth of a level road seen from CAM_HEIGHT: w = (v - v_horizon + roll (u - W/2)) / (F h)."""
    return (v - horizon + roll * (u - W / 2)) / (F * CAM_HEIGHT)


def _rows_on(inv_fn, n, rng, v_min=0.0):
    u = rng.uniform(0, W - 1, n)
    v = rng.uniform(v_min, H - 1, n)
    return np.stack([u, v, 1.0 / inv_fn(u, v), np.ones(n)], 1).astype(np.float32)


def test_sparse_rows_from_sparse_points_filter_and_confidence():
    # 3 points: point 0 seen in 4 frames (error 0.2 px), point 1 in 2 frames (error 2 px), point 2 in 3 frames
    pts = SparsePoints(
        xyz=np.zeros((3, 3)), rgb=np.zeros((3, 3), np.uint8), error_px=np.array([0.2, 2.0, 0.5]),
        obs_frame=np.array([0, 1, 2, 3, 0, 1, 0, 1, 2]), obs_point=np.array([0, 0, 0, 0, 1, 1, 2, 2, 2]),
        obs_uv=np.array([[10, 10], [11, 10], [12, 10], [13, 10], [50, 40], [51, 40], [-5, 3], [20, 20], [30, 200]],
                        float),
        obs_depth=np.array([5.0, 4.9, 4.8, 4.7, 9.0, 8.8, 3.0, -1.0, 3.0]))
    rows = sparse_depth_rows(pts, 4, W, H)
    assert len(rows) == 4 and all(r.dtype == np.float32 and r.shape[1] == 4 for r in rows)
    assert [len(r) for r in rows] == [2, 2, 1, 1]  # outside the image (u < 0, v > H) and depth <= 0 dropped
    np.testing.assert_allclose(rows[0][:, :3], [[10, 10, 5.0], [50, 40, 9.0]])
    c_long, c_short = rows[0][0, 3], rows[0][1, 3]
    assert c_long == pytest.approx(1.0 / (1.0 + 0.2 ** 2))  # 4 observations: track factor 1
    assert c_short == pytest.approx((1.0 / 3.0) / (1.0 + 2.0 ** 2))  # 2 observations, large error
    assert 0 < c_short < c_long <= 1


def test_densify_recovers_a_plane_and_handles_few_points():
    rng = np.random.default_rng(0)

    def wall(u, v):  # slanted plane in front of the camera (not a ground: closer to the right)
        return 0.1 + 0.002 * u + 0.0005 * v

    rows = _rows_on(wall, 150, rng)
    depth, conf = densify_depth(rows, _texture(), DepthConfig())
    truth = 1.0 / wall(*np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float)))
    covered = depth > 0
    assert covered.mean() > 0.9
    assert np.median(np.abs(depth[covered] - truth[covered]) / truth[covered]) < 0.01
    assert conf.min() >= 0 and conf.max() <= 1 and conf[covered].mean() > 0.3
    for n in (0, 2):
        d, c = densify_depth(rows[:n], _texture())
        assert d.shape == (H, W) and not d.any() and not c.any()


def test_densify_is_robust_to_outliers_and_leaves_the_sky_empty():
    rng = np.random.default_rng(1)
    rows = _rows_on(_ground_inv_depth, 200, rng, v_min=35)  # road only: nothing above the horizon (v = 30)
    bad = rng.choice(len(rows), 15, replace=False)
    rows[bad, 2] *= rng.choice([0.2, 6.0], len(bad))  # 7.5 % gross outliers, nearer and farther
    depth, _ = densify_depth(rows, _texture())
    uu, vv = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
    with np.errstate(divide="ignore"):
        truth = 1.0 / _ground_inv_depth(uu, vv)
    road = (vv > 40) & (depth > 0)
    assert road.sum() > 0.8 * (vv > 40).sum()
    assert np.median(np.abs(depth[road] - truth[road]) / truth[road]) < 0.02
    assert not depth[:15].any()  # far above the horizon and the rows: no depth


def test_ground_plane_snaps_agents_behind_it():
    """A car driving with the ego is triangulated far away (behind the road): its rows go onto the ground."""
    rng = np.random.default_rng(2)
    road = _rows_on(_ground_inv_depth, 150, rng, v_min=35)
    u = rng.uniform(60, 100, 30)
    v = rng.uniform(50, 70, 30)
    car = np.stack([u, v, np.full(30, 80.0), np.ones(30)], 1).astype(np.float32)  # far, but below the horizon
    plane = fit_ground_plane(road[:, :2].astype(float), 1.0 / road[:, 2].astype(float), W, H)
    assert plane is not None and plane[1] == pytest.approx(1 / (F * CAM_HEIGHT), rel=0.02)
    depth, _ = densify_depth(np.concatenate([road, car]), _texture())
    ground_depth = 1.0 / _ground_inv_depth(80.0, 70.0)
    assert depth[70, 80] <= 1.05 * ground_depth  # not 80: nothing static is seen behind the ground
    clip_plane = clip_ground_plane([road, road[:50]], W, H)
    np.testing.assert_allclose(clip_plane, plane, rtol=0.05, atol=0.05)


def test_densify_clip_shapes_progress_and_frame_types():
    rng = np.random.default_rng(3)
    rows = [_rows_on(_ground_inv_depth, 80, rng, v_min=35) for _ in range(3)]
    frames = (np.stack([_texture(i) for i in range(3)]) * 255).astype(np.uint8)
    seen = []
    depth, conf = densify_clip(rows, frames, progress=seen.append)
    assert depth.shape == conf.shape == (3, H, W) and depth.dtype == np.float32 and seen == [0, 1, 2]
    assert (depth[:, 60] > 0).all()


class _Scripted:
    """A scripted model returning a fixed relative inverse depth (half resolution) of the ground plane."""

    @staticmethod
    def save(path, scale, shift):
        import torch

        uu, vv = np.meshgrid(np.arange(0, W, 2, dtype=float) + 0.5, np.arange(0, H, 2, dtype=float) + 0.5)
        rel = (_ground_inv_depth(uu, vv) - shift) / scale  # what the net "predicts" (relative inverse depth)

        class Net(torch.nn.Module):
            def __init__(self):
                super().__init__()
                self.register_buffer("rel", torch.tensor(rel, dtype=torch.float32)[None])

            def forward(self, x: torch.Tensor) -> torch.Tensor:
                return self.rel + 0.0 * x.mean()

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)
            torch.jit.script(Net()).save(str(path))


def test_mono_depth_alignment_recovers_scale_and_shift(tmp_path):
    model_path = tmp_path / "mono.pt"
    _Scripted.save(model_path, scale=3.0, shift=-0.05)
    model = MonoDepthModel(model_path)
    rng = np.random.default_rng(4)
    rows = _rows_on(_ground_inv_depth, 60, rng, v_min=40)
    rows[:6, 2] *= 4.0  # outliers
    depth, conf = model.predict(_texture(), rows)
    uu, vv = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
    with np.errstate(divide="ignore"):
        truth = 1.0 / _ground_inv_depth(uu, vv)
    band = (vv > 45) & (vv < H - 2)
    assert (depth[band] > 0).all()
    assert np.median(np.abs(depth[band] - truth[band]) / truth[band]) < 0.03
    assert 0.6 < conf[band].max() <= 0.8 and not depth[:25].any()  # above the horizon: negative inverse depth
    d, c = model.predict(_texture(), rows[:5])  # too few rows: no mono depth
    assert not d.any() and not c.any()
    s, t, inl = align_scale_shift(np.arange(10.0), 2 * np.arange(10.0) + 1, np.ones(10), 0.05)
    assert (s, t) == pytest.approx((2.0, 1.0)) and inl.all()


def test_bad_inputs_raise_clear_errors(tmp_path):
    with pytest.raises(DepthPriorError, match="rows"):
        densify_depth(np.zeros((5, 2)), _texture())
    with pytest.raises(DepthPriorError, match="image"):
        densify_depth(np.zeros((5, 4)), np.zeros((H, W, 4)))
    with pytest.raises(DepthPriorError, match="row sets"):
        densify_clip([np.zeros((0, 4))], np.zeros((2, H, W, 3), np.uint8))
    with pytest.raises(DepthPriorError, match="SparsePoints"):
        sparse_depth_rows(object(), 2, W, H)
    pts = SparsePoints(np.zeros((1, 3)), np.zeros((1, 3), np.uint8), np.zeros(1), np.array([5]), np.array([0]),
                       np.zeros((1, 2)), np.ones(1))
    with pytest.raises(DepthPriorError, match="obs_frame"):
        sparse_depth_rows(pts, 2, W, H)
    with pytest.raises(DepthPriorError, match="not found"):
        MonoDepthModel(tmp_path / "missing.pt")
    (tmp_path / "junk.pt").write_bytes(b"not a model")
    with pytest.raises(DepthPriorError, match="TorchScript"):
        MonoDepthModel(tmp_path / "junk.pt")
    with pytest.raises(DepthPriorError):
        DepthConfig(outlier_ratio=0.5)
