"""The scene graph built from a bundle: only the nodes the scene needs, placed where the priors say."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from agg.graph import SceneGraph
from agg.io.bundle import SceneBundle
from agg.nodes.gaussians import GaussianParams
from agg.nodes.init import InitConfig
from agg.synth.corrupt import NoiseConfig
from agg.synth.scene import SceneConfig
from agg.synth.suite import generate, write_bundle


@pytest.fixture(scope="module")
def synth(tmp_path_factory):
    """A synthetic bundle with exact priors (poses, depth, masks, tracklets) and its ground truth."""
    gt, priors = generate(SceneConfig(seed=0, frames=8, width=160, height=96), NoiseConfig())
    path = tmp_path_factory.mktemp("g") / "b"
    write_bundle(path, gt, priors, NoiseConfig())
    return SceneBundle.load(path), gt


def _psnr(a: torch.Tensor, b: np.ndarray, where: np.ndarray) -> float:
    return float(-10 * torch.log10(((a - torch.as_tensor(b)) ** 2)[torch.as_tensor(where)].mean()))


def test_initial_graph_renders_the_clip_and_its_agents(synth):
    bundle, gt = synth
    graph = SceneGraph.from_bundle(bundle, InitConfig(opacity=0.9))
    assert graph.rigid is not None
    assert graph.rigid.num_instances == sum(c == "rigid" for c in bundle.tracklets.classes)
    for frame in (0, 5):
        with torch.no_grad():
            out = graph.render(frame)
        # coloured points at their true depths, before any training; the sky (no depth, no sky node yet) is left out
        psnr = _psnr(out.color, gt.rgb[frame], gt.depth_valid[frame])
        assert psnr > 18.0, psnr
        assert out.alpha[torch.as_tensor(gt.depth_valid[frame])].mean() > 0.95
        g = graph.compose(frame)
        assert g["means"].shape[0] == g["node"].shape[0] == graph.num_gaussians()
    # the agents' Gaussians land on their pixels: render node ids as colours and compare with the GT instances
    from agg.render import rasterize

    g = graph.compose(5)
    onehot = torch.nn.functional.one_hot(g["node"]).float()  # [N, 1 + K]
    with torch.no_grad():
        out = rasterize(g["means"], g["quats"], g["scales"], g["opacities"], colors=onehot, K=graph.K[0],
                        width=160, height=96, viewmat=graph.camera.camera_from_world(torch.tensor([5]))[0])
    node_map = out.color.argmax(-1).numpy()  # [H, W]
    checked = 0
    ids = [int(i) for i in bundle.tracklets.ids]
    for j, tid in enumerate(graph.slot_track_ids().tolist()):
        row = ids.index(tid)
        mask = gt.instance[5] == tid
        if not bundle.tracklets.valid[row, 5] or mask.sum() < 40:
            continue
        drawn = node_map == j + 1
        iou = (drawn & mask).sum() / (drawn | mask).sum()
        assert iou > 0.5, (row, iou)
        checked += 1
    assert checked >= 2


def test_a_scene_without_agents_gets_no_agent_node(synth, tmp_path):
    bundle, _ = synth
    import shutil

    shutil.copytree(bundle.path, tmp_path / "static")
    static = SceneBundle.load(tmp_path / "static")
    static.remove("tracklets")
    graph = SceneGraph.from_bundle(static)
    assert graph.rigid is None and graph.nonrigid is None and set(graph.compose(0)["node"].tolist()) == {0}


def test_initialisation_needs_poses_and_depth(synth, tmp_path):
    import shutil

    shutil.copytree(synth[0].path, tmp_path / "b")
    b = SceneBundle.load(tmp_path / "b")
    b.remove("depth_dense")
    with pytest.raises(ValueError, match="needs depth"):
        SceneGraph.from_bundle(b)
    b.remove("poses")
    with pytest.raises(ValueError, match="needs camera poses"):
        SceneGraph.from_bundle(b)


def test_agent_overrides_move_and_hide_agents_and_state_round_trips(synth):
    bundle, _ = synth
    graph = SceneGraph.from_bundle(bundle, InitConfig(opacity=0.9))
    tid = int(graph.slot_track_ids()[0])
    base = graph.compose(3)
    hidden = graph.compose(3, agent_valid={tid: False})
    rows = base["node"] == 1
    assert base["opacities"][rows].sum() > 0 and hidden["opacities"][rows].sum() == 0
    moved_pose = graph.rigid.world_from_box(3)[0].detach().clone()
    moved_pose[0, 3] += 2.0
    moved = graph.compose(3, agent_poses={tid: moved_pose})
    torch.testing.assert_close(moved["means"][rows], base["means"][rows] + torch.tensor([2.0, 0, 0]))
    torch.testing.assert_close(moved["means"][~rows], base["means"][~rows])
    again = SceneGraph.from_state(graph.state())
    with torch.no_grad():
        torch.testing.assert_close(again.render(3).color, graph.render(3).color)


def test_anchored_agents_keep_their_view_when_the_camera_moves(synth):
    """An anchored instance moves with the camera node's correction, so its pixels neither move nor pull the
    camera; unanchored instances and the background stay in the world. Surgery and the state keep the flags."""
    bundle, _ = synth
    graph = SceneGraph.from_bundle(bundle, InitConfig(opacity=0.9))
    node, frame = graph.rigid, 5
    node.anchored[0] = True
    before = node.world_from_box(frame).detach().clone()  # [K, 4, 4] zero camera correction: the priors
    torch.testing.assert_close(before, node.prior[frame] @ torch.eye(4), atol=1e-5, rtol=0)
    with torch.no_grad():
        graph.camera.tau[frame] = torch.tensor([0.3, -0.1, 0.5])
        graph.camera.omega[frame] = torch.tensor([0.01, 0.02, -0.01])
    cfw = graph.camera.camera_from_world(torch.tensor([frame]))[0].detach()
    prior_cfw = torch.linalg.inv(graph.camera.prior[frame])
    after = node.world_from_box(frame).detach()
    torch.testing.assert_close(cfw @ after[0], prior_cfw @ before[0], atol=1e-5, rtol=0)  # same view of the box
    torch.testing.assert_close(after[1:], before[1:])  # the others keep their world poses
    assert (after[0, :3, 3] - before[0, :3, 3]).norm() > 0.2

    # the anchored agent's pixels give the camera (almost) no gradient: its render does not depend on the camera
    from agg.render import rasterize

    def camera_grad(anchored: bool) -> float:
        node.anchored[0] = anchored
        graph.camera.zero_grad()
        g = graph.compose(frame)
        sel = g["node"] == 1  # the instance's Gaussians alone (the background would occlude them)
        out = rasterize(g["means"][sel], g["quats"][sel], g["scales"][sel], g["opacities"][sel],
                        colors=torch.ones(int(sel.sum()), 1), K=graph.K[0], width=graph.width, height=graph.height,
                        viewmat=graph.camera.camera_from_world(torch.tensor([frame]))[0])
        (out.color[..., 0] ** 2).sum().backward()
        return float(torch.cat([graph.camera.tau.grad[frame], graph.camera.omega.grad[frame]]).norm())

    free, held = camera_grad(False), camera_grad(True)
    assert free > 0 and held < 1e-3 * free, (free, held)

    # surgery: spawned instances are not anchored, removal keeps the flags aligned, the state round-trips
    sel = node.instance == 1
    copy = GaussianParams.from_state({k: v[sel] for k, v in node.gaussians.state().items()})
    node.add_instances(copy, torch.zeros(int(sel.sum()), dtype=torch.long), node.prior[:, 1:2], node.valid[:, 1:2],
                       torch.tensor([99]))
    assert node.anchored.tolist()[-1] is False and bool(node.anchored[0])
    node.remove_instances(torch.arange(node.num_instances) != 1)
    assert bool(node.anchored[0]) and not bool(node.anchored[1:].any())
    again = SceneGraph.from_state(graph.state())
    assert again.rigid.anchored.tolist() == node.anchored.tolist()
    torch.testing.assert_close(again.rigid.world_from_box(frame), node.world_from_box(frame).detach())
