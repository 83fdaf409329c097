"""agg.v1.SceneService: a tenant's scenes, their time range and cameras, and their scene graphs."""

from __future__ import annotations

import json
from collections.abc import Callable, Iterable

import numpy as np

from agg.scene import Scene, SceneNotReady, metres_per_unit
from worker.grpc_common import Auth, unary
from worker.grpc_convert import intrinsics_to_proto, json_safe, pose_to_proto
from worker.grpc_proto import common_pb2, scene_pb2, scene_pb2_grpc
from worker.grpc_scenes import SceneCache, SceneLookupError, SceneResolver, read_meta

CAMERA_NAME = "camera_0"  # AGG reconstructs monocular clips
NODE_KINDS = {"camera": scene_pb2.NODE_KIND_CAMERA, "background": scene_pb2.NODE_KIND_BACKGROUND,
              "sky": scene_pb2.NODE_KIND_SKY, "rigid": scene_pb2.NODE_KIND_RIGID_AGENT,
              "non-rigid": scene_pb2.NODE_KIND_NON_RIGID_AGENT}


def _time_range(ts) -> common_pb2.TimeRange:
    ts = [int(t) for t in ts]
    return common_pb2.TimeRange(start_us=ts[0], end_us=ts[-1]) if ts else common_pb2.TimeRange()


def _samples(timestamps, poses, valid) -> list[common_pb2.PoseSample]:
    return [common_pb2.PoseSample(timestamp_us=int(t), pose=pose_to_proto(p if v else np.eye(4)), valid=bool(v))
            for t, p, v in zip(timestamps, poses, valid)]


class SceneServicer(scene_pb2_grpc.SceneServiceServicer):
    """``list_scenes(tenant) -> scene ids`` enumerates a tenant's scenes (the job store's jobs); without it the
    resolver's root folder is scanned and filtered by owner."""

    def __init__(self, auth: Auth, resolver: SceneResolver, cache: SceneCache,
                 list_scenes: Callable[[str], Iterable[str]] | None = None):
        self.auth, self.resolver, self.cache, self.list_scenes = auth, resolver, cache, list_scenes

    def _scene_ids(self, tenant: str) -> list[str]:
        if self.list_scenes is not None:
            return list(self.list_scenes(tenant))
        return [sid for sid in self.resolver.candidates() if self.resolver.scene_tenant(sid) == tenant]

    def _meta(self, scene_id: str, tenant: str):
        folder = self.resolver.folder(scene_id, tenant)
        meta = read_meta(folder)
        if meta is None:
            raise SceneNotReady(f"scene {scene_id!r} has not been created yet")
        return folder, meta

    @unary
    def ListScenes(self, request, context):  # noqa: N802
        tenant = self.auth.tenant(context, "read")
        out = []
        for sid in self._scene_ids(tenant):
            try:
                folder = self.resolver.folder(sid, tenant)
            except SceneLookupError:
                continue
            meta = read_meta(folder)
            if meta is None:
                continue
            ts = meta.get("timestamps_us") or []
            out.append(scene_pb2.SceneSummary(scene_id=sid, status=str(meta.get("status", "")),
                                              time_range=_time_range(ts), num_frames=len(ts)))
        return scene_pb2.ListScenesResponse(scenes=out)

    @unary
    def GetScene(self, request, context):  # noqa: N802
        tenant = self.auth.tenant(context, "read")
        folder, meta = self._meta(request.scene_id, tenant)
        ts = [int(t) for t in meta.get("timestamps_us") or []]
        K = np.asarray(meta.get("K") or np.eye(3), dtype=np.float64).reshape(-1, 3, 3)  # noqa: N806
        width, height = int(meta.get("width", 0)), int(meta.get("height", 0))
        camera = scene_pb2.SceneCamera(name=CAMERA_NAME, intrinsics=intrinsics_to_proto(K[0], width, height))
        info = scene_pb2.SceneInfo(scene_id=request.scene_id, status=str(meta.get("status", "")),
                                   time_range=_time_range(ts), timestamps_us=ts,
                                   train_frames=[int(i) for i in meta.get("train_frames") or []],
                                   test_frames=[int(i) for i in meta.get("test_frames") or []],
                                   preset=str(meta.get("preset", "")), scale=metres_per_unit(meta) or 1.0)
        try:
            scene = self.cache.get(folder)
        except SceneNotReady:
            scene = None
        if scene is not None:
            info.ready, info.iteration = True, scene.iteration
            camera.poses.extend(_samples(scene.timestamps_us, scene.world_from_camera(),
                                         np.ones(scene.num_frames, bool)))
        info.cameras.append(camera)
        return info

    @unary
    def GetSceneGraph(self, request, context):  # noqa: N802
        tenant = self.auth.tenant(context, "read")
        folder, _ = self._meta(request.scene_id, tenant)
        scene: Scene = self.cache.get(folder)
        ts = scene.timestamps_us
        nodes = []
        for n in scene.nodes():
            node = scene_pb2.SceneNode(id=n.id, kind=NODE_KINDS[n.kind], class_name=n.kind, track_id=n.track_id,
                                       num_gaussians=n.num_gaussians,
                                       num_valid_frames=int(n.valid.sum()) if n.valid is not None else 0)
            if n.poses is not None and not request.skip_poses:
                node.poses.extend(_samples(ts, n.poses, n.valid))
            nodes.append(node)
        graph = scene_pb2.SceneGraph(scene_id=request.scene_id, timestamps_us=[int(t) for t in ts], nodes=nodes,
                                     iteration=scene.iteration)
        if request.include_json:
            graph.graph_json = json.dumps(json_safe(scene.graph_json()), allow_nan=False)
        return graph
