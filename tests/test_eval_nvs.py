"""Novel-view evaluation: the split, pose interpolation, image metrics, LPIPS from local files, evaluate()."""

from __future__ import annotations

import json
import math
import warnings

import numpy as np
import pytest
import torch
from kornia.geometry.liegroup import So3

from agg.eval.interpolate import interpolate_agents, interpolate_camera, interpolate_pose, split_frames
from agg.eval.metrics import Lpips, LpipsNet, psnr, ssim


def _pose(rotvec, t) -> torch.Tensor:
    p = torch.eye(4)
    p[:3, :3] = So3.exp(torch.tensor([rotvec], dtype=torch.float32)).matrix()[0]
    p[:3, 3] = torch.tensor(t, dtype=torch.float32)
    return p


def _angle(r: torch.Tensor) -> float:
    return math.degrees(math.acos(max(-1.0, min(1.0, (float(torch.trace(r)) - 1) / 2))))


# ---- split and interpolation -------------------------------------------------------------------------------------

def test_split_holds_out_every_fifth_frame_and_trains_frame_zero():
    train, test = split_frames(12)
    assert test == [4, 9]
    assert train == [0, 1, 2, 3, 5, 6, 7, 8, 10, 11]
    assert split_frames(4) == ([0, 1, 2, 3], [])
    with pytest.raises(ValueError):
        split_frames(10, every=1)


def test_slerp_midpoint_of_a_quarter_turn_is_45_degrees_and_endpoints_are_exact():
    a = _pose([0.0, 0.0, 0.0], [0.0, 0.0, 0.0])
    b = _pose([0.0, math.pi / 2, 0.0], [2.0, -4.0, 6.0])
    mid = interpolate_pose(a, b, 0.5)
    assert _angle(mid[:3, :3]) == pytest.approx(45.0, abs=1e-4)
    assert _angle(a[:3, :3].T @ mid[:3, :3]) == pytest.approx(45.0, abs=1e-4)
    assert _angle(mid[:3, :3].T @ b[:3, :3]) == pytest.approx(45.0, abs=1e-4)
    # the rotation axis is kept (y), the translation is the midpoint, the result is a rigid transform
    expected = So3.exp(torch.tensor([[0.0, math.pi / 4, 0.0]])).matrix()[0]
    assert torch.allclose(mid[:3, :3], expected, atol=1e-6)
    assert torch.allclose(mid[:3, 3], torch.tensor([1.0, -2.0, 3.0]))
    assert torch.allclose(mid[3], torch.tensor([0.0, 0.0, 0.0, 1.0]))
    assert torch.equal(interpolate_pose(a, b, 0.0), a) and torch.equal(interpolate_pose(a, b, 1.0), b)
    quarter = interpolate_pose(a, b, 0.25)
    assert _angle(quarter[:3, :3]) == pytest.approx(22.5, abs=1e-4)


def test_camera_interpolation_uses_the_neighbouring_train_frames_and_holds_at_the_ends():
    t = 10
    cams = torch.stack([_pose([0.0, 0.1 * i, 0.0], [0.0, 0.0, 1.0 * i]) for i in range(t)])  # [T, 4, 4]
    train, test = split_frames(t)
    mid = interpolate_camera(cams, train, 4)  # between 3 and 5: exactly frame 4's pose on this uniform path
    assert torch.allclose(mid, cams[4], atol=1e-5)
    assert torch.equal(interpolate_camera(cams, train, 3), cams[3])  # a train frame is its own pose
    # past the last train frame (frame 9 when 9 is held out and 8 is the last train frame): hold frame 8
    assert torch.equal(interpolate_camera(cams, [0, 1, 2, 3, 5, 6, 7, 8], 9), cams[8])
    # uneven gap: weight (7 - 5) / (8 - 5)
    w = interpolate_camera(cams, [5, 8], 7)
    assert float(w[2, 3]) == pytest.approx(7.0)
    assert _angle(cams[5][:3, :3].T @ w[:3, :3]) == pytest.approx(math.degrees(0.2), abs=1e-3)


