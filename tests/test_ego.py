"""The ego vehicle's pixels (agg.eval.ego): resampled to a size, left out of the training data's losses, the
tracking rounds and the background's initial points (the priors' rule and the scores are tested in
test_priors_masks.py and test_eval_nvs.py)."""

from __future__ import annotations

import shutil
from dataclasses import replace

import numpy as np
import pytest
import torch

from agg.eval.ego import scene_pixels, with_ego_from
from agg.graph import SceneGraph
from agg.io.bundle import SceneBundle
from agg.nodes.gaussians import SH_C0
from agg.nodes.init import InitConfig, init_from_bundle
from agg.synth.corrupt import NoiseConfig
from agg.synth.scene import SceneConfig
from agg.synth.suite import generate, write_bundle
from agg.train.camera_tracking import TrackingConfig, track_cameras
from agg.train.config import get_preset
from agg.train.data import load_train_data
from agg.train.tick_tock import Phase
from agg.train.trainer import Trainer, seed_everything

BONNET_ROWS = 16  # of 80


@pytest.fixture(scope="module")
def bundles(tmp_path_factory):
    """(the clip's bundle, the same with an ego mask over its bottom rows, the mask [H, W])."""
    root = tmp_path_factory.mktemp("ego")
    noise = NoiseConfig(camera_translation_max=0.2)
    gt, priors = generate(SceneConfig(seed=1, frames=10, width=128, height=80), noise)
    write_bundle(root / "plain", gt, priors, noise)
    shutil.copytree(root / "plain", root / "ego")
    ego = np.zeros((80, 128), bool)
    ego[-BONNET_ROWS:] = True
    with_ego = SceneBundle.load(root / "ego")
    with_ego.write_ego_mask(ego)
    return SceneBundle.load(root / "plain"), with_ego, ego


def _scrawled(images: torch.Tensor, ego: np.ndarray) -> torch.Tensor:
    out = images.clone()
    out[:, torch.as_tensor(ego)] = torch.tensor([1.0, 0.0, 1.0])
    return out


def test_scene_pixels_leave_out_every_pixel_the_mask_touches_at_any_size(bundles):
    plain, with_ego, ego = bundles
    assert scene_pixels(plain, 64, 40) is None
    np.testing.assert_array_equal(scene_pixels(with_ego, 128, 80).numpy(), ~ego)
    half = scene_pixels(with_ego, 64, 40)  # [40, 64]: 8 bonnet rows at half size
    assert not half[-8:].any() and half[:-8].all()
    odd = scene_pixels(with_ego, 57, 36)  # 16 of 80 rows is 7.2 of 36: the eighth row straddles the edge
    assert not odd[-8:].any() and odd[:-8].all()
    render, target = torch.rand(80, 128, 3, requires_grad=True), torch.rand(80, 128, 3)
    mixed = with_ego_from(target, render, torch.as_tensor(~ego).float())
    mixed.sum().backward()
    assert torch.equal(mixed[torch.as_tensor(ego)], target[torch.as_tensor(ego)])
    assert render.grad[torch.as_tensor(ego)].abs().max() == 0 and render.grad[torch.as_tensor(~ego)].min() == 1
    assert with_ego_from(target, render, None) is render


def test_training_data_weigh_the_ego_pixels_zero_in_both_losses(bundles):
    plain, with_ego, ego = bundles
    assert load_train_data(plain, 128).scene_weight is None
    data = load_train_data(with_ego, 128)
    np.testing.assert_array_equal(data.scene_weight.numpy(), (~ego).astype(np.float32))
    assert data.m_bg is not None  # the suite's maps pass the gate; Eq. 3 reads nothing on the bonnet either
    assert data.m_bg[:, -BONNET_ROWS:].abs().max() == 0 and data.m_ag[:, -BONNET_ROWS:].abs().max() == 0
    assert data.m_bg[:, :-BONNET_ROWS].max() > 0


def _gradients(tr: Trainer, frame: int, phase: Phase) -> tuple[float, list[torch.Tensor]]:
    loss, _, _ = tr.forward_backward(frame, phase)
    params = [p for group in tr.group_params().values() for p in group if p.grad is not None]
    grads = [p.grad.clone() for p in params]
    for p in params:
        p.grad = None
    return float(loss.detach()), grads


@pytest.mark.parametrize("tick_agent_mask", [False, True])
def test_what_the_ego_pixels_show_changes_no_loss_and_no_gradient(bundles, tick_agent_mask):
    plain, with_ego, ego = bundles
    cfg = replace(get_preset("tiny"), iterations=40, ssim_weight=0.0, tick_agent_mask=tick_agent_mask,
                  ablate=frozenset({"topology"}))  # L1 alone: SSIM's windows at the bonnet's edge see its pixels
    tick = Phase("tick", frozenset({"camera", "static"}), 1.0, "bg")
    warmup = Phase("warmup", frozenset({"camera", "static", "agents"}), 1.0, None)
    for bundle, same in ((with_ego, True), (plain, False)):
        seed_everything(cfg.seed)
        tr = Trainer(SceneGraph.from_bundle(bundle, cfg.init), load_train_data(bundle, 128), cfg, bundle)
        for phase in (tick, warmup):
            loss, grads = _gradients(tr, 3, phase)
            images = tr.data.images
            tr.data.images = _scrawled(images, ego)
            loss2, grads2 = _gradients(tr, 3, phase)
            tr.data.images = images
            assert (loss2 == loss) is same and len(grads2) == len(grads) > 0
            assert all(torch.equal(a, b) for a, b in zip(grads, grads2)) is same


def test_a_tracking_round_does_not_read_the_ego_pixels(bundles):
    _, with_ego, ego = bundles
    cfg = get_preset("tiny")
    graph = SceneGraph.from_bundle(with_ego, cfg.init)
    data = load_train_data(with_ego, 128)
    graph.K, graph.width, graph.height = data.K.clone(), data.width, data.height
    for p in graph.parameters():
        p.requires_grad_(False)
    track = TrackingConfig(at=(1,), levels=(2, 1), steps=3)
    results = []
    for images in (data.images, _scrawled(data.images, ego)):
        with torch.no_grad():
            graph.camera.omega.zero_()
            graph.camera.tau.zero_()
        report = track_cameras(graph, images, data.train_frames, track, 1.0, ssim_weight=0.0,
                               weight=data.scene_weight)
        assert report is not None
        results.append((graph.camera.omega.detach().clone(), graph.camera.tau.detach().clone()))
    assert results[0][0].abs().max() > 0  # the round moved the cameras, the same way both times
    assert torch.equal(results[0][0], results[1][0]) and torch.equal(results[0][1], results[1][1])


def test_no_background_point_starts_on_the_ego_pixels(bundles, tmp_path):
    plain, _, ego = bundles
    shutil.copytree(plain.path, tmp_path / "b")
    frames = np.array(plain.frames.raw)
    frames[:, ego] = (255, 0, 255)  # a magenta bonnet
    np.save(tmp_path / "b" / "frames.npy", frames)
    painted = SceneBundle.load(tmp_path / "b")

    def magenta_points(bundle) -> int:
        rgb = init_from_bundle(bundle, InitConfig())["background"].sh[:, 0] * SH_C0 + 0.5  # [N, 3]
        return int(((rgb[:, 0] > 0.9) & (rgb[:, 1] < 0.1) & (rgb[:, 2] > 0.9)).sum())

    assert magenta_points(painted) > 20  # without the mask the bonnet's pixels become road points
    painted.write_ego_mask(ego)
    assert magenta_points(SceneBundle.load(tmp_path / "b")) == 0
