"""Job endpoints: submit (streamed upload), list, get, events (SSE), cancel."""

from __future__ import annotations

import json

import anyio
from fastapi import APIRouter, Depends, Header, Query, Request, Response
from fastapi.concurrency import run_in_threadpool
from sse_starlette.sse import EventSourceResponse

from service import uploads
from service.deps import owned_job, require_tenant
from service.errors import ApiError, error_responses
from service.jobstore import EVENT_ID_RE, TERMINAL, QuotaExceeded, decode_event, events_key, new_id
from service.models import CancelResult, Job, JobCreated, JobDetail, JobList

router = APIRouter(prefix="/v1/jobs", tags=["jobs"])

# Test decodes are CPU-heavy: at most two at a time per API process.
DECODE_LIMITER = anyio.CapacityLimiter(2)


def upload_schema(presets: list[str], max_frames_limit: int) -> dict:
    """The multipart request body, documented by hand (the endpoint parses the stream itself)."""
    props = {
        "video": {"type": "string", "format": "binary", "description": "the video file (MP4/MOV, MKV/WebM, AVI, ...)"},
        "preset": {"type": "string", "enum": presets, "description": "training preset (sets the time limit too)"},
        "intrinsics": {"type": "string", "description": "'fx,fy,cx,cy' in source pixels (default: estimated)",
                       "example": "1000,1000,640,360"},
        "max_frames": {"type": "integer", "minimum": 2, "maximum": max_frames_limit,
                       "description": "keep at most this many frames"},
        "calibration": {"type": "string", "format": "binary",
                        "description": "optional OpenCV calibration file (K, dist, image_size) as YAML/XML/JSON"},
    }
    return {"requestBody": {"required": True, "content": {"multipart/form-data": {
        "schema": {"type": "object", "required": ["video", "preset"], "properties": props},
        "encoding": {"video": {"contentType": "application/octet-stream"}}}}}}


def job_model(job: dict) -> dict:
    return {k: job.get(k) for k in Job.model_fields if k != "input"} | {"input": job.get("input") or None}


@router.post("", status_code=202, response_model=JobCreated, summary="Upload a video and queue a reconstruction",
             responses={202: {"headers": {"Location": {"description": "the job's URL",
                                                       "schema": {"type": "string"}}}},
                        **error_responses(400, 401, 413, 415, 422, 429)})
async def submit_job(request: Request, response: Response, tenant: str = Depends(require_tenant)) -> JobCreated:
    app = request.app.state
    cfg, js, metrics = app.config, app.store, app.metrics
    try:
        await run_in_threadpool(js.check_quota, tenant, cfg.max_active_jobs, cfg.max_jobs_per_day)
    except QuotaExceeded as exc:
        metrics.upload_rejected.labels("quota_exceeded").inc()
        raise ApiError(429, "quota_exceeded", str(exc), {"Retry-After": str(exc.retry_after_s)}) from None
    job_id = new_id("j")
    dest = cfg.uploads_dir / job_id
    await run_in_threadpool(js.begin_upload, tenant)
    try:
        form = await uploads.receive_form(request, dest, cfg.max_upload_bytes)
        preset = form.fields.get("preset", "").strip()
        if preset not in cfg.preset_timeouts:
            raise ApiError(422, "invalid_preset", f"preset must be one of {', '.join(cfg.presets)}")
        options: dict = {}
        if form.fields.get("max_frames", "").strip():
            options["max_frames"] = uploads.parse_max_frames(form.fields["max_frames"], cfg.max_frames_limit)
        if form.fields.get("intrinsics", "").strip():
            options["intrinsics"] = ",".join(repr(v) for v in uploads.parse_intrinsics(form.fields["intrinsics"]))
        video = form.files.get("video")
        if video is None:
            raise ApiError(422, "missing_video", "the multipart body has no 'video' file part")
        if "calibration" in form.files:
            calib = await run_in_threadpool(uploads.check_calibration, form.files["calibration"])
            options["calibration"] = calib.name  # next to the video; no server path in the job record
        info = await anyio.to_thread.run_sync(uploads.inspect_video, video, limiter=DECODE_LIMITER)
        if video.filename:
            info["filename"] = video.filename
        await run_in_threadpool(
            lambda: js.create(job_id, tenant, preset, input_path=str(video.path.resolve()),
                              timeout_s=cfg.preset_timeouts[preset], options=options, input_info=info,
                              max_active=cfg.max_active_jobs, max_per_day=cfg.max_jobs_per_day))
    except ApiError as exc:
        uploads.discard(dest)
        metrics.upload_rejected.labels(exc.code).inc()
        raise
    except QuotaExceeded as exc:
        uploads.discard(dest)
        metrics.upload_rejected.labels("quota_exceeded").inc()
        raise ApiError(429, "quota_exceeded", str(exc), {"Retry-After": str(exc.retry_after_s)}) from None
    except BaseException:
        uploads.discard(dest)
        raise
    finally:
        with anyio.CancelScope(shield=True):
            await run_in_threadpool(js.end_upload, tenant)
    metrics.upload_bytes.inc(video.size)
    metrics.jobs_submitted.labels(preset).inc()
    job = js.get(job_id)
    response.headers["Location"] = f"/v1/jobs/{job_id}"
    return JobCreated(job_id=job_id, scene_id=job["scene_id"], state=job["state"])


