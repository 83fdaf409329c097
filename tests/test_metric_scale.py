"""Metres per scene unit (agg/priors/metric_scale.py): metric bundles keep their scale, monocular ones are read
from the road plane of their depth, and training's metric settings (pose-translation rates, the deformation
network's position scale) follow it."""

from __future__ import annotations

import shutil
from dataclasses import replace

import pytest

from agg.io.bundle import SceneBundle
from agg.priors.metric_scale import ASSUMED_CAMERA_HEIGHT_M, MetricScale, estimate_metric_scale
from agg.synth.corrupt import NoiseConfig
from agg.synth.scene import SceneConfig
from agg.synth.suite import generate, write_bundle
from agg.train.config import get_preset
from agg.train.data import load_train_data
from agg.train.reconstruct import _graph_for
from agg.train.trainer import Trainer

SCENE = SceneConfig(seed=2, frames=6, width=160, height=96, pedestrians=1)  # camera_height 1.6 m


@pytest.fixture(scope="module")
def bundles(tmp_path_factory):
    """A metric synthetic bundle and a monocular-like copy: every length divided by its path length f, then
    marked not metric with scale 1 (what `agg priors` writes for a video)."""
    root = tmp_path_factory.mktemp("ms")
    noise = NoiseConfig(camera_translation_max=0.2)
    gt, priors = generate(SCENE, noise)
    metric = write_bundle(root / "metric", gt, priors, noise)
    shutil.copytree(metric.path, root / "mono")
    mono = SceneBundle.load(root / "mono")
    f = mono.normalise_scale("path_length")
    mono.set_scale(1.0, metric=False)
    return metric, SceneBundle.load(root / "mono"), f


def test_a_metric_bundle_keeps_its_scale(bundles):
    metric, _, _ = bundles
    assert estimate_metric_scale(metric) == MetricScale(1.0, "metric")


def test_a_monocular_bundle_is_read_from_the_road_plane(bundles):
    _, mono, f = bundles
    est = estimate_metric_scale(mono)
    assert est.source == "camera_height" and est.frames_with_road == SCENE.frames
    # the road plane recovers the camera height (1.6 m / f units) within 2 %; the rest is the assumed 1.5 m
    assert est.camera_height_units * f == pytest.approx(SCENE.camera_height, rel=0.02)
    assert est.metres_per_unit == pytest.approx(f * ASSUMED_CAMERA_HEIGHT_M / SCENE.camera_height, rel=0.02)


def test_sparse_rows_alone_give_the_estimate_and_no_depth_falls_back(tmp_path):
    noise = NoiseConfig()
    gt, priors = generate(SCENE, noise)
    b = write_bundle(tmp_path / "sparse", gt, priors, noise, depth_format="sparse")
    f = b.normalise_scale("path_length")
    b.set_scale(1.0, metric=False)
    b = SceneBundle.load(b.path)
    assert not b.has("depth_dense") and b.has("depth_sparse")
    est = estimate_metric_scale(b)
    assert est.source == "camera_height"
    assert est.camera_height_units * f == pytest.approx(SCENE.camera_height, rel=0.02)
    b.remove("depth_sparse")
    assert estimate_metric_scale(SceneBundle.load(b.path)) == MetricScale(1.0, "bundle_scale")


def test_training_rates_and_deformation_scale_follow_the_metres(bundles):
    """The same scene in metres and in units of f metres: translation rates (metres per step) and the deformation
    network's position scale (metres) are f times smaller in units; rotation rates do not change."""
    metric, mono, f = bundles
    cfg = get_preset("tiny")

    def trainer(b):
        est = estimate_metric_scale(b)
        data = load_train_data(b, cfg.max_width)
        return Trainer(_graph_for(b, cfg, est), data, cfg, b, metric=est), est

    (tm, em), (tu, eu) = trainer(metric), trainer(mono)
    ratio = eu.units_per_metre / em.units_per_metre  # about 1 / f (times the true / assumed camera height)
    assert ratio == pytest.approx(SCENE.camera_height / (ASSUMED_CAMERA_HEIGHT_M * f), rel=0.02)

    def lrs(t):
        return {g["name"]: g["lr"] for opt in t.optimizers.values() for g in opt.param_groups}

    lm, lu = lrs(tm), lrs(tu)
    assert lu["camera#tau"] == pytest.approx(lm["camera#tau"] * ratio, rel=1e-6)
    assert lu["camera#omega"] == pytest.approx(lm["camera#omega"], rel=1e-6)
    for node in ("rigid", "nonrigid"):  # agent box translations scale, their rotations do not
        assert lu[f"{node}#tau"] == pytest.approx(lm[f"{node}#tau"] * ratio, rel=1e-6)
        assert lu[f"{node}#omega"] == pytest.approx(lm[f"{node}#omega"], rel=1e-6)
    assert tm.graph.nonrigid is not None and tu.graph.nonrigid is not None
    assert tu.graph.nonrigid.config.pos_scale == pytest.approx(tm.graph.nonrigid.config.pos_scale * ratio)
    assert tm.graph.nonrigid.config.pos_scale == pytest.approx(1.0)


def test_a_metric_scale_must_be_positive():
    with pytest.raises(ValueError):
        replace(MetricScale(1.0, "metric"), metres_per_unit=0.0)
