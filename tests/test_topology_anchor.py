"""Re-anchoring a spawned agent's box on its rendered surface (agg.train.topology_anchor): a box whose origin sits
ahead of the car it carries is moved onto the car's centre, and no render changes."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from agg.graph import SceneGraph
from agg.nodes.gaussians import GaussianParams
from agg.nodes.init import InitConfig
from agg.synth.corrupt import NoiseConfig
from agg.synth.scene import SceneConfig
from agg.synth.suite import generate, load_gt_extras, write_bundle
from agg.train.topology_anchor import anchor_offset, estimate_offset, reanchor, reanchor_spawned
from agg.train.topology_track import visible_surface_offset

LEAD = np.array([1.0, 0.0, 0.0])  # the box origin sits 1 m ahead of the car (spawned boxes lead by ~1 m)


def _box_surface(half: np.ndarray, step: float = 0.12) -> np.ndarray:
    """Points [P, 3] on the six faces of a box of half extents [3], centred at the origin."""
    pts = []
    for a in range(3):
        b, c = [i for i in range(3) if i != a]
        gb = np.arange(-half[b], half[b] + 1e-9, step)
        gc = np.arange(-half[c], half[c] + 1e-9, step)
        for sign in (-1.0, 1.0):
            face = np.zeros((len(gb), len(gc), 3))
            face[..., a] = sign * half[a]
            face[..., b], face[..., c] = gb[:, None], gc[None, :]
            pts.append(face.reshape(-1, 3))
    return np.concatenate(pts)


@pytest.fixture(scope="module")
def leading_box(tmp_path_factory):
    """A clip whose missed car is added back as a rigid instance with the right Gaussians (a dense box surface)
    but a box origin ``LEAD`` ahead of the car's centre, as a spawn leaves it."""
    path = tmp_path_factory.mktemp("anchor") / "clip"
    noise = NoiseConfig(missed=1)
    gt, priors = generate(SceneConfig(seed=0, frames=8, width=160, height=96, pedestrians=0), noise)
    bundle = write_bundle(path, gt, priors, noise)
    torch.manual_seed(0)
    graph = SceneGraph.from_bundle(bundle, InitConfig(background_budget=2000, seed=0))
    extras = load_gt_extras(path)
    ids = [a["id"] for a in extras["index"]["agents"]]
    k = ids.index(extras["index"]["missed_ids"][0])
    l, w, h = extras["index"]["agents"][k]["size_lwh"]
    half = 0.5 * np.array([l, h, w])  # box frame: x = l, y = h, z = w
    gt_pose = extras["world_from_agent"][k]  # [T, 4, 4]
    valid = extras["pixel_count"][k] > 0  # [T]
    surface = _box_surface(half) - LEAD  # canonical: the car's centre is LEAD behind the origin
    params = GaussianParams.from_points(surface, np.full((len(surface), 3), 0.6), graph.rigid.gaussians.sh_degree,
                                        opacity=0.99, scales=np.full(len(surface), 0.08))
    lead = np.eye(4)
    lead[:3, 3] = LEAD
    prior = torch.as_tensor(gt_pose @ lead, dtype=torch.float32)[:, None]  # [T, 1, 4, 4]
    new_id = int(graph.rigid.track_ids.max()) + 100
    graph.rigid.add_instances(params, torch.zeros(len(surface), dtype=torch.long), prior,
                              torch.as_tensor(valid)[:, None], torch.tensor([new_id]))
    with torch.no_grad():  # corrections that are not zero: the shift must compose with them
        graph.rigid.omega[:, -1] = torch.tensor([0.0, 0.02, 0.0])
        graph.rigid.tau[:, -1] = torch.tensor([0.05, 0.0, -0.03])
    return graph, new_id, half, gt_pose, valid


def _centres(node, j: int) -> np.ndarray:
    with torch.no_grad():
        return np.stack([node.world_from_box(t)[j, :3, 3].numpy() for t in range(node.num_frames)])


