"""The `cuda` backend (gsplat) against the native `cpu` backend. Skipped without CUDA and gsplat."""

from __future__ import annotations

import pytest
import torch

from agg.render import rasterize
from tests.render_scenes import look_K, random_scene

pytestmark = pytest.mark.cuda

if not torch.cuda.is_available():
    pytest.skip("no CUDA device", allow_module_level=True)
gsplat = pytest.importorskip("gsplat")

W, H = 96, 64


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("sh_degree", [None, 1, 3])
def test_cuda_matches_cpu(seed, sh_degree):
    scene = random_scene(500, seed, sh_degree=sh_degree)
    results = {}
    for device, backend in (("cpu", "cpu"), ("cuda", "cuda")):
        leaves = {k: v.detach().to(device).clone().requires_grad_(True) for k, v in scene.items()}
        out = rasterize(leaves["means"], leaves["quats"], leaves["scales"], leaves["opacities"],
                        leaves.get("colors"), sh=leaves.get("sh"), K=look_K(W, H).to(device), width=W, height=H,
                        viewmat=leaves["viewmat"], background=torch.tensor([0.1, 0.2, 0.3], device=device),
                        backend=backend)
        target = torch.rand(out.color.shape, generator=torch.Generator().manual_seed(seed)).to(device)
        out.meta.means2d.retain_grad()  # what densification reads
        ((out.color - target).abs().mean() + out.alpha.mean()).backward()
        grads = {k: v.grad.cpu() for k, v in leaves.items()}
        assert out.meta.means2d.grad is not None, backend
        grads["means2d"] = out.meta.means2d.grad.cpu()
        results[backend] = (out, grads)
    (a, ga), (b, gb) = results["cpu"], results["cuda"]
    assert b.meta.backend == "cuda"
    # gsplat's boxes and float ordering differ slightly at splat edges: compare means and tails separately.
    diff = (a.color - b.color.cpu()).abs()
    assert diff.mean() < 2e-3 and diff.max() < 5e-2
    assert (a.alpha - b.alpha.cpu()).abs().mean() < 2e-3
    for name in ga:
        cos = torch.nn.functional.cosine_similarity(ga[name].flatten(), gb[name].flatten(), dim=0)
        assert cos > 0.98, f"{name}: gradient cosine {cos:.4f}"
