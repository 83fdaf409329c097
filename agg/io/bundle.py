"""The scene bundle: one clip plus its priors, as a folder of memory-mapped ``.npy`` files and a manifest.

The format, the conventions of every part and this API are documented in ``docs/BUNDLE.md``. Frames, timestamps
(int64 microseconds) and pinhole intrinsics (training resolution, OpenCV pixel centres) are required; poses
(``world_from_camera``, OpenCV camera axes, world = first camera), depth, dynamic masks, the ego-vehicle mask,
tracklets, semantic features and the ``gt/`` sidecar are optional. Lengths are in scene units:
``metric = scale * scene_units``.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from agg.io.bundle_priors import (PROTOTYPE_NAMES, TRACK_ANCHORS, TRACK_CLASSES, BundlePriorsMixin, SemanticFeatures,
                                  Tracklets, _check, _save_npy, _shape_str)
from agg.io.errors import BundleExistsError, BundleNotFoundError, BundleValidationError, BundleVersionError

__all__ = ["FORMAT", "VERSION", "PARTS", "TRACK_CLASSES", "TRACK_ANCHORS", "PROTOTYPE_NAMES", "SceneBundle",
           "LazyFrames", "Tracklets", "SemanticFeatures", "rebase_to_first_camera", "compute_scale_factor"]

FORMAT = "agg-bundle"
VERSION = 1
MANIFEST = "manifest.json"
PARTS = ("poses", "depth_sparse", "depth_dense", "dynamic_masks", "ego_mask", "tracklets", "semantics", "gt")
_PART_DIRS = {"poses": "poses", "depth_sparse": "depth", "depth_dense": "depth", "dynamic_masks": "masks",
              "ego_mask": "masks", "tracklets": "tracklets", "semantics": "semantics", "gt": "gt"}


class LazyFrames:
    """Array-like view of the uint8 frame memmap that returns float32 RGB in [0, 1] when indexed."""

    def __init__(self, raw: np.ndarray):
        self.raw = raw  # [T, H, W, 3] uint8 memmap

    @property
    def shape(self) -> tuple[int, ...]:
        return tuple(self.raw.shape)

    def __len__(self) -> int:
        return int(self.raw.shape[0])

    def __getitem__(self, index: Any) -> np.ndarray:
        return np.asarray(self.raw[index], dtype=np.float32) / np.float32(255.0)

    def __iter__(self):
        for i in range(len(self)):
            yield self[i]


def rebase_to_first_camera(world_from_camera: np.ndarray) -> np.ndarray:
    """[T, 4, 4] poses re-expressed in the first camera's frame: ``inv(P[0]) @ P[i]`` (so the result's [0] is I)."""
    poses = np.asarray(world_from_camera, dtype=np.float64)
    out = np.linalg.inv(poses[0]) @ poses
    out[0] = np.eye(4)
    out[:, 3] = (0.0, 0.0, 0.0, 1.0)
    return out


def compute_scale_factor(world_from_camera: np.ndarray | None = None, depths: np.ndarray | None = None,
                         method: str = "auto") -> float:
    """The factor f that scene lengths are divided by to normalise the scene (see docs/BUNDLE.md).

    ``"path_length"``: f = sum of |c[i+1] - c[i]| over camera centres of ``world_from_camera`` [T, 4, 4].
    ``"median_depth"``: f = median of the positive finite values of ``depths`` (any shape).
    ``"auto"``: path length when poses are given and the path is longer than 1e-9, else median depth.
    """
    if method not in ("auto", "path_length", "median_depth"):
        raise ValueError(f"unknown scale method {method!r}; use auto, path_length or median_depth")
    if method in ("auto", "path_length") and world_from_camera is not None:
        centres = np.asarray(world_from_camera, dtype=np.float64)[:, :3, 3]  # [T, 3]
        length = float(np.linalg.norm(np.diff(centres, axis=0), axis=1).sum())
        if length > 1e-9:
            return length
        if method == "path_length":
            raise ValueError("camera path length is zero (static camera): use method='median_depth'")
    elif method == "path_length":
        raise ValueError("method='path_length' needs poses")
    if depths is None:
        raise ValueError("no poses with a non-zero path and no depth: cannot compute a scale factor")
    d = np.asarray(depths, dtype=np.float64).ravel()
    d = d[np.isfinite(d) & (d > 0)]
    if d.size == 0:
        raise ValueError("no positive depth values: cannot compute a scale factor")
    return float(np.median(d))


class SceneBundle(BundlePriorsMixin):
    """A scene bundle folder. Use ``SceneBundle.create`` to write a new one, ``SceneBundle.load`` to open one."""

    def __init__(self, path: Path, manifest: dict, parent: "SceneBundle | None" = None):
        self.path = Path(path)
        self._manifest = manifest
        self._parent = parent
        self._cache: dict[str, Any] = {}

    # ------------------------------------------------------------------ creation and loading
    @classmethod
    def create(cls, path: str | os.PathLike, frames: Any, timestamps_us: Sequence[int], intrinsics: np.ndarray,
               *, frame_names: Sequence[str] | None = None, intrinsics_source: str = "given", scale: float = 1.0,
               metric: bool = False, meta: dict | None = None, overwrite: bool = False) -> "SceneBundle":
        """Write a new bundle with its required parts.

        frames: [T, H, W, 3] uint8, or float in [0, 1] (stored as round(255 x)), or a sequence of [H, W, 3];
        timestamps_us: [T] strictly increasing integers (microseconds); intrinsics: [3, 3] or [T, 3, 3] pinhole K
        in pixels at the frames' resolution.
        """
        path = Path(path)
        if path.exists() and any(path.iterdir()):
            if not overwrite:
                raise BundleExistsError(f"{path} exists and is not empty (pass overwrite=True to replace it)")
            shutil.rmtree(path)
        path.mkdir(parents=True, exist_ok=True)
        n = len(frames)
        _check(n >= 1, "a bundle needs at least one frame")
        first = np.asarray(frames[0])
        _check(first.ndim == 3 and first.shape[2] == 3, f"frames must be [T, H, W, 3] RGB, got frame {first.shape}")
        h, w = int(first.shape[0]), int(first.shape[1])
        out = np.lib.format.open_memmap(path / "frames.npy", mode="w+", dtype=np.uint8, shape=(n, h, w, 3))
        for i in range(n):
            f = np.asarray(frames[i])
            _check(f.shape == (h, w, 3), f"frame {i} has shape {f.shape}, expected {(h, w, 3)}")
            if f.dtype != np.uint8:
                _check(bool(np.isfinite(f).all()), f"frame {i} has non-finite values")
                f = np.clip(np.rint(np.asarray(f, dtype=np.float32) * 255.0), 0, 255).astype(np.uint8)
            out[i] = f
        out.flush()
        del out
        manifest = {"format": FORMAT, "version": VERSION, "kind": "scene", "num_frames": n, "width": w, "height": h,
                    "frames": {"file": "frames.npy", "dtype": "uint8", "layout": "THWC", "color": "rgb"},
                    "timestamps": {"file": "timestamps_us.npy", "unit": "us"},
                    "scale": float(scale), "metric": bool(metric), "meta": dict(meta or {})}
        if frame_names is not None:
            _check(len(frame_names) == n, f"{len(frame_names)} frame names for {n} frames")
            manifest["frame_names"] = [str(s) for s in frame_names]
        bundle = cls(path, manifest)
        ts = np.asarray(timestamps_us)
        _check(ts.shape == (n,) and np.issubdtype(ts.dtype, np.integer),
               f"timestamps_us must be [{n}] integers, got {_shape_str(ts)}")
        _check(bool(np.all(np.diff(ts) > 0)), "timestamps_us must be strictly increasing")
        _save_npy(path / "timestamps_us.npy", ts.astype(np.int64))
        bundle.write_intrinsics(intrinsics, source=intrinsics_source)
        return bundle

    @classmethod
    def load(cls, path: str | os.PathLike) -> "SceneBundle":
        """Open and validate a bundle (lazily: large arrays are memory-mapped on first access)."""
        path = Path(path)
        mpath = path / MANIFEST
        if not mpath.is_file():
            raise BundleNotFoundError(f"no scene bundle at {path}: {MANIFEST} is missing")
        try:
            manifest = json.loads(mpath.read_text())
        except json.JSONDecodeError as exc:
            raise BundleValidationError(f"{mpath} is not valid JSON: {exc}") from exc
        fmt = manifest.get("format") if isinstance(manifest, dict) else None
        if fmt != FORMAT:
            raise BundleVersionError(f"{mpath}: format is {fmt!r}, expected {FORMAT!r}")
        if manifest.get("version") != VERSION:
            raise BundleVersionError(f"{mpath}: bundle version {manifest.get('version')!r} is not supported "
                                     f"(this AGG reads version {VERSION})")
        if manifest.get("kind") == "gt":  # a sidecar is opened through its parent scene
            return cls.load(path.parent).gt
        bundle = cls(path, manifest)
        bundle.validate()
        return bundle

    def validate(self) -> None:
        """Check every present part against the manifest (shapes and dtypes from the .npy headers)."""
        m = self._manifest
        for key in ("num_frames", "width", "height"):
            _check(isinstance(m.get(key), int) and m[key] > 0, f"manifest {key} must be a positive integer")
        try:
            self._validate_parts()
        except (KeyError, TypeError, IndexError) as exc:
            raise BundleValidationError(f"{self.path / MANIFEST}: malformed manifest entry ({exc!r})") from exc

    def _validate_parts(self) -> None:
        n, h, w = self.num_frames, self.height, self.width
        if self.kind == "scene":
            fr = self._npy("frames.npy")
            _check(fr.shape == (n, h, w, 3) and fr.dtype == np.uint8,
                   f"frames.npy is {_shape_str(fr)}, manifest says ({n}, {h}, {w}, 3) uint8")
            ts = self.timestamps_us
            _check(ts.shape == (n,) and bool(np.all(np.diff(ts) > 0)),
                   f"timestamps_us.npy must be [{n}] strictly increasing, got {_shape_str(ts)}")
        k = self.intrinsics
        _check(k.shape == (n, 3, 3), f"intrinsics must be [3, 3] or [{n}, 3, 3], got {k.shape}")
        if self.has("poses"):
            p, c = self.world_from_camera, self.pose_confidence
            _check(p.shape == (n, 4, 4), f"poses/world_from_camera.npy is {p.shape}, expected ({n}, 4, 4)")
            _check(c.shape == (n,), f"poses/confidence.npy is {c.shape}, expected ({n},)")
            _check(len(self.pose_source) == n, f"poses.source has {len(self.pose_source)} entries, expected {n}")
        if self.has("depth_sparse"):
            pts, off = self._sparse()
            _check(pts.ndim == 2 and pts.shape[1] == 4, f"sparse depth points are {pts.shape}, expected [N, 4]")
            _check(off.shape == (n + 1,) and off[0] == 0 and off[-1] == pts.shape[0] and bool(np.all(np.diff(off) >= 0)),
                   f"sparse depth offsets must be [{n + 1}] non-decreasing from 0 to {pts.shape[0]}")
        for part, arr in (("depth_dense", self.dense_depth), ("depth_dense", self.dense_depth_confidence),
                          ("dynamic_masks", self.dynamic_masks)):
            if arr is not None:
                _check(arr.shape == (n, h, w), f"{part} array is {arr.shape}, expected ({n}, {h}, {w})")
        if self.has("ego_mask"):
            rel = self._manifest["ego_mask"]["file"]
            ego = self._npy(rel)
            _check(ego.shape == (h, w), f"{rel} (the ego mask) is {ego.shape}, expected ({h}, {w})")
        tr = self.tracklets
        if tr is not None:
            kk = len(tr.classes)
            _check(tr.boxes.shape == (kk, n, 7), f"tracklet boxes are {tr.boxes.shape}, expected ({kk}, {n}, 7)")
            _check(tr.valid.shape == (kk, n), f"tracklet valid is {tr.valid.shape}, expected ({kk}, {n})")
            _check(tr.anchor in TRACK_ANCHORS, f"tracklets.anchor must be one of {TRACK_ANCHORS}, got {tr.anchor!r}")
        sem = self.semantics
        if sem is not None:
            _check(sem.features.ndim == 4 and sem.features.shape[0] == n,
                   f"semantic features are {sem.features.shape}, expected [{n}, h, w, C]")
            c = sem.features.shape[3]
            _check(all(0 <= int(i) < c for i in sem.C_bg + sem.C_ag), f"C_bg / C_ag index outside [0, {c})")
            _check(sem.pca_basis is None or sem.pca_basis.shape[1] == c, f"pca_basis must have {c} columns")
        gt = self.gt
        if gt is not None:
            gt.validate()

    # ------------------------------------------------------------------ manifest helpers
    def _write_manifest(self) -> None:
        tmp = self.path / (MANIFEST + ".tmp")
        tmp.write_text(json.dumps(self._manifest, indent=1))
        os.replace(tmp, self.path / MANIFEST)
        self._cache.clear()

    def _npy(self, rel: str) -> np.ndarray:
        """Memory-map ``rel`` (cached); a missing or unreadable file is a validation error."""
        if rel not in self._cache:
            file = self.path / rel
            _check(file.is_file(), f"{file} is listed in the manifest but missing")
            try:
                self._cache[rel] = np.load(file, mmap_mode="r", allow_pickle=False)
            except ValueError as exc:
                raise BundleValidationError(f"{file} is not a readable .npy file: {exc}") from exc
        return self._cache[rel]

    def has(self, part: str) -> bool:
        if part not in PARTS:
            raise ValueError(f"unknown bundle part {part!r}; parts are {PARTS}")
        return part in self._manifest

    @property
    def manifest(self) -> dict:
        return json.loads(json.dumps(self._manifest))

    # ------------------------------------------------------------------ required parts
    kind = property(lambda self: self._manifest.get("kind", "scene"))
    num_frames = property(lambda self: int(self._manifest["num_frames"]))
    width = property(lambda self: int(self._manifest["width"]))
    height = property(lambda self: int(self._manifest["height"]))
    meta = property(lambda self: self._manifest.get("meta", {}))
    scale = property(lambda self: float(self._manifest.get("scale", 1.0)))
    metric = property(lambda self: bool(self._manifest.get("metric", False)))

    def __len__(self) -> int:
        return self.num_frames

    @property
    def frame_names(self) -> list[str] | None:
        if self._parent is not None:
            return self._parent.frame_names
        return self._manifest.get("frame_names")

    @property
    def frames(self) -> LazyFrames:
        """Lazy [T, H, W, 3]; indexing gives float32 RGB in [0, 1]; ``.raw`` is the uint8 memmap."""
        if self._parent is not None:
            return self._parent.frames
        return LazyFrames(self._npy("frames.npy"))

    def frame(self, i: int) -> np.ndarray:
        """Frame i as float32 RGB [H, W, 3] in [0, 1]."""
        return self.frames[int(i)]

    @property
    def timestamps_us(self) -> np.ndarray:
        """[T] int64 microseconds."""
        if self._parent is not None:
            return self._parent.timestamps_us
        return np.asarray(self._npy("timestamps_us.npy"), dtype=np.int64)

    @property
    def intrinsics(self) -> np.ndarray:
        """[T, 3, 3] float64 pinhole K at the training resolution (a shared K is broadcast)."""
        if "intrinsics" not in self._manifest and self._parent is not None:
            return self._parent.intrinsics
        k = np.asarray(self._npy("intrinsics.npy"), dtype=np.float64)
        return np.broadcast_to(k, (self.num_frames, 3, 3)).copy() if k.shape == (3, 3) else k

    @property
    def intrinsics_source(self) -> str:
        if "intrinsics" not in self._manifest and self._parent is not None:
            return self._parent.intrinsics_source
        return self._manifest["intrinsics"].get("source", "given")

    def write_intrinsics(self, intrinsics: np.ndarray, source: str = "given") -> None:
        """Replace the intrinsics: [3, 3] shared or [T, 3, 3] per frame, pixels at the training resolution."""
        k = np.asarray(intrinsics, dtype=np.float64)
        n = self.num_frames
        _check(k.shape in ((3, 3), (n, 3, 3)), f"intrinsics must be [3, 3] or [{n}, 3, 3], got {k.shape}")
        kk = k.reshape(-1, 3, 3)
        _check(bool(np.isfinite(kk).all()) and bool(np.all(kk[:, 0, 0] > 0)) and bool(np.all(kk[:, 1, 1] > 0)),
               "intrinsics must be finite with positive fx, fy")
        _check(bool(np.allclose(kk[:, 2], (0, 0, 1))) and bool(np.allclose(kk[:, 1, 0], 0)),
               "intrinsics must be upper-triangular pinhole K with last row (0, 0, 1)")
        _save_npy(self.path / "intrinsics.npy", k)
        self._manifest["intrinsics"] = {"file": "intrinsics.npy", "per_frame": k.ndim == 3, "source": source}
        self._write_manifest()

    # ------------------------------------------------------------------ poses
    @property
    def world_from_camera(self) -> np.ndarray | None:
        """[T, 4, 4] float64 camera-to-world (OpenCV axes, world = first camera), or None."""
        return np.array(self._npy("poses/world_from_camera.npy"), dtype=np.float64) if self.has("poses") else None

    @property
    def camera_from_world(self) -> np.ndarray | None:
        """[T, 4, 4] world-to-camera view matrices (the renderer's ``viewmat``), or None."""
        p = self.world_from_camera
        return None if p is None else np.linalg.inv(p)

    @property
    def pose_confidence(self) -> np.ndarray | None:
        return np.array(self._npy("poses/confidence.npy"), dtype=np.float32) if self.has("poses") else None

    @property
    def pose_source(self) -> list[str] | None:
        return list(self._manifest["poses"]["source"]) if self.has("poses") else None

    def write_poses(self, world_from_camera: np.ndarray, source: str | Sequence[str] = "given",
                    confidence: float | np.ndarray = 1.0, rebase: bool = False) -> None:
        """Write [T, 4, 4] camera-to-world poses; ``[0]`` must be I (to 1e-6) unless ``rebase`` re-expresses them."""
        n = self.num_frames
        p = np.asarray(world_from_camera, dtype=np.float64)
        _check(p.shape == (n, 4, 4), f"world_from_camera must be [{n}, 4, 4], got {p.shape}")
        _check(bool(np.isfinite(p).all()), "world_from_camera has non-finite values")
        _check(bool(np.allclose(p[:, 3], (0, 0, 0, 1), atol=1e-9)), "world_from_camera last rows must be (0, 0, 0, 1)")
        rot = p[:, :3, :3]
        err = np.abs(rot @ rot.transpose(0, 2, 1) - np.eye(3)).max()
        _check(err < 1e-5 and bool(np.all(np.linalg.det(rot) > 0)), f"pose rotations are not proper rotations (err {err:.2e})")
        if rebase:
            p = rebase_to_first_camera(p)
        _check(float(np.abs(p[0] - np.eye(4)).max()) <= 1e-6,
               "world_from_camera[0] must be the identity (world = first camera); pass rebase=True to re-express")
        conf = np.broadcast_to(np.asarray(confidence, dtype=np.float32), (n,)).copy()
        _check(bool(np.all((conf >= 0) & (conf <= 1))), "pose confidence must be in [0, 1]")
        src = [source] * n if isinstance(source, str) else [str(s) for s in source]
        _check(len(src) == n, f"{len(src)} pose sources for {n} frames")
        _save_npy(self.path / "poses/world_from_camera.npy", p)
        _save_npy(self.path / "poses/confidence.npy", conf)
        self._manifest["poses"] = {"file": "poses/world_from_camera.npy", "confidence_file": "poses/confidence.npy",
                                   "source": src}
        self._write_manifest()

    # ------------------------------------------------------------------ scale, removal, gt sidecar
    def set_scale(self, scale: float, metric: bool = False) -> None:
        """Record ``metric = scale * scene_units`` (does not change any stored length)."""
        _check(np.isfinite(scale) and scale > 0, f"scale must be positive and finite, got {scale}")
        self._manifest["scale"], self._manifest["metric"] = float(scale), bool(metric)
        self._write_manifest()

    def remove(self, part: str) -> None:
        """Delete an optional part (its files and its manifest entry)."""
        if not self.has(part):
            return
        entry = self._manifest.pop(part)
        if part == "gt":
            shutil.rmtree(self.path / entry, ignore_errors=True)
        else:
            files = [v for k, v in entry.items() if k.endswith("file") and v]
            files += list((entry.get("prototypes") or {}).values())
            for rel in files:
                (self.path / rel).unlink(missing_ok=True)
        self._write_manifest()

    def create_gt(self, overwrite: bool = False) -> "SceneBundle":
        """Create (or, with ``overwrite``, replace) the ``gt/`` sidecar and return it as a writable bundle."""
        _check(self.kind == "scene", "a gt sidecar cannot have its own gt")
        if self.has("gt"):
            if not overwrite:
                raise BundleExistsError(f"{self.path}/gt exists (pass overwrite=True to replace it)")
            self.remove("gt")
        (self.path / "gt").mkdir()
        manifest = {"format": FORMAT, "version": VERSION, "kind": "gt", "num_frames": self.num_frames,
                    "width": self.width, "height": self.height, "scale": 1.0, "metric": False, "meta": {}}
        gt = SceneBundle(self.path / "gt", manifest, parent=self)
        gt._write_manifest()
        self._manifest["gt"] = "gt"
        self._write_manifest()
        return gt

    @property
    def gt(self) -> "SceneBundle | None":
        """The ground-truth sidecar (kind "gt", shares frames/timestamps/intrinsics with this bundle), or None."""
        if not self.has("gt"):
            return None
        if "gt" not in self._cache:
            mpath = self.path / self._manifest["gt"] / MANIFEST
            if not mpath.is_file():
                raise BundleValidationError(f"manifest lists a gt sidecar but {mpath} is missing")
            self._cache["gt"] = SceneBundle(mpath.parent, json.loads(mpath.read_text()), parent=self)
        return self._cache["gt"]

    def normalise_scale(self, method: str = "auto", include_gt: bool = False) -> float:
        """Divide every stored length by f = ``compute_scale_factor(...)`` and multiply ``scale`` by f; return f."""
        depths = None
        if self.has("depth_sparse"):
            depths = self._sparse()[0][:, 2]
        elif self.has("depth_dense"):  # up to 64 evenly spaced frames: enough for a median, bounded memory
            d = self.dense_depth
            depths = d[np.unique(np.linspace(0, d.shape[0] - 1, min(64, d.shape[0])).astype(int))]
        f = compute_scale_factor(self.world_from_camera, depths, method)
        targets = [self] + ([self.gt] if include_gt and self.gt is not None else [])
        for b in targets:
            b._divide_lengths(f)
        return f

    def _divide_lengths(self, f: float) -> None:
        if self.has("poses"):
            p = self.world_from_camera
            p[:, :3, 3] /= f
            _save_npy(self.path / "poses/world_from_camera.npy", p)
        if self.has("depth_sparse"):
            pts = np.array(self._sparse()[0])
            pts[:, 2] /= f
            _save_npy(self.path / self._manifest["depth_sparse"]["points_file"], pts)
        if self.has("depth_dense"):
            d, path = self.dense_depth, self.path / self._manifest["depth_dense"]["file"]
            tmp = path.with_name(path.name + ".tmp.npy")
            out = np.lib.format.open_memmap(tmp, mode="w+", dtype=d.dtype, shape=d.shape)
            for i in range(d.shape[0]):  # frame by frame: a long clip's dense maps need not fit in RAM
                out[i] = (d[i].astype(np.float32) / f).astype(d.dtype)
            out.flush()
            del out
            os.replace(tmp, path)
        if self.has("tracklets"):
            e = self._manifest["tracklets"]
            boxes = np.array(self._npy(e["boxes_file"]))
            boxes[..., :6] /= f
            _save_npy(self.path / e["boxes_file"], boxes)
        self._manifest["scale"] = self.scale * f
        self._write_manifest()
