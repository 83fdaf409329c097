"""A spawned agent's per-frame centroid read off its semantic silhouette (agg/train/topology_silhouette.py), on a
rendered synthetic clip with exact cameras, depth and features."""

from __future__ import annotations

import numpy as np
import pytest

from agg.synth.corrupt import NoiseConfig
from agg.synth.scene import SEM, SceneConfig
from agg.synth.suite import generate, load_gt_extras, write_bundle
from agg.train import topology_track as tt
from agg.train.topology_silhouette import frame_cells, silhouette_centroid


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    path = tmp_path_factory.mktemp("silhouette") / "clip"
    gt, priors = generate(SceneConfig(seed=0, frames=4, width=320, height=192, pedestrians=0), NoiseConfig())
    bundle = write_bundle(path, gt, priors, NoiseConfig())
    extras = load_gt_extras(path)
    # the car with the most visible pixels in frame 1 (GT ids are 1..K)
    k = int(np.argmax(extras["pixel_count"][:, 1])) + 1
    return bundle, extras, k, tt.prototype_bank(bundle.semantics)


def _pixel_centroid(bundle, extras, k: int, t: int) -> np.ndarray:
    """The car's GT pixels back-projected at the exact depth, weighted by cos^3 (solid angle): its visible
    surface centroid."""
    vs, us = np.nonzero(extras["instance"][t] == k)
    uv = np.stack([us, vs], 1).astype(np.float64)
    K = bundle.intrinsics[min(t, len(bundle.intrinsics) - 1)]  # noqa: N806
    xy = (uv - K[:2, 2]) / np.diag(K)[:2]
    w = (1.0 + (xy ** 2).sum(1)) ** -1.5
    p = tt.backproject(uv, bundle.dense_depth[t][vs, us], bundle.camera_from_world[t], K)
    return (p * w[:, None]).sum(0) / w.sum()


def _args(bundle, t: int):
    K = bundle.intrinsics[min(t, len(bundle.intrinsics) - 1)]  # noqa: N806
    return bundle.semantics.features[t], bundle.dense_depth[t], bundle.camera_from_world[t], K


def test_the_silhouette_centroid_is_the_whole_car_from_any_point_on_it(clip):
    bundle, extras, k, bank = clip
    t = 1
    feats, depth, cfw, K = _args(bundle, t)  # noqa: N806
    truth = _pixel_centroid(bundle, extras, k, t)
    pose = extras["world_from_agent"][k - 1, t]  # [4, 4]
    half = np.array([2.25, 0.8, 0.9])
    # seeds on the car's surface: its visible centroid and the pixels nearest its front and rear ends
    vs, us = np.nonzero(extras["instance"][t] == k)
    surface = tt.backproject(np.stack([us, vs], 1).astype(np.float64), depth[vs, us], cfw, K)  # [P, 3]
    along = (surface - pose[:3, 3]) @ pose[:3, 0]  # [P] along its heading
    cells = frame_cells(feats, bank, 0.5, depth, cfw, K)
    ends = surface[np.argmax(along)], surface[np.argmin(along)]
    assert min(np.linalg.norm(e - truth) for e in ends) > 1.0  # the ends are far from the centroid
    for seed in (truth, *ends):
        found = silhouette_centroid(seed, cells, cfw, K, 2.0 * np.linalg.norm(half))
        assert found is not None
        centre, n = found
        # a 4-pixel feature cell quantises the outline: within 0.25 m of the pixels' centroid, wherever the seed
        assert np.linalg.norm(centre - truth) < 0.25, (centre, truth)
        assert n >= 10


def test_other_agents_masks_and_missing_views_give_nothing(clip):
    bundle, extras, k, bank = clip
    t = 1
    feats, depth, cfw, K = _args(bundle, t)  # noqa: N806
    truth = _pixel_centroid(bundle, extras, k, t)
    reach = 2.0 * np.linalg.norm([2.25, 0.8, 0.9])
    # the car's own pixels explained by another agent (its prior dynamic mask): no silhouette is left
    own = extras["instance"][t] == k
    assert silhouette_centroid(truth, frame_cells(feats, bank, 0.5, depth, cfw, K, own), cfw, K, reach) is None
    cells = frame_cells(feats, bank, 0.5, depth, cfw, K)
    # a seed behind the camera, or on the road far from any agent-like cell
    behind = cfw[:3, :3].T @ (np.array([0.0, 0.0, -5.0]) - cfw[:3, 3])
    assert silhouette_centroid(behind, cells, cfw, K, reach) is None
    road = (extras["instance"][t] == 0) & (extras["semantic"][t] == SEM["road"])
    far = np.ones_like(road)
    for i in range(1, extras["instance"].max() + 1):  # pixels more than 20 px from every agent
        vs, us = np.nonzero(extras["instance"][t] == i)
        if len(vs):
            far[max(vs.min() - 20, 0):vs.max() + 21, max(us.min() - 20, 0):us.max() + 21] = False
    vs, us = np.nonzero(road & far & (depth > 0))
    assert len(vs), "the clip has road away from the agents"
    seed = tt.backproject(np.array([[us[0], vs[0]]], np.float64), depth[vs[:1], us[:1]], cfw, K)[0]
    assert silhouette_centroid(seed, cells, cfw, K, reach) is None
    # too small a reach keeps too few cells
    assert silhouette_centroid(truth, cells, cfw, K, 0.05) is None
