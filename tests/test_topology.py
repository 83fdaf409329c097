"""Adaptive topology evolution (Algorithm 1) on synthetic clips: spawning a missed car from real background
gradients, pruning a dead false agent, reassigning entangled background Gaussians, no spawn in a static scene."""

from __future__ import annotations

import copy
from dataclasses import replace

import numpy as np
import pytest
import torch

from agg.graph import SceneGraph
from agg.io.bundle import SceneBundle
from agg.nodes.gaussians import GaussianParams, append_rows
from agg.nodes.init import InitConfig
from agg.priors.metric_scale import estimate_metric_scale
from agg.synth.corrupt import NoiseConfig
from agg.synth.scene import SceneConfig
from agg.synth.suite import generate, load_gt_extras, write_bundle
from agg.train.topology import TopologyConfig, TopologyEvolution, frame_seconds
from agg.train.topology_motion import MotionConfig
from agg.train.topology_spawn import box_speed
from agg.train.topology_track import visible_surface_offset

LRS = {"means": 1e-3, "log_scales": 5e-3, "quats": 1e-3, "opacity_logits": 5e-2, "sh": 5e-3}


def _clip(path, scene: SceneConfig, noise: NoiseConfig, budget: int) -> tuple[SceneBundle, SceneGraph]:
    gt, priors = generate(scene, noise)
    bundle = write_bundle(path, gt, priors, noise)
    torch.manual_seed(0)
    return bundle, SceneGraph.from_bundle(bundle, InitConfig(background_budget=budget, seed=0))


def _topology(bundle: SceneBundle, images: np.ndarray | None = None, seconds: float | None = None,
              **overrides) -> TopologyEvolution:
    """The evolution of a bundle; with ``images`` ([T, H, W, 3] uint8, e.g. the bundle's frames) a planned spawn
    must move in them (topology_motion), as in training. A planned spawn's speed is read with the bundle's frame
    interval, as in training, or with ``seconds`` per frame."""
    return TopologyEvolution(TopologyConfig(**overrides), bundle.semantics, bundle.intrinsics, bundle.width,
                             bundle.height, bundle.scale, depth=bundle.dense_depth, reserved_ids=bundle.tracklets.ids,
                             images=images, frame_seconds=seconds or frame_seconds(bundle.timestamps_us))


def _frames(bundle: SceneBundle) -> np.ndarray:
    """[T, H, W, 3] uint8 frames of a bundle (the synthetic suite stores them as floats in [0, 1])."""
    f = np.stack([bundle.frame(i) for i in range(bundle.num_frames)])
    return f if f.dtype == np.uint8 else np.round(np.clip(f, 0.0, 1.0) * 255.0).astype(np.uint8)


def _fit_background(bundle: SceneBundle, graph: SceneGraph, topo: TopologyEvolution, steps: int):
    """A real photometric fit of the background only (Adam, L1), feeding the topology statistics each step."""
    opt = torch.optim.Adam(graph.background.param_groups("background", LRS))
    frames = torch.as_tensor(_frames(bundle), dtype=torch.float32) / 255.0  # [T, H, W, 3]
    for step in range(steps):
        f = step % bundle.num_frames
        loss = (graph.render(f).color - frames[f]).abs().mean()
        opt.zero_grad()
        loss.backward()
        topo.accumulate(f, graph.background.means.grad)
        opt.step()
    return opt


@pytest.fixture(scope="module")
def missed(tmp_path_factory):
    """8 frames whose most visible moving car is missing from the priors, background fitted for 80 steps."""
    path = tmp_path_factory.mktemp("topo") / "missed"
    bundle, graph = _clip(path, SceneConfig(seed=0, frames=8, width=160, height=96, pedestrians=0),
                          NoiseConfig(missed=1), budget=6000)
    topo = _topology(bundle, _frames(bundle))
    opt = _fit_background(bundle, graph, topo, steps=80)
    return bundle, graph, topo, opt, load_gt_extras(path)


