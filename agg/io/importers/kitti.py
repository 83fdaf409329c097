"""Import a KITTI odometry sequence (``image_l/`` or ``image_0/``, ``calib.txt``, ``poses.txt``, ``times.txt``).

KITTI's ``poses.txt`` holds, per frame, the left (cam0) camera's camera-to-world 3x4 matrix in OpenCV camera axes
(x right, y down, z forward), in metres. The importer re-expresses them so that frame 0 is the world origin
(``world_from_camera[0] = I``) and, for another camera c, composes ``world_from_cam0 @ cam0_from_camc`` with the
rectified baseline from ``P_c``. ``calib.txt`` rows ``P0..P3`` are 3x4 projection matrices (``Pk:`` prefixes are
optional); K is their left 3x3 block, taken as OpenCV pixel centres.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from agg.io.bundle import SceneBundle, rebase_to_first_camera
from agg.io.errors import ImporterError
from agg.io.video import IngestConfig, list_images, read_images

IMAGE_DIRS = {0: ("image_l", "image_0"), 1: ("image_r", "image_1"), 2: ("image_2",), 3: ("image_3",)}


def read_calib(path: str | Path) -> dict[str, np.ndarray]:
    """``calib.txt`` -> {"P0": [3, 4], ...}; rows without a name are P0, P1, ... in order."""
    out: dict[str, np.ndarray] = {}
    for row, line in enumerate(l for l in Path(path).read_text().splitlines() if l.strip()):
        name, _, rest = line.partition(":") if ":" in line else (f"P{row}", "", line)
        try:
            vals = np.array([float(v) for v in rest.split()], dtype=np.float64)
        except ValueError as exc:
            raise ImporterError(f"{path}: line {row + 1} has non-numeric values") from exc
        if vals.size == 12:
            out[name.strip()] = vals.reshape(3, 4)
    if "P0" not in out:
        raise ImporterError(f"{path}: no P0 row (expected 3x4 projection matrices, 12 numbers per row)")
    return out


def read_poses(path: str | Path) -> np.ndarray:
    """``poses.txt`` (one row-major 3x4 camera-to-world matrix per line) -> [N, 4, 4] float64."""
    try:
        rows = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except ValueError as exc:
        raise ImporterError(f"{path}: not a KITTI pose file ({exc})") from exc
    if rows.shape[1] != 12:
        raise ImporterError(f"{path}: pose rows need 12 numbers, got {rows.shape[1]}")
    poses = np.tile(np.eye(4), (rows.shape[0], 1, 1))
    poses[:, :3, :4] = rows.reshape(-1, 3, 4)
    return poses


def import_kitti(src: str | Path, out: str | Path, *, camera: int = 0, with_poses: bool | None = None,
                 gt_poses: bool = False, config: IngestConfig | None = None,
                 overwrite: bool = False) -> SceneBundle:
    """Write a scene bundle at ``out`` from the KITTI odometry folder ``src``.

    camera: which rectified camera (0 = left grayscale, ``image_l``/``image_0``). with_poses: write ``poses.txt``
    as the bundle's poses (source "gt", confidence 1, metric): True, False (the bundle has no poses, e.g. for
    ``agg priors`` to estimate them), or None = when ``poses.txt`` exists. gt_poses: also write them into the
    ``gt/`` sidecar (metric). config: sampling / resize (``K`` and ``dist`` in it are ignored: calib.txt wins).
    Timestamps come from ``times.txt`` (seconds), else 10 Hz.
    """
    src = Path(src)
    config = replace(config or IngestConfig(), dtype="uint8", K=None, dist=None, calib_size=None)
    image_dir = next((src / d for d in IMAGE_DIRS.get(camera, ()) if (src / d).is_dir()), None)
    if image_dir is None:
        raise ImporterError(f"{src}: no image folder for camera {camera} (looked for {IMAGE_DIRS.get(camera)})")
    paths = list_images(image_dir)
    if not paths:
        raise ImporterError(f"{image_dir}: no images")
    calib_path = src / "calib.txt"
    if not calib_path.is_file():
        raise ImporterError(f"{src}: calib.txt is missing")
    P = read_calib(calib_path).get(f"P{camera}")
    if P is None:
        raise ImporterError(f"{calib_path}: no P{camera} row")
    K = P[:, :3]
    times = None
    if (src / "times.txt").is_file():
        times = np.loadtxt(src / "times.txt", dtype=np.float64, ndmin=1)
        if times.shape[0] < len(paths):
            raise ImporterError(f"{src}/times.txt has {times.shape[0]} rows for {len(paths)} images")
        times = times[: len(paths)]
    pose_path = src / "poses.txt"
    if with_poses is None:
        with_poses = pose_path.is_file()
    poses = None
    if with_poses or gt_poses:
        if not pose_path.is_file():
            raise ImporterError(f"{src}: poses.txt is missing (pass with_poses=False, gt_poses=False to import "
                                f"without poses)")
        poses = read_poses(pose_path)  # [N, 4, 4] world_from_cam0
        if poses.shape[0] < len(paths):
            raise ImporterError(f"{pose_path} has {poses.shape[0]} poses for {len(paths)} images")
        cam0_from_camc = np.eye(4)
        cam0_from_camc[:3, 3] = -np.linalg.solve(K, P[:, 3])  # rectified: camc_from_cam0 = [I | K^-1 P[:, 3]]
        poses = poses @ cam0_from_camc
    result = read_images(paths, config, timestamps_s=times, K=K, source=str(image_dir))
    meta = {"importer": "kitti", "source": str(src), "camera": camera, "source_size": list(result.source_size),
            "source_indices": result.source_indices.tolist()}
    bundle = SceneBundle.create(out, result.frames, result.timestamps_us, result.K, frame_names=result.frame_names,
                                intrinsics_source="calibration", scale=1.0, metric=bool(with_poses), meta=meta,
                                overwrite=overwrite)
    if poses is not None:
        world_from_camera = rebase_to_first_camera(poses[result.source_indices])  # [T, 4, 4], metres
        if with_poses:
            bundle.write_poses(world_from_camera, source="gt", confidence=1.0)
        if gt_poses:
            gt = bundle.create_gt()
            gt.write_poses(world_from_camera, source="gt", confidence=1.0)
            gt.set_scale(1.0, metric=True)
    return bundle
