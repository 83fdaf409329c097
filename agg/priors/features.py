"""Semantic feature prior: per-pixel descriptors -> per-scene PCA (F_low) -> channel subsets C_bg / C_ag -> prototypes.

One ``FeatureExtractor`` interface, two backends (``make_extractor``):

* ``builtin`` (default, no weights): a fixed stack of ``BUILTIN_DIM = 85`` hand-made descriptors per feature cell
  (colour, multi-scale texture, colour/texture context, image position, flow residual); see ``BuiltinExtractor``.
* ``dino``: the patch tokens of a local DINOv2 / DINOv3 ViT checkpoint (transformers, offline); see
  ``DinoExtractor``.

``build_semantics`` extracts every frame, fits the PCA per scene, projects to F_low float16 [T, h, w, C], chooses
the channel subsets by their correlation with the dynamic masks and builds the prototype bank (``prototypes.py``).
The rules, defaults and measured separation are in docs/PRIORS.md ("Semantic features").
"""

from __future__ import annotations

import abc
import math
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from agg.io.bundle_priors import SemanticFeatures
from agg.priors.prototypes import (LabelledFolderError, PrototypeBank, PrototypeBankError, cell_classes,
                                   check_bank_matches, check_prototype_bank, cosine_scores, label_fractions,
                                   load_prototype_bank, project_bank, prototypes_from_labelled_folder,
                                   save_prototype_bank, scene_prototypes)
from agg.priors.semantic_pca import fit_pca, select_channel_subsets

__all__ = ["FeatureConfig", "FeatureExtractor", "BuiltinExtractor", "DinoExtractor", "make_extractor",
           "build_semantics", "select_channel_subsets", "prototypes_from_labelled_folder", "load_prototype_bank",
           "save_prototype_bank", "PrototypeBank", "FeatureError", "FeatureConfigError", "WeightsError",
           "PrototypeBankError", "LabelledFolderError", "BUILTIN_DIM"]


class FeatureError(ValueError):
    """Bad input to the semantic feature prior (frames, masks, shapes)."""


class FeatureConfigError(FeatureError):
    """A ``FeatureConfig`` value is out of range."""


class WeightsError(FeatureError):
    """The DINO weights path is missing, of an unknown layout, or not a supported model."""


BACKENDS = ("builtin", "dino")


@dataclass(frozen=True)
class FeatureConfig:
    """Settings of the semantic feature prior (defaults documented in docs/PRIORS.md)."""

    backend: str = "builtin"  # "builtin" (no weights) | "dino" (local DINOv2/v3 checkpoint in ``weights``)
    weights: str | None = None  # dino: a save_pretrained folder, or a weights file next to its config.json
    device: str = "cpu"  # dino: torch device string
    n_components: int = 64  # C; the effective C is min(n_components, D_in, sampled cells - 1)
    stride: int = 4  # builtin: image pixels per feature cell (the smallest allowed)
    max_feature_side: int = 160  # builtin: the stride grows so that max(h, w) <= this
    dino_long_side: int = 640  # dino: the longer image side fed to the ViT, rounded to whole patches
    standardize: bool | None = None  # z-score descriptors before the PCA (None: builtin yes, dino no)
    pca_samples: int = 40000  # feature cells sampled (seeded, spread over the frames) for the PCA fit
    select_samples: int = 60000  # cells sampled for the C_bg / C_ag rule and the per-scene prototypes
    max_ag_channels: int = 16  # |C_ag| at most
    max_bg_channels: int = 16  # |C_bg| at most
    min_gain: float = 0.005  # greedy subset growth stops when the correlation gains less than this
    prototypes_per_class: int = 8  # k-means centroids per class (fewer when a class has fewer cells)
    prototype_purity: float = 0.75  # a cell is a class sample when that class covers >= this fraction of it
    cache_bytes: int = 1 << 30  # raw descriptors are kept in memory up to this size, else re-extracted
    seed: int = 0

    def __post_init__(self) -> None:
        if self.backend not in BACKENDS:
            raise FeatureConfigError(f"backend must be one of {BACKENDS}, got {self.backend!r}")
        for name in ("n_components", "stride", "max_feature_side", "dino_long_side", "pca_samples",
                     "select_samples", "max_ag_channels", "max_bg_channels", "prototypes_per_class"):
            if int(getattr(self, name)) < 1:
                raise FeatureConfigError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not 0.5 <= self.prototype_purity <= 1.0:
            raise FeatureConfigError(f"prototype_purity must be in [0.5, 1], got {self.prototype_purity}")


