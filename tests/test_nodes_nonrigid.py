"""Non-rigid agents: a deformation MLP on canonical Gaussians (agg/nodes/nonrigid.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from agg.nodes.gaussians import GaussianParams
from agg.nodes.nonrigid import DeformConfig, NonRigidAgents, fourier_encode
from agg.nodes.rigid import RigidAgents
from agg.render import rasterize

W, H = 48, 32
K = torch.tensor([[40.0, 0, (W - 1) / 2], [0, 40.0, (H - 1) / 2], [0, 0, 1]])
LRS = {"means": 1e-3, "log_scales": 1e-3, "quats": 1e-3, "opacity_logits": 1e-2, "sh": 1e-2}


@pytest.fixture(autouse=True)
def _one_thread():
    """Tiny renders: one intra-op thread avoids oversubscription on a shared CPU (30x slower under load)."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def _blob(n: int, seed: int, colour=(0.9, 0.2, 0.1)) -> GaussianParams:
    rng = np.random.default_rng(seed)
    xyz = rng.normal(0, 0.12, (n, 3))
    return GaussianParams.from_points(xyz, np.tile(colour, (n, 1)), sh_degree=0, opacity=0.9,
                                      scales=np.full(n, 0.12))


def _node(k: int = 2, t: int = 2, n: int = 12, config: DeformConfig = DeformConfig()) -> NonRigidAgents:
    g = _blob(n * k, 0)
    instance = torch.arange(n * k) // n
    wfb = torch.eye(4).repeat(t, k, 1, 1)
    wfb[..., 0, 3] = torch.linspace(-0.6, 0.6, k)  # instances side by side, 5 m ahead
    wfb[..., 2, 3] = 5.0
    return NonRigidAgents(g, instance, wfb, torch.ones(t, k, dtype=torch.bool), torch.arange(10, 10 + k), config)


def _render(node: NonRigidAgents, frame: int, t: float | None = None):
    g = node.compose(frame, t=t)
    return rasterize(g["means"], g["quats"], g["scales"], g["opacities"], sh=g["sh"], K=K, width=W, height=H,
                     viewmat=torch.eye(4))


def test_fourier_encoding_and_config_checks():
    x = torch.tensor([[0.25, -0.5, 1.0]])
    e = fourier_encode(x, 2)
    assert e.shape == (1, 15)
    torch.testing.assert_close(e[0, :3], x[0])
    torch.testing.assert_close(e[0, 3:9], torch.sin(torch.pi * torch.tensor([0.25, 0.5, -0.5, -1.0, 1.0, 2.0])))
    assert DeformConfig(pos_freqs=2, time_freqs=1, embed_dim=4).in_dim == 15 + 3 + 4
    with pytest.raises(ValueError):
        DeformConfig(width=0)


def test_starts_exactly_at_the_canonical_gaussians_and_matches_a_rigid_node():
    node = _node()
    canon = node.gaussians.activated()
    for t in (0.0, 0.37, 1.0):
        g = node.canonical(0, t)
        for key in ("means", "quats", "scales", "opacities", "sh"):
            assert torch.equal(g[key], canon[key]), key
    rigid = RigidAgents(node.gaussians, node.instance, node.prior, node.valid)
    for frame in (0, 1):
        a, b = node.compose(frame), rigid.compose(frame)
        for key in a:
            assert torch.equal(a[key], b[key]), key
    dmu, dq, ds = node.deformation(0.5)
    assert dmu.abs().max() == 0 and ds.abs().max() == 0
    torch.testing.assert_close(dq, torch.tensor([1.0, 0, 0, 0]).expand_as(dq))


def test_gradients_reach_the_mlp_and_the_embeddings_through_the_renderer():
    torch.manual_seed(0)
    node = _node()
    opt = torch.optim.Adam(node.param_groups("nonrigid", LRS, 1e-3, 1e-2))
    assert [g["name"] for g in opt.param_groups][-1] == "nonrigid#deform"
    target = torch.rand(H, W, 3)
    for step in range(2):  # the zero head passes no gradient before its first update
        opt.zero_grad()
        loss = (_render(node, 1).color - target).abs().mean()
        loss.backward()
        if step == 0:
            assert node.deform.head.weight.grad.abs().sum() > 0
            assert node.embeddings.grad is None or node.embeddings.grad.abs().sum() == 0
        opt.step()
    for name, p in node.deform.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0, name
    assert node.embeddings.grad.abs().sum(1).gt(0).all()  # every instance's code gets gradient
    assert node.omega.grad[1].abs().sum() > 0 and node.gaussians.means.grad.abs().sum() > 0


