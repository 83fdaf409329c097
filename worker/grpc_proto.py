"""The generated agg.v1 modules, (re)generated on first import when missing or stale (``worker.grpc_codegen``).

Clients and the server import them from here::

    from worker.grpc_proto import common_pb2, render_pb2, render_pb2_grpc
"""

from __future__ import annotations

from worker.grpc_codegen import ensure_generated

ensure_generated()

from worker._gen import (common_pb2, job_pb2, job_pb2_grpc, render_pb2, render_pb2_grpc,  # noqa: E402
                         scene_pb2, scene_pb2_grpc)

SERVICE_NAMES = tuple(m.DESCRIPTOR.services_by_name[s].full_name
                      for m, s in ((job_pb2, "JobService"), (scene_pb2, "SceneService"),
                                   (render_pb2, "RenderService")))

__all__ = ["SERVICE_NAMES", "common_pb2", "job_pb2", "job_pb2_grpc", "render_pb2", "render_pb2_grpc", "scene_pb2",
           "scene_pb2_grpc"]
