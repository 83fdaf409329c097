"""Oracle-like feature maps that stand in for a foundation model's PCA-reduced features (the paper's F_low).

Each semantic class c has a fixed unit embedding ``e_c`` in R^D (D = 64 by default). The channels are split once
(by ``embedding_seed``) into the agent subset ``C_ag`` (16 of 64 channels) and the background subset ``C_bg`` (the
rest): background classes live only on ``C_bg``, agent classes (car, pedestrian) only on ``C_ag``, with
non-negative entries, so that the paper's attention maps ``M_bg`` / ``M_ag`` (sums over the subsets after global
min-max normalisation) light up the right regions. Within a subset the direction of each class is random
(``|N(0, 1)|`` entries, normalised).

The feature map of a frame is the area average of ``e_{semantic(pixel)}`` over the pixels that each feature cell
covers (a plain resize of the image grid by ``1 / factor``, as in docs/BUNDLE.md), plus optional i.i.d. Gaussian
noise of standard deviation ``sigma`` per element (added in ``corrupt.py``).

The prototype bank follows the paper (feature centroids): ``rigid`` = e_car, ``non-rigid`` = e_pedestrian,
``background`` = the normalised mean of the background class embeddings; each is a [1, D] matrix in the same
("pca") space as the features.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from agg.synth.scene import BACKGROUND_CLASSES, SEM, SEMANTIC_CLASSES


class FeatureConfigError(ValueError):
    """Invalid feature-map settings (dimension, factor, image size)."""


@dataclass(frozen=True)
class FeatureConfig:
    dim: int = 64  # D, the paper's PCA dimension
    agent_channels: int = 16  # |C_ag|
    factor: int = 4  # feature map = image size / factor
    embedding_seed: int = 0  # fixed across scenes, like a foundation model's feature space


@dataclass
class ClassEmbeddings:
    vectors: np.ndarray  # [n_classes, D] unit rows, indexed by semantic id
    C_bg: list[int]
    C_ag: list[int]
    prototypes: dict[str, np.ndarray]  # "rigid" / "non-rigid" / "background" -> [1, D]


def class_embeddings(cfg: FeatureConfig = FeatureConfig()) -> ClassEmbeddings:
    """The fixed class embeddings, channel subsets and prototype bank for a feature config."""
    if not 0 < cfg.agent_channels < cfg.dim:
        raise FeatureConfigError(f"agent_channels must be in (0, dim={cfg.dim}), got {cfg.agent_channels}")
    rng = np.random.default_rng([cfg.embedding_seed, 0xFEA7])
    perm = rng.permutation(cfg.dim)
    c_ag = sorted(int(i) for i in perm[:cfg.agent_channels])
    c_bg = sorted(int(i) for i in perm[cfg.agent_channels:])
    vecs = np.zeros((len(SEMANTIC_CLASSES), cfg.dim))
    for name in SEMANTIC_CLASSES:
        chans = c_bg if name in BACKGROUND_CLASSES else c_ag
        v = np.abs(rng.standard_normal(len(chans)))
        vecs[SEM[name], chans] = v / np.linalg.norm(v)
    bg = vecs[[SEM[c] for c in BACKGROUND_CLASSES]].mean(0)
    protos = {"rigid": vecs[SEM["car"]][None], "non-rigid": vecs[SEM["pedestrian"]][None],
              "background": (bg / np.linalg.norm(bg))[None]}
    return ClassEmbeddings(vecs, c_bg, c_ag, protos)


def feature_size(width: int, height: int, factor: int) -> tuple[int, int]:
    """(w, h) of the feature map; the image size must be divisible by ``factor``."""
    if factor < 1 or width % factor or height % factor:
        raise FeatureConfigError(f"image {width}x{height} is not divisible by the feature factor {factor}")
    return width // factor, height // factor


def feature_maps(semantic: np.ndarray, emb: ClassEmbeddings, factor: int) -> np.ndarray:
    """Noise-free features [T, h, w, D] float32 from semantic maps [T, H, W] (ids), by area averaging."""
    t, height, width = semantic.shape
    w, h = feature_size(width, height, factor)
    out = np.zeros((t, h, w, emb.vectors.shape[1]), np.float32)
    for c in range(len(emb.vectors)):  # fraction of each cell covered by class c, times its embedding
        frac = (semantic == c).reshape(t, h, factor, w, factor).mean((2, 4))  # [T, h, w]
        if frac.any():
            out += frac[..., None].astype(np.float32) * emb.vectors[c].astype(np.float32)
    return out


def attention_maps(features: np.ndarray, emb: ClassEmbeddings) -> tuple[np.ndarray, np.ndarray]:
    """The paper's global-latent-normalised attention (M_bg, M_ag), each [..., h, w], from features [..., h, w, D]."""
    lo, hi = float(features.min()), float(features.max())
    norm = (features - lo) / max(hi - lo, 1e-12)
    return norm[..., emb.C_bg].sum(-1), norm[..., emb.C_ag].sum(-1)


def classify(features: np.ndarray, emb: ClassEmbeddings) -> np.ndarray:
    """argmax of cosine similarity with the prototypes: 0 = background, 1 = rigid, 2 = non-rigid; [...]."""
    bank = np.concatenate([emb.prototypes[k] for k in ("background", "rigid", "non-rigid")])  # [3, D]
    f = features / np.maximum(np.linalg.norm(features, axis=-1, keepdims=True), 1e-12)
    return (f @ bank.T).argmax(-1)
