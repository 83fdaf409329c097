"""The scene graph built from a bundle: only the nodes the scene needs, placed where the priors say."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from agg.graph import SceneGraph
from agg.io.bundle import SceneBundle
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
        assert g["means"].shape[0] == g["node"].shape[0] == len(graph.background) + len(graph.rigid.gaussians)
    # the agents' Gaussians land on their pixels: render node ids as colours and compare with the GT instances
    from agg.render import rasterize

    g = graph.compose(5)
    onehot = torch.nn.functional.one_hot(g["node"]).float()  # [N, 1 + K]
    with torch.no_grad():
        out = rasterize(g["means"], g["quats"], g["scales"], g["opacities"], colors=onehot, K=graph.K[0],
                        width=160, height=96, viewmat=graph.camera.camera_from_world(torch.tensor([5]))[0])
    node_map = out.color.argmax(-1).numpy()  # [H, W]
    checked = 0
    for j, row in enumerate(graph.track_rows):
        mask = gt.instance[5] == int(bundle.tracklets.ids[row])
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
    assert graph.rigid is None and set(graph.compose(0)["node"].tolist()) == {0}


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
