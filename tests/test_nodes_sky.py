"""The sky node and the sky rule (agg/nodes/sky.py) on synthetic clips with exact ground truth (and KITTI)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from agg.io.bundle import SceneBundle
from agg.nodes.gaussians import keep_rows
from agg.nodes.sky import SkyConfig, SkyNode, fibonacci_sphere, has_sky, sky_mask
from agg.render import rasterize
from agg.synth.corrupt import NoiseConfig
from agg.synth.scene import SceneConfig
from agg.synth.suite import generate, write_bundle

KITTI = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "kitti06_51"


def _clip(root: Path, name: str, sky: bool = True, noise: NoiseConfig = NoiseConfig(), depth_format: str = "dense"):
    gt, priors = generate(SceneConfig(seed=0, frames=6, width=160, height=96, sky=sky), noise)
    return gt, write_bundle(root / name, gt, priors, noise, depth_format=depth_format)


@pytest.fixture(scope="module")
def sky_clip(tmp_path_factory):
    return _clip(tmp_path_factory.mktemp("sky"), "sky")


def _precision_recall(mask: np.ndarray, gt_sky: np.ndarray) -> tuple[float, float]:
    hit = float((mask & gt_sky).sum())
    return hit / max(mask.sum(), 1), hit / gt_sky.sum()


def _render(node: SkyNode, pose: np.ndarray, K: np.ndarray, w: int, h: int):
    g = node.compose()
    return rasterize(g["means"], g["quats"], g["scales"], g["opacities"], sh=g["sh"],
                     K=torch.as_tensor(K, dtype=torch.float32), width=w, height=h,
                     world_from_camera=torch.as_tensor(pose, dtype=torch.float32))


def test_sky_rule_finds_the_synthetic_sky(sky_clip):
    gt, bundle = sky_clip
    assert has_sky(bundle)
    mask = sky_mask(bundle)
    assert mask.shape == (6, 96, 160) and mask.dtype == bool
    precision, recall = _precision_recall(mask, ~gt.depth_valid)
    assert precision > 0.99 and recall > 0.6, (precision, recall)
    assert not mask[:, 60:].any()  # nothing below the horizon (image centre row 47.5, level camera)
    sub = sky_mask(bundle, frames=[0, 5])
    np.testing.assert_array_equal(sub, mask[[0, 5]])


def test_sky_node_renders_the_gt_sky(sky_clip):
    gt, bundle = sky_clip
    node = SkyNode.from_bundle(bundle, n=3000, sh_degree=1)
    assert 2500 < len(node) < 3500 and node.sh_degree == 1
    # on a sphere centred on the camera path, far behind everything the depth saw
    r = (node.means.detach() - node.centre).norm(dim=1)
    torch.testing.assert_close(r, node.radius.expand_as(r), rtol=1e-4, atol=0)
    path = np.linalg.norm(gt.world_from_camera[:, :3, 3] - node.centre.numpy(), axis=1).max()
    assert float(node.radius) - path > np.percentile(gt.depth[gt.depth_valid], 99)
    sky = ~gt.depth_valid
    mean_colour = gt.rgb[sky].mean(0)  # the trivial baseline: one colour for the whole sky
    psnr, base, alpha = [], [], []
    for i in range(gt.rgb.shape[0]):
        out = _render(node, bundle.world_from_camera[i], bundle.intrinsics[i], 160, 96)
        colour, target = out.color.detach().numpy(), gt.rgb[i]
        psnr.append(-10 * np.log10(((colour - target)[sky[i]] ** 2).mean()))
        base.append(-10 * np.log10(((mean_colour - target[sky[i]]) ** 2).mean()))
        alpha.append(float(out.alpha.detach().numpy()[sky[i]].min()))
    print(f"sky PSNR {np.round(psnr, 2)} vs constant colour {np.round(base, 2)}; min alpha {np.round(alpha, 3)}")
    assert min(psnr) > 32 and min(np.subtract(psnr, base)) > 10
    assert min(alpha) > 0.9
    # static: the same Gaussians at every frame and time
    a, b = node.compose(0), node.compose(5, t=1.0)
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_black_far_field_and_missing_depth_are_not_sky(tmp_path):
    gt, bundle = _clip(tmp_path, "black", sky=False)
    assert not has_sky(bundle)
    assert sky_mask(bundle).sum() == 0
    with pytest.raises(ValueError, match="no sky"):
        SkyNode.from_bundle(bundle, n=500)
    _, no_depth = _clip(tmp_path, "nodepth", depth_format="none")
    assert sky_mask(no_depth) is None and not has_sky(no_depth)


def test_depth_dropouts_and_sparse_depth(tmp_path):
    gt, holes = _clip(tmp_path, "holes", noise=NoiseConfig(depth_keep_fraction=0.5))
    precision, recall = _precision_recall(sky_mask(holes), ~gt.depth_valid)  # dropouts are not sky
    assert precision > 0.99 and recall > 0.6, (precision, recall)
    _, sparse = _clip(tmp_path, "sparse", depth_format="sparse")
    assert has_sky(sparse)
    precision, recall = _precision_recall(sky_mask(sparse), ~gt.depth_valid)
    assert precision > 0.99 and recall > 0.15, (precision, recall)  # only pixels far from every row


def test_state_round_trip_and_pruning(sky_clip):
    _, bundle = sky_clip
    node = SkyNode.from_bundle(bundle, n=800, sh_degree=0, config=SkyConfig(radius_factor=3.0, max_frames=3))
    again = SkyNode.from_state(node.state())
    assert float(again.radius) == float(node.radius) and torch.equal(again.centre, node.centre)
    a = _render(node, bundle.world_from_camera[2], bundle.intrinsics[2], 160, 96)
    b = _render(again, bundle.world_from_camera[2], bundle.intrinsics[2], 160, 96)
    torch.testing.assert_close(a.color, b.color, atol=0, rtol=0)
    opt = torch.optim.Adam(node.param_groups("sky", dict.fromkeys(("means", "log_scales", "quats",
                                                                     "opacity_logits", "sh"), 1e-3)))
    a.color.sum().backward()
    opt.step()
    keep_rows(node, torch.arange(len(node)) % 2 == 0, opt)  # a SkyNode is a GaussianParams
    assert opt.state[node.sh]["exp_avg"].shape[0] == len(node)
    dirs = fibonacci_sphere(1000)
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=1), 1.0)
    assert np.abs(dirs.mean(0)).max() < 0.01  # evenly spread


@pytest.mark.slow
@pytest.mark.skipif(not (KITTI / "poses.txt").is_file(), reason="kitti06_51 not present")
def test_kitti_has_sky(tmp_path):
    from agg.io.importers import import_kitti
    from agg.io.video import IngestConfig
    from agg.priors.pipeline import PriorsConfig, run_priors

    bundle = import_kitti(KITTI, tmp_path / "kitti", config=IngestConfig(width=480, stride=2, max_frames=20))
    run_priors(bundle, PriorsConfig(stages=("poses", "depth")))
    bundle = SceneBundle.load(bundle.path)
    mask = sky_mask(bundle, frames=[0, 10, 19])
    print(f"KITTI sky fraction per frame {mask.mean((1, 2)).round(3)}")
    assert has_sky(bundle) and mask.mean() > 0.03
    h = bundle.height
    assert mask[:, : h // 4].mean() > 4 * mask[:, h // 2:].mean()  # the sky is at the top
    node = SkyNode.from_bundle(bundle, n=2000, sh_degree=0)
    out = _render(node, bundle.world_from_camera[0], bundle.intrinsics[0], bundle.width, h)
    img = np.asarray(bundle.frame(0), np.float32)
    err = np.abs(out.color.detach().numpy() - img)[mask[0]].mean()
    assert out.alpha.detach().numpy()[mask[0]].min() > 0.9 and err < 0.1, err
