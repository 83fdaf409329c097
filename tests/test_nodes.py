"""Scene-graph building blocks: the camera node and Gaussian parameter sets with optimiser-state surgery."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from agg.nodes.camera import CameraNode
from agg.nodes.gaussians import GaussianParams, append_rows, keep_rows, knn_scales
from agg.nodes.rigid import RigidAgents
from agg.render import rasterize


def _poses(t: int = 5) -> torch.Tensor:
    p = torch.eye(4).repeat(t, 1, 1)
    p[:, 2, 3] = torch.arange(t, dtype=torch.float32)  # driving forward along z
    return p


def test_camera_starts_at_the_prior_and_keeps_frame_zero_fixed():
    prior = _poses()
    cam = CameraNode(prior)
    torch.testing.assert_close(cam.world_from_camera(), prior)
    torch.testing.assert_close(cam.camera_from_world() @ cam.world_from_camera(), torch.eye(4).repeat(5, 1, 1))
    with torch.no_grad():
        cam.omega += 0.1
        cam.tau += 0.2
    p = cam.world_from_camera()
    torch.testing.assert_close(p[0], prior[0])  # the gauge: world = first camera
    assert not torch.allclose(p[1:], prior[1:])
    r = p[1:, :3, :3]
    torch.testing.assert_close(r @ r.transpose(1, 2), torch.eye(3).repeat(4, 1, 1), atol=1e-5, rtol=0)
    # the correction is applied in the camera frame: tau moves the centre along the camera's own axes
    torch.testing.assert_close(p[2, :3, 3] - prior[2, :3, 3], r[1] @ torch.full((3,), 0.2), atol=1e-6, rtol=0)


def test_camera_gradients_reach_the_correction_through_the_renderer():
    cam = CameraNode(_poses(3))
    g = GaussianParams.from_points(np.array([[0.0, 0.0, 6.0], [0.5, 0.2, 7.0]]), np.array([[1, 0, 0], [0, 1, 0.]]),
                                   sh_degree=0, opacity=0.8, scales=np.array([0.3, 0.3]))
    a = g.activated()
    K = torch.tensor([[40.0, 0, 15.5], [0, 40.0, 11.5], [0, 0, 1]])
    out = rasterize(a["means"], a["quats"], a["scales"], a["opacities"], sh=a["sh"], K=K, width=32, height=24,
                    viewmat=cam.camera_from_world(torch.tensor([1]))[0])
    out.color.sum().backward()
    assert torch.isfinite(cam.omega.grad).all() and cam.omega.grad[1].abs().sum() > 0
    assert cam.tau.grad[1].abs().sum() > 0
    assert cam.omega.grad[[0, 2]].abs().sum() == 0 and cam.tau.grad[[0, 2]].abs().sum() == 0
    assert g.means.grad.abs().sum() > 0 and g.sh.grad.abs().sum() > 0


def test_camera_rejects_bad_priors():
    with pytest.raises(ValueError, match=r"\[T, 4, 4\]"):
        CameraNode(torch.eye(3)[None])
    bad = _poses()
    bad[2, 0, 3] = float("nan")
    with pytest.raises(ValueError, match="non-finite"):
        CameraNode(bad)


def test_knn_scales_clamp_duplicates_and_isolated_points():
    xyz = np.array([[0, 0, 0], [0, 0, 0], [0, 0, 0], [1, 0, 0], [100, 0, 0]], float)
    s = knn_scales(xyz, k=2, min_scale=1e-3, max_scale=5.0)
    assert np.all(np.isfinite(np.log(s)))  # duplicates: no log(0) = -inf
    assert s[0] == pytest.approx(1e-3) and s[4] == pytest.approx(5.0)
    g = GaussianParams.from_points(xyz, np.full((5, 3), 0.5), sh_degree=2, max_scale=5.0)
    a = g.activated()
    assert a["sh"].shape == (5, 9, 3) and torch.isfinite(a["scales"]).all()
    torch.testing.assert_close(a["opacities"], torch.full((5,), 0.1))


def test_pruning_and_appending_keep_adam_state_aligned():
    xyz = np.random.default_rng(0).normal(size=(6, 3))
    keep = torch.tensor([True, False, True, True, False, True])
    target = torch.randn(6, 3, generator=torch.Generator().manual_seed(0))
    lrs = dict(means=0.01, log_scales=0.01, quats=0.01, opacity_logits=0.05, sh=0.01)

    def step(g, opt, tgt):
        opt.zero_grad()
        ((g.means - tgt) ** 2).sum().add(g.sh.square().sum()).backward()
        opt.step()

    live = GaussianParams.from_points(xyz, np.full((6, 3), 0.3), sh_degree=1)
    opt_live = torch.optim.Adam(live.param_groups("background", lrs))
    ref = GaussianParams.from_points(xyz[keep.numpy()], np.full((4, 3), 0.3), sh_degree=1,
                                     scales=knn_scales(xyz)[keep.numpy()])  # only the rows that survive
    opt_ref = torch.optim.Adam(ref.param_groups("background", lrs))
    for _ in range(3):
        step(live, opt_live, target)
        step(ref, opt_ref, target[keep])
    keep_rows(live, keep, opt_live)
    assert len(live) == 4 and all(p.shape[0] == 4 for g in opt_live.param_groups for p in g["params"])
    for _ in range(2):  # Adam is per element: the kept rows go on exactly as if the others had never existed
        step(live, opt_live, target[keep])
        step(ref, opt_ref, target[keep])
    for name in ("means", "sh", "log_scales"):
        torch.testing.assert_close(getattr(live, name), getattr(ref, name))
    extra = GaussianParams.from_points(np.zeros((2, 3)) + 5, np.full((2, 3), 0.8), sh_degree=1,
                                       scales=np.array([0.1, 0.1]))
    append_rows(live, extra, opt_live)
    assert len(live) == 6
    st = opt_live.state[live.means]
    assert st["exp_avg"].shape == (6, 3) and st["exp_avg"][4:].abs().sum() == 0
    step(live, opt_live, torch.randn(6, 3))  # the optimiser runs on the resized parameters
    assert torch.isfinite(live.means).all()
    with pytest.raises(ValueError, match="SH shapes differ"):
        append_rows(live, GaussianParams.from_points(np.zeros((1, 3)), np.zeros((1, 3)), sh_degree=0,
                                                     scales=np.array([0.1])))


def _quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    w, x, y, z = (q / q.norm(dim=-1, keepdim=True)).unbind(-1)
    return torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1).reshape(*q.shape[:-1], 3, 3)


def _rigid(t: int = 4):
    from agg.nodes.rigid import RigidAgents

    rng = np.random.default_rng(1)
    g = GaussianParams.from_points(rng.normal(size=(6, 3)) * 0.5, np.full((6, 3), 0.5), sh_degree=0,
                                   scales=np.full(6, 0.2))
    with torch.no_grad():
        g.quats.copy_(torch.as_tensor(rng.normal(size=(6, 4)), dtype=torch.float32))
        g.log_scales.copy_(torch.as_tensor(rng.normal(size=(6, 3)) * 0.3 - 1.5, dtype=torch.float32))
    wfb = torch.eye(4).repeat(t, 2, 1, 1)  # [T, K, 4, 4]
    for i in range(t):
        a = 0.3 * i
        wfb[i, 0, :3, :3] = torch.tensor([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
        wfb[i, 0, :3, 3] = torch.tensor([1.0 * i, 0.0, 10.0])
        wfb[i, 1, :3, 3] = torch.tensor([-3.0, 0.0, 8.0 + i])
    valid = torch.ones(t, 2, dtype=torch.bool)
    valid[2, 1] = False
    return RigidAgents(g, torch.tensor([0, 0, 0, 1, 1, 1]), wfb, valid), wfb


def test_rigid_compose_moves_means_and_covariances_with_the_box():
    node, wfb = _rigid()
    out = node.compose(1)
    g = node.gaussians.activated()
    pose = wfb[1][node.instance]  # [N, 4, 4]
    want = (pose[:, :3, :3] @ g["means"][..., None])[..., 0] + pose[:, :3, 3]
    torch.testing.assert_close(out["means"], want, atol=1e-5, rtol=0)
    # covariance R S S R^T of the world Gaussian = pose rotation applied to the canonical covariance
    cov = lambda q, s: _quat_to_matrix(q) @ torch.diag_embed(s ** 2) @ _quat_to_matrix(q).transpose(-1, -2)  # noqa: E731
    r = pose[:, :3, :3]
    torch.testing.assert_close(cov(out["quats"], out["scales"]), r @ cov(g["quats"], g["scales"]) @ r.transpose(1, 2),
                               atol=1e-5, rtol=0)


def test_rigid_validity_zeroes_absent_instances_and_their_gradients():
    node, _ = _rigid()
    out = node.compose(2)
    assert (out["opacities"][3:] == 0).all() and (out["opacities"][:3] > 0).all()
    K = torch.tensor([[60.0, 0, 31.5], [0, 60.0, 23.5], [0, 0, 1]])
    img = rasterize(out["means"], out["quats"], out["scales"], out["opacities"], sh=out["sh"], K=K, width=64,
                    height=48, viewmat=torch.eye(4))
    img.color.sum().backward()
    assert node.tau.grad[2, 0].abs().sum() > 0 and node.omega.grad[2, 0].abs().sum() > 0
    assert node.tau.grad[2, 1].abs().sum() == 0 and node.gaussians.means.grad[3:].abs().sum() == 0
    assert node.tau.grad[[0, 1, 3]].abs().sum() == 0  # only the rendered frame's pose learns


def test_rigid_rejects_bad_inputs():
    from agg.nodes.rigid import RigidAgents

    g = GaussianParams.from_points(np.zeros((2, 3)), np.zeros((2, 3)), sh_degree=0, scales=np.ones(2))
    with pytest.raises(ValueError, match=r"\[T, K, 4, 4\]"):
        RigidAgents(g, torch.tensor([0, 0]), torch.eye(4).repeat(3, 1, 1), torch.ones(3, 1, dtype=torch.bool))
    with pytest.raises(ValueError, match="instance indices"):
        RigidAgents(g, torch.tensor([0, 2]), torch.eye(4).repeat(3, 2, 1, 1), torch.ones(3, 2, dtype=torch.bool))
    bad = torch.eye(4).repeat(3, 1, 1, 1)
    bad[1, 0, 0, 3] = float("nan")
    with pytest.raises(ValueError, match="finite where valid"):
        RigidAgents(g, torch.tensor([0, 0]), bad, torch.ones(3, 1, dtype=torch.bool))
    valid = torch.ones(3, 1, dtype=torch.bool)
    valid[1, 0] = False  # a NaN pose where the instance is absent is fine (the bundle writes NaN there)
    assert RigidAgents(g, torch.tensor([0, 0]), bad, valid).compose(1)["opacities"].abs().sum() == 0


def test_spawning_two_agents_at_once_keeps_one_instance_index_per_gaussian():
    """Regression: topology evolution concatenates the spawned sets; the instance index must be counted first."""
    from agg.nodes.rigid import RigidAgents
    from agg.train import topology

    t = 3
    base = GaussianParams.from_points(np.zeros((4, 3)), np.full((4, 3), 0.5), 0, 0.5, scales=np.full(4, 0.1))
    node = RigidAgents(base, torch.zeros(4, dtype=torch.long), torch.eye(4).repeat(t, 1, 1, 1),
                       torch.ones(t, 1, dtype=torch.bool), torch.tensor([1]))

    class Graph:
        rigid = node
        background = GaussianParams.from_points(np.random.default_rng(0).normal(size=(30, 3)),
                                                np.full((30, 3), 0.5), 0, 0.5, scales=np.full(30, 0.1))

        def agent_nodes(self):
            return [node]

    evo = topology.TopologyEvolution(topology.TopologyConfig(), None, np.eye(3)[None], 32, 24)
    plans = [{"rows": np.arange(0, 7), "frame_of": np.zeros(7, int), "poses": np.tile(np.eye(4), (t, 1, 1)),
              "valid": np.ones(t, bool), "frames": t, "class": "rigid"},
             {"rows": np.arange(7, 12), "frame_of": np.zeros(5, int), "poses": np.tile(np.eye(4), (t, 1, 1)),
              "valid": np.ones(t, bool), "frames": t, "class": "rigid"}]
    report = {"pruned": [], "spawned": [], "new_nodes": [], "reassigned": 0, "rows_changed": [],
              "bg_src": torch.arange(30)}
    g = Graph()
    evo._apply(g, None, report, np.full((30, 2), -1), np.zeros(30, int), [], plans)
    assert len(node.instance) == len(node.gaussians) == 16
    assert node.instance.tolist() == [0] * 4 + [1] * 7 + [2] * 5 and node.num_instances == 3
    assert len(g.background) == 18


def _node(means: torch.Tensor, instance: list[int], half) -> RigidAgents:
    n, k = len(means), max(instance) + 1
    g = GaussianParams(means, torch.zeros(n, 3), torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1), torch.zeros(n),
                       torch.zeros(n, 1, 3))
    return RigidAgents(g, torch.tensor(instance), torch.eye(4).repeat(2, k, 1, 1), torch.ones(2, k, dtype=torch.bool),
                       torch.arange(k), None if half is None else torch.tensor(half, dtype=torch.float32))


def test_confine_clamps_means_into_the_grown_box_and_leaves_unknown_sizes_free():
    means = torch.tensor([[3.0, -2.0, 0.1], [0.5, 0.2, -0.3], [9.0, 9.0, -9.0]])
    node = _node(means, [0, 0, 1], [[2.0, 1.0, 1.0], [float("nan"), 1.0, 1.0]])
    assert torch.isinf(node.half_extents[1]).all()  # a size that is not finite and positive is unknown
    node.confine(0.25)
    m = node.gaussians.means.detach()
    assert torch.allclose(m[0], torch.tensor([2.5, -1.25, 0.1]))  # outside on x and y: onto the grown faces
    assert torch.equal(m[1], means[1])  # inside: untouched
    assert torch.equal(m[2], means[2])  # instance of unknown size: free
    free = _node(means.clone(), [0, 0, 1], None)
    free.confine(0.25)
    assert torch.equal(free.gaussians.means.detach(), means)
    one = _node(means.clone(), [0, 0, 1], [[2.0, 1.0, 1.0], [1.0, 1.0, 1.0]])
    one.confine(0.0, torch.tensor([1]))  # only instance 1, into its box itself
    assert torch.equal(one.gaussians.means.detach()[:2], means[:2])
    assert torch.equal(one.gaussians.means.detach()[2], torch.tensor([1.0, 1.0, -1.0]))


def test_box_sizes_follow_instances_and_checkpoints():
    node = _node(torch.zeros(3, 3), [0, 1, 1], [[2.0, 1.0, 1.0], [1.0, 0.5, 0.5]])
    one = GaussianParams(torch.zeros(1, 3), torch.zeros(1, 3), torch.tensor([[1.0, 0, 0, 0]]), torch.zeros(1),
                         torch.zeros(1, 1, 3))
    node.add_instances(one, torch.zeros(1), torch.eye(4).repeat(2, 1, 1, 1), torch.ones(2, 1, dtype=torch.bool),
                       torch.tensor([7]), half_extents=torch.tensor([[3.0, 2.0, 1.0]]))
    assert node.half_extents.tolist() == [[2.0, 1.0, 1.0], [1.0, 0.5, 0.5], [3.0, 2.0, 1.0]]
    node.remove_instances(torch.tensor([True, False, True]))
    assert node.half_extents.tolist() == [[2.0, 1.0, 1.0], [3.0, 2.0, 1.0]]
    again = RigidAgents.from_state(node.state())
    assert torch.equal(again.half_extents, node.half_extents)
    old = {k: v for k, v in node.state().items() if k != "half_extents"}  # a checkpoint from before the boxes
    assert torch.isinf(RigidAgents.from_state(old).half_extents).all()
