"""A small Python client of the agg.v1 services (the README demo, the load benchmark, scripts).

    with AggClient("127.0.0.1:50051", api_key) as c:
        info = c.scene(scene_id)
        cam = c.camera_of(info, frame=3)                      # the clip's own camera at frame 3
        images = c.render(scene_id, info.timestamps_us[3], [cam], depth=True)
        cv2.imwrite("view.png", cv2.cvtColor(images[0]["rgb"], cv2.COLOR_RGB2BGR))

Arrays come back decoded (``worker.grpc_convert.decode_image``): rgb uint8 [H, W, 3] (PNG/JPEG) or float32 (RAW),
depth float32 in scene units, alpha float32 in [0, 1], instance int32 track ids. Errors raise ``grpc.RpcError``
with the status codes of docs/API_GRPC.md.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence

import grpc
import numpy as np

from worker.grpc_convert import decode_image, intrinsics_to_proto, pose_to_proto
from worker.grpc_proto import common_pb2, job_pb2, job_pb2_grpc, render_pb2, render_pb2_grpc, scene_pb2, scene_pb2_grpc

ENCODINGS = {"png": common_pb2.IMAGE_ENCODING_PNG, "jpeg": common_pb2.IMAGE_ENCODING_JPEG,
             "raw": common_pb2.IMAGE_ENCODING_RAW}


def camera(world_from_camera, K, width: int, height: int, name: str = "") -> common_pb2.CameraSpec:  # noqa: N803
    """A CameraSpec from a [4, 4] camera-to-world pose (OpenCV axes) and a [3, 3] K."""
    K = np.asarray(K, dtype=np.float64)  # noqa: N806
    return common_pb2.CameraSpec(name=name, intrinsics=intrinsics_to_proto(K, int(width), int(height)),
                                 world_from_camera=pose_to_proto(np.asarray(world_from_camera, dtype=np.float64)))


def decoded(image: render_pb2.CameraImage) -> dict[str, np.ndarray]:
    """{"rgb", and "depth" / "alpha" / "instance" when present} as physical values (depth / alpha unscaled)."""
    out = {"rgb": decode_image(image.rgb)}
    for name in ("depth", "alpha", "instance"):
        if image.HasField(name):
            msg = getattr(image, name)
            a = decode_image(msg)
            out[name] = a.astype(np.int32) if name == "instance" else a.astype(np.float32) / (msg.scale or 1.0)
    return out


class AggClient:
    """Stubs of the three services over one channel, with the API key sent on every call."""

    def __init__(self, address: str, api_key: str, *, max_message_mb: int = 64, timeout_s: float = 120.0):
        limit = int(max_message_mb) << 20
        self.channel = grpc.insecure_channel(address, options=[("grpc.max_receive_message_length", limit),
                                                               ("grpc.max_send_message_length", limit)])
        self.metadata = (("authorization", f"Bearer {api_key}"),)
        self.timeout_s = timeout_s
        self.renders = render_pb2_grpc.RenderServiceStub(self.channel)
        self.scenes = scene_pb2_grpc.SceneServiceStub(self.channel)
        self.jobs = job_pb2_grpc.JobServiceStub(self.channel)

    def __enter__(self) -> "AggClient":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self.channel.close()

    def _call(self, method, request):
        return method(request, metadata=self.metadata, timeout=self.timeout_s)

    # ----------------------------------------------------------------------------------------------- scenes
    def scene(self, scene_id: str) -> scene_pb2.SceneInfo:
        return self._call(self.scenes.GetScene, scene_pb2.GetSceneRequest(scene_id=scene_id))

    def scene_graph(self, scene_id: str, poses: bool = True) -> scene_pb2.SceneGraph:
        return self._call(self.scenes.GetSceneGraph, scene_pb2.GetSceneGraphRequest(scene_id=scene_id,
                                                                                    skip_poses=not poses))

    @staticmethod
    def camera_of(info: scene_pb2.SceneInfo, frame: int, name: str = "camera_0") -> common_pb2.CameraSpec:
        """The clip's refined camera at ``frame`` (GetScene's poses and intrinsics) as a CameraSpec."""
        cam = info.cameras[0]
        return common_pb2.CameraSpec(name=name, intrinsics=cam.intrinsics, world_from_camera=cam.poses[frame].pose)

    # ----------------------------------------------------------------------------------------------- renders
    def render(self, scene_id: str, timestamp_us: int, cameras: Sequence[common_pb2.CameraSpec], *,
               hide: Sequence[int] = (), move: Mapping[int, np.ndarray] | None = None, depth: bool = False,
               alpha: bool = False, instance: bool = False, encoding: str = "png", jpeg_quality: int = 0,
               raw_aux: bool = True) -> list[dict[str, np.ndarray]]:
        """Decoded images of every camera at ``timestamp_us``; ``hide`` / ``move`` override agents by track id."""
        overrides = [render_pb2.AgentOverride(track_id=int(t), hide=True) for t in hide]
        overrides += [render_pb2.AgentOverride(track_id=int(t), world_from_box=pose_to_proto(p))
                      for t, p in (move or {}).items()]
        output = render_pb2.OutputSpec(rgb_encoding=ENCODINGS[encoding], jpeg_quality=jpeg_quality, depth=depth,
                                       alpha=alpha, instance=instance,
                                       aux_encoding=ENCODINGS["raw" if raw_aux else "png"])
        reply = self._call(self.renders.Render, render_pb2.RenderRequest(
            scene_id=scene_id, timestamp_us=int(timestamp_us), cameras=list(cameras), agent_overrides=overrides,
            output=output))
        return [decoded(img) for img in reply.images]

    # ----------------------------------------------------------------------------------------------- jobs
    def job(self, job_id: str) -> job_pb2.Job:
        return self._call(self.jobs.GetJob, job_pb2.GetJobRequest(job_id=job_id))

    def watch(self, job_id: str, after_event_id: str = "") -> Iterator[job_pb2.JobEvent]:
        """Events until the job ends (no timeout: a long job streams for as long as it trains)."""
        return self.jobs.WatchJob(job_pb2.WatchJobRequest(job_id=job_id, after_event_id=after_event_id,
                                                          follow=True), metadata=self.metadata)
