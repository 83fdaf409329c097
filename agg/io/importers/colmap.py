"""Import a COLMAP sparse model (``cameras``, ``images``, ``points3D``; binary or text) read with pycolmap.

COLMAP stores ``cam_from_world`` (world-to-camera) in OpenCV camera axes and puts the centre of the top-left pixel
at (0.5, 0.5), so ``cx_opencv = cx - 0.5``. Only registered images are imported, in natural name order; image
files of ``images_dir`` that the model does not register are listed in the bundle's
``meta["images_not_registered"]``. Poses are inverted to ``world_from_camera`` and re-expressed so that frame 0 is
the world origin. Distorted camera models (SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV) are undistorted with OpenCV
at import.

Sparse depth: every 3D point observed in an image is projected with that image's pose into the (undistorted,
resized) pinhole image; rows are (u, v, z-depth, confidence) with ``confidence = 1 / (1 + reprojection error in
px)`` (1 when COLMAP did not compute the error). Points behind the camera or outside the image are dropped.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from agg.io.bundle import SceneBundle, rebase_to_first_camera
from agg.io.errors import ImporterError
from agg.io.video import IngestConfig, list_images, natural_key, read_images


def camera_to_opencv(model: str, params: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """COLMAP camera model + params -> K [3, 3] (OpenCV pixel centres) and OpenCV distortion coefficients."""
    p = [float(v) for v in params]
    if model == "SIMPLE_PINHOLE":
        (f, cx, cy), dist = p, []
        fx = fy = f
    elif model == "PINHOLE":
        (fx, fy, cx, cy), dist = p, []
    elif model == "SIMPLE_RADIAL":
        f, cx, cy, k = p
        fx = fy = f
        dist = [k, 0.0, 0.0, 0.0]
    elif model == "RADIAL":
        f, cx, cy, k1, k2 = p
        fx = fy = f
        dist = [k1, k2, 0.0, 0.0]
    elif model == "OPENCV":
        fx, fy, cx, cy = p[:4]
        dist = p[4:8]  # k1, k2, p1, p2
    elif model == "FULL_OPENCV":
        fx, fy, cx, cy = p[:4]
        dist = p[4:12]  # k1, k2, p1, p2, k3, k4, k5, k6 (OpenCV's rational model)
    else:
        raise ImporterError(f"COLMAP camera model {model} is not supported (pinhole, radial and OpenCV models are)")
    K = np.array([[fx, 0.0, cx - 0.5], [0.0, fy, cy - 0.5], [0.0, 0.0, 1.0]])
    return K, np.asarray(dist, dtype=np.float64)


def _sparse_points(rec, image, camera_from_world: np.ndarray, K: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """[N, 4] (u, v, z, confidence) of the 3D points observed in ``image``, projected with pinhole K."""
    ids = [p.point3D_id for p in image.points2D if p.has_point3D()]
    if not ids:
        return np.zeros((0, 4), np.float32)
    pts = [rec.points3D[i] for i in ids]
    xyz = np.array([p.xyz for p in pts])  # [N, 3] world
    err = np.array([max(float(p.error), 0.0) for p in pts])  # [N] px (-1 = not computed)
    cam = xyz @ camera_from_world[:3, :3].T + camera_from_world[:3, 3]  # [N, 3]
    z = cam[:, 2]
    front = z > 1e-9
    uv = (cam[front, :2] / z[front, None]) @ K[:2, :2].T + K[:2, 2]  # [M, 2]
    rows = np.column_stack([uv, z[front], 1.0 / (1.0 + err[front])])
    w, h = size
    inside = (rows[:, 0] >= -0.5) & (rows[:, 0] <= w - 0.5) & (rows[:, 1] >= -0.5) & (rows[:, 1] <= h - 0.5)
    return rows[inside].astype(np.float32)


def import_colmap(sparse_dir: str | Path, images_dir: str | Path, out: str | Path, *, with_poses: bool = True,
                  with_depth: bool = True, config: IngestConfig | None = None, fps: float = 10.0,
                  overwrite: bool = False) -> SceneBundle:
    """Write a scene bundle at ``out`` from the COLMAP model in ``sparse_dir`` and the images in ``images_dir``.

    with_poses: write the SfM poses (source "sfm", confidence 1, not metric). with_depth: write the sparse depth
    of the observed 3D points. config: sampling and resize (its K / dist are ignored). fps: timestamps (COLMAP has
    none). All registered images must share one camera.
    """
    import pycolmap

    sparse_dir, images_dir = Path(sparse_dir), Path(images_dir)
    if not sparse_dir.is_dir():
        raise ImporterError(f"{sparse_dir}: no such folder")
    try:
        rec = pycolmap.Reconstruction(str(sparse_dir))
    except Exception as exc:  # pycolmap raises plain RuntimeError/ValueError on unreadable models
        raise ImporterError(f"{sparse_dir}: not a readable COLMAP model ({exc})") from exc
    images = sorted((im for im in rec.images.values() if im.has_pose), key=lambda im: natural_key(im.name))
    if not images:
        raise ImporterError(f"{sparse_dir}: the model has no registered image")
    cam_ids = {im.camera_id for im in images}
    if len(cam_ids) != 1:
        raise ImporterError(f"{sparse_dir}: registered images use {len(cam_ids)} cameras; only one is supported")
    camera = rec.cameras[cam_ids.pop()]
    K, dist = camera_to_opencv(camera.model_name, np.asarray(camera.params))
    paths = [images_dir / im.name for im in images]
    absent = [str(p) for p in paths if not p.is_file()]
    if absent:
        raise ImporterError(f"{images_dir}: {len(absent)} image file(s) of the model missing, e.g. {absent[0]}")
    camera_from_world = np.tile(np.eye(4), (len(images), 1, 1))  # [N, 4, 4]
    for i, im in enumerate(images):
        camera_from_world[i, :3] = im.cam_from_world().matrix()
    config = replace(config or IngestConfig(), dtype="uint8", image_fps=fps,
                     calib_size=(int(camera.width), int(camera.height)))
    result = read_images(paths, config, K=K, dist=dist, source=str(images_dir))
    sel = result.source_indices
    registered = {im.name for im in images}
    skipped = [p.name for p in list_images(images_dir) if p.name not in registered]  # not registered by SfM
    info = {"importer": "colmap", "source": str(sparse_dir), "images": str(images_dir), "camera_model":
            camera.model_name, "source_size": list(result.source_size), "source_indices": sel.tolist(),
            "images_not_registered": skipped}
    bundle = SceneBundle.create(out, result.frames, result.timestamps_us, result.K, frame_names=result.frame_names,
                                intrinsics_source="sfm", scale=1.0, metric=False, meta=info, overwrite=overwrite)
    if with_poses:
        bundle.write_poses(rebase_to_first_camera(np.linalg.inv(camera_from_world[sel])), source="sfm",
                           confidence=1.0)
    if with_depth:
        bundle.write_sparse_depth([_sparse_points(rec, images[i], camera_from_world[i], result.K, result.size)
                                   for i in sel], source="sfm")
    return bundle