def test_the_rendered_surface_moves_a_leading_box_onto_the_car_and_renders_do_not_change(leading_box):
    graph, new_id, half, gt_pose, valid = leading_box
    node = graph.rigid
    j = node.track_ids.tolist().index(new_id)
    before = np.linalg.norm(_centres(node, j) - gt_pose[:, :3, 3], axis=1)[valid]
    assert np.all(before > 0.9)
    offset, frames, fit = estimate_offset(graph, node, j, half, near=0.3)
    assert frames == int(valid.sum()) and fit > 0.95  # a box surface: the moved box holds all of it
    assert np.linalg.norm(offset + LEAD) < 0.25, offset  # the car's centre: LEAD behind the origin
    with torch.no_grad():
        renders = [graph.render(t) for t in range(0, graph.num_frames, 3)]
    moved = reanchor_spawned(graph, {new_id}, {new_id: half}, near=0.3, metres_per_unit=1.0)
    assert list(moved) == [str(new_id)] and moved[str(new_id)]["applied"]
    assert moved[str(new_id)]["offset_m"][1:] == [0.0, 0.0]  # along the heading only
    after = np.linalg.norm(_centres(node, j) - gt_pose[:, :3, 3], axis=1)[valid]
    assert np.all(after < 0.25), after
    with torch.no_grad():
        for t, r in zip(range(0, graph.num_frames, 3), renders):
            again = graph.render(t)
            # float32 rounding of the shifted means can swap the depth order of coplanar face Gaussians: a few
            # pixels may move by a few 1e-4, nothing more
            for a, b in ((again.color, r.color), (again.alpha, r.alpha)):
                diff = (a - b).abs()
                assert diff.max() < 1e-2 and (diff > 1e-4).float().mean() < 1e-3, diff.max()
    # a second pass finds the box centred along its heading and leaves it
    offset2, _, _ = estimate_offset(graph, node, j, half, near=0.3)
    assert abs(offset2[0]) < 0.05, offset2


def test_instances_not_spawned_keep_their_boxes(leading_box):
    graph, new_id, half, _, _ = leading_box
    prior_ids = [int(t) for t in graph.rigid.track_ids.tolist() if t != new_id]
    tau = graph.rigid.tau.detach().clone()
    assert reanchor_spawned(graph, set(), {t: half for t in prior_ids}, near=0.3, metres_per_unit=1.0) == {}
    assert torch.equal(graph.rigid.tau, tau)


def test_a_box_that_does_not_explain_the_surface_is_left_alone(leading_box):
    """The fit gate: with a share the box cannot reach, the offset is reported and not applied."""
    graph, new_id, half, _, _ = leading_box
    tau, means = graph.rigid.tau.detach().clone(), graph.rigid.gaussians.means.detach().clone()
    out = reanchor_spawned(graph, {new_id}, {new_id: half}, near=0.3, metres_per_unit=1.0, min_fit=1.01)
    assert out[str(new_id)]["applied"] is False and 0 < out[str(new_id)]["fit"] <= 1
    assert torch.equal(graph.rigid.tau, tau) and torch.equal(graph.rigid.gaussians.means, means)


def test_anchor_offset_inverts_the_visible_surface_model():
    half = np.array([2.2, 0.75, 0.9])
    centre = np.array([-0.8, 0.1, 0.3])  # box-frame centre the surface belongs to
    cams = np.array([[-12.0, 1.5, 2.0], [-8.0, 1.5, -3.0], [5.0, 1.4, 9.0]])  # behind, behind-right, ahead-left
    m = np.stack([centre + visible_surface_offset(half, c - centre) for c in cams])  # [3, 3] visible centroids
    offset, per_frame = anchor_offset(m, cams, half)
    np.testing.assert_allclose(per_frame, np.tile(centre, (3, 1)), atol=1e-3)
    np.testing.assert_allclose(offset, centre, atol=1e-3)


def test_reanchor_composes_with_the_pose_corrections():
    """world_from_box = prior @ [exp(omega) | tau]: after the shift every canonical point lands where it did."""
    from agg.nodes.rigid import RigidAgents

    torch.manual_seed(1)
    g = GaussianParams.from_points(np.random.default_rng(0).normal(size=(30, 3)), np.full((30, 3), 0.5), 0,
                                   opacity=0.5, scales=np.full(30, 0.1))
    node = RigidAgents(g, torch.zeros(30, dtype=torch.long), torch.eye(4).repeat(4, 1, 1, 1),
                       torch.ones(4, 1, dtype=torch.bool))
    with torch.no_grad():
        node.omega.normal_(0, 0.3)
        node.tau.normal_(0, 1.0)
    before = [node.compose(t)["means"].detach().clone() for t in range(4)]
    reanchor(node, 0, np.array([0.7, -0.2, 1.1]))
    for t in range(4):
        torch.testing.assert_close(node.compose(t)["means"], before[t], atol=1e-5, rtol=0)
