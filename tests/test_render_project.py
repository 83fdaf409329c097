"""The native CPU projection (csrc/project.cpp) against its plain-torch twin, on values and gradients."""

from __future__ import annotations

import pytest
import torch

from agg.render.project_cpu import project_gaussians_cpu
from agg.render.projection import project_gaussians
from tests.render_scenes import look_K, random_scene

W, H = 80, 56


def project_both(scene, near=0.1, extra=None):
    results = []
    for fn in (project_gaussians_cpu, project_gaussians):
        leaves = {k: v.detach().clone().requires_grad_(True) for k, v in scene.items()}
        p = fn(leaves["means"], leaves["quats"], leaves["scales"], leaves["opacities"], leaves["viewmat"],
               look_K(W, H), W, H, near, 1e10)
        g = torch.Generator().manual_seed(0)
        loss = ((p.means2d * torch.randn(p.means2d.shape, generator=g)).sum()
                + (p.conics * torch.randn(p.conics.shape, generator=g)).sum() * 10.0
                + (p.depths * torch.randn(p.depths.shape, generator=g)).sum())
        loss.backward()
        results.append((p, {k: v.grad for k, v in leaves.items() if k != "opacities" and v.grad is not None}))
    return results


def assert_rel(a, b, rel, name):
    err = (a - b).abs().max().item()
    scale = b.abs().max().item() + 1e-12
    assert err <= rel * scale, f"{name}: {err:.3e} > {rel:g} x {scale:.3e}"


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_native_projection_matches_torch(seed):
    scene = random_scene(500, seed)
    # Push some Gaussians off-screen and behind the near plane so the clamps are exercised.
    with torch.no_grad():
        scene["means"][:20, 0] += 40.0
        scene["means"][20:30, 2] = torch.linspace(-1.0, 0.05, 10)
    (a, ga), (b, gb) = project_both(scene)
    torch.testing.assert_close(a.means2d, b.means2d, atol=1e-3, rtol=1e-5)
    torch.testing.assert_close(a.conics, b.conics, atol=1e-7, rtol=1e-4)
    torch.testing.assert_close(a.depths, b.depths)
    assert torch.equal(a.visible, b.visible) and torch.equal(a.radii, b.radii)
    for name in ("means", "quats", "scales", "viewmat"):
        assert gb[name].abs().max() > 0
        assert_rel(ga[name], gb[name], 1e-4, name)


def test_native_projection_extremes_are_finite():
    n = 6
    scene = {
        "means": torch.tensor([[0.1, 0, 0.0], [0, 0, -1.0], [0, 0, 1e4], [0, 0.1, 3], [0.2, 0, 2], [0, 0, 2]]),
        "quats": torch.tensor([[0.0, 0, 0, 0]] + [[1.0, 0, 0, 0]] * (n - 1)),
        "scales": torch.tensor([[1e-6] * 3, [1e3] * 3, [1.0] * 3, [1e3, 1e-6, 1e-6], [0.1] * 3, [0.1] * 3]),
        "opacities": torch.full((n,), 0.5),
        "viewmat": torch.eye(4),
    }
    (a, ga), (b, gb) = project_both(scene)
    for name, g in ga.items():
        assert torch.isfinite(g).all(), name
    assert (ga["quats"][0] == 0).all()
    assert torch.isfinite(a.conics).all() and torch.isfinite(a.means2d).all()
    torch.testing.assert_close(a.conics, b.conics, atol=1e-6, rtol=1e-3)