def test_a_missed_moving_car_is_spawned_on_its_trajectory(missed):
    bundle, graph, topo, opt, extras = missed
    missed_id = extras["index"]["missed_ids"][0]
    gt_poses = extras["world_from_agent"][missed_id - 1]  # [T, 4, 4]; GT ids are 1..K
    n_bg, n_agents = len(graph.background), graph.rigid.num_instances
    # the motion test at half the training width (its residual shrinks wider frames: MotionConfig.max_width) reads
    # the car's motion too (measured 0.25, 0.18 at full width), on copies of the graph and the statistics
    half_width = copy.deepcopy(topo)
    half_width.config = replace(topo.config, motion=MotionConfig(max_width=bundle.width // 2))
    shrunk = half_width.evolve(copy.deepcopy(graph), None, iteration=80)
    assert len(shrunk["spawned"]) == 1 and shrunk["moving"][0] >= topo.config.motion.min_share, shrunk["moving"]
    # with a spawn box (spawn_box_slack, off by default) the spawn takes only the planned rows inside its box, the
    # guessed car size grown by the slack; the others (the car's smear along its path) stay in the background, and
    # the node keeps the box, so the trainer confines the agent to it
    boxed = copy.deepcopy(topo)
    boxed.config = replace(topo.config, spawn_box_slack=0.25)
    boxed_graph = copy.deepcopy(graph)
    in_box = boxed.evolve(boxed_graph, None, iteration=80)
    assert len(in_box["spawned"]) == 1 and len(in_box["boxed"]) == 1
    node, k = boxed_graph.rigid, boxed_graph.rigid.num_instances - 1
    assert np.allclose(node.half_extents[k].numpy(), boxed.box_half[in_box["spawned"][0]] * 1.25, rtol=1e-5)
    assert (node.gaussians.means[node.instance == k].abs() <= node.half_extents[k] + 1e-5).all()
    # spawn_box_rows="all": it takes every planned row and pulls the ones outside the box onto it
    pulled = copy.deepcopy(topo)
    pulled.config = replace(topo.config, spawn_box_slack=0.25, spawn_box_rows="all")
    pulled_graph = copy.deepcopy(graph)
    all_rows = pulled.evolve(pulled_graph, None, iteration=80)
    assert len(all_rows["spawned"]) == 1 and all_rows["boxed"] == in_box["boxed"]
    node_all, k_all = pulled_graph.rigid, pulled_graph.rigid.num_instances - 1
    assert (node_all.gaussians.means[node_all.instance == k_all].abs() <= node_all.half_extents[k_all] + 1e-5).all()
    with pytest.raises(ValueError, match="spawn_box_rows"):
        replace(topo.config, spawn_box_rows="outside")
    report = topo.evolve(graph, opt, iteration=80)
    assert len(report["spawned"]) == 1 and report["structure_changed"] and report["candidates"] > 100
    # it moves in the video: more of its box's pixels than of the frame (topology_motion; measured 0.18 here)
    assert report["static"] == [] and len(report["moving"]) == 1, report
    assert report["moving"][0] >= topo.config.motion.min_share, report["moving"]
    new_id = report["spawned"][0]
    assert new_id == max(int(i) for i in bundle.tracklets.ids) + 1
    assert graph.rigid.num_instances == n_agents + 1
    j = graph.rigid.track_ids.tolist().index(new_id)
    prior, valid = graph.rigid.prior[:, j].numpy(), graph.rigid.valid[:, j].numpy()
    dist = np.linalg.norm(prior[:, :3, 3] - gt_poses[:, :3, 3], axis=1)
    yaw_err = np.rad2deg(np.abs(np.angle(np.exp(1j * (np.arctan2(prior[:, 0, 2], prior[:, 0, 0])
                                                        - np.arctan2(gt_poses[:, 0, 2], gt_poses[:, 0, 0]))))))
    print("spawned-vs-GT centre distance (m) per frame:", np.round(dist, 2), "yaw error (deg):", np.round(yaw_err, 1))
    # after 80 steps of a static fit the clusters' centroids put the box 0.16-0.28 m off the car and its semantic
    # silhouette's 0.12-0.25 m (topology_silhouette); the 0.85-0.95 m ahead that the docs cite for this clip came
    # from the fit this test had before, which aimed at near-black frames
    assert (dist < 0.5).all() and report["silhouette"][0] >= 0.8 * bundle.num_frames, (dist, report["silhouette"])
    assert yaw_err.max() < 15.0, yaw_err
    assert valid.mean() >= 0.8
    # its track's speed is an estimate: only the spawned instance's correction is free (nodes/rigid.py)
    assert graph.rigid.speed_free.tolist() == [i == j for i in range(graph.rigid.num_instances)]
    # its Gaussians left the background (the report's keep mask says which rows), the optimiser follows
    moved = int((graph.rigid.instance == j).sum())
    assert moved >= 100 and len(graph.background) == n_bg - moved == len(report["bg_src"])
    # by default it took every planned row and is left free; with the spawn box it took the share inside the box
    assert report["boxed"] == [] and torch.isinf(graph.rigid.half_extents[j]).all()
    inside = int((boxed_graph.rigid.instance == boxed_graph.rigid.num_instances - 1).sum())
    print(f"spawned rows: {inside} inside the box of {moved} planned ({in_box['boxed']})")
    assert in_box["boxed"] == [round(inside / moved, 3)] and inside < moved
    assert len(boxed_graph.background) == n_bg - inside
    assert int((node_all.instance == k_all).sum()) == moved and len(pulled_graph.background) == n_bg - moved
    assert opt.state[graph.background.means]["exp_avg"].shape[0] == len(graph.background)
    assert topo.sum is None  # statistics reset after an evolution
    # the new agent renders where the car is: its Gaussians cover the missed car's pixels in a middle frame
    frame = bundle.num_frames // 2
    g = graph.compose(frame)
    colors = (g["node"] == j + 1).float()[:, None].repeat(1, 3)  # rigid instance j is compose slot j + 1
    with torch.no_grad():
        drawn = graph.render(frame, colors=colors).color[..., 0].numpy() > 0.5
    car = extras["instance"][frame] == missed_id
    assert (drawn & car).sum() / car.sum() > 0.5
    # later evolutions (and the trainer, when training ends) re-anchor the spawned box: renders do not change
    assert topo.state_dict()["spawned_ids"] == [new_id]
    with torch.no_grad():
        before = graph.render(frame).color
        moved = topo.reanchor(graph)
        assert list(moved) == [str(new_id)] and torch.allclose(graph.render(frame).color, before, atol=1e-4)


def test_a_track_that_does_not_move_in_the_video_is_not_spawned(tmp_path):
    """The missed-car clip and its background fit, with the car frozen at its first pose in the video that the
    motion test reads (re-rendered): the planned spawn's box shows no motion against the static world, so it spawns
    no agent and the report lists its share under ``static``. The real video spawns it
    (test_a_missed_moving_car_is_spawned_on_its_trajectory)."""
    from agg.synth.raycast import ValueNoise, render_scene_frame
    from agg.synth.scene import make_scene

    scene_cfg = SceneConfig(seed=0, frames=8, width=160, height=96, pedestrians=0)
    bundle, graph = _clip(tmp_path / "frozen", scene_cfg, NoiseConfig(missed=1), budget=6000)
    missed_id = load_gt_extras(tmp_path / "frozen")["index"]["missed_ids"][0]
    scene = make_scene(scene_cfg)
    car = scene.agents[missed_id - 1]  # GT ids are 1..K in the scene's order
    assert car.moving
    car.world_from_agent[:] = car.world_from_agent[0]
    noise = ValueNoise(scene.texture_seed)
    frozen = np.stack([render_scene_frame(scene, i, noise).rgb for i in range(scene.frames)])  # [T, H, W, 3]
    frozen = np.round(frozen * 255.0).astype(np.uint8)
    changed = np.abs(frozen.astype(np.int16) - _frames(bundle)).max(-1) > 8  # [T, H, W]: only the car differs
    assert changed[0].mean() < 0.01 and 0.005 < changed[1:].mean() < 0.1
    topo = _topology(bundle, frozen)
    opt = _fit_background(bundle, graph, topo, steps=80)  # on the real frames: the same gradients
    n_agents = graph.rigid.num_instances
    report = topo.evolve(graph, opt, iteration=80)
    print("excess moving share of the frozen car's box:", report["static"], report["moving"])
    assert report["spawned"] == [] and graph.rigid.num_instances == n_agents
    assert len(report["static"]) == 1 and report["static"][0] < topo.config.motion.min_share, report["static"]


def test_a_monocular_scale_spawns_the_missed_car_where_metres_are_estimated(tmp_path):
    """The missed-car clip with every length divided by its path length f and marked not metric (what a video's
    priors are: median sparse depth 1). Read through the road-plane estimate of metres per unit, the car spawns
    as in metres (0.12-0.25 m off). (Reading scene units as metres puts every metric threshold f times too wide;
    on this clean clip the silhouette, which needs no metric threshold, still places the box: it was a negative
    control here only while the test's background fit aimed at frames divided by 255 twice.)"""
    path = tmp_path / "mono"
    bundle, _ = _clip(path, SceneConfig(seed=0, frames=8, width=160, height=96, pedestrians=0), NoiseConfig(missed=1),
                      budget=6000)
    f = bundle.normalise_scale("path_length")
    bundle.set_scale(1.0, metric=False)
    bundle = SceneBundle.load(path)
    torch.manual_seed(0)
    graph = SceneGraph.from_bundle(bundle, InitConfig(background_budget=6000, seed=0))
    est = estimate_metric_scale(bundle)
    assert est.source == "camera_height" and est.metres_per_unit == pytest.approx(f, rel=0.1)
    topo = TopologyEvolution(TopologyConfig(), bundle.semantics, bundle.intrinsics, bundle.width, bundle.height,
                             est.metres_per_unit, depth=bundle.dense_depth, reserved_ids=bundle.tracklets.ids,
                             images=_frames(bundle))
    opt = _fit_background(bundle, graph, topo, steps=80)
    extras = load_gt_extras(path)
    gt_poses = extras["world_from_agent"][extras["index"]["missed_ids"][0] - 1]  # [T, 4, 4], metres
    report = topo.evolve(graph, opt, iteration=80)
    assert len(report["spawned"]) == 1
    j = graph.rigid.track_ids.tolist().index(report["spawned"][0])
    dist = np.linalg.norm(graph.rigid.prior[:, j, :3, 3].numpy() * f - gt_poses[:, :3, 3], axis=1)  # metres
    print("spawned-vs-GT centre distance (m):", np.round(dist, 2))
    assert (dist < 0.5).all(), dist


def test_a_dead_false_agent_is_pruned(tmp_path):
    bundle, graph = _clip(tmp_path / "false", SceneConfig(seed=1, frames=4, width=96, height=64, pedestrians=0),
                          NoiseConfig(false=1), budget=2000)
    false_id = load_gt_extras(tmp_path / "false")["index"]["false_ids"][0]
    ids_before = graph.rigid.track_ids.tolist()
    assert false_id in ids_before
    opt = torch.optim.Adam(graph.rigid.param_groups("rigid", LRS, 1e-4))
    with torch.no_grad():  # the false agent's opacities decayed to ~0 (what training does to an empty box)
        dead = graph.rigid.instance == ids_before.index(false_id)
        graph.rigid.gaussians.opacity_logits[dead] = -12.0
    topo = _topology(bundle)
    report = topo.evolve(graph, opt)
    assert report["pruned"] == [false_id] and report["structure_changed"] and report["spawned"] == []
    assert graph.rigid.track_ids.tolist() == [i for i in ids_before if i != false_id]
    assert (torch.sigmoid(graph.rigid.gaussians.opacity_logits) > 0.01).all()
    # the optimiser's rows follow the node (one Adam step on the pruned node works)
    loss = graph.render(0).color.mean()
    opt.zero_grad()
    loss.backward()
    opt.step()
    assert topo.evolve(graph, opt)["pruned"] == []
    # a pruned id is never handed out again
    assert topo.next_track_id(graph) > max(ids_before)


def test_a_live_false_agent_on_the_road_is_demoted_to_background(tmp_path):
    """A planted false car keeps its road Gaussians opaque (nothing dies out), but it is static and reads road
    features: it leaves the graph, its Gaussians join the background where they render the same pixels, and
    every real agent (moving cars, parked cars) stays."""
    bundle, graph = _clip(tmp_path / "live", SceneConfig(seed=1, frames=6, width=128, height=80, pedestrians=0),
                          NoiseConfig(false=1), budget=3000)
    index = load_gt_extras(tmp_path / "live")["index"]
    false_id = index["false_ids"][0]
    ids_before = graph.rigid.track_ids.tolist()
    k = ids_before.index(false_id)
    mine = graph.rigid.instance == k
    opacity = torch.sigmoid(graph.rigid.gaussians.opacity_logits.detach()[mine])
    assert int(mine.sum()) > 20 and float(opacity.min()) > 0.05  # alive: nothing died out
    frame = int(np.flatnonzero(graph.rigid.valid[:, k].numpy())[0])
    with torch.no_grad():
        before = graph.render(frame).color
    n_bg, n_false = len(graph.background), int(mine.sum())
    report = _topology(bundle).evolve(graph, None)
    assert report["demoted"] == [false_id] and report["pruned"] == [false_id] and report["structure_changed"]
    assert graph.rigid.track_ids.tolist() == [i for i in ids_before if i != false_id]  # real agents all stay
    assert len(graph.background) == n_bg + n_false
    assert (report["bg_src"][n_bg:] == -1).all() and (report["bg_src"][:n_bg] == torch.arange(n_bg)).all()
    with torch.no_grad():  # the road it rendered is still rendered (same Gaussians, now in the background)
        after = graph.render(frame).color
    assert float((after - before).abs().max()) < 1e-4


def test_demotion_needs_a_static_agent():
    from agg.train.topology_demote import static_instances

    t = np.arange(10.0)
    centres = np.stack([np.stack([0 * t, 0 * t, 0.05 * t], 1), np.stack([0 * t, 0 * t, 0.5 * t], 1)], 1)  # [T, 2, 3]
    valid = np.ones((10, 2), bool)
    assert static_instances(centres, valid, 1.0).tolist() == [True, False]
    valid[:, 0] = False
    assert static_instances(centres, valid, 1.0).tolist() == [False, False]  # no valid frame: nothing to judge


def test_background_gaussians_inside_an_agent_box_are_reassigned(tmp_path):
    bundle, graph = _clip(tmp_path / "exact", SceneConfig(seed=2, frames=4, width=96, height=64, pedestrians=0),
                          NoiseConfig(), budget=2000)
    rigid = graph.rigid
    frame = 2
    # the parked car valid at that frame with the most Gaussians: its canonical Gaussians planted in the background
    # (world frame), as if the background had absorbed it (a parked car: every frame's pose puts them back in place)
    travel = (rigid.prior[:, :, :3, 3] - rigid.prior[frame, None, :, :3, 3]).norm(dim=-1).amax(0)  # [K]
    counts = torch.bincount(rigid.instance, minlength=rigid.num_instances) * rigid.valid[frame] * (travel < 1e-3)
    k = int(counts.argmax())
    assert counts[k] > 50
    sel = rigid.instance == k
    canon = rigid.gaussians.means.detach()[sel].clone()
    with torch.no_grad():
        world = rigid.compose(frame)["means"][sel]
    planted = GaussianParams(world, rigid.gaussians.log_scales.detach()[sel], rigid.gaussians.quats.detach()[sel],
                             rigid.gaussians.opacity_logits.detach()[sel], rigid.gaussians.sh.detach()[sel])
    n_bg = len(graph.background)
    append_rows(graph.background, planted)
    # gradient statistics: the planted rows pull hard (10x the rest) in every frame
    grad = torch.full((len(graph.background), 3), 1e-4)
    grad[n_bg:] = 1e-3
    topo = _topology(bundle, min_samples=10)
    for f in range(bundle.num_frames):
        topo.accumulate(f, grad)
    n_agent = len(rigid.gaussians)
    report = topo.evolve(graph, None)
    assert report["spawned"] == [] and not report["structure_changed"]
    assert report["reassigned"] >= 0.9 * len(planted), (report["reassigned"], len(planted))
    assert len(graph.background) == n_bg + len(planted) - report["reassigned"]
    assert len(rigid.gaussians) == n_agent + report["reassigned"]
    assert set(range(n_bg)) <= set(report["bg_src"].tolist())  # no original background row moved
    new = rigid.gaussians.means.detach()[n_agent:]
    assert (rigid.instance[n_agent:] == k).all()
    # in the canonical frame they land back on the instance's own Gaussians
    d = torch.cdist(new, canon).min(1).values
    assert float(d.max()) < 1e-3


def test_a_static_scene_spawns_nothing(tmp_path):
    bundle, graph = _clip(tmp_path / "static", SceneConfig(seed=3, frames=6, width=128, height=80, moving_cars=0,
                                                           pedestrians=0), NoiseConfig(), budget=4000)
    topo = _topology(bundle)
    opt = _fit_background(bundle, graph, topo, steps=48)
    n_agents = graph.rigid.num_instances
    report = topo.evolve(graph, opt)
    assert report["spawned"] == [] and report["pruned"] == []
    assert graph.rigid.num_instances == n_agents


def test_statistics_follow_row_changes_and_checkpoints(missed, tmp_path):
    bundle = missed[0]
    topo = _topology(bundle)
    grads = torch.arange(12, dtype=torch.float32)[:, None] * torch.tensor([[1.0, 0.0, 0.0]])  # norms 0..11
    topo.accumulate(1, grads)
    topo.accumulate(1, 3 * grads)
    mean, has = topo.mean_gradients()
    assert has.tolist() == [i == 1 for i in range(bundle.num_frames)] and np.allclose(mean[1], 2 * np.arange(12))
    topo.on_rows_changed(torch.tensor([0, 5, 5, 11]))  # prune most, clone row 5
    assert np.allclose(topo.mean_gradients()[0][1], [0, 10, 10, 22])
    with pytest.raises(ValueError, match="on_rows_changed"):
        topo.accumulate(0, grads)
    torch.save(topo.state_dict(), tmp_path / "topo.pt")
    other = _topology(bundle)
    other.load_state_dict(torch.load(tmp_path / "topo.pt"))
    assert np.allclose(other.mean_gradients()[0], topo.mean_gradients()[0]) and other.retired == topo.retired
    cfg = TopologyConfig().scaled(0.1)
    assert (cfg.every, cfg.stop) == (500, 2000)
    assert [i for i in range(0, 2500, 250) if cfg.due(i)] == [500, 1000, 1500, 2000]
    balanced = TopologyConfig().scaled(2000 / 30000)  # 333.3 rounds to 333: stop stays a multiple of it
    assert [i for i in range(2001) if balanced.due(i)] == [333, 666, 999, 1332]
    assert [balanced.due_after(i, 2000) for i in (0, 333, 1000, 1332)] == [4, 3, 1, 0]
    assert balanced.due_after(0, 700) == 2  # a shorter run stops at its end


def test_visible_surface_offset_recovers_a_box_centre():
    half = np.array([2.0, 0.75, 0.9])
    # seen straight from behind (camera on -x looking along +x): the visible face is x = -l/2
    assert np.allclose(visible_surface_offset(half, np.array([-20.0, 0.0, 0.0])), [-2.0, 0.0, 0.0])
    # seen from the front-left and above: the centroid moves toward every visible face, never past the box
    off = visible_surface_offset(half, np.array([0.6, -0.3, -0.74]) * 15.0)
    assert off[0] > 0 and off[1] < 0 and off[2] < 0 and np.all(np.abs(off) <= half)


def test_a_spawned_trajectory_extends_while_the_features_see_the_agent():
    """A track seen on frames 5..9 (1 m / frame along x) is extrapolated at its velocity: 2 frames on either side
    while in view, and further for as long as every frame shows evidence of the agent; then held (invalid)."""
    from agg.train.topology_track import trajectory_poses

    t = np.arange(20.0)
    state = np.full((20, 6), np.nan)
    state[5:10] = np.stack([t[5:10], 0 * t[5:10], 10 + 0 * t[5:10], 1 + 0 * t[5:10], 0 * t[5:10], 0 * t[5:10]], 1)
    kw = {"min_speed": 0.05, "extend": 2, "in_view": lambda i, c: True, "fallback_yaw": 0.0}
    poses, valid = trajectory_poses(state, **kw)
    assert np.flatnonzero(valid).tolist() == list(range(3, 12))
    seen = []  # in_view is asked about the extrapolated box: its centre and the track's heading (+x)
    trajectory_poses(state, **{**kw, "in_view": lambda i, pose: seen.append((i, pose)) or True})
    i, pose = next((i, pose) for i, pose in seen if i == 11)
    np.testing.assert_allclose(pose[:3, 3], [11.0, 0.0, 10.0])
    np.testing.assert_allclose(pose[:3, 0], [1.0, 0.0, 0.0], atol=1e-12)
    poses, valid = trajectory_poses(state, **kw, evidence=lambda i, c: 1 <= i <= 14 and i != 13)
    assert np.flatnonzero(valid).tolist() == list(range(1, 13))  # the chain stops at the first frame without it
    np.testing.assert_allclose(poses[:13, 0, 3], np.concatenate([[1.0], t[1:13]]))  # x = frame, linear
    np.testing.assert_allclose(poses[13:, 0, 3], 12.0)  # held after the last valid frame
    assert poses[0, 0, 3] == 1.0


def test_region_agent_fraction_reads_the_cells_around_a_pixel_and_skips_other_agents():
    from agg.train.topology_view import region_agent_fraction

    bank = {"background": np.array([[1.0, 0, 0]]), "rigid": np.array([[0, 1.0, 0]]),
            "non-rigid": np.array([[0, 0, 1.0]])}
    feats = np.zeros((10, 20, 3), np.float32)
    feats[..., 0] = 1.0  # background everywhere (cells of 8 x 8 pixels at 160 x 80)
    feats[2:6, 4:8] = [0, 1, 0]  # a car: cells x 4..7, y 2..5 = pixels x 32..63, y 16..47
    car = np.array([48.0, 32.0])
    assert region_agent_fraction(feats, bank, 0.5, car, 12.0, 160, 80) == 1.0
    assert region_agent_fraction(feats, bank, 0.5, np.array([130.0, 60.0]), 12.0, 160, 80) == 0.0
    # a larger square: cells x 1..11, y 0..9 (clipped), 16 of those 110 on the car
    assert region_agent_fraction(feats, bank, 0.5, car, 40.0, 160, 80) == pytest.approx(16 / 110)
    exclude = np.zeros((80, 160), bool)
    exclude[16:48, 32:64] = True  # another agent's prior mask covers the car: no cell of it counts
    assert region_agent_fraction(feats, bank, 0.5, car, 12.0, 160, 80, exclude) == 0.0
    # the larger square cut to the car's pixels (a box's part in the image) reads the car alone
    within = (np.array([32.0, 16.0]), np.array([63.0, 47.0]))
    assert region_agent_fraction(feats, bank, 0.5, car, 40.0, 160, 80, within=within) == 1.0
    assert region_agent_fraction(feats, bank, 0.5, np.array([130.0, 60.0]), 12.0, 160, 80, within=within) == 0.0


def test_height_above_road_reads_the_image_space_plane_of_a_pitched_camera():
    """The inverse-depth plane w = a u + b v + c that a pitched and rolled camera sees of a flat road gives every
    camera-frame point's height over that road, and the camera's own height."""
    from agg.priors.tracklet_ground import height_above_road
    from agg.synth.scene import rot_y

    K = np.array([[200.0, 0, 80], [0, 200.0, 50], [0, 0, 1]])  # noqa: N806
    pitch, roll = np.deg2rad(4.0), np.deg2rad(2.0)
    rx = np.array([[1, 0, 0], [0, np.cos(pitch), -np.sin(pitch)], [0, np.sin(pitch), np.cos(pitch)]])
    rz = np.array([[np.cos(roll), -np.sin(roll), 0], [np.sin(roll), np.cos(roll), 0], [0, 0, 1]])
    cam_from_road = rz @ rx @ rot_y(0.3)  # road frame: y down, road surface y = 0, camera 1.6 m above it
    up_road = np.array([0.0, -1.0, 0.0])

    def to_cam(p_road):  # road-frame points [N, 3] -> camera frame (camera at road (0, -1.6, 0))
        return (p_road - np.array([0.0, -1.6, 0.0])) @ cam_from_road.T

    rng = np.random.default_rng(0)
    road = to_cam(np.c_[rng.uniform(-8, 8, 200), np.zeros(200), rng.uniform(4, 40, 200)])
    uv = road[:, :2] / road[:, 2:] @ K[:2, :2].T + K[:2, 2]
    plane = np.linalg.lstsq(np.c_[uv, np.ones(len(uv))], 1.0 / road[:, 2], rcond=None)[0]  # exact: a plane
    heights = np.array([0.0, 0.8, 5.0, -1.0])
    pts = to_cam(np.c_[[2.0, -3.0, 0.5, 1.0], np.zeros(4), [10.0, 20.0, 30.0, 15.0]] + heights[:, None] * up_road)
    assert height_above_road(plane, K, pts) == pytest.approx(heights, abs=1e-6)
    assert height_above_road(plane, K, np.zeros((1, 3)))[0] == pytest.approx(1.6, abs=1e-6)


def test_a_track_that_floats_above_the_road_is_not_spawned(tmp_path):
    """The missed-car clip, with the road planes the evolution reads lowered by 5 m: the car's track now floats
    5 m above the road (as a tree crown or a hillside would) and spawns no agent; the report says how high it
    floated. Without the ground check (tolerance None) the same track spawns."""
    path = tmp_path / "float"
    reports = {}
    for check in ("on", "off"):
        bundle, graph = _clip(path / check, SceneConfig(seed=0, frames=8, width=160, height=96, pedestrians=0),
                              NoiseConfig(missed=1), budget=6000)
        topo = _topology(bundle, **({} if check == "on" else {"ground_tolerance_m": None}))
        planes = topo.road_planes()
        assert all(p is not None for p in planes)
        lowered = []
        for t, p in enumerate(planes):  # n . X = 1 with |n| = 1 / h; the road 5 m lower: n / (1 + 5 |n|)
            h = 1.0 / np.linalg.norm(np.array([p[0] * bundle.intrinsics[t][0, 0], p[1] * bundle.intrinsics[t][1, 1],
                                               p[0] * bundle.intrinsics[t][0, 2] + p[1] * bundle.intrinsics[t][1, 2]
                                               + p[2]]))
            lowered.append(p / (1.0 + 5.0 / h))
        topo._planes = lowered
        opt = _fit_background(bundle, graph, topo, steps=80)
        reports[check] = topo.evolve(graph, opt, iteration=80)
    assert reports["off"]["spawned"] and not reports["off"]["floating"]
    assert not reports["on"]["spawned"]
    assert len(reports["on"]["floating"]) == 1 and 4.0 < reports["on"]["floating"][0] < 6.0, reports["on"]["floating"]


def test_a_track_faster_than_any_road_user_is_not_spawned(tmp_path):
    """The missed-car clip (10 frames a second; the car drives about 10 m/s) read as if its frames were 100 times
    closer in time: the car's track now moves at about 1,000 m/s, over ``max_speed_mps``, and spawns no agent;
    the report says how fast it was. At the clip's own frame interval the same track spawns (the test above)."""
    bundle, graph = _clip(tmp_path / "fast", SceneConfig(seed=0, frames=8, width=160, height=96, pedestrians=0),
                          NoiseConfig(missed=1), budget=6000)
    seconds = frame_seconds(bundle.timestamps_us)
    assert seconds == pytest.approx(0.1)
    topo = _topology(bundle, seconds=seconds / 100.0)
    opt = _fit_background(bundle, graph, topo, steps=80)
    report = topo.evolve(graph, opt, iteration=80)
    assert not report["spawned"]
    assert len(report["fast"]) == 1 and 300.0 < report["fast"][0] < 3000.0, report["fast"]


def test_box_speed_reads_consecutive_valid_frames_and_frame_seconds_the_timestamps():
    poses = np.tile(np.eye(4), (6, 1, 1))  # [T, 4, 4]: 1 unit a frame along x, 3 units at the jump to frame 5
    poses[:, 0, 3] = [0.0, 1.0, 2.0, 3.0, 4.0, 7.0]
    valid = np.array([True, True, True, False, True, True])  # frames 2-4 are no pair: their gap is skipped
    assert box_speed(poses, valid, 0.1) == pytest.approx(10.0)  # steps 1, 1 and 3: the median 1 unit in 0.1 s
    assert box_speed(poses, valid, None) is None
    assert box_speed(poses, np.array([True, False, True, False, True, False]), 0.1) is None
    assert frame_seconds([0, 40_000, 80_000, 120_000]) == pytest.approx(0.04)
    assert frame_seconds([0]) is None and frame_seconds(None) is None and frame_seconds([0, 0, 0]) is None