def test_the_mlp_moves_a_blob_differently_at_t0_and_t1():
    torch.manual_seed(0)
    node = _node(k=1, t=2, n=10)
    canon = node.gaussians.activated()
    box = node.prior[0, 0, :3, 3]  # the box centre (no rotation)
    targets = []
    for dx in (0.35, -0.35):  # the blob sits right of its box centre at t = 0 and left of it at t = 1
        with torch.no_grad():
            means = canon["means"] + box + torch.tensor([dx, 0.0, 0.0])
            targets.append(rasterize(means, canon["quats"], canon["scales"], canon["opacities"], sh=canon["sh"], K=K,
                                     width=W, height=H, viewmat=torch.eye(4)).color)
    opt = torch.optim.Adam([*node.deform.parameters(), node.embeddings], lr=3e-3)
    losses = []
    for _ in range(100):
        opt.zero_grad()
        loss = sum(((_render(node, f).color - targets[f]) ** 2).mean() for f in (0, 1))
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    assert losses[-1] < 0.1 * losses[0], (losses[0], losses[-1])
    with torch.no_grad():
        x0 = node.canonical(0, 0.0)["means"][:, 0].mean() - canon["means"][:, 0].mean()
        x1 = node.canonical(1, 1.0)["means"][:, 0].mean() - canon["means"][:, 0].mean()
        x_mid = node.canonical(0, 0.5)["means"][:, 0].mean() - canon["means"][:, 0].mean()  # a held-out time
    print(f"loss {losses[0]:.2e} -> {losses[-1]:.2e}; mean dx at t=0 {x0:.3f}, t=1 {x1:.3f}, t=0.5 {x_mid:.3f}")
    assert x0 > 0.25 and x1 < -0.25, (float(x0), float(x1))
    assert x1 < x_mid < x0


def test_add_and_remove_instances_keep_adam_state_consistent():
    torch.manual_seed(0)
    node = _node(k=2)
    opt = torch.optim.Adam(node.param_groups("nonrigid", LRS, 1e-3, 1e-2))
    target = torch.rand(H, W, 3)

    def step():
        opt.zero_grad()
        (_render(node, 0).color - target).abs().mean().backward()
        opt.step()

    for _ in range(3):
        step()
    old_emb = node.embeddings.detach().clone()
    old_m = opt.state[node.embeddings]["exp_avg"].clone()
    assert old_m.abs().sum() > 0
    wfb = torch.eye(4).repeat(2, 1, 1, 1)
    wfb[..., 2, 3] = 4.0
    node.add_instances(_blob(8, 1, (0.1, 0.3, 0.9)), torch.zeros(8, dtype=torch.long), wfb,
                       torch.ones(2, 1, dtype=torch.bool), torch.tensor([42]), opt)
    assert node.num_instances == 3 and node.embeddings.shape == (3, 16)
    torch.testing.assert_close(node.embeddings[:2].detach(), old_emb)
    assert node.embeddings[2].abs().sum() > 0  # a fresh code, not zeros
    st = opt.state[node.embeddings]
    assert st["exp_avg"].shape == (3, 16) and st["exp_avg_sq"].shape == (3, 16)
    torch.testing.assert_close(st["exp_avg"][:2], old_m)
    assert st["exp_avg"][2].abs().sum() == 0
    deform_group = next(g for g in opt.param_groups if g["name"] == "nonrigid#deform")
    assert any(p is node.embeddings for p in deform_group["params"])
    step()  # Adam runs on the resized tensors
    assert node.embeddings.grad.shape == (3, 16) and node.embeddings.grad[2].abs().sum() > 0

    m = opt.state[node.embeddings]["exp_avg"].clone()
    emb = node.embeddings.detach().clone()
    node.remove_instances(torch.tensor([True, False, True]), opt)
    assert node.num_instances == 2 and node.track_ids.tolist() == [10, 42]
    torch.testing.assert_close(node.embeddings.detach(), emb[[0, 2]])
    torch.testing.assert_close(opt.state[node.embeddings]["exp_avg"], m[[0, 2]])
    assert len(node.gaussians) == 12 + 8 and node.instance.max() == 1
    step()
    assert torch.isfinite(node.embeddings).all()


def test_state_round_trip_renders_identically():
    torch.manual_seed(0)
    cfg = DeformConfig(width=32, depth=2, embed_dim=8, seed=3)
    node = _node(config=cfg)
    with torch.no_grad():  # a non-trivial deformation and pose correction
        node.deform.head.weight.normal_(0, 0.05)
        node.deform.head.bias.normal_(0, 0.05)
        node.tau[1, 0] = torch.tensor([0.1, 0.0, 0.0])
    state = node.state()
    again = NonRigidAgents.from_state(state)
    assert again.config == cfg
    for frame, t in ((0, None), (1, None), (0, 0.4)):
        a, b = _render(node, frame, t), _render(again, frame, t)
        assert a.alpha.max() > 0.5
        torch.testing.assert_close(a.color, b.color, atol=0, rtol=0)
    assert not torch.allclose(_render(node, 0).color, _render(node, 1).color)  # time does deform it
