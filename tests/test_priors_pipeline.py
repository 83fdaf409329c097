"""The priors pipeline keeps what the user gave and estimates the rest, in the given frame and scale."""

from __future__ import annotations

import numpy as np
import pytest

from agg.io.bundle import SceneBundle
from agg.priors.pipeline import PriorsConfig, run_priors
from agg.synth.corrupt import NoiseConfig
from agg.synth.scene import SceneConfig
from agg.synth.suite import generate, write_bundle


@pytest.fixture(scope="module")
def given(tmp_path_factory):
    """A synthetic bundle whose user gave exact poses (metres) and masks, but no depth, tracks or features."""
    gt, priors = generate(SceneConfig(seed=2, frames=12, width=320, height=192), NoiseConfig())
    path = tmp_path_factory.mktemp("given") / "b"
    b = write_bundle(path, gt, priors, NoiseConfig())
    for part in ("depth_dense", "tracklets", "semantics"):
        b.remove(part)
    summary = run_priors(SceneBundle.load(path), PriorsConfig())
    return SceneBundle.load(path), gt, summary


def test_given_parts_are_kept(given):
    b, gt, summary = given
    assert summary.poses["source"] == "given" and summary.skipped["masks"] == "given"
    np.testing.assert_array_equal(b.world_from_camera, gt.world_from_camera)
    np.testing.assert_array_equal(np.asarray(b.dynamic_masks) > 0, gt.instance > 0)
    assert b.pose_source == ["gt"] * b.num_frames
    assert {"poses", "depth", "tracklets", "semantics"} <= set(summary.ran)  # poses ran for SfM points only


def test_sfm_depth_is_moved_into_the_given_metric_frame(given):
    b, gt, _ = given
    ratios = []
    for i in range(b.num_frames):
        rows = b.sparse_depth(i)  # [k, 4] (u, v, depth, confidence)
        u, v = np.rint(rows[:, 0]).astype(int), np.rint(rows[:, 1]).astype(int)
        ok = gt.depth_valid[i, v, u]
        ratios.append(rows[ok, 2] / gt.depth[i, v[ok], u[ok]])
    ratios = np.concatenate(ratios)
    assert len(ratios) > 500
    assert abs(np.median(ratios) - 1.0) < 0.03  # SfM's arbitrary scale was aligned to the given metres
    assert np.median(np.abs(ratios - 1.0)) < 0.08  # point noise of SfM at 320x192 (measured 0.04)


def test_tracks_follow_the_given_masks(given):
    b, gt, summary = given
    assert b.has("tracklets") and summary.tracklets["count"] >= 1
    assert summary.scores["masks"]["iou_all_agents"] == 1.0  # the given masks are the GT ones


def test_a_stage_run_again_from_the_bundle_gives_what_the_full_run_gave(tmp_path):
    """The semantics read the flow residual; a re-run reads the one the bundle keeps (float16), so the full run
    uses those values too and both give the same features."""
    import shutil

    gt, priors = generate(SceneConfig(seed=2, frames=12, width=320, height=192), NoiseConfig())
    b = write_bundle(tmp_path / "a", gt, priors, NoiseConfig())
    for part in ("depth_dense", "dynamic_masks", "tracklets", "semantics"):
        b.remove(part)
    summary = run_priors(SceneBundle.load(tmp_path / "a"), PriorsConfig())
    assert {"masks", "semantics"} <= set(summary.ran)
    shutil.copytree(tmp_path / "a", tmp_path / "b")
    again = run_priors(SceneBundle.load(tmp_path / "b"), PriorsConfig(recompute=("semantics",)))
    assert again.ran == ["semantics"]
    first, second = SceneBundle.load(tmp_path / "a").semantics, SceneBundle.load(tmp_path / "b").semantics
    np.testing.assert_array_equal(np.asarray(first.features), np.asarray(second.features))
