"""Agents stay in their boxes: the canonical means of every agent instance are clamped into its box (grown by
``TrainConfig.agent_box_margin``) after each optimiser step on the agents, and the box sizes travel with the node
(initialisation from the tracklets, spawned agents, checkpoints, removal)."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from agg.graph import SceneGraph
from agg.io.bundle import SceneBundle
from agg.nodes.gaussians import GaussianParams
from agg.nodes.rigid import RigidAgents
from agg.synth.corrupt import NoiseConfig
from agg.synth.scene import SceneConfig
from agg.synth.suite import generate, write_bundle
from agg.train.config import get_preset
from agg.train.data import load_train_data
from agg.train.trainer import Trainer, seed_everything


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


@pytest.fixture(scope="module")
def bundle(tmp_path_factory):
    noise = NoiseConfig(camera_translation_max=0.5)
    gt, priors = generate(SceneConfig(seed=1, frames=10, width=128, height=80), noise)
    path = tmp_path_factory.mktemp("boxes") / "b"
    write_bundle(path, gt, priors, noise)
    return SceneBundle.load(path)


@pytest.mark.parametrize("margin", [0.25, None])
def test_training_keeps_every_agent_gaussian_in_its_box(bundle, margin):
    """A real (tiny) training run at the paper's x10 agent rates: with the margin every canonical mean ends
    inside its tracklet box grown by it; without (None, the old behaviour) the agents' Gaussians leave it."""
    cfg = replace(get_preset("tiny"), iterations=60, agent_box_margin=margin, ablate=frozenset({"topology"}))
    seed_everything(cfg.seed)
    graph = SceneGraph.from_bundle(bundle, cfg.init)
    expected = {int(t): 0.5 * bundle.tracklets.box_size(k) for k, t in enumerate(bundle.tracklets.ids)}
    for node in graph.agent_nodes():
        for j, tid in enumerate(node.track_ids.tolist()):  # sizes come from the tracklets
            assert node.half_extents[j].tolist() == pytest.approx(expected[tid].tolist())
    Trainer(graph, load_train_data(bundle, cfg.max_width), cfg, bundle).run()
    ratio = torch.cat([(n.gaussians.means.detach().abs() / n.half_extents[n.instance]).amax(-1)
                       for n in graph.agent_nodes()])  # [N] largest |coordinate| / half extent
    if margin is None:
        assert (ratio > 1.25 + 1e-4).any()
    else:
        assert ratio.max() <= 1.25 + 1e-4