def test_agent_interpolation_validity_follows_the_neighbours_used():
    t, k = 10, 4
    wfb = torch.stack([torch.stack([_pose([0.0, 0.0, 0.0], [float(i), float(j), 0.0]) for j in range(k)])
                       for i in range(t)])  # [T, K, 4, 4]
    valid = torch.ones(t, k, dtype=torch.bool)
    valid[5:, 1] = False  # agent 1 leaves after frame 4: at frame 4 only the earlier neighbour (3) is valid
    valid[:5, 2] = False  # agent 2 appears at frame 5: only the later neighbour (5) is valid
    valid[:, 3] = False  # agent 3 never valid
    train = [0, 1, 2, 3, 5, 6, 7, 8]
    poses, ok = interpolate_agents(wfb, valid, train, 4)
    assert ok.tolist() == [True, True, True, False]
    assert float(poses[0, 0, 3]) == pytest.approx(4.0)  # interpolated between frames 3 and 5
    assert float(poses[1, 0, 3]) == pytest.approx(3.0)  # held from frame 3
    assert float(poses[2, 0, 3]) == pytest.approx(5.0)  # held from frame 5
    assert torch.equal(poses[3], torch.eye(4))
    poses, ok = interpolate_agents(wfb, valid, train, 9)  # after the last train frame: frame 8 held
    assert ok.tolist() == [True, False, True, False] and float(poses[0, 0, 3]) == pytest.approx(8.0)


# ---- metrics ------------------------------------------------------------------------------------------------------

def test_psnr_matches_the_mse_by_hand_and_masked_variants():
    rng = np.random.default_rng(0)
    gt = rng.uniform(0.2, 0.8, (24, 32, 3)).astype(np.float32)
    pred = gt + 0.1  # MSE = 0.01 everywhere -> 20 dB
    assert psnr(pred, gt) == pytest.approx(20.0, abs=1e-4)
    mask = np.zeros((24, 32), bool)
    mask[:, :16] = True
    pred2 = gt.copy()
    pred2[:, :16] += 0.05  # MSE 0.0025 inside the mask -> 26.02 dB; 0 outside
    assert psnr(pred2, gt, mask) == pytest.approx(10 * math.log10(1 / 0.0025), abs=1e-4)
    assert psnr(pred2, gt) == pytest.approx(10 * math.log10(1 / 0.00125), abs=1e-4)
    assert psnr(pred2, gt, ~mask) == pytest.approx(100.0)  # identical pixels: the 100 dB ceiling
    assert psnr(pred, gt, np.zeros((24, 32), bool)) is None
    # uint8 input is scaled to [0, 1]
    assert psnr((gt * 255).round().astype(np.uint8), (gt * 255).round().astype(np.uint8)) == pytest.approx(100.0)


def test_ssim_is_one_for_identical_images_lower_for_noise_and_masked():
    rng = np.random.default_rng(1)
    gt = torch.as_tensor(rng.uniform(0, 1, (40, 48, 3)), dtype=torch.float32)
    assert ssim(gt, gt) == pytest.approx(1.0, abs=1e-5)
    noisy = (gt + 0.2 * torch.randn_like(gt)).clamp(0, 1)
    assert ssim(noisy, gt) < 0.9
    half = gt.clone()
    half[:, 24:] = noisy[:, 24:]
    mask = torch.zeros(40, 48, dtype=torch.bool)
    mask[:, :12] = True  # far from the noisy half (the 11 x 11 window reaches 5 px)
    assert ssim(half, gt, mask) == pytest.approx(1.0, abs=1e-5)
    assert ssim(half, gt, ~mask) < ssim(half, gt, mask)
    assert ssim(half, gt, torch.zeros(40, 48, dtype=torch.bool)) is None


def test_lpips_without_weights_reports_none_and_why(monkeypatch):
    monkeypatch.delenv("AGG_LPIPS_WEIGHTS", raising=False)
    m = Lpips()
    img = torch.rand(32, 32, 3)
    assert not m.available and m(img, img) is None and "AGG_LPIPS_WEIGHTS" in m.note
    bad = Lpips("/nonexistent/lpips.pth")
    assert not bad.available and "could not load" in bad.note


