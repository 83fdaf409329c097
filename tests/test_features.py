"""Tests of the semantic feature prior (agg/priors/features.py, prototypes.py, semantic_pca.py, `agg prototypes`)."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
from sklearn.metrics import roc_auc_score

from agg.cli import main
from agg.io.bundle import SceneBundle
from agg.priors.features import (BUILTIN_DIM, BuiltinExtractor, DinoExtractor, FeatureConfig, FeatureConfigError,
                                 FeatureError, LabelledFolderError, PrototypeBankError, WeightsError, build_semantics,
                                 load_prototype_bank, make_extractor, prototypes_from_labelled_folder,
                                 save_prototype_bank)
from agg.priors.prototypes import PrototypeBank, cell_fractions, cityscapes_classes, cosine_scores
from agg.priors.semantic_pca import select_channel_subsets
from agg.synth.scene import SEM, SceneConfig
from agg.synth.suite import render_clip

# synthetic semantic id -> Cityscapes label id (sky 23, road 7, sidewalk 8, building 11, car 26, person 24)
CITYSCAPES_OF_SEM = {SEM["sky"]: 23, SEM["road"]: 7, SEM["marking"]: 7, SEM["sidewalk"]: 8, SEM["building"]: 11,
                     SEM["car"]: 26, SEM["pedestrian"]: 24}


def _class_masks(gt) -> np.ndarray:
    cm = np.zeros(gt.semantic.shape, np.uint8)  # [T, H, W] 0 background, 1 rigid, 2 non-rigid
    cm[gt.semantic == SEM["car"]] = 1
    cm[gt.semantic == SEM["pedestrian"]] = 2
    return cm


def _agent_cells(cm: np.ndarray, h: int, w: int) -> np.ndarray:
    frac = np.stack([cell_fractions(c, h, w) for c in cm])  # [T, h, w, 3]
    return frac[..., 1] + frac[..., 2] >= 0.5


def _attention(sem, subset) -> np.ndarray:
    f = np.asarray(sem.features, np.float32)
    return ((f - sem.feature_min) / (sem.feature_max - sem.feature_min))[..., subset].sum(-1)  # paper's M_i


@pytest.fixture(scope="module")
def clip():
    return render_clip(SceneConfig(seed=0, frames=12, width=160, height=96))


@pytest.fixture(scope="module")
def sem(clip):
    info = {}
    out = build_semantics(clip.rgb, FeatureConfig(), class_masks=_class_masks(clip), info=info)
    return out, info


def _tiny_dino(path: Path, v3: bool = False) -> Path:
    import torch
    from transformers import Dinov2Config, Dinov2Model, DINOv3ViTConfig, DINOv3ViTModel

    torch.manual_seed(0)
    kw = dict(hidden_size=32, num_hidden_layers=2, num_attention_heads=2, intermediate_size=64)
    model = DINOv3ViTModel(DINOv3ViTConfig(patch_size=16, num_register_tokens=4, **kw)) if v3 else \
        Dinov2Model(Dinov2Config(patch_size=14, image_size=56, **kw))
    model.save_pretrained(path)
    return path


def _labelled_folder(root: Path, seeds=(10, 11), cityscapes_names: bool = False) -> Path:
    for s in seeds:
        gt = render_clip(SceneConfig(seed=s, frames=9, width=160, height=96))
        for i in (0, 4, 8):
            ids = np.zeros(gt.semantic[i].shape, np.uint8)
            for k, v in CITYSCAPES_OF_SEM.items():
                ids[gt.semantic[i] == k] = v
            rgb = cv2.cvtColor((gt.rgb[i] * 255).round().astype(np.uint8), cv2.COLOR_RGB2BGR)
            if cityscapes_names:
                city = root / "leftImg8bit" / "train" / "synth"
                lab = root / "gtFine" / "train" / "synth"
                city.mkdir(parents=True, exist_ok=True)
                lab.mkdir(parents=True, exist_ok=True)
                cv2.imwrite(str(city / f"synth_{s}_{i:06d}_leftImg8bit.png"), rgb)
                cv2.imwrite(str(lab / f"synth_{s}_{i:06d}_gtFine_labelIds.png"), ids)
            else:
                (root / "images").mkdir(parents=True, exist_ok=True)
                (root / "labels").mkdir(parents=True, exist_ok=True)
                cv2.imwrite(str(root / "images" / f"s{s}_{i}.png"), rgb)
                cv2.imwrite(str(root / "labels" / f"s{s}_{i}.png"), ids)
    return root


# ------------------------------------------------------------------------------------------------ builtin

def test_builtin_extractor_shapes_determinism_and_flow_channels(clip):
    ex = BuiltinExtractor()
    d = ex.extract(clip.rgb[0])
    assert d.shape == (24, 40, BUILTIN_DIM) and d.dtype == np.float32 and np.isfinite(d).all()
    np.testing.assert_array_equal(d, ex.extract(clip.rgb[0]))
    np.testing.assert_allclose(ex.extract((clip.rgb[0] * 255).round().astype(np.uint8)), d, atol=0.05)
    assert not d[..., -3:].any()  # no flow residual -> zero flow channels
    resid = np.zeros((96, 160), np.float32)
    resid[40:60, 60:100] = 5.0
    df = ex.extract(clip.rgb[0], resid)
    np.testing.assert_array_equal(df[..., :-3], d[..., :-3])
    assert df[12, 20, -3] == pytest.approx(np.log1p(5.0), rel=1e-5) and df[0, 0, -3] == 0
    assert ex.grid_size(720, 1280) == (90, 160) and ex.grid_size(96, 160) == (24, 40)
    with pytest.raises(FeatureError, match=r"\[H, W, 3\]"):
        ex.extract(clip.rgb[0, ..., 0])
    with pytest.raises(FeatureError, match="flow_residual"):
        ex.extract(clip.rgb[0], resid[:10])
    with pytest.raises(FeatureConfigError, match="backend"):
        FeatureConfig(backend="vgg")


def test_pca_features_and_subsets_separate_agents(clip, sem):
    s, info = sem
    t, h, w, c = s.features.shape
    assert (t, h, w, c) == (12, 24, 40, 64) and s.features.dtype == np.float16
    assert s.pca_basis.shape == (BUILTIN_DIM, 64) and s.pca_mean.shape == (BUILTIN_DIM,)
    assert s.prototype_space == "pca" and info["label_source"] == "class_masks"
    assert s.C_ag and s.C_bg and not set(s.C_ag) & set(s.C_bg)
    # F_low = (F - pca_mean) @ pca_basis, as docs/BUNDLE.md states
    raw = BuiltinExtractor().extract(clip.rgb[5]).astype(np.float16).astype(np.float32)
    np.testing.assert_allclose((raw - s.pca_mean) @ s.pca_basis, s.features[5].astype(np.float32), atol=0.05, rtol=0.01)
    agent = _agent_cells(_class_masks(clip), h, w)
    m_ag, m_bg = _attention(s, s.C_ag), _attention(s, s.C_bg)
    assert m_ag[agent].mean() > m_ag[~agent].mean() and m_bg[~agent].mean() > m_bg[agent].mean()
    assert roc_auc_score(agent.ravel(), m_ag.ravel()) > 0.85
    assert roc_auc_score(~agent.ravel(), m_bg.ravel()) > 0.8
    # prototypes: each class's cells are most similar to their own class
    scores = cosine_scores(np.asarray(s.features, np.float32), s.prototypes)  # [T, h, w, 3]
    frac = np.stack([cell_fractions(cm, h, w) for cm in _class_masks(clip)])
    pure = frac.max(-1) >= 0.75
    cls = frac.argmax(-1)
    for k in (0, 1):
        sel = pure & (cls == k)
        assert (scores[sel].argmax(-1) == k).mean() > 0.7
    assert scores[pure & (cls == 1)][:, 1].mean() > scores[pure & (cls == 0)][:, 1].mean() + 0.3
    assert roc_auc_score(agent.ravel(), (scores[..., 1:].max(-1) - scores[..., 0]).ravel()) > 0.9


def test_build_semantics_is_deterministic_and_writes_to_a_bundle(clip, sem, tmp_path):
    s, _ = sem
    calls = []
    again = build_semantics((clip.rgb * 255).round().astype(np.uint8), FeatureConfig(cache_bytes=0),
                            class_masks=_class_masks(clip), progress=calls.append)
    assert calls == list(range(12)) * 2  # no cache: every frame is extracted twice
    np.testing.assert_allclose(again.features.astype(np.float32), s.features.astype(np.float32), atol=0.1)
    same = build_semantics(clip.rgb, FeatureConfig(), class_masks=_class_masks(clip))
    np.testing.assert_array_equal(same.features, s.features)
    assert same.C_ag == s.C_ag and same.C_bg == s.C_bg
    b = SceneBundle.create(tmp_path / "b", clip.rgb, clip.timestamps_us, clip.K)
    b.write_semantics(s)
    back = SceneBundle.load(tmp_path / "b").semantics
    assert back.features.shape == s.features.shape and back.C_ag == s.C_ag
    assert back.feature_min == pytest.approx(s.feature_min) and set(back.prototypes) == {"rigid", "non-rigid",
                                                                                          "background"}


def test_dynamic_masks_only_and_no_labels(clip):
    masks = (clip.instance > 0).astype(np.uint8)
    info = {}
    s = build_semantics(clip.rgb[:6], FeatureConfig(), masks=masks[:6], info=info)
    assert info["label_source"] == "masks" and "B_non-rigid = B_rigid" in info["prototypes"]
    np.testing.assert_array_equal(s.prototypes["non-rigid"], s.prototypes["rigid"])
    with pytest.warns(UserWarning, match="placeholders"):
        s2 = build_semantics(clip.rgb[:3], FeatureConfig())
    assert s2.prototypes is None and len(s2.C_bg) == 16 and len(s2.C_ag) == 16
    with pytest.raises(FeatureError, match="masks must be"):
        build_semantics(clip.rgb[:3], FeatureConfig(), masks=masks[:2])
    with pytest.raises(FeatureError, match="class_masks values"):
        build_semantics(clip.rgb[:3], FeatureConfig(), class_masks=masks[:3] * 3)


def test_subset_rule_on_planted_channels():
    rng = np.random.default_rng(0)
    y = rng.random(5000) < 0.2
    f = rng.standard_normal((5000, 6))
    f[:, 2] -= 2.0 * y  # agents low on channel 2 -> C_ag after a flip
    f[:, 4] += 1.5 * ~y  # background high on channel 4
    ch = select_channel_subsets(f, y, max_ag=3, max_bg=3, min_gain=0.01)
    assert 2 in ch.C_ag and ch.signs[2] == -1 and 4 in ch.C_bg and ch.signs[4] == 1
    assert not set(ch.C_ag) & set(ch.C_bg) and ch.corr_ag > 0.6


# ------------------------------------------------------------------------------------------------ dino

def test_dino_tiny_model_loads_offline_and_gives_patch_features(clip, tmp_path):
    folder = _tiny_dino(tmp_path / "dinov2-tiny")
    ex = DinoExtractor(folder, long_side=112)
    assert ex.dim == 32 and ex.grid_size(96, 160) == (5, 8)
    d = ex.extract(clip.rgb[0])
    assert d.shape == (5, 8, 32) and np.isfinite(d).all()
    np.testing.assert_array_equal(DinoExtractor(folder / "model.safetensors", long_side=112).extract(clip.rgb[0]), d)
    cfg = FeatureConfig(backend="dino", weights=str(folder), dino_long_side=112)
    s = build_semantics(clip.rgb[:4], cfg, class_masks=_class_masks(clip)[:4])
    assert s.features.shape == (4, 5, 8, 32)  # C = min(64, D_in = 32)
    assert s.pca_basis.shape == (32, 32) and s.prototypes["rigid"].shape[1] == 32
    v3 = DinoExtractor(_tiny_dino(tmp_path / "dinov3-tiny", v3=True), long_side=128)
    assert v3.extract(clip.rgb[0]).shape == (5, 8, 32)


def test_dino_bad_weights_paths(tmp_path):
    with pytest.raises(WeightsError, match="needs a weights path"):
        make_extractor(FeatureConfig(backend="dino"))
    with pytest.raises(WeightsError, match="does not exist"):
        DinoExtractor(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(WeightsError, match="no config.json"):
        DinoExtractor(tmp_path / "empty")
    (tmp_path / "bert").mkdir()
    (tmp_path / "bert" / "config.json").write_text(json.dumps({"model_type": "bert"}))
    with pytest.raises(WeightsError, match="supported"):
        DinoExtractor(tmp_path / "bert")


# ------------------------------------------------------------------------------------------------ bank

def test_labelled_folder_bank_command_and_use(clip, tmp_path):
    folder = _labelled_folder(tmp_path / "labelled")
    ex = BuiltinExtractor()
    bank = prototypes_from_labelled_folder(folder, ex, n_per_class=8)
    assert set(bank) == {"rigid", "non-rigid", "background"} and bank["rigid"].shape == (8, BUILTIN_DIM)
    assert bank.meta["backend"] == "builtin" and bank.meta["n_images"] == 6
    city = prototypes_from_labelled_folder(_labelled_folder(tmp_path / "city", cityscapes_names=True), ex)
    np.testing.assert_allclose(city["rigid"], bank["rigid"], rtol=1e-5, atol=1e-5)  # same data, other layout
    out = tmp_path / "bank.npz"
    assert main(["prototypes", str(folder), "-o", str(out)]) == 0  # default: 8 per class
    loaded = load_prototype_bank(out, backend="builtin", dim=BUILTIN_DIM)
    np.testing.assert_allclose(loaded["background"], bank["background"], rtol=1e-6)
    assert main(["prototypes", str(folder), "-o", str(out)]) == 2  # exists, no --overwrite
    # a bank from other scenes labels this scene without any masks
    info = {}
    s = build_semantics(clip.rgb, FeatureConfig(), prototype_bank=loaded, info=info)
    assert info["label_source"].startswith("prototype bank") and s.prototypes["rigid"].shape == (8, 64)
    h, w = s.features.shape[1:3]
    agent = _agent_cells(_class_masks(clip), h, w)
    scores = cosine_scores(np.asarray(s.features, np.float32), s.prototypes)
    assert roc_auc_score(agent.ravel(), (scores[..., 1:].max(-1) - scores[..., 0]).ravel()) > 0.85
    assert roc_auc_score(agent.ravel(), _attention(s, s.C_ag).ravel()) > 0.7  # 0.76 with this 6-image bank


def test_bank_and_folder_errors(clip, tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(LabelledFolderError, match="no image/label pairs"):
        prototypes_from_labelled_folder(tmp_path / "empty", BuiltinExtractor())
    assert main(["prototypes", str(tmp_path / "empty"), "-o", str(tmp_path / "x.npz")]) == 2
    other = PrototypeBank({k: np.ones((2, 32), np.float32) for k in ("rigid", "non-rigid", "background")},
                          {"format": "agg-prototype-bank", "backend": "dino", "D_in": 32,
                           "descriptor": "dinov2-d32-L2-p14"})
    path = save_prototype_bank(tmp_path / "dino.npz", other)
    with pytest.raises(PrototypeBankError, match="D_in = 32"):
        load_prototype_bank(path, backend="builtin", dim=BUILTIN_DIM)
    with pytest.raises(PrototypeBankError, match="rebuild the bank"):
        build_semantics(clip.rgb[:2], FeatureConfig(), prototype_bank=load_prototype_bank(path))
    np.savez(tmp_path / "junk.npz", rigid=np.ones((1, 3)))
    with pytest.raises(PrototypeBankError, match="not a prototype bank"):
        load_prototype_bank(tmp_path / "junk.npz")
    with pytest.raises(PrototypeBankError, match="does not exist"):
        load_prototype_bank(tmp_path / "none.npz")
    ids = np.array([[0, 7, 24, 26], [33, 25, 3, 11]])
    np.testing.assert_array_equal(cityscapes_classes(ids), [[-1, 0, 2, 1], [1, 2, -1, 0]])
