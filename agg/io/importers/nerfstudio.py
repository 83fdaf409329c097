"""Import a nerfstudio dataset (``transforms.json`` + images).

nerfstudio stores camera-to-world ``transform_matrix`` in OpenGL camera axes (x right, y up, z backward); AGG uses
OpenCV axes (x right, y down, z forward): ``world_from_camera_cv = world_from_camera_gl @ diag(1, -1, -1, 1)``, then
re-expressed so that frame 0 is the world origin. nerfstudio (like COLMAP) puts the centre of the top-left pixel at
(0.5, 0.5), so ``cx_opencv = cx - 0.5`` (same for cy). Distortion (``k1, k2, p1, p2, k3``; camera model OPENCV) is
removed with OpenCV at import. Frames are ordered by ``file_path`` (natural order), as nerfstudio's data parser does.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np

from agg.io.bundle import SceneBundle, rebase_to_first_camera
from agg.io.errors import ImporterError
from agg.io.video import IngestConfig, natural_key, read_images

OPENGL_FROM_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])  # camera axes flip: y and z
INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h", "k1", "k2", "k3", "k4", "p1", "p2", "camera_model")
PINHOLE_MODELS = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE")


def _intrinsics(meta: dict, frame: dict, where: str) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
    """K [3, 3] (OpenCV pixel centres), dist (k1, k2, p1, p2, k3) and (w, h) from top-level keys and frame overrides."""
    m = {k: frame.get(k, meta.get(k)) for k in INTRINSIC_KEYS}
    model = m["camera_model"] or "OPENCV"
    if model not in PINHOLE_MODELS:
        raise ImporterError(f"{where}: camera_model {model!r} is not supported (only {PINHOLE_MODELS})")
    missing = [k for k in ("fl_x", "cx", "cy", "w", "h") if m[k] is None]
    if missing:
        raise ImporterError(f"{where}: missing intrinsics {missing}")
    if m["k4"]:
        raise ImporterError(f"{where}: k4 distortion is not supported")
    fx = float(m["fl_x"])
    fy = float(m["fl_y"]) if m["fl_y"] is not None else fx
    K = np.array([[fx, 0.0, float(m["cx"]) - 0.5], [0.0, fy, float(m["cy"]) - 0.5], [0.0, 0.0, 1.0]])
    dist = np.array([float(m[k] or 0.0) for k in ("k1", "k2", "p1", "p2", "k3")])
    return K, dist, (int(m["w"]), int(m["h"]))


def import_nerfstudio(transforms: str | Path, out: str | Path, *, with_poses: bool = True,
                      config: IngestConfig | None = None, fps: float = 10.0,
                      overwrite: bool = False) -> SceneBundle:
    """Write a scene bundle at ``out`` from a nerfstudio ``transforms.json`` (or the folder holding it).

    with_poses: write the given poses (source "given", confidence 1, scale not metric). config: sampling and
    resize (its K / dist are ignored). fps: the frame rate used for timestamps (nerfstudio has none).
    Limitation: every frame must share the same intrinsics (per-frame overrides are allowed if equal).
    """
    path = Path(transforms)
    path = path / "transforms.json" if path.is_dir() else path
    if not path.is_file():
        raise ImporterError(f"{path}: no transforms.json")
    try:
        meta = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ImporterError(f"{path}: not valid JSON ({exc})") from exc
    frames = meta.get("frames") if isinstance(meta, dict) else None
    if not frames:
        raise ImporterError(f"{path}: no frames")
    if any("file_path" not in f or "transform_matrix" not in f for f in frames):
        raise ImporterError(f"{path}: every frame needs file_path and transform_matrix")
    frames = sorted(frames, key=lambda f: natural_key(str(f["file_path"])))
    K, dist, size = _intrinsics(meta, frames[0], str(path))
    for f in frames[1:]:
        k2, d2, s2 = _intrinsics(meta, f, f"{path} ({f['file_path']})")
        if not (np.allclose(k2, K) and np.allclose(d2, dist) and s2 == size):
            raise ImporterError(f"{path}: frame {f['file_path']} has different intrinsics; only shared intrinsics "
                                f"are supported")
    paths = [path.parent / f["file_path"] for f in frames]
    absent = [str(p) for p in paths if not p.is_file()]
    if absent:
        raise ImporterError(f"{path}: {len(absent)} image file(s) missing, e.g. {absent[0]}")
    world_from_gl = np.array([np.asarray(f["transform_matrix"], dtype=np.float64).reshape(-1, 4)[:3]
                              for f in frames])  # [N, 3, 4]
    poses = np.tile(np.eye(4), (len(frames), 1, 1))
    poses[:, :3] = world_from_gl
    poses = poses @ OPENGL_FROM_OPENCV  # world_from_camera in OpenCV axes, nerfstudio world
    config = replace(config or IngestConfig(), dtype="uint8", image_fps=fps, calib_size=size)
    result = read_images(paths, config, K=K, dist=dist, source=str(path))
    info = {"importer": "nerfstudio", "source": str(path), "source_size": list(result.source_size),
            "source_indices": result.source_indices.tolist(), "distortion": dist.tolist()}
    bundle = SceneBundle.create(out, result.frames, result.timestamps_us, result.K, frame_names=result.frame_names,
                                intrinsics_source="given", scale=1.0, metric=False, meta=info, overwrite=overwrite)
    if with_poses:
        bundle.write_poses(rebase_to_first_camera(poses[result.source_indices]), source="given", confidence=1.0)
    return bundle
