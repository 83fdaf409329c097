"""agg.v1.RenderService: stateless renders of a scene at one timestamp (``Render``) or along a trajectory
(``RenderTrajectory``), several cameras per request, agents moved or hidden per request.

Checks run from cheap to costly, so a bad request costs no render: key (UNAUTHENTICATED / PERMISSION_DENIED),
scene ownership (NOT_FOUND), request shape and limits (INVALID_ARGUMENT / RESOURCE_EXHAUSTED), the scene's
checkpoint (FAILED_PRECONDITION), then time and track ids against the scene (OUT_OF_RANGE / INVALID_ARGUMENT).
"""

from __future__ import annotations

from dataclasses import dataclass

from agg.scene import Camera, Scene, SceneRequestError
from worker.grpc_common import Auth, Code, RpcFailure, streaming, unary
from worker.grpc_convert import OutputPlan, camera_from_proto, encode_image, overrides_from_proto
from worker.grpc_proto import render_pb2, render_pb2_grpc
from worker.grpc_scenes import SceneCache, SceneResolver


@dataclass(frozen=True)
class RenderLimits:
    """Per-request limits (RESOURCE_EXHAUSTED beyond them); the message limit is the server's (64 MiB)."""

    max_cameras: int = 16  # cameras per Render request or trajectory step
    max_pixels: int = 16_777_216  # width * height summed over the cameras of one request / step (e.g. 8 x 1080p)
    max_steps: int = 10_000  # steps of one RenderTrajectory call
    max_message_bytes: int = 64 << 20


@dataclass
class _Step:
    timestamp_us: int
    cameras: list[Camera]
    names: list[str]
    agent_poses: dict
    hidden: set


class RenderServicer(render_pb2_grpc.RenderServiceServicer):
    def __init__(self, auth: Auth, resolver: SceneResolver, cache: SceneCache, limits: RenderLimits = RenderLimits()):
        self.auth, self.resolver, self.cache, self.limits = auth, resolver, cache, limits

    # ----------------------------------------------------------------------------------------------- checks

    def _step(self, timestamp_us: int, cameras, overrides, plan: OutputPlan, base=None, where: str = "") -> _Step:
        """Validate one request / step without touching the scene."""
        lim = self.limits
        if not cameras:
            raise SceneRequestError(f"{where}at least one camera is required")
        if len(cameras) > lim.max_cameras:
            raise RpcFailure(Code.RESOURCE_EXHAUSTED, f"{where}{len(cameras)} cameras; at most {lim.max_cameras} "
                                                      "per request")
        cams = [camera_from_proto(c, i) for i, c in enumerate(cameras)]
        pixels = sum(c.width * c.height for c in cams)
        if pixels > lim.max_pixels:
            raise RpcFailure(Code.RESOURCE_EXHAUSTED, f"{where}{pixels} pixels over all cameras; at most "
                                                      f"{lim.max_pixels} per request")
        size = pixels * plan.bytes_per_pixel() + 1024 * len(cams)
        if size > lim.max_message_bytes:
            raise RpcFailure(Code.RESOURCE_EXHAUSTED,
                             f"{where}the answer would take about {size / 2**20:.1f} MiB; the message limit is "
                             f"{lim.max_message_bytes / 2**20:.0f} MiB (use fewer or smaller cameras, or PNG/JPEG)")
        poses, hidden = dict(base[0]) if base else {}, set(base[1]) if base else set()
        p, h = overrides_from_proto(overrides)
        for tid in h:
            poses.pop(tid, None)
        hidden = (hidden - set(p)) | h
        poses.update(p)
        return _Step(int(timestamp_us), cams, [c.name for c in cameras], poses, hidden)

    def _check_against(self, scene: Scene, step: _Step, where: str = "") -> None:
        """Time and track ids against the scene (OUT_OF_RANGE / INVALID_ARGUMENT) before anything renders."""
        scene.frame_at(step.timestamp_us)
        known = set(scene.track_ids)
        for tid in [*step.agent_poses, *step.hidden]:
            if tid not in known:
                raise SceneRequestError(f"{where}unknown track id {tid} (the scene's agents: {sorted(known)})")

    def _render(self, scene: Scene, scene_id: str, step: _Step, plan: OutputPlan, index: int = 0):
        results = scene.render_cameras(step.timestamp_us, step.cameras, step.agent_poses, step.hidden, plan.outputs)
        images = []
        for name, res in zip(step.names, results):
            img = render_pb2.CameraImage(camera_name=name)
            for out in plan.outputs:
                enc = plan.rgb_encoding if out == "rgb" else plan.aux_encoding
                getattr(img, out).CopyFrom(encode_image(out, res[out], enc, plan.jpeg_quality))
            images.append(img)
        reply = render_pb2.RenderResponse(scene_id=scene_id, timestamp_us=step.timestamp_us,
                                          frame=scene.frame_at(step.timestamp_us), images=images,
                                          iteration=scene.iteration, source=scene.source, step=index)
        if reply.ByteSize() > self.limits.max_message_bytes:
            raise RpcFailure(Code.RESOURCE_EXHAUSTED, "the encoded images exceed the message limit")
        return reply

    # ----------------------------------------------------------------------------------------------- RPCs

    @unary
    def Render(self, request, context):  # noqa: N802
        tenant = self.auth.tenant(context, "render")
        folder = self.resolver.folder(request.scene_id, tenant)
        plan = OutputPlan.from_proto(request.output)
        step = self._step(request.timestamp_us, request.cameras, request.agent_overrides, plan)
        scene = self.cache.get(folder)
        self._check_against(scene, step)
        return self._render(scene, request.scene_id, step, plan)

    @streaming
    def RenderTrajectory(self, request, context):  # noqa: N802
        tenant = self.auth.tenant(context, "render")
        folder = self.resolver.folder(request.scene_id, tenant)
        plan = OutputPlan.from_proto(request.output)
        n = len(request.steps)
        if n == 0:
            raise SceneRequestError("at least one step is required")
        if n > self.limits.max_steps:
            raise RpcFailure(Code.RESOURCE_EXHAUSTED, f"{n} steps; at most {self.limits.max_steps} per call")
        base = overrides_from_proto(request.agent_overrides)
        steps = [self._step(s.timestamp_us, s.cameras, s.agent_overrides, plan, base, f"steps[{i}]: ")
                 for i, s in enumerate(request.steps)]
        scene = self.cache.get(folder)  # one version of the scene for the whole rollout
        for i, step in enumerate(steps):
            self._check_against(scene, step, f"steps[{i}]: ")
        for i, step in enumerate(steps):
            if not context.is_active():
                return
            yield self._render(scene, request.scene_id, step, plan, i)
