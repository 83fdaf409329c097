"""Optional prior parts of the scene bundle: depth, dynamic masks, tracklets and semantic features.

``BundlePriorsMixin`` gives ``SceneBundle`` (``agg/io/bundle.py``) the readers and writers of these parts; the
on-disk layout and conventions are in ``docs/BUNDLE.md``. Lengths are scene units, pixels are at the training
resolution with OpenCV pixel centres.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from agg.io.errors import BundleValidationError

TRACK_CLASSES = ("rigid", "non-rigid")
TRACK_ANCHORS = ("world", "camera")
PROTOTYPE_NAMES = ("rigid", "non-rigid", "background")

@dataclass
class Tracklets:
    """Agent tracks over the clip's T frames (world frame, scene units; see docs/BUNDLE.md for the box axes)."""

    ids: np.ndarray  # [K] int64, unique
    classes: list[str]  # [K] "rigid" | "non-rigid"
    boxes: np.ndarray  # [K, T, 7] (cx, cy, cz, l, w, h, yaw); l, w, h, yaw NaN for centre-only tracks
    valid: np.ndarray  # [K, T] bool
    confidence: np.ndarray | None = None  # [K, T] float32 in [0, 1]
    labels: list[str] | None = None  # [K] free text
    anchor: str = "world"  # what the boxes were measured against: "world", independently of the bundle's camera
    # poses (ground truth, annotations); "camera", each frame's box from that frame's camera and lifted into the
    # world through the bundle's poses (agg priors), so it carries those poses' error (TrainConfig.agent_anchor)

    def box_size(self, k: int) -> np.ndarray:
        """[3] median (l, h, w) of track row k's valid boxes, in box-frame axis order (x = l, y = h, z = w); NaN
        where unknown (centre-only tracks, no valid frame)."""
        valid = np.asarray(self.valid[k], bool)
        if not valid.any():
            return np.full(3, np.nan)
        lhw = np.asarray(self.boxes[k], np.float64)[valid][:, [3, 5, 4]]  # [n, 3]
        if np.isnan(lhw).all():
            return np.full(3, np.nan)
        return np.nanmedian(lhw, 0)


@dataclass
class SemanticFeatures:
    """PCA-reduced foundation-model features F_low with the channel subsets and the prototype bank."""

    features: np.ndarray  # [T, h, w, C] float16
    C_bg: list[int]
    C_ag: list[int]
    pca_basis: np.ndarray | None = None  # [D_in, C]; F_low = (F - pca_mean) @ pca_basis
    pca_mean: np.ndarray | None = None  # [D_in]
    prototypes: dict[str, np.ndarray] | None = None  # name in PROTOTYPE_NAMES -> [n, D_p]
    prototype_space: str = "pca"  # "pca": D_p = C; "raw": D_p = D_in
    feature_min: float | None = None  # global extrema of F_low (filled in on write)
    feature_max: float | None = None

