"""The semantic loss needs attention maps that separate the agents (``agg.train.semantic.semantic_gate``): maps that
put about the same weight on the priors' dynamic masks as elsewhere turn Eq. 3 into a near-uniform extra L1, and the
scene trains without it."""

from __future__ import annotations

import shutil
from dataclasses import replace

import numpy as np
import pytest
import torch

from agg.graph import SceneGraph
from agg.io.bundle import SceneBundle
from agg.synth.corrupt import NoiseConfig
from agg.synth.scene import SceneConfig
from agg.synth.suite import generate, write_bundle
from agg.train.config import get_preset
from agg.train.data import load_train_data
from agg.train.semantic import semantic_gate
from agg.train.trainer import Trainer, seed_everything


@pytest.fixture(scope="module")
def bundle(tmp_path_factory):
    noise = NoiseConfig(camera_translation_max=0.2)
    gt, priors = generate(SceneConfig(seed=1, frames=10, width=128, height=80), noise)
    path = tmp_path_factory.mktemp("gate") / "b"
    write_bundle(path, gt, priors, noise)
    return SceneBundle.load(path)


def test_the_gate_reads_each_maps_contrast_on_the_masks():
    masks = torch.zeros(2, 4, 6, dtype=torch.bool)
    masks[:, 1:3, 2:4] = True  # 8 of 24 pixels a frame
    m_ag = torch.where(masks, 3.0, 1.0)
    m_bg = torch.where(masks, 1.0, 2.0)
    g = semantic_gate(m_bg, m_ag, masks, 1.5)
    assert g == {"active": True, "contrast_ag": 3.0, "contrast_bg": 2.0, "reason": None}
    flat_bg = torch.where(masks, 1.0, 1.2)  # M_bg barely lower on the agents: Tick routes nothing
    g = semantic_gate(flat_bg, m_ag, masks, 1.5)
    assert not g["active"] and g["contrast_bg"] == 1.2 and "M_bg 1.20 < 1.5" in g["reason"]
    assert "M_ag" not in g["reason"]
    assert semantic_gate(flat_bg, m_ag, masks, None)["active"]  # the paper's rule: always on
    # nothing to measure on (no masks, empty ones, or masks over every pixel): no agent to route to, loss off
    for none in (None, torch.zeros_like(masks)):
        assert semantic_gate(m_bg, m_ag, none, 1.5) == {
            "active": False, "contrast_ag": None, "contrast_bg": None,
            "reason": "no dynamic-mask pixels to measure the attention maps' contrast on"}
    assert semantic_gate(m_bg, m_ag, torch.ones_like(masks), 1.5)["reason"] == "the dynamic masks cover every pixel"
    assert semantic_gate(m_bg, m_ag, None, None)["active"]
    only_agents = torch.where(masks, 2.0, 0.0)  # M_ag 0 off the agents: infinite contrast, reported as None in JSON
    assert semantic_gate(m_bg, only_agents, masks, 1.5) == {"active": True, "contrast_ag": None, "contrast_bg": 2.0,
                                                           "reason": None}
    assert semantic_gate(m_bg, torch.zeros_like(m_ag), masks, 1.5)["reason"] == "an attention map is 0 on every pixel"


def test_maps_that_miss_the_agents_train_without_the_semantic_loss(bundle, tmp_path):
    data = load_train_data(bundle, 128, min_contrast=1.5)
    g = data.semantic  # the suite's features are the classes': the maps separate the priors' masks clearly
    assert g["active"] and g["contrast_ag"] > 3 and g["contrast_bg"] > 3 and data.m_bg is not None
    # the same features, with dynamic masks that sit where no agent is (the road's bottom rows): no contrast
    path = tmp_path / "moved"
    shutil.copytree(bundle.path, path)
    moved = SceneBundle.load(path)
    masks = np.zeros((moved.num_frames, moved.height, moved.width), np.uint8)
    masks[:, -6:, :] = 1
    moved.write_dynamic_masks(masks)
    off = load_train_data(moved, 128, min_contrast=1.5)
    assert not off.semantic["active"] and off.semantic["contrast_ag"] < 1.5
    assert off.m_bg is None and off.m_ag is None
    cfg = replace(get_preset("tiny"), iterations=40)
    seed_everything(cfg.seed)
    tr = Trainer(SceneGraph.from_bundle(moved, cfg.init), off, cfg, moved)
    rows = [tr.step() for _ in range(40)]
    assert {r["phase"] for r in rows} >= {"tick", "tock"}
    assert all(r["sem"] is None for r in rows)  # Tick and Tock alike
    on = load_train_data(moved, 128)  # no min_contrast: the paper's rule keeps the loss
    assert on.semantic["active"] and on.m_bg is not None
