"""Numerical stability at the extremes: outputs and gradients stay finite, and the right gradients are zero."""

from __future__ import annotations

import pytest
import torch

from agg.render import rasterize
from tests.render_scenes import look_K

BACKENDS = ["cpu", "torch"]
W, H = 48, 32


def scene_of(means, scales=None, quats=None, opacities=None, colors=None):
    n = len(means)
    leaves = {
        "means": torch.tensor(means, dtype=torch.float32).reshape(n, 3),
        "quats": torch.tensor(quats, dtype=torch.float32) if quats is not None else torch.tensor([[1.0, 0, 0, 0]] * n),
        "scales": torch.tensor(scales, dtype=torch.float32) if scales is not None else torch.full((n, 3), 0.3),
        "opacities": torch.tensor(opacities, dtype=torch.float32) if opacities is not None else torch.full((n,), 0.8),
        "colors": torch.tensor(colors, dtype=torch.float32) if colors is not None else torch.rand(n, 3),
    }
    leaves["quats"] = leaves["quats"].reshape(n, 4)
    leaves["scales"] = leaves["scales"].reshape(n, 3)
    leaves["colors"] = leaves["colors"].reshape(n, 3)
    leaves["viewmat"] = torch.eye(4)
    return {k: v.requires_grad_(True) for k, v in leaves.items()}


def run(scene, backend, width=W, height=H, loss_on=("color", "depth", "alpha"), near=0.1):
    out = rasterize(scene["means"], scene["quats"], scene["scales"], scene["opacities"], scene["colors"],
                    K=look_K(width, height), width=width, height=height, viewmat=scene["viewmat"], near=near,
                    background=torch.tensor([0.3, 0.3, 0.3]), backend=backend)
    g = torch.Generator().manual_seed(0)
    loss = 0.0
    for name in loss_on:
        t = getattr(out, name)
        loss = loss + (t * torch.rand(t.shape, generator=g)).sum()
    loss.backward()
    for name in ("color", "depth", "alpha"):
        assert torch.isfinite(getattr(out, name)).all(), f"{name} not finite"
    for k, v in scene.items():
        assert v.grad is not None and torch.isfinite(v.grad).all(), f"gradient of {k} not finite"
    return out


@pytest.mark.parametrize("backend", BACKENDS)
def test_scales_from_1e_minus6_to_1e3(backend):
    scales = [[s, s, s] for s in (1e-6, 1e-3, 1.0, 1e2, 1e3)] + [[1e3, 1e-6, 1e-6], [1e-6, 1e3, 1e-6]]
    means = [[0.1 * i, 0.05, 3.0 + i] for i in range(len(scales))]
    quats = [[0.9, 0.3, -0.2, 0.1]] * len(scales)
    out = run(scene_of(means, scales=scales, quats=quats), backend)
    assert out.alpha.max() > 0.5  # the huge ones cover the image


@pytest.mark.parametrize("backend", BACKENDS)
def test_depth_extremes_zero_near_behind_far(backend):
    near = 0.1
    means = [
        [0.2, 0.1, 0.0],  # z = 0
        [0.0, 0.0, near],  # exactly at the near plane (culled: needs z > near)
        [0.1, 0.0, -2.0],  # behind the camera
        [0.0, 0.0, 1e4],  # 10 km away
        [0.0, 0.1, 3.0],  # ordinary
    ]
    scene = scene_of(means, scales=[[0.5] * 3] * 4 + [[0.3] * 3])
    out = run(scene, backend, near=near)
    vis = out.meta.visible
    assert vis.tolist() == [False, False, False, True, True]
    for k in ("means", "quats", "scales", "opacities", "colors"):
        assert (scene[k].grad[:3] == 0).all(), f"culled Gaussians got a gradient in {k}"
    assert scene["colors"].grad[4].abs().sum() > 0