def _save_npy(path: Path, array: np.ndarray) -> None:
    """Write ``array`` to ``path`` atomically (temporary file + rename)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp.npy")
    np.save(tmp, np.ascontiguousarray(array))
    os.replace(tmp, path)


def _check(cond: bool, message: str) -> None:
    if not cond:
        raise BundleValidationError(message)


def _shape_str(array: np.ndarray) -> str:
    return f"{tuple(array.shape)} {array.dtype}"

class BundlePriorsMixin:
    """Readers and writers of the optional prior parts (mixed into ``SceneBundle``)."""
    # ------------------------------------------------------------------ depth
    def _sparse(self) -> tuple[np.ndarray, np.ndarray]:
        e = self._manifest["depth_sparse"]
        return self._npy(e["points_file"]), np.asarray(self._npy(e["offsets_file"]), dtype=np.int64)

    def sparse_depth(self, i: int) -> np.ndarray:
        """[N_i, 4] float32 rows (u, v, z-depth, confidence) of frame i, pixels at training resolution."""
        if not self.has("depth_sparse"):
            raise BundleValidationError(f"bundle {self.path} has no sparse depth")
        pts, off = self._sparse()
        return np.array(pts[off[i]:off[i + 1]], dtype=np.float32)

    def write_sparse_depth(self, points: Sequence[np.ndarray], source: str = "sfm") -> None:
        """Write per-frame sparse depth: ``points[i]`` is [N_i, 4] (u, v, depth > 0, confidence in [0, 1])."""
        n = self.num_frames
        _check(len(points) == n, f"sparse depth needs one array per frame ({n}), got {len(points)}")
        arrs = [np.asarray(p, dtype=np.float32).reshape(-1, 4) for p in points]
        allp = np.concatenate(arrs, axis=0) if arrs else np.zeros((0, 4), np.float32)  # [N, 4]
        _check(bool(np.isfinite(allp).all()), "sparse depth has non-finite values")
        _check(bool(np.all(allp[:, 2] > 0)), "sparse depth values must be > 0")
        _check(bool(np.all((allp[:, 3] >= 0) & (allp[:, 3] <= 1))), "sparse depth confidence must be in [0, 1]")
        off = np.concatenate([[0], np.cumsum([len(a) for a in arrs])]).astype(np.int64)  # [T + 1]
        _save_npy(self.path / "depth/sparse_points.npy", allp)
        _save_npy(self.path / "depth/sparse_offsets.npy", off)
        self._manifest["depth_sparse"] = {"points_file": "depth/sparse_points.npy",
                                          "offsets_file": "depth/sparse_offsets.npy",
                                          "num_points": int(allp.shape[0]), "source": source}
        self._write_manifest()

    @property
    def dense_depth(self) -> np.ndarray | None:
        """Memmap [T, H, W] float16/float32 z-depth in scene units (0 = none), or None."""
        return self._npy(self._manifest["depth_dense"]["file"]) if self.has("depth_dense") else None

    @property
    def dense_depth_confidence(self) -> np.ndarray | None:
        e = self._manifest.get("depth_dense") or {}
        return self._npy(e["confidence_file"]) if e.get("confidence_file") else None

    def write_dense_depth(self, depth: np.ndarray, confidence: np.ndarray | None = None, dtype: str = "float16",
                          source: str = "mono") -> None:
        """Write dense [T, H, W] z-depth (scene units, 0 = no depth) and an optional [T, H, W] confidence."""
        n, h, w = self.num_frames, self.height, self.width
        _check(dtype in ("float16", "float32"), f"dense depth dtype must be float16 or float32, got {dtype}")
        d = np.asarray(depth)
        _check(d.shape == (n, h, w), f"dense depth must be [{n}, {h}, {w}], got {d.shape}")
        d = d.astype(dtype)
        _check(bool(np.all(d[np.isfinite(d)] >= 0)), "dense depth must be >= 0")
        _save_npy(self.path / "depth/dense.npy", d)
        entry = {"file": "depth/dense.npy", "dtype": dtype, "confidence_file": None, "source": source}
        if confidence is not None:
            c = np.asarray(confidence, dtype=np.float16)
            _check(c.shape == (n, h, w), f"dense depth confidence must be [{n}, {h}, {w}], got {c.shape}")
            _check(bool(np.all((c >= 0) & (c <= 1))), "dense depth confidence must be in [0, 1]")
            _save_npy(self.path / "depth/dense_confidence.npy", c)
            entry["confidence_file"] = "depth/dense_confidence.npy"
        self._manifest["depth_dense"] = entry
        self._write_manifest()

    # ------------------------------------------------------------------ masks
    @property
    def dynamic_masks(self) -> np.ndarray | None:
        """Memmap uint8 [T, H, W], 1 = dynamic agent pixel, or None."""
        return self._npy(self._manifest["dynamic_masks"]["file"]) if self.has("dynamic_masks") else None

    def write_dynamic_masks(self, masks: np.ndarray, source: str = "given") -> None:
        n, h, w = self.num_frames, self.height, self.width
        m = np.asarray(masks)
        _check(m.shape == (n, h, w), f"dynamic masks must be [{n}, {h}, {w}], got {m.shape}")
        _check(m.dtype == bool or bool(np.isin(m, (0, 1)).all()), "dynamic masks must be bool or 0/1")
        _save_npy(self.path / "masks/dynamic.npy", m.astype(np.uint8))
        self._manifest["dynamic_masks"] = {"file": "masks/dynamic.npy", "source": source}
        self._write_manifest()

    @property
    def ego_mask(self) -> np.ndarray | None:
        """bool [H, W], True on the recording vehicle's own pixels (its bonnet or dashboard, fixed in the image in
        every frame), or None. Training and scoring leave these pixels out (docs/BUNDLE.md)."""
        return np.asarray(self._npy(self._manifest["ego_mask"]["file"])) > 0 if self.has("ego_mask") else None

    def write_ego_mask(self, mask: np.ndarray, source: str = "given") -> None:
        h, w = self.height, self.width
        m = np.asarray(mask)
        _check(m.shape == (h, w), f"the ego mask must be [{h}, {w}], got {m.shape}")
        _check(m.dtype == bool or bool(np.isin(m, (0, 1)).all()), "the ego mask must be bool or 0/1")
        _check(not bool(m.astype(bool).all()), "the ego mask covers the whole image")
        _save_npy(self.path / "masks/ego.npy", m.astype(np.uint8))
        self._manifest["ego_mask"] = {"file": "masks/ego.npy", "source": source}
        self._write_manifest()

    # ------------------------------------------------------------------ tracklets
    @property
    def tracklets(self) -> Tracklets | None:
        if not self.has("tracklets"):
            return None
        e = self._manifest["tracklets"]
        tracks = e["tracks"]
        labels = [t.get("label", "") for t in tracks]
        return Tracklets(ids=np.array([t["id"] for t in tracks], dtype=np.int64),
                         classes=[t["class"] for t in tracks], boxes=self._npy(e["boxes_file"]),
                         valid=self._npy(e["valid_file"]),
                         confidence=self._npy(e["confidence_file"]) if e.get("confidence_file") else None,
                         labels=labels if any(labels) else None, anchor=e.get("anchor", "world"))

    def write_tracklets(self, tracklets: Tracklets) -> None:
        n, t = self.num_frames, tracklets
        k = len(t.classes)
        ids = np.asarray(t.ids, dtype=np.int64).reshape(-1)
        boxes = np.asarray(t.boxes, dtype=np.float64)
        valid = np.asarray(t.valid, dtype=bool)
        _check(ids.shape == (k,) and len(set(ids.tolist())) == k, f"tracklet ids must be {k} unique integers")
        _check(all(c in TRACK_CLASSES for c in t.classes), f"tracklet classes must be in {TRACK_CLASSES}")
        _check(t.anchor in TRACK_ANCHORS, f"tracklet anchor must be one of {TRACK_ANCHORS}, got {t.anchor!r}")
        _check(boxes.shape == (k, n, 7), f"tracklet boxes must be [{k}, {n}, 7], got {boxes.shape}")
        _check(valid.shape == (k, n), f"tracklet valid must be [{k}, {n}], got {valid.shape}")
        _check(bool(np.isfinite(boxes[..., :3][valid]).all()), "valid tracklet entries need finite centres")
        boxes = np.where(valid[..., None], boxes, np.nan)
        entry = {"boxes_file": "tracklets/boxes.npy", "valid_file": "tracklets/valid.npy", "confidence_file": None,
                 "tracks": [{"id": int(i), "class": c} for i, c in zip(ids, t.classes)]}
        if t.labels is not None:
            _check(len(t.labels) == k, f"{len(t.labels)} tracklet labels for {k} tracks")
            for tr, lab in zip(entry["tracks"], t.labels):
                tr["label"] = str(lab)
        _save_npy(self.path / "tracklets/boxes.npy", boxes)
        _save_npy(self.path / "tracklets/valid.npy", valid)
        if t.confidence is not None:
            c = np.asarray(t.confidence, dtype=np.float32)
            _check(c.shape == (k, n) and bool(np.all((c >= 0) & (c <= 1))), "tracklet confidence must be [K, T] in [0, 1]")
            _save_npy(self.path / "tracklets/confidence.npy", c)
            entry["confidence_file"] = "tracklets/confidence.npy"
        if t.anchor != "world":  # absent means "world", as in bundles written before the key existed
            entry["anchor"] = t.anchor
        self._manifest["tracklets"] = entry
        self._write_manifest()

    # ------------------------------------------------------------------ semantics
    @property
    def semantics(self) -> SemanticFeatures | None:
        if not self.has("semantics"):
            return None
        e = self._manifest["semantics"]
        protos = {k: np.array(self._npy(v)) for k, v in (e.get("prototypes") or {}).items()}
        return SemanticFeatures(
            features=self._npy(e["features_file"]), C_bg=list(e["C_bg"]), C_ag=list(e["C_ag"]),
            pca_basis=np.array(self._npy(e["pca_basis_file"])) if e.get("pca_basis_file") else None,
            pca_mean=np.array(self._npy(e["pca_mean_file"])) if e.get("pca_mean_file") else None,
            prototypes=protos or None, prototype_space=e.get("prototype_space", "pca"),
            feature_min=e.get("feature_min"), feature_max=e.get("feature_max"))

    def write_semantics(self, sem: SemanticFeatures) -> None:
        n = self.num_frames
        f = np.asarray(sem.features, dtype=np.float16)
        _check(f.ndim == 4 and f.shape[0] == n, f"semantic features must be [{n}, h, w, C], got {f.shape}")
        _check(bool(np.isfinite(f).all()), "semantic features have non-finite values (float16 overflow?)")
        c = f.shape[3]
        for name, sub in (("C_bg", sem.C_bg), ("C_ag", sem.C_ag)):
            _check(all(0 <= int(i) < c for i in sub), f"{name} has channel indices outside [0, {c})")
        _check(sem.prototype_space in ("pca", "raw"), "prototype_space must be 'pca' or 'raw'")
        d = "semantics/"
        entry: dict[str, Any] = {"features_file": d + "features.npy", "channels": c, "feature_height": f.shape[1],
                                 "feature_width": f.shape[2], "C_bg": [int(i) for i in sem.C_bg],
                                 "C_ag": [int(i) for i in sem.C_ag], "pca_basis_file": None, "pca_mean_file": None,
                                 "feature_min": float(f.min()), "feature_max": float(f.max()),
                                 "prototype_space": sem.prototype_space, "prototypes": {}}
        d_in = None
        if sem.pca_basis is not None:
            basis = np.asarray(sem.pca_basis, dtype=np.float32)
            _check(basis.ndim == 2 and basis.shape[1] == c, f"pca_basis must be [D_in, {c}], got {basis.shape}")
            d_in = basis.shape[0]
            _save_npy(self.path / (d + "pca_basis.npy"), basis)
            entry["pca_basis_file"] = d + "pca_basis.npy"
        if sem.pca_mean is not None:
            mean = np.asarray(sem.pca_mean, dtype=np.float32)
            _check(mean.ndim == 1 and (d_in is None or mean.shape[0] == d_in), f"pca_mean must be [D_in], got {mean.shape}")
            _save_npy(self.path / (d + "pca_mean.npy"), mean)
            entry["pca_mean_file"] = d + "pca_mean.npy"
        dp = c if sem.prototype_space == "pca" else d_in
        for name, vecs in (sem.prototypes or {}).items():
            _check(name in PROTOTYPE_NAMES, f"prototype name {name!r} not in {PROTOTYPE_NAMES}")
            v = np.asarray(vecs, dtype=np.float32)
            v = v[None] if v.ndim == 1 else v
            _check(v.ndim == 2 and v.shape[0] >= 1 and (dp is None or v.shape[1] == dp),
                   f"prototype {name!r} must be [n, {dp}], got {v.shape}")
            rel = d + f"prototype_{name}.npy"
            _save_npy(self.path / rel, v)
            entry["prototypes"][name] = rel
        _save_npy(self.path / (d + "features.npy"), f)
        self._manifest["semantics"] = entry
        self._write_manifest()
