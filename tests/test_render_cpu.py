"""The native `cpu` backend against the plain-torch reference, on values and on the gradients of every input."""

from __future__ import annotations

import pytest
import torch

from agg.render import rasterize
from tests.render_scenes import look_K, random_scene

W, H = 80, 56


def render_and_grads(scene: dict, backend: str, bg: torch.Tensor | None = None, seed: int = 0):
    leaves = {k: v.detach().clone().requires_grad_(True) for k, v in scene.items()}
    colors = leaves.get("colors")
    out = rasterize(
        leaves["means"], leaves["quats"], leaves["scales"], leaves["opacities"], colors, sh=leaves.get("sh"),
        K=look_K(W, H), width=W, height=H, viewmat=leaves["viewmat"], background=bg, backend=backend,
    )
    g = torch.Generator().manual_seed(seed + 100)
    target = torch.rand(out.color.shape, generator=g)
    w_depth = torch.rand(H, W, generator=g)
    w_alpha = torch.rand(H, W, generator=g)
    loss = (out.color - target).abs().mean() + 0.01 * (w_depth * out.depth).mean() + (w_alpha * out.alpha).mean()
    loss.backward()
    return out, {k: v.grad for k, v in leaves.items()}


def assert_close_rel(a: torch.Tensor, b: torch.Tensor, rel: float, name: str):
    scale = b.abs().max().item() + 1e-12
    err = (a - b).abs().max().item()
    assert err <= rel * scale, f"{name}: max abs error {err:.3e} exceeds {rel:g} x {scale:.3e}"


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("channels", [3, 8])
def test_cpu_matches_torch_colors(seed, channels):
    scene = random_scene(400, seed, channels=channels)
    bg = torch.rand(channels)
    a, ga = render_and_grads(scene, "cpu", bg, seed)
    b, gb = render_and_grads(scene, "torch", bg, seed)
    assert a.meta.backend == "cpu" and b.meta.backend == "torch"
    assert a.meta.visible.sum() > 100  # most of the scene is on screen
    torch.testing.assert_close(a.color, b.color, atol=2e-5, rtol=1e-4)
    torch.testing.assert_close(a.alpha, b.alpha, atol=2e-5, rtol=1e-4)
    torch.testing.assert_close(a.depth, b.depth, atol=5e-4, rtol=1e-4)
    for name in ga:
        assert torch.isfinite(ga[name]).all()
        assert gb[name].abs().max() > 0, f"reference gradient of {name} is all zero"
        assert_close_rel(ga[name], gb[name], 2e-4, name)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_cpu_matches_torch_sh(degree):
    scene = random_scene(300, 10 + degree, sh_degree=degree)
    a, ga = render_and_grads(scene, "cpu", None, degree)
    b, gb = render_and_grads(scene, "torch", None, degree)
    assert a.color.shape == (H, W, 3)
    torch.testing.assert_close(a.color, b.color, atol=2e-5, rtol=1e-4)
    for name in ga:
        assert gb[name].abs().max() > 0, name
        assert_close_rel(ga[name], gb[name], 2e-4, name)


def test_dense_overlap_terminates_identically():
    """Many opaque layers: pixels hit the T < 1e-4 stop and the alpha clamp; both backends must agree."""
    scene = random_scene(600, 7, channels=3, depth_range=(3.0, 3.5), scale_range=(0.3, 0.8))
    with torch.no_grad():
        scene["opacities"].fill_(0.999)
    a, ga = render_and_grads(scene, "cpu")
    b, gb = render_and_grads(scene, "torch")
    assert (a.alpha > 0.999).float().mean() > 0.5
    torch.testing.assert_close(a.color, b.color, atol=2e-5, rtol=1e-4)
    for name in ga:
        assert_close_rel(ga[name], gb[name], 2e-4, name)


def test_world_from_camera_equals_viewmat():
    scene = random_scene(100, 3)
    view = scene["viewmat"].detach()
    kw = dict(K=look_K(W, H), width=W, height=H, backend="cpu")
    args = [scene[k].detach() for k in ("means", "quats", "scales", "opacities", "colors")]
    a = rasterize(*args, viewmat=view, **kw)
    b = rasterize(*args, world_from_camera=torch.linalg.inv(view), **kw)
    torch.testing.assert_close(a.color, b.color, atol=1e-5, rtol=1e-5)


def test_means2d_gradient_is_readable():
    """Densification reads dL/dmeans2d from meta.means2d after backward."""
    scene = random_scene(50, 4)
    out = rasterize(scene["means"], scene["quats"], scene["scales"], scene["opacities"], scene["colors"],
                    K=look_K(W, H), width=W, height=H, viewmat=scene["viewmat"], backend="cpu")
    out.meta.means2d.retain_grad()
    out.color.sum().backward()
    g = out.meta.means2d.grad
    assert g is not None and g.shape == (50, 2)
    assert (g[out.meta.visible].abs().sum(-1) > 0).float().mean() > 0.9
    assert (g[~out.meta.visible] == 0).all()


def test_bad_arguments_raise_clear_errors():
    scene = random_scene(10, 0)
    args = [scene[k].detach() for k in ("means", "quats", "scales", "opacities", "colors")]
    with pytest.raises(ValueError, match="exactly one of viewmat"):
        rasterize(*args, K=look_K(W, H), width=W, height=H)
    with pytest.raises(ValueError, match="at least 1x1"):
        rasterize(*args, K=look_K(W, H), width=0, height=H, viewmat=torch.eye(4))
    with pytest.raises(ValueError, match="backend"):
        rasterize(*args, K=look_K(W, H), width=W, height=H, viewmat=torch.eye(4), backend="metal")
    with pytest.raises(ValueError, match="fx > 0"):
        rasterize(*args, K=torch.zeros(3, 3), width=W, height=H, viewmat=torch.eye(4))
    with pytest.raises(ValueError, match=r"SH needs K = \(d\+1\)\^2"):
        rasterize(*args[:4], sh=torch.zeros(10, 5, 3), K=look_K(W, H), width=W, height=H, viewmat=torch.eye(4))


def test_a_stale_build_baton_does_not_hang_the_next_load():
    """A process killed while building leaves torch's ``lock`` file in the build folder; the next load removes it
    under its own flock and goes on, instead of waiting forever."""
    import subprocess
    import sys

    from agg.render import native

    code = "from agg.render import native; native.load(); print('loaded')"
    first = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
    assert first.returncode == 0 and "loaded" in first.stdout, first.stderr[-2000:]
    (native.cache_dir() / "lock").touch()  # what a SIGKILLed builder leaves
    again = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert again.returncode == 0 and "loaded" in again.stdout, again.stderr[-2000:]
    assert not (native.cache_dir() / "lock").exists()


def test_gsplat_screen_means_receive_the_gradient_of_the_means_gsplat_used():
    """The cuda backend's ``meta.means2d`` (derived from the tensor gsplat composites from) gets dL/dmeans2d in
    ``.grad``, accumulating over backward passes, without autograd warnings: densification reads it."""
    import warnings

    from agg.render.raster_gsplat import _screen_means

    x = torch.randn(1, 7, 2, requires_grad=True)
    used = x * 2.0  # [1, N, 2] what gsplat would composite from
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ours = _screen_means(used)
        ours.retain_grad()  # as the trainer does
        loss = (used ** 2).sum()
        loss.backward(retain_graph=True)
        assert torch.allclose(ours.grad, 2 * used[0].detach())
        loss.backward()
        assert torch.allclose(ours.grad, 4 * used[0].detach())
    assert torch.allclose(_screen_means(used.detach()), used[0].detach() - 0.5)