@pytest.mark.parametrize("backend", BACKENDS)
def test_opacity_zero_and_almost_one(backend):
    # A huge almost-opaque Gaussian saturates alpha at 0.99 on every pixel: its opacity and conic (hence mean,
    # scale, rotation) gradients through the colour must be exactly zero; an opacity-0 Gaussian contributes
    # nothing and gets no gradient at all.
    scene = scene_of([[0.0, 0.0, 5.0], [0.1, 0.0, 2.0]], scales=[[50.0] * 3, [0.3] * 3],
                     opacities=[1 - 1e-7, 0.0])
    out = run(scene, backend, loss_on=("color",))
    assert torch.allclose(out.alpha, torch.full_like(out.alpha, 0.99))
    assert scene["opacities"].grad[0] == 0
    assert (scene["means"].grad[0, :2] == 0).all() and (scene["scales"].grad[0] == 0).all()
    assert (scene["quats"].grad[0] == 0).all()
    assert scene["colors"].grad[0].abs().sum() > 0
    for k in ("means", "quats", "scales", "opacities", "colors"):
        assert (scene[k].grad[1] == 0).all(), f"opacity-0 Gaussian got a gradient in {k}"


@pytest.mark.parametrize("backend", BACKENDS)
def test_zero_quaternion_and_duplicate_means(backend):
    scene = scene_of([[0.0, 0.0, 3.0], [0.3, 0.2, 4.0], [0.3, 0.2, 4.0]],
                     quats=[[0.0, 0.0, 0.0, 0.0], [1.0, 0, 0, 0], [1.0, 0, 0, 0]],
                     scales=[[0.4, 0.1, 0.2], [0.2] * 3, [0.2] * 3])
    out = run(scene, backend)
    assert out.alpha.max() > 0.5
    assert (scene["quats"].grad[0] == 0).all()  # a zero quaternion is the identity with zero gradient
    assert scene["means"].grad[1:].abs().sum() > 0


@pytest.mark.parametrize("backend", BACKENDS)
def test_empty_scene(backend):
    scene = scene_of([])
    out = run(scene, backend)
    assert (out.alpha == 0).all() and torch.allclose(out.color, torch.full_like(out.color, 0.3))
    assert scene["means"].grad.shape == (0, 3)


@pytest.mark.parametrize("backend", BACKENDS)
def test_every_gaussian_culled(backend):
    scene = scene_of([[0.0, 0.0, -1.0], [100.0, 0.0, 1.0], [0.0, 0.0, 0.0]])
    out = run(scene, backend)
    assert not out.meta.visible.any()
    assert (out.alpha == 0).all() and (out.depth == 0).all()
    for k in ("means", "quats", "scales", "opacities", "colors"):
        assert (scene[k].grad == 0).all()


@pytest.mark.parametrize("width,height", [(1, 1), (4096, 64)])
def test_tiny_and_wide_images_match_reference(width, height):
    g = torch.Generator().manual_seed(3)
    n = 40
    z = torch.empty(n).uniform_(2.0, 6.0, generator=g)
    x = (torch.rand(n, generator=g) - 0.5) * 2.0 * z * (0.5 * width / look_K(width, height)[0, 0])
    y = (torch.rand(n, generator=g) - 0.5) * 0.5 * z
    means = torch.stack([x, y, z], -1).tolist()
    outs = {}
    for backend in BACKENDS:
        torch.manual_seed(0)
        scene = scene_of(means, scales=[[0.2, 0.3, 0.25]] * n)
        out = run(scene, backend, width=width, height=height)
        assert out.color.shape == (height, width, 3)
        outs[backend] = (out, scene)
    (a, sa), (b, sb) = outs["cpu"], outs["torch"]
    if width == 1:
        assert a.alpha.item() > 0  # the single pixel is covered
    torch.testing.assert_close(a.color, b.color, atol=2e-5, rtol=1e-4)
    torch.testing.assert_close(sa["means"].grad, sb["means"].grad, atol=1e-3, rtol=1e-3)
