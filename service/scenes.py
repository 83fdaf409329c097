"""Scene folders seen by the API: metadata, artifacts, and an LRU cache of loaded scenes for renders.

A scene is loaded with ``agg.scene.Scene.load`` (the final model, or the latest checkpoint while its job trains);
the cache key includes the model/checkpoint file's mtime, so a newer checkpoint is picked up on the next render.
"""

from __future__ import annotations

import io
import json
import threading
from collections import OrderedDict
from pathlib import Path

import numpy as np

from service.errors import ApiError
from service.models import ArtifactName, RenderRequest, SceneInfo, SceneStatus

STATUS_OF_JOB = {"queued": SceneStatus.pending, "running": SceneStatus.training, "succeeded": SceneStatus.ready,
                 "failed": SceneStatus.failed, "cancelled": SceneStatus.cancelled}


def read_meta(scene_dir: Path) -> dict:
    try:
        return json.loads((scene_dir / "scene.json").read_text())
    except (OSError, ValueError):
        return {}


def model_file(scene_dir: Path) -> Path | None:
    for name in ("model.pt", "checkpoint.pt"):
        if (scene_dir / name).is_file():
            return scene_dir / name
    return None


def scene_info(scene_id: str, scene_dir: Path, job: dict | None) -> SceneInfo:
    meta = read_meta(scene_dir)
    if job is not None:
        status = STATUS_OF_JOB[job["state"]]
    else:
        status = SceneStatus.ready if (scene_dir / "model.pt").is_file() else SceneStatus.pending
    K = meta.get("K")  # noqa: N806
    if isinstance(K, list) and K and isinstance(K[0], list) and K[0] and isinstance(K[0][0], list):
        K = K[0]  # noqa: N806 - [T][3][3] -> first frame
    return SceneInfo(scene_id=scene_id, job_id=job["job_id"] if job else meta.get("job_id"), status=status,
                     preset=meta.get("preset") or (job or {}).get("preset"), num_frames=meta.get("num_frames"),
                     width=meta.get("width"), height=meta.get("height"), timestamps_us=meta.get("timestamps_us"),
                     intrinsics=K if isinstance(K, list) else None,
                     artifacts=[a.value for a in ArtifactName if (scene_dir / a.value).is_file()],
                     renderable=model_file(scene_dir) is not None)


class SceneCache:
    """At most ``size`` loaded scenes, least recently used evicted; one render at a time per process."""

    def __init__(self, size: int = 2):
        self.size, self._items, self._lock = max(1, size), OrderedDict(), threading.Lock()
        self.render_lock = threading.Lock()

    def get(self, scene_dir: Path):
        try:
            from agg.scene import Scene, SceneNotReady, SceneUnreadable
        except ImportError:
            raise ApiError(503, "renderer_unavailable", "the scene renderer (agg.scene) is not installed") from None
        f = model_file(scene_dir)
        if f is None:
            raise ApiError(409, "scene_not_ready", "the scene has no checkpoint yet; retry when training has "
                                                   "written its first checkpoint")
        key = (str(scene_dir), f.name, f.stat().st_mtime_ns)
        with self._lock:
            if key in self._items:
                self._items.move_to_end(key)
                return self._items[key]
        try:
            scene = Scene.load(scene_dir)
        except SceneNotReady:
            raise ApiError(409, "scene_not_ready", "the scene has no checkpoint yet") from None
        except SceneUnreadable:  # a checkpoint being replaced; the next try reads the new one
            raise ApiError(503, "scene_busy", "the scene's checkpoint is being rewritten; retry",
                           {"Retry-After": "1"}) from None
        with self._lock:
            for k in [k for k in self._items if k[0] == key[0]]:
                del self._items[k]
            self._items[key] = scene
            while len(self._items) > self.size:
                self._items.popitem(last=False)
        return scene


def render_image(scene, req: RenderRequest, max_pixels: int, lock: threading.Lock) -> tuple[bytes, str]:
    """Validate ``req`` against the scene and render it; (encoded image, media type). Raises ApiError 422."""
    from PIL import Image

    stamps = [int(t) for t in np.asarray(scene.timestamps_us).reshape(-1)]
    if not stamps or not stamps[0] <= req.timestamp_us <= stamps[-1]:
        raise ApiError(422, "timestamp_out_of_range", f"timestamp_us must be within the scene's range "
                                                      f"[{stamps[0] if stamps else 0}, {stamps[-1] if stamps else 0}]")
    width, height = req.width or int(scene.width), req.height or int(scene.height)
    if width * height > max_pixels:
        raise ApiError(422, "image_too_large", f"width x height must be at most {max_pixels} pixels")
    if req.intrinsics is not None:
        i = req.intrinsics
        K = np.array([[i.fx, 0, i.cx], [0, i.fy, i.cy], [0, 0, 1]], dtype=np.float64)  # noqa: N806
    else:
        Ks = np.asarray(scene.K, dtype=np.float64).reshape(-1, 3, 3)  # noqa: N806 - [T or 1, 3, 3]
        i = int(np.searchsorted(np.asarray(stamps), req.timestamp_us)) if len(Ks) > 1 else 0
        K0 = Ks[min(i, len(Ks) - 1)]  # noqa: N806 - the frame at (or just after) the timestamp
        sx, sy = width / float(scene.width), height / float(scene.height)
        K = K0.copy()  # noqa: N806
        K[0, 0], K[0, 2] = K0[0, 0] * sx, (K0[0, 2] + 0.5) * sx - 0.5
        K[1, 1], K[1, 2] = K0[1, 1] * sy, (K0[1, 2] + 0.5) * sy - 0.5
    from agg.scene import SceneRequestError

    poses = {int(k): np.asarray(v, dtype=np.float64) for k, v in req.agent_poses.items()}
    try:
        with lock:
            out = scene.render(req.timestamp_us, np.asarray(req.world_from_camera, dtype=np.float64), K, width,
                               height, agent_poses=poses, hidden=set(req.hidden), outputs=("rgb",))
    except SceneRequestError as exc:  # InvalidCamera, InvalidPose, UnknownTrack, OutOfRange
        code = {"OutOfRange": "timestamp_out_of_range", "UnknownTrack": "unknown_track",
                "InvalidPose": "invalid_pose", "InvalidCamera": "invalid_camera"}.get(type(exc).__name__,
                                                                                     "invalid_render_request")
        raise ApiError(422, code, str(exc)) from None
    rgb = out["rgb"]
    rgb = rgb.detach().cpu().numpy() if hasattr(rgb, "detach") else np.asarray(rgb)
    img = Image.fromarray((np.clip(np.nan_to_num(rgb[..., :3]), 0, 1) * 255 + 0.5).astype(np.uint8))
    buf = io.BytesIO()
    if req.format == "jpeg":
        img.save(buf, format="JPEG", quality=req.jpeg_quality)
        return buf.getvalue(), "image/jpeg"
    img.save(buf, format="PNG")
    return buf.getvalue(), "image/png"
