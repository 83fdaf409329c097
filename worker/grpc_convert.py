"""Conversions between agg.v1 messages and the engine's arrays (poses, cameras, images, jobs).

Validation of poses and cameras is the engine's (``agg.scene``): these functions only unpack the messages and
raise the engine's ``SceneRequestError`` subclasses, which the servers answer with INVALID_ARGUMENT.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass

import cv2
import numpy as np
from google.protobuf import struct_pb2

from agg.scene import (Camera, InvalidCamera, InvalidPose, SceneRequestError, intrinsics_matrix, matrix_to_wxyz,
                       pose_from_quaternion, pose_matrix)
from worker.grpc_proto import common_pb2, job_pb2

PNG, JPEG, RAW = common_pb2.IMAGE_ENCODING_PNG, common_pb2.IMAGE_ENCODING_JPEG, common_pb2.IMAGE_ENCODING_RAW
DEPTH_PNG_SCALE = 256.0  # depth PNG: uint16 = depth * 256 (KITTI's convention)
DEFAULT_JPEG_QUALITY = 90
# worst-case bytes per pixel of each output, by encoding (PNG/JPEG: 8 or 16 bits a sample, plus filter bytes)
BYTES_PER_PIXEL = {"rgb": {RAW: 12, PNG: 3.1, JPEG: 3.1}, "depth": {RAW: 4, PNG: 2.1},
                   "alpha": {RAW: 4, PNG: 1.1}, "instance": {RAW: 4, PNG: 2.1}}
JOB_STATES = {"queued": job_pb2.JOB_STATE_QUEUED, "running": job_pb2.JOB_STATE_RUNNING,
              "succeeded": job_pb2.JOB_STATE_SUCCEEDED, "failed": job_pb2.JOB_STATE_FAILED,
              "cancelled": job_pb2.JOB_STATE_CANCELLED}


class InvalidOutput(SceneRequestError):
    """An OutputSpec the server cannot honour (JPEG depth, an unknown encoding, a bad JPEG quality)."""


# ----------------------------------------------------------------------------------------------- geometry


def pose_from_proto(pose: common_pb2.Pose, what: str) -> np.ndarray:
    """[4, 4] float64 from a Pose (``matrix`` wins when both are set); InvalidPose when neither is set."""
    if pose.HasField("matrix"):
        return pose_matrix(list(pose.matrix.values), what)
    if pose.HasField("rigid"):
        t, q = pose.rigid.translation, pose.rigid.rotation
        return pose_from_quaternion([t.x, t.y, t.z], [q.w, q.x, q.y, q.z], what)
    raise InvalidPose(f"{what} is required (set rigid or matrix)")


def pose_to_proto(m: np.ndarray) -> common_pb2.Pose:
    """A Pose with both representations of the rigid [4, 4] ``m``."""
    m = np.asarray(m, dtype=np.float64)
    q = matrix_to_wxyz(m[:3, :3])
    return common_pb2.Pose(
        rigid=common_pb2.RigidTransform(translation=common_pb2.Vec3(x=m[0, 3], y=m[1, 3], z=m[2, 3]),
                                        rotation=common_pb2.Quaternion(w=q[0], x=q[1], y=q[2], z=q[3])),
        matrix=common_pb2.Matrix4x4(values=m.reshape(-1).tolist()))


def intrinsics_to_proto(K: np.ndarray, width: int, height: int) -> common_pb2.PinholeIntrinsics:  # noqa: N803
    return common_pb2.PinholeIntrinsics(fx=K[0, 0], fy=K[1, 1], cx=K[0, 2], cy=K[1, 2], width=width, height=height)


def camera_from_proto(cam: common_pb2.CameraSpec, index: int) -> Camera:
    """A validated engine ``Camera`` from a CameraSpec (``index`` names it in error messages)."""
    label = f"cameras[{index}]" + (f" ({cam.name})" if cam.name else "")
    if not cam.HasField("intrinsics"):
        raise InvalidCamera(f"{label}: intrinsics are required")
    i = cam.intrinsics
    try:
        K = intrinsics_matrix(i.fx, i.fy, i.cx, i.cy, i.width, i.height)  # noqa: N806
    except InvalidCamera as exc:
        raise InvalidCamera(f"{label}: {exc}") from None
    return Camera(pose_from_proto(cam.world_from_camera, f"{label}.world_from_camera"), K, int(i.width),
                  int(i.height))


def overrides_from_proto(overrides) -> tuple[dict[int, np.ndarray], set[int]]:
    """({track id: world_from_box}, {hidden track ids}) from AgentOverride messages (a later entry wins)."""
    poses: dict[int, np.ndarray] = {}
    hidden: set[int] = set()
    for o in overrides:
        tid, has_pose = int(o.track_id), o.HasField("world_from_box")
        if has_pose == bool(o.hide):
            raise SceneRequestError(f"agent override of track {tid}: set exactly one of world_from_box and hide")
        if o.hide:
            hidden.add(tid)
            poses.pop(tid, None)
        else:
            poses[tid] = pose_from_proto(o.world_from_box, f"world_from_box of track {tid}")
            hidden.discard(tid)
    return poses, hidden


# ----------------------------------------------------------------------------------------------- images


@dataclass(frozen=True)
class OutputPlan:
    """What to render and how to encode it (a validated OutputSpec)."""

    outputs: tuple[str, ...]  # "rgb" first, then the requested auxiliary outputs
    rgb_encoding: int
    aux_encoding: int
    jpeg_quality: int

    @classmethod
    def from_proto(cls, spec) -> "OutputPlan":
        """From an agg.v1.OutputSpec; InvalidOutput for what cannot be honoured."""
        rgb = spec.rgb_encoding or PNG
        aux = spec.aux_encoding or PNG
        if rgb not in (PNG, JPEG, RAW):
            raise InvalidOutput(f"unknown rgb_encoding {rgb}")
        if aux not in (PNG, RAW):
            raise InvalidOutput("aux_encoding must be PNG or RAW (depth, alpha and instance are not JPEG-encoded)")
        q = spec.jpeg_quality or DEFAULT_JPEG_QUALITY
        if not 1 <= q <= 100:
            raise InvalidOutput(f"jpeg_quality must be in [1, 100], got {q}")
        aux_names = tuple(n for n in ("depth", "alpha", "instance") if getattr(spec, n))
        return cls(("rgb", *aux_names), rgb, aux, q)

    def bytes_per_pixel(self) -> float:
        return sum(BYTES_PER_PIXEL[n][self.rgb_encoding if n == "rgb" else self.aux_encoding] for n in self.outputs)


def encode_image(name: str, array: np.ndarray, encoding: int, jpeg_quality: int = DEFAULT_JPEG_QUALITY
                 ) -> common_pb2.Image:
    """An Image message of one output (rgb [H, W, 3] float, depth / alpha [H, W] float, instance [H, W] int)."""
    h, w = array.shape[:2]
    scale = 1.0
    if encoding == RAW:
        if name == "instance":
            data, dtype = np.ascontiguousarray(array, dtype="<i4"), common_pb2.DATA_TYPE_INT32
        else:
            data, dtype = np.ascontiguousarray(array, dtype="<f4"), common_pb2.DATA_TYPE_FLOAT32
        return common_pb2.Image(encoding=RAW, width=w, height=h, channels=3 if name == "rgb" else 1, dtype=dtype,
                                scale=1.0, data=data.tobytes())
    if name == "rgb":
        img = cv2.cvtColor(np.round(np.clip(array, 0.0, 1.0) * 255).astype(np.uint8), cv2.COLOR_RGB2BGR)
        dtype, channels = common_pb2.DATA_TYPE_UINT8, 3
    elif name == "depth":
        scale = DEPTH_PNG_SCALE
        v = np.round(np.nan_to_num(array, nan=0.0, posinf=0.0) * scale)
        img = np.where((v > 0) & (v <= 65535), v, 0).astype(np.uint16)
        dtype, channels = common_pb2.DATA_TYPE_UINT16, 1
    elif name == "alpha":
        scale = 255.0
        img = np.round(np.clip(array, 0.0, 1.0) * scale).astype(np.uint8)
        dtype, channels = common_pb2.DATA_TYPE_UINT8, 1
    elif name == "instance":
        if array.size and (array.max() > 65535 or array.min() < 0):
            raise InvalidOutput("track ids above 65535 do not fit a 16-bit PNG: ask for aux_encoding RAW")
        img, dtype, channels = array.astype(np.uint16), common_pb2.DATA_TYPE_UINT16, 1
    else:
        raise InvalidOutput(f"unknown output {name!r}")
    if encoding == JPEG:
        ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
    else:
        ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise RuntimeError(f"could not encode the {name} image")
    return common_pb2.Image(encoding=encoding, width=w, height=h, channels=channels, dtype=dtype, scale=scale,
                            data=buf.tobytes())


def decode_image(image: common_pb2.Image) -> np.ndarray:
    """The array of an Image message as stored (RGB order; PNG/JPEG decoded, RAW reshaped); for clients."""
    if image.encoding == RAW:
        dtype = "<i4" if image.dtype == common_pb2.DATA_TYPE_INT32 else "<f4"
        a = np.frombuffer(image.data, dtype=dtype)
        shape = (image.height, image.width, image.channels) if image.channels > 1 else (image.height, image.width)
        return a.reshape(shape)
    a = cv2.imdecode(np.frombuffer(image.data, np.uint8), cv2.IMREAD_UNCHANGED)
    return cv2.cvtColor(a, cv2.COLOR_BGR2RGB) if a.ndim == 3 else a


# ----------------------------------------------------------------------------------------------- jobs


def json_safe(obj):
    """A JSON-compatible copy (non-finite floats -> None, unknown objects -> str)."""
    if isinstance(obj, dict):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, (str, int, float, bool)) or obj is None:
        return obj
    if hasattr(obj, "tolist"):
        return json_safe(obj.tolist())
    return str(obj)


def to_struct(d: dict) -> struct_pb2.Struct:
    s = struct_pb2.Struct()
    s.update(json.loads(json.dumps(json_safe(d))))
    return s


def job_to_proto(job: dict, private: tuple[str, ...] = ("input_path", "tenant", "worker")) -> job_pb2.Job:
    """A Job message from a job-store record; ``private`` fields (server paths, ...) are left out of ``fields``."""
    created = job.get("created_at")
    created_us = int(round(float(created) * 1e6)) if isinstance(created, (int, float)) and created == created else 0
    return job_pb2.Job(job_id=str(job.get("job_id") or ""),
                       state=JOB_STATES.get(str(job.get("state")), job_pb2.JOB_STATE_UNSPECIFIED),
                       progress=float(job.get("progress") or 0.0), scene_id=str(job.get("scene_id") or ""),
                       error=str(job.get("error") or ""), preset=str(job.get("preset") or ""),
                       created_at_us=created_us,
                       fields=to_struct({k: v for k, v in job.items() if k not in private}))
