"""``agg.scene.Scene``: loading a scene directory and stateless renders at any timestamp, with validation."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from agg.eval.interpolate import interpolate_pose
from agg.scene import (InvalidCamera, InvalidPose, OutOfRange, Scene, SceneNotReady, SceneRequestError,
                       UnknownTrack, matrix_to_wxyz, pose_from_quaternion, pose_matrix)
from tests.scene_dirs import make_bundle, make_graph, psnr, write_scene_dir


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    root = tmp_path_factory.mktemp("scenes")
    bundle, gt = make_bundle(root)
    graph = make_graph(bundle)
    d = write_scene_dir(root, "s1", bundle, graph, iteration=7)
    return Scene.load(d), graph, bundle, gt, root


def _camera(scene: Scene, frame: int):
    return scene.world_from_camera()[frame], scene.K[min(frame, len(scene.K) - 1)]


def test_load_prefers_model_and_reports_missing_checkpoints(built, tmp_path):
    scene, graph, bundle, _, _ = built
    assert scene.source == "model" and scene.iteration == 7
    assert scene.num_frames == bundle.num_frames and (scene.timestamps_us == bundle.timestamps_us).all()
    assert (scene.width, scene.height) == (bundle.width, bundle.height)
    assert scene.track_ids == graph.slot_track_ids().tolist()
    empty = write_scene_dir(tmp_path, "empty", bundle, None)
    with pytest.raises(SceneNotReady):
        Scene.load(empty)
    ckpt = write_scene_dir(tmp_path, "ckpt", bundle, graph, file="checkpoint.pt", iteration=3, status="training")
    loaded = Scene.load(ckpt)
    assert (loaded.source, loaded.iteration) == ("checkpoint", 3)
    assert Scene.source_file(ckpt).name == "checkpoint.pt"


def test_render_at_a_frame_timestamp_matches_the_graph(built):
    scene, graph, bundle, gt, _ = built
    for frame in (0, 4):
        wfc, K = _camera(scene, frame)
        out = scene.render(int(bundle.timestamps_us[frame]), wfc, K, scene.width, scene.height)
        with torch.no_grad():
            ref = graph.render(frame)
        assert out["rgb"].shape == (scene.height, scene.width, 3) and out["rgb"].dtype == np.float32
        assert np.abs(out["rgb"] - ref.color.clamp(0, 1).numpy()).max() < 1e-4
        assert np.abs(out["alpha"] - ref.alpha.numpy()).max() < 1e-4
        target = bundle.frame(frame)  # float32 [0, 1]
        assert psnr(out["rgb"], target) > 15.0  # the initial (untrained) graph already resembles the clip
        assert abs(psnr(out["rgb"], target) - psnr(ref.color.clamp(0, 1).numpy(), target)) < 1e-3
        assert out["depth"].dtype == np.float32 and (out["depth"][out["alpha"] > 0.5] > 0).all()


def test_instance_map_follows_the_agents(built):
    scene, _, bundle, gt, _ = built
    frame = 2
    wfc, K = _camera(scene, frame)
    ts = int(bundle.timestamps_us[frame])
    out = scene.render(ts, wfc, K, scene.width, scene.height)
    inst = out["instance"]
    assert inst.dtype == np.int32 and set(np.unique(inst)) <= {0, *scene.track_ids}
    seen = [tid for tid in scene.track_ids if (gt.instance[frame] == tid).sum() >= 30]
    assert seen
    for tid in seen:  # the rendered id covers most of the agent's true pixels
        true = gt.instance[frame] == tid
        iou = ((inst == tid) & true).sum() / ((inst == tid) | true).sum()
        assert iou > 0.4, (tid, iou)
    big = max(seen, key=lambda tid: (gt.instance[frame] == tid).sum())
    hidden = scene.render(ts, wfc, K, scene.width, scene.height, hidden={big})
    assert not (hidden["instance"] == big).any()
    mask = gt.instance[frame] == big
    assert np.abs(hidden["rgb"] - out["rgb"])[mask].mean() > 0.02  # its pixels change
    assert np.abs(hidden["rgb"] - out["rgb"])[~mask].mean() < 0.01  # the rest hardly
    # move the agent 100 units away: gone from the image as well
    far = scene.agent_state(frame)[0][big].copy()
    far[:3, 3] += [0.0, 0.0, 100.0]
    moved = scene.render(ts, wfc, K, scene.width, scene.height, agent_poses={big: far})
    assert (moved["instance"] == big).sum() < 0.2 * (inst == big).sum()


def test_several_cameras_share_one_compose(built):
    scene, _, bundle, _, _ = built
    from agg.scene import Camera

    wfc, K = _camera(scene, 1)
    small = K.copy()
    small[:2] *= 0.5
    cams = [Camera.checked(wfc, K, scene.width, scene.height), Camera.checked(wfc, small, 48, 32)]
    a, b = scene.render_cameras(int(bundle.timestamps_us[1]), cams, outputs=("rgb",))
    assert a["rgb"].shape == (64, 96, 3) and b["rgb"].shape == (32, 48, 3) and set(a) == {"rgb"}
    half = a["rgb"].reshape(32, 2, 48, 2, 3).mean((1, 3))
    assert psnr(b["rgb"], half) > 20.0


def test_time_is_continuous_between_frames(built, tmp_path):
    scene, graph, bundle, _, _ = built
    ts = bundle.timestamps_us
    assert scene.frame_at(int(ts[3])) == 3.0
    assert scene.frame_at(int((ts[2] + ts[3]) // 2)) == pytest.approx(2.5)
    for bad in (int(ts[0]) - 1, int(ts[-1]) + 1):
        with pytest.raises(OutOfRange):
            scene.frame_at(bad)
    poses, valid = scene.agent_state(2.5)
    tid = scene.track_ids[0]
    with torch.no_grad():
        a, b = graph.rigid.world_from_box(2)[0], graph.rigid.world_from_box(3)[0]
    assert np.allclose(poses[tid], interpolate_pose(a, b, 0.5).numpy(), atol=1e-5) and valid[tid]
    wfc, K = _camera(scene, 2)
    mid = scene.render(int((ts[2] + ts[3]) // 2), wfc, K, scene.width, scene.height)
    assert np.isfinite(mid["rgb"]).all() and mid["alpha"].mean() > 0.3
    # a held-out frame (not optimised) takes its agents from the neighbouring train frames
    held = Scene.load(write_scene_dir(tmp_path, "held", bundle, graph, train_frames=[0, 1, 2, 4, 5]))
    poses3, _ = held.agent_state(3.0)
    with torch.no_grad():
        c = graph.rigid.world_from_box(4)[0]
    assert np.allclose(poses3[tid], interpolate_pose(a, c, 0.5).numpy(), atol=1e-5)


def test_bad_requests_raise_specific_value_errors(built):
    scene, _, bundle, _, _ = built
    wfc, K = _camera(scene, 0)
    ts = int(bundle.timestamps_us[0])
    w, h = scene.width, scene.height
    nan_pose = wfc.copy()
    nan_pose[0, 3] = np.nan
    sheared = wfc.copy()
    sheared[0, 1] += 0.3
    bad_k = K.copy()
    bad_k[0, 0] = 0.0
    cases = [
        (InvalidPose, dict(world_from_camera=nan_pose)),
        (InvalidPose, dict(world_from_camera=sheared)),
        (InvalidCamera, dict(K=bad_k)),
        (InvalidCamera, dict(width=0)),
        (InvalidCamera, dict(width=100000)),
        (OutOfRange, dict(timestamp_us=int(bundle.timestamps_us[-1]) + 10)),
        (UnknownTrack, dict(hidden={9999})),
        (UnknownTrack, dict(agent_poses={9999: np.eye(4)})),
        (InvalidPose, dict(agent_poses={scene.track_ids[0]: np.full((4, 4), np.nan)})),
    ]
    for exc, change in cases:
        args = dict(timestamp_us=ts, world_from_camera=wfc, K=K, width=w, height=h) | change
        with pytest.raises(exc) as info:
            scene.render(**args)
        assert isinstance(info.value, SceneRequestError) and isinstance(info.value, ValueError)
        assert str(info.value)
    with pytest.raises(InvalidPose, match="zero quaternion"):
        pose_from_quaternion([0, 0, 0], [0, 0, 0, 0])


def test_pose_helpers_round_trip():
    q = np.array([0.9, 0.1, -0.3, 0.2])
    m = pose_from_quaternion([1.0, 2.0, 3.0], q * 5.0)  # any norm
    assert np.allclose(m[:3, :3] @ m[:3, :3].T, np.eye(3)) and np.allclose(m[:3, 3], [1, 2, 3])
    assert np.allclose(matrix_to_wxyz(m[:3, :3]), q / np.linalg.norm(q))
    assert np.allclose(pose_matrix(m.reshape(-1)), m)


def test_nodes_list_the_graph(built):
    scene, graph, _, _, _ = built
    nodes = scene.nodes()
    kinds = [n.kind for n in nodes]
    assert kinds[:2] == ["camera", "background"]
    agents = [n for n in nodes if n.kind in ("rigid", "non-rigid")]
    assert [n.track_id for n in agents] == scene.track_ids
    assert sum(n.num_gaussians for n in agents) == sum(len(a.gaussians) for a in graph.agent_nodes())
    for n in agents:
        assert n.poses.shape == (scene.num_frames, 4, 4) and n.valid.shape == (scene.num_frames,)
    assert {"rigid", "non-rigid"} <= set(kinds)


def test_graph_json_uses_the_exporter(built):
    scene = built[0]
    doc = scene.graph_json()
    assert doc["schema"] == "agg.scene_graph" and doc["timestamps_us"] == scene.timestamps_us.tolist()
    assert [n["id"] for n in doc["nodes"]] == [n.id for n in scene.nodes()]
    assert doc["meta"]["scene_id"] == "s1"