class FeatureExtractor(abc.ABC):
    """Per-frame raw descriptors. ``dim`` is D_in; ``descriptor`` identifies the feature space (bank checks)."""

    name: str
    dim: int
    descriptor: str

    @abc.abstractmethod
    def extract(self, image: np.ndarray, flow_residual: np.ndarray | None = None) -> np.ndarray:
        """image [H, W, 3] float32 in [0,1]; flow_residual [H, W] or None -> raw descriptors [h, w, D_in] float32."""

    @abc.abstractmethod
    def grid_size(self, height: int, width: int) -> tuple[int, int]:
        """(h, w) of the descriptor map of an H x W image."""


def _check_image(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[2] != 3:
        raise FeatureError(f"image must be [H, W, 3], got {img.shape}")
    if img.dtype == np.uint8:
        return img.astype(np.float32) / 255.0
    return np.clip(img.astype(np.float32), 0.0, 1.0)


# ---------------------------------------------------------------------------------------------------- builtin
_TEXTURE_SCALES = (1.0, 2.0, 4.0)  # Gaussian sigmas in work pixels (4 work pixels per feature cell)
_CONTEXT_SIGMAS = (1.5, 4.0)  # Gaussian sigmas in feature cells
_N_BASE = 8 + 6 * len(_TEXTURE_SCALES)  # colour + texture maps
BUILTIN_DIM = 3 * _N_BASE + 4 + 3  # base maps at 3 context scales + position + flow residual = 85


class BuiltinExtractor(FeatureExtractor):
    """Hand-made per-cell descriptors, D_in = 85 (all channels O(1), fixed scales so banks transfer).

    The image is resized (INTER_AREA) to a work image of 4 x 4 pixels per feature cell. Base maps (26):
    colour R, G, B, CIELAB L*/100, a*/100, b*/100, chroma sqrt(a^2 + b^2)/100, HSV saturation; for each texture
    scale sigma in (1, 2, 4) work px (Gaussian-smoothed L*/100): scale-normalised gradient magnitude, the
    structure tensor's sqrt(J_xx), sqrt(J_yy) and coherence, the scale-normalised Laplacian of Gaussian, and the
    local standard deviation of L. They are area-averaged to the cell grid, then each is repeated at two context
    scales (Gaussian blur of 1.5 and 4 cells) -> 78 channels. Position (4): y, x in [-1, 1] (cell centres), |x|,
    y^2. Flow residual (3): log(1 + r) per cell and at the two context scales (zeros when none is given).
    """

    name = "builtin"
    descriptor = "builtin-v1"
    dim = BUILTIN_DIM

    def __init__(self, stride: int = 4, max_feature_side: int = 160):
        self.stride, self.max_feature_side = int(stride), int(max_feature_side)

    def grid_size(self, height: int, width: int) -> tuple[int, int]:
        s = max(self.stride, math.ceil(max(height, width) / self.max_feature_side))
        return max(1, round(height / s)), max(1, round(width / s))

    def extract(self, image: np.ndarray, flow_residual: np.ndarray | None = None) -> np.ndarray:
        img = _check_image(image)  # [H, W, 3]
        H, W = img.shape[:2]
        h, w = self.grid_size(H, W)
        work = cv2.resize(img, (4 * w, 4 * h), interpolation=cv2.INTER_AREA)  # [4h, 4w, 3]
        base = _base_maps(work)  # [4h, 4w, 26]
        cells = cv2.resize(base, (w, h), interpolation=cv2.INTER_AREA).reshape(h, w, -1)  # [h, w, 26]
        out = [cells] + [_blur(cells, s) for s in _CONTEXT_SIGMAS]
        ys = (np.arange(h, dtype=np.float32) + 0.5) / h * 2 - 1
        xs = (np.arange(w, dtype=np.float32) + 0.5) / w * 2 - 1
        yy, xx = np.meshgrid(ys, xs, indexing="ij")
        out.append(np.stack([yy, xx, np.abs(xx), yy * yy], -1))  # [h, w, 4]
        if flow_residual is None:
            out.append(np.zeros((h, w, 3), np.float32))
        else:
            r = np.asarray(flow_residual, dtype=np.float32)
            if r.shape != (H, W):
                raise FeatureError(f"flow_residual must be [{H}, {W}], got {r.shape}")
            r = np.log1p(np.maximum(np.nan_to_num(r, nan=0.0, posinf=0.0), 0.0))
            rc = cv2.resize(r, (w, h), interpolation=cv2.INTER_AREA).reshape(h, w, 1)
            out.append(np.concatenate([rc] + [_blur(rc, s) for s in _CONTEXT_SIGMAS], -1))
        return np.concatenate(out, -1).astype(np.float32)  # [h, w, 85]


def _blur(x: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian blur of [h, w, n] over the grid, reflected borders; shape kept."""
    out = cv2.GaussianBlur(x, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
    return out.reshape(x.shape)


def _base_maps(rgb: np.ndarray) -> np.ndarray:
    """Colour and texture maps [H, W, 26] float32 of an RGB image [H, W, 3] in [0, 1]."""
    lab = cv2.cvtColor(rgb, cv2.COLOR_RGB2Lab) / np.float32(100.0)  # L in [0, 1], a, b ~ [-1.3, 1.3]
    hsv_s = cv2.cvtColor(rgb, cv2.COLOR_RGB2HSV)[..., 1]
    chroma = np.sqrt(lab[..., 1] ** 2 + lab[..., 2] ** 2)
    maps = [rgb[..., 0], rgb[..., 1], rgb[..., 2], lab[..., 0], lab[..., 1], lab[..., 2], chroma, hsv_s]
    lum = np.ascontiguousarray(lab[..., 0])
    eps = np.float32(1e-3)  # gradient energy (~0.03 L/100 per pixel) below which coherence fades to 0
    for s in _TEXTURE_SCALES:
        ls = cv2.GaussianBlur(lum, (0, 0), s, borderType=cv2.BORDER_REFLECT)
        gx = cv2.Sobel(ls, cv2.CV_32F, 1, 0, ksize=3, scale=s / 8.0, borderType=cv2.BORDER_REFLECT)
        gy = cv2.Sobel(ls, cv2.CV_32F, 0, 1, ksize=3, scale=s / 8.0, borderType=cv2.BORDER_REFLECT)
        jxx = cv2.GaussianBlur(gx * gx, (0, 0), 2 * s, borderType=cv2.BORDER_REFLECT)
        jyy = cv2.GaussianBlur(gy * gy, (0, 0), 2 * s, borderType=cv2.BORDER_REFLECT)
        jxy = cv2.GaussianBlur(gx * gy, (0, 0), 2 * s, borderType=cv2.BORDER_REFLECT)
        coherence = np.sqrt((jxx - jyy) ** 2 + 4 * jxy ** 2) / (jxx + jyy + eps)
        log = cv2.Laplacian(ls, cv2.CV_32F, ksize=1, scale=s * s, borderType=cv2.BORDER_REFLECT)
        m1 = cv2.GaussianBlur(lum, (0, 0), 2 * s, borderType=cv2.BORDER_REFLECT)
        m2 = cv2.GaussianBlur(lum * lum, (0, 0), 2 * s, borderType=cv2.BORDER_REFLECT)
        std = np.sqrt(np.maximum(m2 - m1 * m1, 0.0))
        maps += [np.sqrt(gx * gx + gy * gy), np.sqrt(jxx), np.sqrt(jyy), coherence, log, std]
    return np.stack(maps, -1).astype(np.float32)


# ---------------------------------------------------------------------------------------------------- dino
_DINO_MODELS = {"dinov2": "Dinov2Model", "dinov2_with_registers": "Dinov2WithRegistersModel",
                "dinov3_vit": "DINOv3ViTModel"}  # config.json model_type -> transformers class
_WEIGHT_SUFFIXES = (".safetensors", ".bin", ".pt", ".pth")
_IMAGENET_MEAN = np.array([0.485, 0.456, 0.406], np.float32)
_IMAGENET_STD = np.array([0.229, 0.224, 0.225], np.float32)


class DinoExtractor(FeatureExtractor):
    """Last-layer patch tokens of a local DINOv2 / DINOv3 ViT (transformers), [h, w, hidden_size] per frame.

    ``path`` is either a folder written by ``save_pretrained`` (``config.json`` + ``model.safetensors`` or
    ``pytorch_model.bin``) or one weights file (``.safetensors`` / ``.bin`` / ``.pt`` / ``.pth``, a transformers
    state dict, optionally under "state_dict" / "model" and with a "dinov2." / "model." / "backbone." prefix) with
    that folder's ``config.json`` next to it. ``config.json``'s model_type must be dinov2, dinov2_with_registers
    or dinov3_vit. Nothing is ever downloaded (``local_files_only=True``).

    The image is resized so that its longer side is ``long_side`` rounded to whole patches and the shorter side
    keeps the aspect ratio (rounded to whole patches), ImageNet-normalised, and the patch tokens (after the CLS
    and register tokens) are returned on the patch grid. ``flow_residual`` is not used.
    """

    name = "dino"

    def __init__(self, path: str | Path, device: str = "cpu", long_side: int = 640):
        model, cfg = _load_dino(path)
        self.model = model.to(device).eval()
        self.device, self.long_side = device, int(long_side)
        self.patch, self.dim = int(cfg.patch_size), int(cfg.hidden_size)
        self.descriptor = f"{cfg.model_type}-d{cfg.hidden_size}-L{cfg.num_hidden_layers}-p{cfg.patch_size}"

    def grid_size(self, height: int, width: int) -> tuple[int, int]:
        n_long = max(1, round(self.long_side / self.patch))
        n_short = max(1, round(n_long * min(height, width) / max(height, width)))
        return (n_long, n_short) if height >= width else (n_short, n_long)

    def extract(self, image: np.ndarray, flow_residual: np.ndarray | None = None) -> np.ndarray:
        import torch

        img = _check_image(image)  # [H, W, 3]
        gh, gw = self.grid_size(*img.shape[:2])
        size = (gw * self.patch, gh * self.patch)
        shrink = size[0] * size[1] < img.shape[0] * img.shape[1]
        x = cv2.resize(img, size, interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)
        x = (x - _IMAGENET_MEAN) / _IMAGENET_STD  # [H', W', 3]
        t = torch.from_numpy(np.ascontiguousarray(x.transpose(2, 0, 1)))[None].to(self.device)  # [1, 3, H', W']
        with torch.inference_mode():
            tokens = self.model(pixel_values=t).last_hidden_state[0, -gh * gw:]  # [h * w, D]
        return tokens.float().cpu().numpy().reshape(gh, gw, self.dim)


def _load_dino(path: str | Path):
    """(model, config) of a local DINOv2 / DINOv3 checkpoint (see DinoExtractor for the accepted paths)."""
    import transformers

    hint = "see docs/PRIORS.md (Semantic features) for how to obtain DINOv2 / DINOv3 weights"
    if path is None:
        raise WeightsError(f"the dino backend needs a weights path; {hint}")
    p = Path(path).expanduser()
    if not p.exists():
        raise WeightsError(f"DINO weights path {p} does not exist; {hint}")
    folder = p if p.is_dir() else p.parent
    if p.is_file() and p.suffix not in _WEIGHT_SUFFIXES:
        raise WeightsError(f"DINO weights file {p} must end in one of {_WEIGHT_SUFFIXES}")
    if not (folder / "config.json").is_file():
        raise WeightsError(f"no config.json in {folder}: expected a transformers save_pretrained folder; {hint}")
    try:
        cfg = transformers.AutoConfig.from_pretrained(folder, local_files_only=True)
    except (OSError, ValueError) as exc:
        raise WeightsError(f"cannot read {folder / 'config.json'}: {exc}") from exc
    if cfg.model_type not in _DINO_MODELS:
        raise WeightsError(f"{folder} holds a {cfg.model_type!r} model; supported: {sorted(_DINO_MODELS)}")
    cls = getattr(transformers, _DINO_MODELS[cfg.model_type])
    if p.is_dir():
        return _from_pretrained(cls, p), cfg
    return _model_from_file(cls, folder, p), cfg


def _from_pretrained(cls, folder: Path):
    try:
        model, loading = cls.from_pretrained(folder, local_files_only=True, output_loading_info=True)
    except (OSError, ValueError) as exc:
        raise WeightsError(f"cannot load DINO weights from {folder}: {exc}") from exc
    if loading.get("missing_keys"):
        raise WeightsError(f"DINO weights in {folder} lack {sorted(loading['missing_keys'])[:3]}... "
                           f"({len(loading['missing_keys'])} tensors): not a checkpoint of this model")
    return model


def _model_from_file(cls, folder: Path, path: Path):
    """Load one weights file: unwrap, strip the prefix before ``embeddings.cls_token``, load via a temp folder."""
    import shutil
    import tempfile

    import torch
    from safetensors.torch import load_file, save_file

    try:
        state = load_file(str(path)) if path.suffix == ".safetensors" else \
            torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any unreadable file is a weights error for the user
        raise WeightsError(f"cannot read DINO weights file {path}: {exc}") from exc
    for key in ("state_dict", "model"):
        if isinstance(state, dict) and isinstance(state.get(key), dict):
            state = state[key]
    anchors = [k for k in state if k.endswith("embeddings.cls_token")] if isinstance(state, dict) else []
    if not anchors:
        raise WeightsError(f"{path} is not a transformers DINO state dict (no 'embeddings.cls_token' tensor)")
    pre = anchors[0][: -len("embeddings.cls_token")]
    state = {k[len(pre):]: v.contiguous() for k, v in state.items() if k.startswith(pre) and torch.is_tensor(v)}
    with tempfile.TemporaryDirectory() as tmp:  # from_pretrained applies transformers' key conversions
        shutil.copy(folder / "config.json", Path(tmp) / "config.json")
        save_file(state, str(Path(tmp) / "model.safetensors"), metadata={"format": "pt"})
        return _from_pretrained(cls, Path(tmp))


def make_extractor(config: FeatureConfig) -> FeatureExtractor:
    """The extractor of ``config.backend`` (builtin, or dino loaded from ``config.weights``)."""
    if config.backend == "builtin":
        return BuiltinExtractor(config.stride, config.max_feature_side)
    return DinoExtractor(config.weights, device=config.device, long_side=config.dino_long_side)


# ---------------------------------------------------------------------------------------------------- scene
def _frame(frames, i: int) -> np.ndarray:
    return _check_image(np.asarray(frames[i]))


def _per_frame(arr, name: str, t: int, hw: tuple[int, int], max_value: float | None = None) -> np.ndarray | None:
    if arr is None:
        return None
    if len(arr) != t or tuple(np.asarray(arr[0]).shape) != hw:
        raise FeatureError(f"{name} must be [{t}, {hw[0]}, {hw[1]}], got {len(arr)} x {np.asarray(arr[0]).shape}")
    if max_value is not None and any(float(np.max(arr[i])) > max_value for i in range(t)):
        raise FeatureError(f"{name} values must be <= {max_value} (0 background, 1 rigid, 2 non-rigid)")
    return arr


def _finite_or_none(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


def build_semantics(frames, config: FeatureConfig = FeatureConfig(), masks: np.ndarray | None = None,
                    class_masks: np.ndarray | None = None, flow_residual: np.ndarray | None = None,
                    prototype_bank: dict[str, np.ndarray] | None = None,
                    progress: Callable[[int], None] | None = None, extractor: FeatureExtractor | None = None,
                    info: dict | None = None) -> SemanticFeatures:
    """Semantic features of a clip: F_low float16 [T, h, w, C], PCA, C_bg / C_ag and a prototype bank ("pca").

    frames [T, H, W, 3] uint8 or float in [0, 1] (or any sequence of frames, e.g. ``bundle.frames``); masks
    [T, H, W] dynamic masks (0/1); class_masks [T, H, W] (0 background, 1 rigid, 2 non-rigid; used instead of
    masks when both are given); flow_residual [T, H, W] >= 0 (builtin only; e.g. the mask prior's residual);
    prototype_bank: a raw-space bank from ``load_prototype_bank`` (projected into this scene's PCA space; it
    replaces the per-scene prototypes, and its argmax-cosine agents join the mask labels of the subset rule).
    progress(i) is called per frame extracted (twice per frame when the raw descriptors exceed
    ``config.cache_bytes``). extractor: reuse a loaded extractor (else ``make_extractor(config)``). info: if a dict, filled with what was done (rules, counts, correlations).
    """
    t = len(frames)
    if t < 1:
        raise FeatureError("build_semantics needs at least one frame")
    first = _frame(frames, 0)
    H, W = first.shape[:2]
    masks = _per_frame(masks, "masks", t, (H, W))
    class_masks = _per_frame(class_masks, "class_masks", t, (H, W), max_value=2)
    flow_residual = _per_frame(flow_residual, "flow_residual", t, (H, W))
    ex = extractor or make_extractor(config)
    if prototype_bank is not None:
        check_prototype_bank(prototype_bank)
        check_bank_matches(prototype_bank, ex.name, ex.dim, ex.descriptor)
    h, w = ex.grid_size(H, W)
    d_in = ex.dim
    rng = np.random.default_rng(config.seed)
    cache = [] if t * h * w * d_in * 2 <= config.cache_bytes else None

    def extract(i: int) -> np.ndarray:
        d = ex.extract(first if i == 0 else _frame(frames, i), None if flow_residual is None else flow_residual[i])
        if d.shape != (h, w, d_in):
            raise FeatureError(f"frame {i} gives descriptors {d.shape}, expected {(h, w, d_in)} (frame sizes differ?)")
        if not np.isfinite(d).all():
            raise FeatureError(f"frame {i} gives non-finite descriptors (NaN or inf in the frame?)")
        if progress is not None:
            progress(i)
        return d.reshape(h * w, d_in)

    n_pca = min(h * w, math.ceil(config.pca_samples / t))  # cells per frame for the PCA fit
    rows = []
    for i in range(t):  # pass 1: descriptors, PCA sample
        d = extract(i)
        if cache is not None:
            cache.append(d.astype(np.float16))
        rows.append(d[rng.choice(h * w, n_pca, replace=False)])
    if t * n_pca < 2:
        raise FeatureError(f"the PCA needs at least 2 feature cells, the clip gives {t * n_pca}")
    standardize = ex.name == "builtin" if config.standardize is None else config.standardize
    mean, basis = fit_pca(np.concatenate(rows), config.n_components, standardize)  # [D], [D, C]
    c = basis.shape[1]

    n_sel = min(h * w, math.ceil(config.select_samples / t))  # cells per frame for subsets / prototypes
    feats = np.empty((t, h, w, c), np.float16)
    samp_f, samp_frac = [], []
    for i in range(t):  # pass 2: projection, labelled sample
        d = (cache[i] if cache is not None else extract(i).astype(np.float16)).astype(np.float32)  # same both ways
        f = ((d - mean) @ basis).astype(np.float32)  # [h*w, C]
        feats[i] = np.clip(f, -6e4, 6e4).reshape(h, w, c)
        idx = rng.choice(h * w, n_sel, replace=False)
        samp_f.append(f[idx])
        frac = label_fractions(None if masks is None else masks[i],
                               None if class_masks is None else class_masks[i], h, w)  # [h*w, 3] or None
        if frac is not None:
            samp_frac.append(frac[idx])
    del cache
    sample = np.concatenate(samp_f)  # [N, C]
    bank_pca = project_bank(prototype_bank, mean, basis) if prototype_bank is not None else None
    agent, classes, label_source = None, None, "none"
    if samp_frac:
        frac = np.concatenate(samp_frac)  # [N, 3]
        agent, label_source = frac[:, 1] + frac[:, 2] >= 0.5, "class_masks" if class_masks is not None else "masks"
        classes = cell_classes(frac, config.prototype_purity)
    if bank_pca is not None:  # bank labels: argmax cosine; with masks, agent = mask OR bank (masks miss agents)
        bank_agent = cosine_scores(sample, bank_pca).argmax(-1) > 0
        agent = bank_agent if agent is None else agent | bank_agent
        label_source = "prototype bank (argmax cosine)" + ("" if label_source == "none" else f" | {label_source}")
    choice = select_channel_subsets(sample, agent, config.max_ag_channels, config.max_bg_channels, config.min_gain)
    if choice.rule.startswith("fallback"):
        warnings.warn(f"build_semantics: no agent/background labels ({label_source}), so C_bg / C_ag are "
                      "placeholders (first channels)", stacklevel=2)
    flip = np.flatnonzero(choice.signs < 0)  # orient C_ag up on agents, C_bg up on background
    basis[:, flip] *= -1
    sample[:, flip] *= -1
    feats[..., flip] = -feats[..., flip]
    if bank_pca is not None:
        protos, proto_note = project_bank(prototype_bank, mean, basis), "prototype bank projected to the scene PCA"
    elif classes is not None and samp_frac:
        protos, proto_note = scene_prototypes(sample, classes, config.prototypes_per_class, config.seed)
    else:
        protos, proto_note = None, "no labels: no prototypes"
    if info is not None:
        info.update({"backend": ex.name, "descriptor": ex.descriptor, "D_in": d_in, "C": c, "grid": [h, w],
                     "standardize": standardize, "label_source": label_source, "subset_rule": choice.rule,
                     "corr_ag": _finite_or_none(choice.corr_ag), "corr_bg": _finite_or_none(choice.corr_bg),
                     "prototypes": proto_note,
                     "labelled_cells": int(len(sample)), "agent_cells": int(agent.sum()) if agent is not None else 0})
    return SemanticFeatures(features=feats, C_bg=choice.C_bg, C_ag=choice.C_ag, pca_basis=basis.astype(np.float32),
                            pca_mean=mean.astype(np.float32), prototypes=protos, prototype_space="pca",
                            feature_min=float(feats.min()), feature_max=float(feats.max()))