@router.get("", response_model=JobList, summary="The caller's jobs, newest first",
            responses=error_responses(401, 422))
def list_jobs(request: Request, tenant: str = Depends(require_tenant), limit: int = Query(50, ge=1, le=500),
              offset: int = Query(0, ge=0, le=100_000)) -> JobList:
    js = request.app.state.store
    return JobList(jobs=[job_model(j) for j in js.list(tenant, limit=limit, offset=offset)], total=js.count(tenant))


@router.get("/{job_id}", response_model=JobDetail, summary="One job: state, progress, scene id, history",
            responses=error_responses(401, 404))
def get_job(job_id: str, request: Request, tenant: str = Depends(require_tenant)) -> JobDetail:
    js = request.app.state.store
    job = owned_job(job_id, tenant, js)
    return JobDetail(**job_model(job), history=js.history(job_id), summary=job.get("summary"))


@router.post("/{job_id}/cancel", status_code=202, response_model=CancelResult, summary="Cancel a job",
             description="A queued job is cancelled at once; a running one is asked to stop (the engine polls "
                         "between iterations) and ends in state 'cancelled'. 409 when it has already finished.",
             responses=error_responses(401, 404, 409))
def cancel_job(job_id: str, request: Request, tenant: str = Depends(require_tenant)) -> CancelResult:
    js = request.app.state.store
    job = owned_job(job_id, tenant, js)
    if job["state"] in TERMINAL or not js.request_cancel(job_id, who=f"tenant {tenant}"):
        raise ApiError(409, "job_finished", f"the job has already finished (state {js.get(job_id)['state']})")
    job = js.get(job_id)
    if job["state"] == "cancelled":  # cancelled while queued: no worker will touch the upload
        uploads.discard(request.app.state.config.uploads_dir / job_id)
    return CancelResult(job_id=job_id, state=job["state"], cancel_requested=True)


@router.get("/{job_id}/events", summary="Progress as Server-Sent Events (resumable with Last-Event-ID)",
            description="Each event has the Redis Stream id as its SSE id, the event type ('state', 'progress', "
                        "'cancel_requested') as its name and a JSON object as data. The stream ends after the final "
                        "state; reconnecting with Last-Event-ID resumes after that event (204 when the job has "
                        "finished and nothing is left). Older events beyond the bounded stream are gone.",
            responses={200: {"content": {"text/event-stream": {"schema": {"type": "string"}}},
                             "description": "an event stream"},
                       204: {"description": "the job has finished and there is nothing after Last-Event-ID"},
                       **error_responses(400, 401, 404)})
async def job_events(job_id: str, request: Request, tenant: str = Depends(require_tenant),
                     last_event_id: str | None = Header(None, alias="Last-Event-ID", max_length=64),
                     after: str | None = Query(None, max_length=64, description="same as Last-Event-ID")):
    js, aredis = request.app.state.store, request.app.state.aredis
    job = await run_in_threadpool(owned_job, job_id, tenant, js)
    cursor = (last_event_id or after or "0-0").strip()
    if not EVENT_ID_RE.match(cursor):
        raise ApiError(400, "invalid_event_id", "Last-Event-ID must be a stream id like '1700000000000-0'")
    key = events_key(job_id)
    if job["state"] in TERMINAL and not await aredis.xread({key: cursor}, count=1):
        return Response(status_code=204)
    block_ms = int(request.app.state.sse_block_ms)

    async def stream():
        nonlocal cursor
        while not await request.is_disconnected():
            res = await aredis.xread({key: cursor}, count=100, block=block_ms)
            if not res:
                state = await aredis.hget(f"agg:job:{job_id}", "state")
                if state is None or state.decode() in TERMINAL:
                    return
                continue
            for eid, fields in res[0][1]:
                cursor = eid.decode()
                ev = decode_event(fields)
                yield {"id": cursor, "event": ev.get("type", "progress"), "data": json.dumps(ev)}
                if ev.get("type") == "state" and ev.get("state") in TERMINAL:
                    return

    return EventSourceResponse(stream(), ping=15, headers={"Cache-Control": "no-store", "X-Accel-Buffering": "no"})
