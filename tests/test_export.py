"""Exports: the 3DGS PLY layout and round trip, and the scene-graph JSON of a graph built from a synthetic clip."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from agg.export import export_graph_ply, read_ply, scene_graph_json, write_ply
from agg.export.ply import read_header


def _gaussians(n: int, k: int, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    return {"means": rng.normal(size=(n, 3)).astype(np.float32),
            "quats": (q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32),
            "scales": np.exp(rng.uniform(-5, 0, (n, 3))).astype(np.float32),
            "opacities": rng.uniform(0.01, 0.99, n).astype(np.float32),
            "sh": rng.normal(size=(n, k, 3)).astype(np.float32)}


def test_ply_round_trip_and_the_3dgs_header_order(tmp_path):
    g = _gaussians(50, 4)
    path = write_ply(tmp_path / "s.ply", **g)
    back = read_ply(path)
    for key in ("means", "quats", "scales", "opacities", "sh"):
        np.testing.assert_allclose(back[key], g[key], rtol=1e-5, atol=1e-6, err_msg=key)
    expected = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
                + [f"f_rest_{i}" for i in range(9)] + ["opacity", "scale_0", "scale_1", "scale_2"]
                + ["rot_0", "rot_1", "rot_2", "rot_3"])
    assert back["properties"] == expected
    raw = path.read_bytes()
    header = raw[:raw.index(b"end_header\n") + len(b"end_header\n")].decode()
    assert header.startswith("ply\nformat binary_little_endian 1.0\n") and "element vertex 50\n" in header
    assert all(f"property float {p}\n" in header for p in expected)
    assert len(raw) - len(header) == 50 * len(expected) * 4  # float32 rows, nothing else
    # stored values are the 3DGS parameterisation: logit opacity, log scale, f_rest channel-major
    with open(path, "rb") as f:
        n, props = read_header(f)
        rows = np.frombuffer(f.read(), dtype=np.dtype(props), count=n)
    o = g["opacities"].astype(np.float64)
    np.testing.assert_allclose(rows["opacity"], np.log(o / (1 - o)), rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(rows["scale_1"], np.log(g["scales"][:, 1]), rtol=1e-5)
    np.testing.assert_allclose(rows["nx"], 0.0)
    # f_rest_{c (K-1) + j} = coefficient j + 1 of channel c: f_rest_0..2 are red's, f_rest_3 is green's first
    np.testing.assert_allclose(rows["f_rest_0"], g["sh"][:, 1, 0])
    np.testing.assert_allclose(rows["f_rest_2"], g["sh"][:, 3, 0])
    np.testing.assert_allclose(rows["f_rest_3"], g["sh"][:, 1, 1])
    np.testing.assert_allclose(rows["f_rest_8"], g["sh"][:, 3, 2])
    np.testing.assert_allclose(rows["f_dc_2"], g["sh"][:, 0, 2])


def test_ply_degree_zero_clamps_and_rejects(tmp_path):
    g = _gaussians(5, 1)
    g["opacities"][0], g["opacities"][1] = 0.0, 1.0  # clamped into (0, 1) before the logit
    g["quats"] = g["quats"] * 3.0  # normalised on write
    back = read_ply(write_ply(tmp_path / "d0.ply", **{k: torch.as_tensor(v) for k, v in g.items()}))
    assert not any(p.startswith("f_rest") for p in back["properties"]) and back["sh"].shape == (5, 1, 3)
    assert 0 < back["opacities"][0] < 1e-5 and 1 - 1e-5 < back["opacities"][1] < 1
    np.testing.assert_allclose(np.linalg.norm(back["quats"], axis=1), 1.0, rtol=1e-6)
    bad = dict(g)
    bad["means"] = g["means"].copy()
    bad["means"][2, 0] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        write_ply(tmp_path / "bad.ply", **bad)
    with pytest.raises(ValueError, match="sh must be"):
        write_ply(tmp_path / "bad.ply", **{**g, "sh": g["sh"][:, :, :2]})
    (tmp_path / "ascii.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 0\nend_header\n")
    with pytest.raises(ValueError, match="binary_little_endian"):
        read_ply(tmp_path / "ascii.ply")


@pytest.fixture(scope="module")
def graph_and_bundle(tmp_path_factory):
    from agg.graph import SceneGraph
    from agg.io.bundle import SceneBundle
    from agg.nodes.init import InitConfig
    from agg.synth.corrupt import NoiseConfig
    from agg.synth.scene import SceneConfig
    from agg.synth.suite import generate, write_bundle

    gt, priors = generate(SceneConfig(seed=1, frames=6, width=96, height=64), NoiseConfig())
    path = tmp_path_factory.mktemp("exp") / "b"
    write_bundle(path, gt, priors, NoiseConfig())
    bundle = SceneBundle.load(path)
    return SceneGraph.from_bundle(bundle, InitConfig(opacity=0.9, background_budget=4000, agent_budget=300)), bundle


def test_graph_json_lists_every_node_with_poses_validity_and_cameras(graph_and_bundle):
    graph, bundle = graph_and_bundle
    doc = scene_graph_json(graph, bundle.timestamps_us, meta={"preset": "fast"})
    text = json.dumps(doc, allow_nan=False)
    doc = json.loads(text)
    t = bundle.num_frames
    agents = [n for n in doc["nodes"] if n["type"] == "agent"]
    expected_nodes = 2 + (graph.sky is not None) + graph.num_agents
    assert len(doc["nodes"]) == doc["counts"]["nodes"] == expected_nodes
    assert len(agents) == graph.num_agents == len(bundle.tracklets.ids) > 0
    assert [n["id"] for n in doc["nodes"][:2]] == ["camera", "background"]
    # agents in slot order with their tracklet ids and classes (rigid first, then non-rigid)
    assert [a["track_id"] for a in agents] == graph.slot_track_ids().tolist()
    assert [a["slot"] for a in agents] == list(range(1, len(agents) + 1))
    cls = dict(zip(bundle.tracklets.ids.tolist(), bundle.tracklets.classes))
    assert all(a["class"] == cls[a["track_id"]] for a in agents)
    assert sum(a["n_gaussians"] for a in agents) == sum(len(n.gaussians) for n in graph.agent_nodes())
    row = {int(i): k for k, i in enumerate(bundle.tracklets.ids)}
    for a in agents:
        assert len(a["valid"]) == len(a["world_from_box"]) == t
        assert a["valid"] == bundle.tracklets.valid[row[a["track_id"]]].tolist()
        for i, (ok, pose) in enumerate(zip(a["valid"], a["world_from_box"])):
            assert (pose is not None) == ok
            if ok:  # the initial graph's refined pose is the tracklet box: centre and unit rotation
                p = np.asarray(pose)
                np.testing.assert_allclose(p[:3, 3], bundle.tracklets.boxes[row[a["track_id"]], i, :3], atol=1e-5)
                np.testing.assert_allclose(p[:3, :3] @ p[:3, :3].T, np.eye(3), atol=1e-5)
        assert a["first_frame"] == a["valid"].index(True)
    cams = doc["cameras"]
    assert len(cams["world_from_camera"]) == len(cams["intrinsics"]) == t
    np.testing.assert_allclose(cams["world_from_camera"], bundle.world_from_camera, atol=1e-5)
    np.testing.assert_allclose(cams["intrinsics"], bundle.intrinsics, atol=1e-4)
    assert doc["time_range"] == {"first_timestamp_us": int(bundle.timestamps_us[0]),
                                 "last_timestamp_us": int(bundle.timestamps_us[-1]), "num_frames": t}
    assert doc["conventions"]["quaternions"] == "wxyz" and doc["meta"] == {"preset": "fast"}
    with pytest.raises(ValueError):
        scene_graph_json(graph, bundle.timestamps_us[:-1])


def test_graph_ply_holds_the_visible_gaussians_of_a_frame(graph_and_bundle, tmp_path):
    graph, _ = graph_and_bundle
    frame = 2
    with torch.no_grad():
        g = graph.compose(frame)
    visible = g["opacities"] > 0
    back = read_ply(export_graph_ply(graph, tmp_path / "scene.ply", frame=frame))
    assert len(back["means"]) == int(visible.sum()) > 0
    np.testing.assert_allclose(back["means"], g["means"][visible].numpy(), atol=1e-5)
    np.testing.assert_allclose(back["sh"], g["sh"][visible].numpy(), atol=1e-6)
    np.testing.assert_allclose(back["opacities"], g["opacities"][visible].numpy(), rtol=1e-4, atol=1e-6)
