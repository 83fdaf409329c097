"""Camera intrinsics prior: given K (and optional OpenCV distortion), or a default field of view.

Conventions (docs/CONVENTIONS.md): pinhole ``K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` in pixels, OpenCV's
pixel-centre convention (the centre of the top-left pixel is (0, 0)), distortion ``(k1, k2, p1, p2, k3)``.
COLMAP puts the centre of the top-left pixel at (0.5, 0.5); ``to_colmap`` / ``from_colmap`` convert.

Default when nothing is known: horizontal field of view ``DEFAULT_HFOV_DEG = 60`` degrees and the principal point
at the image centre. Why 60: forward-facing driving cameras that record undistorted (or mildly distorted) video
sit between about 45 and 90 degrees (Udacity dashcam ~58, nuScenes front ~64, Waymo front ~50, KITTI ~82 after
rectification), and 60 is near the middle on the log-focal scale where an error costs SfM the least; COLMAP's
own default (``1.2 * max(W, H)``, ~45 degrees) is narrower than most dashcams. The focal length is then refined
by structure from motion (``agg.priors.poses``), which also reports the refined value.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

DEFAULT_HFOV_DEG = 60.0


class IntrinsicsError(ValueError):
    """Invalid intrinsics input (shape, non-positive focal, bad image size, unreadable file)."""


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics (pixels, OpenCV convention) plus optional OpenCV distortion.

    ``source`` records where they came from: "given", "default_fov", or "<previous>+sfm" after refinement.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))  # [5] k1, k2, p1, p2, k3
    source: str = "given"

    def __post_init__(self) -> None:
        if not (self.fx > 0 and self.fy > 0 and np.isfinite([self.fx, self.fy, self.cx, self.cy]).all()):
            raise IntrinsicsError(f"focal lengths must be positive and finite, got fx={self.fx}, fy={self.fy}")
        if self.width <= 0 or self.height <= 0:
            raise IntrinsicsError(f"image size must be positive, got {self.width}x{self.height}")
        d = np.asarray(self.dist, float).reshape(-1)
        if d.size not in (4, 5) or not np.isfinite(d).all():
            raise IntrinsicsError(f"distortion must be 4 or 5 finite numbers (k1, k2, p1, p2[, k3]), got {d}")
        object.__setattr__(self, "dist", np.pad(d, (0, 5 - d.size)))

    @property
    def K(self) -> np.ndarray:  # noqa: N802  [3, 3]
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(np.abs(self.dist) > 0))

    @property
    def hfov_deg(self) -> float:
        return math.degrees(2.0 * math.atan(self.width / (2.0 * self.fx)))

    def scaled(self, factor: float) -> "CameraIntrinsics":
        """Intrinsics for the image resized by ``factor`` (size rounded to whole pixels)."""
        return self.resized(max(1, round(self.width * factor)), max(1, round(self.height * factor)))

    def resized(self, width: int, height: int) -> "CameraIntrinsics":
        """Intrinsics for the image resized to ``width`` x ``height`` (pixel-centre aware: (c + 0.5) * s - 0.5)."""
        sx, sy = width / self.width, height / self.height
        return replace(self, fx=self.fx * sx, fy=self.fy * sy, cx=(self.cx + 0.5) * sx - 0.5,
                       cy=(self.cy + 0.5) * sy - 0.5, width=int(width), height=int(height))

    def to_colmap(self, refine_focal: bool) -> tuple[str, list[float]]:
        """COLMAP camera model name and parameters (COLMAP's pixel convention).

        With distortion: FULL_OPENCV (k4..k6 = 0) on the raw frames (GUIDE.md: undistorting first then using
        a pinhole camera gave worse paths). Without: SIMPLE_PINHOLE when fx == fy and the focal is refined,
        else PINHOLE.
        """
        cx, cy = self.cx + 0.5, self.cy + 0.5
        if self.has_distortion:
            k1, k2, p1, p2, k3 = self.dist
            return "FULL_OPENCV", [self.fx, self.fy, cx, cy, k1, k2, p1, p2, k3, 0.0, 0.0, 0.0]
        if refine_focal and math.isclose(self.fx, self.fy, rel_tol=1e-6):
            return "SIMPLE_PINHOLE", [self.fx, cx, cy]
        return "PINHOLE", [self.fx, self.fy, cx, cy]

    def from_colmap(self, model: str, params: np.ndarray, refined: bool) -> "CameraIntrinsics":
        """These intrinsics with values replaced by COLMAP parameters of the same image size."""
        p = np.asarray(params, float)
        if model == "SIMPLE_PINHOLE":
            fx = fy = p[0]
            cx, cy = p[1], p[2]
            dist = self.dist
        elif model == "PINHOLE":
            fx, fy, cx, cy = p[:4]
            dist = self.dist
        elif model == "FULL_OPENCV":
            fx, fy, cx, cy = p[:4]
            dist = np.array([p[4], p[5], p[6], p[7], p[8]])
        else:
            raise IntrinsicsError(f"unsupported COLMAP camera model {model!r}")
        source = self.source + "+sfm" if refined and "+sfm" not in self.source else self.source
        return replace(self, fx=float(fx), fy=float(fy), cx=float(cx) - 0.5, cy=float(cy) - 0.5, dist=dist,
                       source=source)


def default_intrinsics(width: int, height: int, hfov_deg: float = DEFAULT_HFOV_DEG) -> CameraIntrinsics:
    """Square pixels, principal point at the image centre ((W-1)/2, (H-1)/2 in OpenCV convention)."""
    if not 1.0 < hfov_deg < 179.0:
        raise IntrinsicsError(f"horizontal field of view must be in (1, 179) degrees, got {hfov_deg}")
    f = width / (2.0 * math.tan(math.radians(hfov_deg) / 2.0))
    return CameraIntrinsics(f, f, (width - 1) / 2.0, (height - 1) / 2.0, int(width), int(height),
                            source="default_fov")


def intrinsics_from_K(K: np.ndarray, width: int, height: int, dist=None) -> CameraIntrinsics:  # noqa: N803
    """Wrap a given 3x3 K (pixels, OpenCV convention) and optional distortion."""
    K = np.asarray(K, float)
    if K.shape != (3, 3):
        raise IntrinsicsError(f"K must be 3x3, got {K.shape}")
    if abs(K[0, 1]) > 1e-9 * abs(K[0, 0]) or not np.allclose(K[2], [0, 0, 1]):
        raise IntrinsicsError("K must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (no skew)")
    return CameraIntrinsics(K[0, 0], K[1, 1], K[0, 2], K[1, 2], int(width), int(height),
                            dist=np.zeros(5) if dist is None else np.asarray(dist, float), source="given")


def intrinsics_for_frames(K, dist, width: int, height: int) -> CameraIntrinsics:  # noqa: N803
    """Intrinsics for frames of ``width`` x ``height`` from None (default FOV), a 3x3 K (+ dist) or
    ``CameraIntrinsics`` (resized when given for another resolution of the same aspect ratio)."""
    if K is None:
        return default_intrinsics(width, height)
    intr = K if isinstance(K, CameraIntrinsics) else intrinsics_from_K(K, width, height, dist)
    if (intr.width, intr.height) != (width, height):
        if abs(intr.width / intr.height - width / height) > 0.01:
            raise IntrinsicsError(f"intrinsics are for {intr.width}x{intr.height}, frames are {width}x{height}")
        intr = intr.resized(width, height)
    return intr


def read_kitti_calib(path: str | Path, width: int, height: int, camera: str = "P0") -> CameraIntrinsics:
    """Intrinsics from a KITTI odometry ``calib.txt`` (rectified, so no distortion).

    Lines are either ``P0: 12 numbers`` or just 12 numbers, in which case line k is camera ``Pk``.
    """
    lines = [ln for ln in Path(path).read_text().splitlines() if ln.strip()]
    for k, line in enumerate(lines):
        key, sep, rest = line.partition(":")
        if (sep and key.strip() == camera) or (not sep and camera == f"P{k}"):
            P = np.array((rest if sep else line).split(), float)  # noqa: N806
            if P.size != 12:
                raise IntrinsicsError(f"{path}: camera {camera!r} needs 12 numbers, got {P.size}")
            return intrinsics_from_K(P.reshape(3, 4)[:, :3], width, height)
    raise IntrinsicsError(f"{path}: no line for camera {camera!r}")


def read_opencv_yaml(path: str | Path) -> CameraIntrinsics:
    """Intrinsics from an OpenCV FileStorage file with ``K``, optional ``dist`` and ``image_size`` (W, H)."""
    import cv2

    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    if not fs.isOpened():
        raise IntrinsicsError(f"cannot open {path}")
    try:
        K = fs.getNode("K").mat()  # noqa: N806
        dist = fs.getNode("dist").mat()
        size = fs.getNode("image_size").mat()
    finally:
        fs.release()
    if K is None or size is None:
        raise IntrinsicsError(f"{path}: needs K and image_size")
    w, h = (int(v) for v in np.asarray(size).reshape(-1)[:2])
    return intrinsics_from_K(K, w, h, None if dist is None else np.asarray(dist).reshape(-1))