def test_lpips_loads_local_state_dicts_and_torchscript(tmp_path, monkeypatch):
    torch.manual_seed(0)
    net = LpipsNet("alex")
    for lin in net.lins:  # the real linear layers are non-negative
        lin.weight.data.abs_()
    # the lpips package's state-dict layout: net.sliceN.<torchvision index>.*, linN.model.1.weight
    slices = {0: 1, 3: 2, 6: 3, 8: 4, 10: 5}
    state = {}
    for name, v in net.state_dict().items():
        if name.startswith("features."):
            idx = int(name.split(".")[1])
            state[f"net.slice{slices[idx]}.{name.split('.', 1)[1]}"] = v
        elif name.startswith("lins."):
            state[f"lin{name.split('.')[1]}.model.1.weight"] = v
    torch.save(state, tmp_path / "lpips_alex.pth")
    monkeypatch.setenv("AGG_LPIPS_WEIGHTS", str(tmp_path / "lpips_alex.pth"))
    m = Lpips()
    assert m.available, m.note
    a = torch.rand(64, 64, 3)
    b = (a + 0.3 * torch.randn_like(a)).clamp(0, 1)
    assert m(a, a) == pytest.approx(0.0, abs=1e-7)
    d = m(a, b)
    assert d > 0
    with torch.no_grad():
        ref = float(net(a.permute(2, 0, 1)[None] * 2 - 1, b.permute(2, 0, 1)[None] * 2 - 1)[0])
    assert d == pytest.approx(ref, rel=1e-5)
    # a torchvision trunk file with separate lin weights gives the same distance
    torch.save({k: v for k, v in net.state_dict().items() if k.startswith("features.")}, tmp_path / "alex.pth")
    torch.save({k: v for k, v in state.items() if k.startswith("lin")}, tmp_path / "lin.pth")
    assert Lpips(tmp_path / "alex.pth", lin_weights=tmp_path / "lin.pth")(a, b) == pytest.approx(d, rel=1e-6)
    # the same network as a TorchScript module and as a torch.export program (traced at the image size)
    x = (a.permute(2, 0, 1)[None] * 2 - 1, b.permute(2, 0, 1)[None] * 2 - 1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        torch.jit.trace(net.eval(), x).save(str(tmp_path / "lpips.ts"))
    torch.export.save(torch.export.export(net.eval(), x), str(tmp_path / "lpips.pt2"))
    for f in ("lpips.ts", "lpips.pt2"):
        m = Lpips(tmp_path / f)
        assert m.available and m(a, b) == pytest.approx(d, rel=1e-5), m.note


# ---- evaluate() on a synthetic clip -------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def synth(tmp_path_factory):
    from agg.io.bundle import SceneBundle
    from agg.synth.corrupt import NoiseConfig
    from agg.synth.scene import SceneConfig
    from agg.synth.suite import generate, write_bundle

    # no sky: the graph has no sky node to draw it, and the test is about the evaluation, not the sky
    gt, priors = generate(SceneConfig(seed=0, frames=10, width=160, height=96, sky=False), NoiseConfig())
    path = tmp_path_factory.mktemp("nvs") / "b"
    write_bundle(path, gt, priors, NoiseConfig())
    return SceneBundle.load(path), gt


def test_evaluate_scores_held_out_frames_of_the_initial_graph(synth, monkeypatch):
    from agg.eval.nvs import evaluate, held_out_overrides
    from agg.graph import SceneGraph
    from agg.nodes.init import InitConfig

    monkeypatch.delenv("AGG_LPIPS_WEIGHTS", raising=False)
    bundle, gt = synth
    graph = SceneGraph.from_bundle(bundle, InitConfig(opacity=0.9))
    train, test = split_frames(bundle.num_frames)
    r = evaluate(graph, bundle, test, train)
    json.dumps(r, allow_nan=False)
    assert r["split"] == "nvs" and r["n_test_frames"] == len(test) == 2
    assert [p["frame"] for p in r["per_frame"]] == test
    assert 15.0 < r["psnr"] < 100.0 and 0.3 < r["ssim"] <= 1.0, r
    assert r["psnr"] == pytest.approx(np.mean([p["psnr"] for p in r["per_frame"]]))
    assert r["agent_mask_source"] == "gt_dynamic_masks"
    assert r["psnr_agents"] is not None and math.isfinite(r["psnr_agents"]) and r["psnr_agents"] > 10.0
    assert r["ssim_agents"] is not None and 0.0 < r["ssim_agents"] <= 1.0
    assert all(p["agent_pixels"] == int((gt.instance[p["frame"]] > 0).sum()) for p in r["per_frame"])
    assert r["lpips"] is None and "AGG_LPIPS_WEIGHTS" in r["lpips_note"]
    assert r["render_fps"] > 0 and r["n_gaussians"] == graph.num_gaussians()
    assert r["n_agents"] == graph.num_agents == len(bundle.tracklets.ids)
    # the held-out camera really is interpolated (not the frame's own pose) and the agents there are valid
    cam, poses, valid = held_out_overrides(graph, train, 4)
    own = graph.camera.world_from_camera()[4].detach()
    assert not torch.equal(cam, own) and torch.allclose(cam, own, atol=0.05)
    assert set(poses) == set(valid) == set(graph.slot_track_ids().tolist())
    # explicit masks win; an empty mask set gives no agent metrics; max_frames subsamples; given frames (here
    # the bundle's as uint8, as a training loop may hold them) replace the bundle's
    empty = np.zeros((bundle.num_frames, bundle.height, bundle.width), bool)
    frames_u8 = torch.as_tensor(np.array(bundle.frames.raw))
    r2 = evaluate(graph, bundle, test, train, agent_masks=empty, max_frames=1, images=frames_u8)
    assert r2["agent_mask_source"] == "argument" and r2["psnr_agents"] is None and r2["ssim_agents"] is None
    assert r2["n_test_frames"] == 1 and r2["per_frame"][0]["psnr"] == pytest.approx(r["per_frame"][0]["psnr"])


def test_evaluate_leaves_the_ego_vehicle_out(synth, tmp_path, monkeypatch):
    import shutil

    from agg.eval.nvs import evaluate
    from agg.graph import SceneGraph
    from agg.io.bundle import SceneBundle
    from agg.nodes.init import InitConfig

    monkeypatch.delenv("AGG_LPIPS_WEIGHTS", raising=False)
    bundle, gt = synth
    shutil.copytree(bundle.path, tmp_path / "b")
    ego = np.zeros((bundle.height, bundle.width), bool)
    ego[-12:, 20:140] = True  # a bonnet over the bottom rows
    mine = SceneBundle.load(tmp_path / "b")
    mine.write_ego_mask(ego)
    graph = SceneGraph.from_bundle(mine, InitConfig(opacity=0.9))
    train, test = split_frames(mine.num_frames)
    frames = torch.as_tensor(np.array(mine.frames[:]))  # [T, H, W, 3]
    scrawled = frames.clone()
    scrawled[:, torch.as_tensor(ego)] = torch.tensor([1.0, 0.0, 1.0])  # what the ego pixels show does not count
    r, r2 = evaluate(graph, mine, test, train), evaluate(graph, mine, test, train, images=scrawled)
    full = evaluate(graph, bundle, test, train, images=frames)  # the same frames without the ego mask
    assert r["ego_pixel_share"] == pytest.approx(ego.mean()) and full["ego_pixel_share"] == 0.0
    for key in ("psnr", "psnr_agents"):
        assert r2[key] == pytest.approx(r[key], abs=1e-9), key
    for key in ("ssim", "ssim_agents"):  # only SSIM's windows that straddle the bonnet's edge see what it shows
        assert r2[key] == pytest.approx(r[key], abs=0.01), key
    assert r["psnr"] != pytest.approx(full["psnr"], abs=1e-6)
    for p, q in zip(r["per_frame"], full["per_frame"]):
        assert p["pixels"] == ego.size - ego.sum() and q["pixels"] == ego.size
        assert p["agent_pixels"] == int(((gt.instance[p["frame"]] > 0) & ~ego).sum())
