"""Prototype bank B = {B_rigid, B_non-rigid, B_bg} of the semantic prior (paper Sec. 3, "prototype-based priors").

A bank holds, per class, a matrix [n, D] of prototype vectors (k-means centroids of that class's features).
Two sources:

* ``prototypes_from_labelled_folder``: raw descriptors of a labelled image folder with Cityscapes label ids, in the
  extractor's raw space [n, D_in]; saved with ``save_prototype_bank`` (``agg prototypes``), read back with
  ``load_prototype_bank``. ``build_semantics`` projects it into each scene's PCA space.
* ``scene_prototypes``: per scene, from the F_low cells under the class masks (or dynamic masks).

Class indices used throughout: 0 = background, 1 = rigid agent, 2 = non-rigid agent (``CLASS_NAMES``).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

CLASS_NAMES = ("background", "rigid", "non-rigid")  # index = class id of class_masks
# Cityscapes label ids (cityscapesScripts labels.py): 0-3 unlabeled / ego vehicle / rectification border / out of
# roi are ignored; person, rider are non-rigid; car .. bicycle are rigid; every other id is background.
CITYSCAPES_IGNORE = (0, 1, 2, 3)
CITYSCAPES_NON_RIGID = (24, 25)
CITYSCAPES_RIGID = (26, 27, 28, 29, 30, 31, 32, 33)
BANK_FORMAT = "agg-prototype-bank"


class PrototypeBankError(ValueError):
    """A prototype bank is malformed or was made for another feature space (backend, D_in, descriptor)."""


class LabelledFolderError(ValueError):
    """A labelled folder has no usable image/label pairs, or a pair is unreadable or inconsistent."""


class PrototypeBank(dict):
    """``{"rigid", "non-rigid", "background"} -> [n, D] float32`` plus ``meta`` (backend, D_in, descriptor...)."""

    def __init__(self, arrays: dict[str, np.ndarray], meta: dict | None = None):
        super().__init__(arrays)
        self.meta = dict(meta or {})


def cityscapes_classes(label_ids: np.ndarray) -> np.ndarray:
    """Cityscapes label ids [H, W] -> int8 [H, W]: -1 ignore, 0 background, 1 rigid, 2 non-rigid."""
    ids = np.asarray(label_ids)
    out = np.zeros(ids.shape, np.int8)
    out[np.isin(ids, CITYSCAPES_RIGID)] = 1
    out[np.isin(ids, CITYSCAPES_NON_RIGID)] = 2
    out[np.isin(ids, CITYSCAPES_IGNORE)] = -1
    return out


def cell_fractions(classes: np.ndarray, h: int, w: int, n_classes: int = 3) -> np.ndarray:
    """Area fraction of each class id 0..n-1 in each cell of an (h, w) grid: classes [H, W] -> [h, w, n].

    Pixels with other ids (e.g. -1 = ignore) count in no class, so the fractions of a cell may sum to < 1.
    """
    c = np.asarray(classes)
    onehot = np.stack([(c == k) for k in range(n_classes)], -1).astype(np.float32)  # [H, W, n]
    return cv2.resize(onehot, (w, h), interpolation=cv2.INTER_AREA).reshape(h, w, n_classes)


def label_fractions(mask: np.ndarray | None, class_mask: np.ndarray | None, h: int, w: int) -> np.ndarray | None:
    """Class area fractions [h*w, 3] (background, rigid, non-rigid) of one frame on the feature grid, or None.

    class_mask [H, W] in {0, 1, 2} wins over mask [H, W] (dynamic 0/1, every agent counted as rigid)."""
    if class_mask is not None:
        return cell_fractions(np.asarray(class_mask), h, w).reshape(h * w, 3)
    if mask is None:
        return None
    frac = cell_fractions((np.asarray(mask) > 0).astype(np.int8), h, w, 2).reshape(h * w, 2)
    return np.concatenate([frac, np.zeros((h * w, 1), np.float32)], 1)


def cell_classes(frac: np.ndarray, purity: float = 0.75) -> np.ndarray:
    """Class id per cell from fractions [N, 3] -> [N] in {-1, 0, 1, 2}: the class covering >= purity of the cell;
    a class with no such cell takes the unassigned cells it covers >= 0.5 of (small agents on coarse grids);
    -1 = mixed or ignored."""
    cls = np.where(frac.max(1) >= purity, frac.argmax(1), -1)
    for c in range(frac.shape[1]):
        if not (cls == c).any():
            cls[(frac[:, c] >= 0.5) & (cls == -1)] = c
    return cls


def find_labelled_pairs(folder: str | Path) -> list[tuple[Path, Path]]:
    """(image, label) pairs of a folder, sorted by image path.

    Accepted layouts: Cityscapes (``**/X_leftImg8bit.png`` with ``**/X_gtFine_labelIds.png`` anywhere below the
    folder, matched by the stem X) or ``images/X.(png|jpg|jpeg)`` with ``labels/X.png``.
    """
    root = Path(folder)
    if not root.is_dir():
        raise LabelledFolderError(f"labelled folder {root} does not exist or is not a folder")
    labels = {p.name[: -len("_gtFine_labelIds.png")]: p for p in root.rglob("*_gtFine_labelIds.png")}
    pairs = [(p, labels[p.name[: -len("_leftImg8bit.png")]]) for p in sorted(root.rglob("*_leftImg8bit.png"))
             if p.name[: -len("_leftImg8bit.png")] in labels]
    if (root / "images").is_dir() and (root / "labels").is_dir():
        for p in sorted((root / "images").iterdir()):
            if p.suffix.lower() in (".png", ".jpg", ".jpeg") and (root / "labels" / (p.stem + ".png")).is_file():
                pairs.append((p, root / "labels" / (p.stem + ".png")))
    if not pairs:
        raise LabelledFolderError(
            f"no image/label pairs in {root}: expected Cityscapes names (X_leftImg8bit.png + X_gtFine_labelIds.png) "
            "or images/X.png + labels/X.png")
    return pairs


def _read_pair(image_path: Path, label_path: Path) -> tuple[np.ndarray, np.ndarray]:
    bgr = cv2.imread(str(image_path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise LabelledFolderError(f"cannot read image {image_path}")
    lab = cv2.imread(str(label_path), cv2.IMREAD_UNCHANGED)
    if lab is None:
        raise LabelledFolderError(f"cannot read label map {label_path}")
    if lab.ndim != 2:
        raise LabelledFolderError(f"label map {label_path} must be single-channel label ids, got shape {lab.shape}")
    if lab.shape != bgr.shape[:2]:
        raise LabelledFolderError(f"label map {label_path} is {lab.shape}, its image is {bgr.shape[:2]}")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB).astype(np.float32) / 255.0, lab


def kmeans_centroids(x: np.ndarray, k: int, seed: int = 0, spherical: bool = False, min_cluster: int = 10,
                     max_samples: int = 5000) -> np.ndarray:
    """k-means centroids [k', D] of x [N, D] (seeded), k' = min(k, N // min_cluster, distinct rows), at least 1.

    At most max_samples rows (a seeded subsample) are clustered. spherical: cluster unit vectors and return unit
    centroids (cosine geometry)."""
    from sklearn.cluster import KMeans

    x = np.asarray(x, dtype=np.float64)
    if len(x) > max_samples:
        x = x[np.sort(np.random.default_rng(seed).choice(len(x), max_samples, replace=False))]
    if spherical:
        x = x / np.maximum(np.linalg.norm(x, axis=1, keepdims=True), 1e-12)
    k = int(min(k, len(x) // min_cluster, len(np.unique(x.round(6), axis=0))))
    if k <= 1:
        c = x.mean(0, keepdims=True)
    else:
        c = KMeans(n_clusters=k, n_init=2, random_state=seed).fit(x).cluster_centers_
    if spherical:
        c = c / np.maximum(np.linalg.norm(c, axis=1, keepdims=True), 1e-12)
    return c.astype(np.float32)


def prototypes_from_labelled_folder(folder: str | Path, extractor, n_per_class: int = 8, seed: int = 0,
                                    samples_per_class: int = 20000, purity: float = 0.75,
                                    max_images: int | None = None,
                                    progress: Callable[[int], None] | None = None) -> PrototypeBank:
    """Raw-space prototype bank [n, D_in] per class from a labelled folder (see ``find_labelled_pairs``).

    Each image's descriptors come from ``extractor``; a feature cell is a sample of a class when that class covers
    at least ``purity`` of its area (Cityscapes ids mapped by ``cityscapes_classes``). Up to ``samples_per_class``
    cells per class (seeded subsample) are clustered by k-means (Euclidean, on descriptors scaled by their pooled
    standard deviation); the centroids are returned in raw units. Raises LabelledFolderError when a class has no
    cell at all.
    """
    pairs = find_labelled_pairs(folder)[: max_images or None]
    rng = np.random.default_rng(seed)
    per_image = max(64, math.ceil(4 * samples_per_class / len(pairs)))
    samples: list[list[np.ndarray]] = [[], [], []]
    for i, (img_path, lab_path) in enumerate(pairs):
        image, ids = _read_pair(img_path, lab_path)
        desc = extractor.extract(image)  # [h, w, D]
        h, w = desc.shape[:2]
        frac = cell_fractions(cityscapes_classes(ids), h, w).reshape(h * w, 3)  # [h*w, 3]
        cls = cell_classes(frac, purity)
        flat = desc.reshape(h * w, -1)
        for c in range(3):
            idx = np.flatnonzero(cls == c)
            if len(idx) > per_image:
                idx = rng.choice(idx, per_image, replace=False)
            samples[c].append(flat[idx])
        if progress is not None:
            progress(i)
    arrays = {}
    stacked = [np.concatenate(s, 0) for s in samples]
    missing = [CLASS_NAMES[c] for c in range(3) if len(stacked[c]) == 0]
    if missing:
        raise LabelledFolderError(f"no feature cell of class {missing} in {folder} ({len(pairs)} images; purity "
                                  f"{purity}); Cityscapes ids: rigid {CITYSCAPES_RIGID}, non-rigid "
                                  f"{CITYSCAPES_NON_RIGID}")
    scale = np.maximum(np.concatenate(stacked, 0).std(0), 1e-3)  # [D]
    for c, x in enumerate(stacked):
        if len(x) > samples_per_class:
            x = x[np.sort(rng.choice(len(x), samples_per_class, replace=False))]
        arrays[CLASS_NAMES[c]] = kmeans_centroids(x / scale, n_per_class, seed) * scale
    meta = {"format": BANK_FORMAT, "backend": extractor.name, "D_in": int(extractor.dim),
            "descriptor": extractor.descriptor, "n_images": len(pairs),
            "cells": {CLASS_NAMES[c]: int(len(stacked[c])) for c in range(3)}}
    return PrototypeBank(arrays, meta)


def save_prototype_bank(path: str | Path, bank: PrototypeBank) -> Path:
    """Write a bank as .npz: arrays rigid / non-rigid / background and the meta fields as 0-d arrays."""
    check_prototype_bank(bank)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    meta = getattr(bank, "meta", {}) or {}
    extras = {k: np.asarray(v) for k, v in meta.items() if isinstance(v, (str, int, float))}
    with open(path, "wb") as fh:  # a file handle keeps numpy from appending ".npz" to other suffixes
        np.savez(fh, **{k: np.asarray(v, np.float32) for k, v in bank.items()}, **extras)
    return path


def check_prototype_bank(bank: dict, dim: int | None = None) -> None:
    """Raise PrototypeBankError unless bank has the three classes as finite [n >= 1, D] arrays of one D (= dim)."""
    missing = [k for k in CLASS_NAMES if k not in bank]
    if missing:
        raise PrototypeBankError(f"prototype bank lacks {missing}; it needs {list(CLASS_NAMES)}")
    dims = set()
    for k in CLASS_NAMES:
        v = np.asarray(bank[k])
        if v.ndim != 2 or v.shape[0] < 1 or not np.isfinite(v).all():
            raise PrototypeBankError(f"prototype {k!r} must be a finite [n >= 1, D] array, got {v.shape}")
        dims.add(v.shape[1])
    if len(dims) != 1:
        raise PrototypeBankError(f"prototype bank classes have different dimensions {sorted(dims)}")
    if dim is not None and dims != {dim}:
        raise PrototypeBankError(f"prototype bank has D = {dims.pop()}, the extractor gives D_in = {dim}")


def load_prototype_bank(path: str | Path, backend: str | None = None, dim: int | None = None,
                        descriptor: str | None = None) -> PrototypeBank:
    """Read and validate a bank written by ``save_prototype_bank`` / ``agg prototypes``.

    backend / dim / descriptor, when given, must match the bank's metadata (else PrototypeBankError: a bank is
    tied to the feature space it was made in).
    """
    path = Path(path)
    if not path.is_file():
        raise PrototypeBankError(f"prototype bank {path} does not exist")
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except (OSError, ValueError) as exc:
        raise PrototypeBankError(f"cannot read prototype bank {path}: {exc}") from exc
    arrays = {k: np.asarray(data.pop(k), np.float32) for k in CLASS_NAMES if k in data}
    meta = {k: v.item() for k, v in data.items() if v.ndim == 0}
    if meta.get("format") != BANK_FORMAT:
        raise PrototypeBankError(f"{path} is not a prototype bank (format {meta.get('format')!r})")
    check_prototype_bank(arrays, int(meta["D_in"]))
    bank = PrototypeBank(arrays, meta)
    check_bank_matches(bank, backend, dim, descriptor, where=str(path))
    return bank


def check_bank_matches(bank: dict, backend: str | None, dim: int | None, descriptor: str | None,
                       where: str = "prototype bank") -> None:
    """Raise PrototypeBankError when the bank's meta or D disagree with the expected feature space."""
    meta = getattr(bank, "meta", {}) or {}
    d = np.asarray(bank[CLASS_NAMES[0]]).shape[1]
    if dim is not None and d != dim:
        raise PrototypeBankError(f"{where} has D_in = {d} (backend {meta.get('backend', '?')}), the extractor "
                                 f"gives D_in = {dim}: rebuild the bank with the same backend and weights")
    for key, want in (("backend", backend), ("descriptor", descriptor)):
        if want is not None and key in meta and meta[key] != want:
            raise PrototypeBankError(f"{where} was made with {key} {meta[key]!r}, this run uses {want!r}: rebuild "
                                     "the bank with the same backend and weights")


def project_bank(bank: dict, pca_mean: np.ndarray, pca_basis: np.ndarray) -> dict[str, np.ndarray]:
    """Raw-space bank [n, D_in] -> the scene's PCA space [n, C]: (B - pca_mean) @ pca_basis."""
    return {k: ((np.asarray(bank[k], np.float64) - pca_mean) @ pca_basis).astype(np.float32) for k in CLASS_NAMES}


def scene_prototypes(features: np.ndarray, classes: np.ndarray, n_per_class: int, seed: int = 0
                     ) -> tuple[dict[str, np.ndarray] | None, str]:
    """Per-scene prototypes from labelled F_low samples: features [N, C], classes [N] in {-1, 0, 1, 2}.

    Spherical k-means centroids per class (cosine geometry, as they are scored). Without non-rigid samples
    B_non-rigid = B_rigid; without any agent or background sample there is no bank (None). Returns (bank, note).
    """
    rows = {c: features[classes == c] for c in range(3)}
    if len(rows[0]) == 0 or len(rows[1]) + len(rows[2]) == 0:
        return None, "no agent or no background cells: no per-scene prototypes"
    note = "per-scene"
    if len(rows[1]) == 0:  # only non-rigid agents: they stand in for the rigid class too
        rows[1], note = rows[2], "per-scene; no rigid cells: B_rigid = B_non-rigid"
    bank = {CLASS_NAMES[c]: kmeans_centroids(rows[c], n_per_class, seed, spherical=True) for c in (0, 1)}
    if len(rows[2]) == 0:
        bank["non-rigid"], note = bank["rigid"].copy(), "per-scene; no non-rigid cells: B_non-rigid = B_rigid"
    else:
        bank["non-rigid"] = kmeans_centroids(rows[2], n_per_class, seed, spherical=True)
    return bank, note


def cosine_scores(features: np.ndarray, bank: dict[str, np.ndarray]) -> np.ndarray:
    """P_v = max over the rows of B_v of the cosine similarity: features [..., C] -> [..., 3] (CLASS_NAMES order)."""
    f = features / np.maximum(np.linalg.norm(features, axis=-1, keepdims=True), 1e-12)
    out = []
    for k in CLASS_NAMES:
        b = np.asarray(bank[k], np.float32)
        b = b / np.maximum(np.linalg.norm(b, axis=-1, keepdims=True), 1e-12)
        out.append((f @ b.T).max(-1))
    return np.stack(out, -1)
