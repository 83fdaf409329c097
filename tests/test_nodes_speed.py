"""The track-speed correction of rigid agents (``RigidAgents.rate``, agg/nodes/rigid.py): what it moves, that it
survives node surgery and checkpoints, and that a photometric loss recovers a track that runs too fast."""

from __future__ import annotations

import numpy as np
import torch

from agg.nodes.gaussians import GaussianParams
from agg.nodes.rigid import RigidAgents
from agg.render import rasterize

K = torch.tensor([[60.0, 0, 31.5], [0, 60.0, 23.5], [0, 0, 1]])


def _blob(n: int = 6, seed: int = 1) -> GaussianParams:
    rng = np.random.default_rng(seed)
    return GaussianParams.from_points(rng.normal(size=(n, 3)) * 0.4, rng.uniform(0.2, 0.9, size=(n, 3)),
                                      sh_degree=0, scales=np.full(n, 0.25))


def _two_instances(t: int = 4) -> tuple[RigidAgents, torch.Tensor, torch.Tensor]:
    wfb = torch.eye(4).repeat(t, 2, 1, 1)  # [T, K, 4, 4]
    for i in range(t):
        a = 0.2 * i
        wfb[i, 0, :3, :3] = torch.tensor([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
        wfb[i, 0, :3, 3] = torch.tensor([1.0 * i - 1.0, 0.0, 10.0])
        wfb[i, 1, :3, 3] = torch.tensor([-2.0, 0.0, 8.0 + i])
    valid = torch.ones(t, 2, dtype=torch.bool)
    valid[3, 0] = False  # frame 3 does not count in instance 0's reference
    return RigidAgents(_blob(), torch.tensor([0, 0, 0, 1, 1, 1]), wfb, valid), wfb, valid


def test_the_rate_scales_free_prior_translations_about_their_valid_mean_and_only_there():
    node, wfb, _ = _two_instances()
    ref0 = wfb[:3, 0, :3, 3].mean(0)  # frames 0-2 are instance 0's valid ones
    torch.testing.assert_close(node.rate_ref[0], ref0)
    with torch.no_grad():
        node.rate.fill_(0.1)
    torch.testing.assert_close(node.world_from_box(1), wfb[1])  # no instance is free: the rate does nothing
    node.speed_free[0] = True
    for f in range(4):
        got = node.world_from_box(f)
        want = node.prior[f].clone()  # frame 3 of instance 0: invalid, its prior is the identity, left as it is
        if f < 3:
            want[0, :3, 3] += 0.1 * (wfb[f, 0, :3, 3] - ref0)
        torch.testing.assert_close(got, want)  # rotations untouched; instance 1 (not free) untouched
    # with per-frame corrections too: [R | t + s] @ [Rc | tc]
    with torch.no_grad():
        node.tau[2, 0] = torch.tensor([0.3, -0.1, 0.2])
    corr = torch.eye(4)
    corr[:3, 3] = node.tau[2, 0].detach()
    want = wfb[2, 0] @ corr
    want[:3, 3] += 0.1 * (wfb[2, 0, :3, 3] - ref0)
    torch.testing.assert_close(node.world_from_box(2)[0], want)


def test_only_a_free_rate_gets_a_gradient_through_the_renderer():
    node, _, _ = _two_instances()
    node.speed_free[0] = True
    out = node.compose(0)
    img = rasterize(out["means"], out["quats"], out["scales"], out["opacities"], sh=out["sh"], K=K, width=64,
                    height=48, viewmat=torch.eye(4))
    img.color.sum().backward()
    assert node.rate.grad[0] != 0 and node.rate.grad[1] == 0


def test_surgery_and_checkpoints_keep_the_rate_aligned_with_its_instance():
    node, _, _ = _two_instances()
    opt = torch.optim.Adam(node.param_groups("rigid", {k: 1e-3 for k in ("means", "log_scales", "quats",
                                                                            "opacity_logits", "sh")},
                                             1e-3, rate_lr=1e-2), eps=1e-15)
    node.speed_free[1] = True
    node.compose(1)["means"].sum().backward()
    opt.step()
    assert node.rate[1] != 0 and node.rate[0] == 0
    moment = opt.state[node.rate]["exp_avg"].clone()  # [2]
    t = node.num_frames
    new = torch.eye(4).repeat(t, 1, 1, 1)
    new[:, 0, 0, 3] = torch.arange(t, dtype=torch.float32) * 2.0  # x = 0, 2, 4, 6
    node.add_instances(_blob(2, seed=3), torch.zeros(2), new, torch.ones(t, 1, dtype=torch.bool),
                       torch.tensor([9]), opt, speed_free=True)
    assert node.speed_free.tolist() == [False, True, True]
    torch.testing.assert_close(node.rate_ref[2], torch.tensor([3.0, 0.0, 0.0]))
    assert node.rate.shape == (3,) and node.rate[2] == 0
    state = opt.state[node.rate]["exp_avg"]
    torch.testing.assert_close(state, torch.cat([moment, torch.zeros(1)]))  # appended rows start at zero moments
    assert any(p is node.rate for g in opt.param_groups for p in g["params"])
    rate1 = node.rate[1].item()
    node.remove_instances(torch.tensor([False, True, True]), opt)
    assert node.speed_free.tolist() == [True, True] and node.rate[0].item() == rate1
    torch.testing.assert_close(opt.state[node.rate]["exp_avg"], torch.stack([moment[1], torch.tensor(0.0)]))
    with torch.no_grad():
        node.rate[1] = -0.05
    again = RigidAgents.from_state(node.state())
    for f in range(t):
        torch.testing.assert_close(again.world_from_box(f), node.world_from_box(f))
    old = {k: v for k, v in node.state().items() if k not in ("rate", "speed_free", "rate_ref")}
    assert not RigidAgents.from_state(old).speed_free.any()  # a checkpoint from before the correction


def test_a_photometric_loss_recovers_a_track_that_runs_eight_percent_too_fast():
    """A blob drives along x at 0.5 units a frame; its prior runs 8 % too fast about the same mean, so the box is
    up to 0.2 units off at the ends. Training the rate alone on renders of the true motion brings it to
    1 / 1.08 - 1 and the boxes onto the true track."""
    t = 7
    true = torch.eye(4).repeat(t, 1, 1, 1)
    true[:, 0, 0, 3] = 0.5 * (torch.arange(t, dtype=torch.float32) - 3)
    true[:, 0, 2, 3] = 8.0
    prior = true.clone()
    prior[:, 0, 0, 3] *= 1.08  # the true mean is x = 0, so the prior shares it
    blob = _blob(8, seed=5)
    truth = RigidAgents(_blob(8, seed=5), torch.zeros(8), true, torch.ones(t, 1, dtype=torch.bool))
    targets = []
    with torch.no_grad():
        for f in range(t):
            g = truth.compose(f)
            targets.append(rasterize(g["means"], g["quats"], g["scales"], g["opacities"], sh=g["sh"], K=K,
                                     width=64, height=48, viewmat=torch.eye(4)).color)
    node = RigidAgents(blob, torch.zeros(8), prior, torch.ones(t, 1, dtype=torch.bool))
    node.speed_free.fill_(True)
    opt = torch.optim.Adam([node.rate], lr=3e-3)
    before = (node.world_from_box(0)[0, :3, 3] - true[0, 0, :3, 3]).norm().item()
    for step in range(120):
        f = step % t
        g = node.compose(f)
        img = rasterize(g["means"], g["quats"], g["scales"], g["opacities"], sh=g["sh"], K=K, width=64, height=48,
                        viewmat=torch.eye(4)).color
        opt.zero_grad()
        (img - targets[f]).abs().mean().backward()
        opt.step()
    assert abs(node.rate.item() - (1 / 1.08 - 1)) < 0.01, node.rate.item()
    err = max((node.world_from_box(f)[0, :3, 3] - true[f, 0, :3, 3]).norm().item() for f in range(t))
    assert before > 0.1 and err < 0.03, (before, err)
