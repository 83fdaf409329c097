"""Pydantic models of the HTTP API (request bodies, responses, errors): the OpenAPI schema is built from these.

Conventions (docs/CONVENTIONS.md): metres, OpenCV camera (x right, y down, z forward), ``world_from_camera``
4x4 row-major camera-to-world matrices, timestamps in integer microseconds, intrinsics in pixels.
"""

from __future__ import annotations

import math
from enum import Enum
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

JobState = Literal["queued", "running", "succeeded", "failed", "cancelled"]
MAX_SIDE = 8192


class Error(BaseModel):
    """Every 4xx/5xx body: a stable machine-readable ``code`` and a human message."""

    code: str = Field(description="stable error code, e.g. unauthorized, job_not_found, not_a_video, "
                                  "quota_exceeded")
    message: str
    details: list[dict] | None = Field(default=None,
                                       description="per-field problems of a request that failed validation")


class VideoInfo(BaseModel):
    container: str | None = None
    frames: int | None = None
    width: int | None = None
    height: int | None = None
    fps: float | None = None
    bytes: int | None = None


class HistoryEntry(BaseModel):
    """One state transition of a job (the worker that made it, the attempt it belonged to, why)."""

    state: JobState
    at: float = Field(description="Unix time in seconds (the Redis server's clock)")
    worker: str | None = None
    attempt: int | None = None
    reason: str | None = None


class Job(BaseModel):
    job_id: str
    state: JobState
    progress: float = Field(ge=0.0, le=1.0, description="0..1; priors fill the first 15 %, training the rest")
    scene_id: str | None = Field(description="the scene this job builds (renders come from its latest checkpoint "
                                             "while it trains; complete once state is succeeded)")
    preset: str | None = None
    error: str | None = None
    created_at: float | None = None
    updated_at: float | None = None
    started_at: float | None = None
    finished_at: float | None = None
    attempt: int = Field(1, description="1 + the number of times the job was requeued after losing its worker")
    phase: str | None = None
    iteration: int | None = None
    total: int | None = None
    cancel_requested: bool = False
    input: VideoInfo | None = None


class JobDetail(Job):
    history: list[HistoryEntry] = Field(default_factory=list)
    summary: dict | None = Field(None, description="the engine's summary once succeeded (iterations, timings, "
                                                   "node counts, NVS metrics)")


class JobCreated(BaseModel):
    job_id: str
    scene_id: str
    state: JobState = "queued"


class JobList(BaseModel):
    jobs: list[Job]
    total: int = Field(description="all jobs of the caller still on record")


class CancelResult(BaseModel):
    job_id: str
    state: JobState
    cancel_requested: bool


class SceneStatus(str, Enum):
    pending = "pending"
    training = "training"
    ready = "ready"
    failed = "failed"
    cancelled = "cancelled"


class SceneInfo(BaseModel):
    scene_id: str
    job_id: str | None = None
    status: SceneStatus
    preset: str | None = None
    num_frames: int | None = None
    width: int | None = None
    height: int | None = None
    timestamps_us: list[int] | None = Field(None, description="microseconds of each training frame")
    intrinsics: list[list[float]] | None = Field(None, description="K [3, 3] of the first frame, pixels")
    artifacts: list[str] = Field(default_factory=list, description="artifact names available now")
    renderable: bool = Field(False, description="a checkpoint or the final model exists")


class ArtifactName(str, Enum):
    ply = "scene.ply"
    graph = "graph.json"
    preview = "preview.mp4"
    metrics = "metrics.json"


ARTIFACT_MEDIA = {"scene.ply": "application/octet-stream", "graph.json": "application/json",
                  "preview.mp4": "video/mp4", "metrics.json": "application/json"}


def _check_pose(m: list[list[float]], what: str) -> list[list[float]]:
    if len(m) != 4 or any(len(r) != 4 for r in m):
        raise ValueError(f"{what} must be 4x4")
    if not all(math.isfinite(v) for r in m for v in r):
        raise ValueError(f"{what} has a NaN or infinite entry")
    if max(abs(a - b) for a, b in zip(m[3], (0.0, 0.0, 0.0, 1.0), strict=True)) > 1e-6:
        raise ValueError(f"{what}: the last row must be [0, 0, 0, 1]")
    r = [row[:3] for row in m[:3]]
    for i in range(3):
        for j in range(3):
            dot = sum(r[k][i] * r[k][j] for k in range(3))
            if abs(dot - (1.0 if i == j else 0.0)) > 1e-3:
                raise ValueError(f"{what}: the rotation part is not orthonormal")
    det = (r[0][0] * (r[1][1] * r[2][2] - r[1][2] * r[2][1]) - r[0][1] * (r[1][0] * r[2][2] - r[1][2] * r[2][0])
           + r[0][2] * (r[1][0] * r[2][1] - r[1][1] * r[2][0]))
    if det < 0:
        raise ValueError(f"{what}: the rotation part is a reflection (det < 0)")
    return m


class Intrinsics(BaseModel):
    """Pinhole intrinsics in pixels at the requested width x height (OpenCV pixel centres)."""

    model_config = ConfigDict(allow_inf_nan=False)
    fx: float = Field(gt=0, le=1e6)
    fy: float = Field(gt=0, le=1e6)
    cx: float = Field(ge=-1e6, le=1e6)
    cy: float = Field(ge=-1e6, le=1e6)


Matrix4 = list[list[float]]


class RenderRequest(BaseModel):
    """One view of a scene at one time; agents can be moved or hidden for this request only."""

    model_config = ConfigDict(allow_inf_nan=False, extra="forbid")
    timestamp_us: int = Field(ge=0, le=10**13, description="microseconds, within the scene's time range")
    world_from_camera: Matrix4 = Field(description="camera-to-world 4x4, OpenCV camera axes")
    intrinsics: Intrinsics | None = Field(None, description="default: the scene's K, scaled to width x height")
    width: int | None = Field(None, ge=1, le=MAX_SIDE, description="default: the scene's width")
    height: int | None = Field(None, ge=1, le=MAX_SIDE, description="default: the scene's height")
    agent_poses: dict[str, Matrix4] = Field(default_factory=dict,
                                            description="track id -> world_from_box 4x4 replacing the agent's pose")
    hidden: list[int] = Field(default_factory=list, max_length=10000, description="track ids not drawn")
    format: Literal["png", "jpeg"] = "png"
    jpeg_quality: int = Field(90, ge=1, le=100)

    @field_validator("world_from_camera")
    @classmethod
    def _pose(cls, v):
        return _check_pose(v, "world_from_camera")

    @field_validator("agent_poses")
    @classmethod
    def _agents(cls, v):
        if len(v) > 10000:
            raise ValueError("too many agent poses")
        for key, m in v.items():
            if not key.lstrip("-").isdigit() or len(key) > 18:
                raise ValueError(f"agent_poses key {key!r} is not an integer track id")
            _check_pose(m, f"agent_poses[{key}]")
        return v


class Health(BaseModel):
    status: Literal["ok"] = "ok"


class Ready(BaseModel):
    status: Literal["ready", "unavailable"]
    redis: bool
    queue_depth: int | None = None
