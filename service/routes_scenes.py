"""Scene endpoints: metadata, scene graph, artifacts (whitelisted names), renders."""

from __future__ import annotations

import json

from fastapi import APIRouter, Depends, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import FileResponse, JSONResponse, Response

from service.deps import owned_scene, require_tenant
from service.errors import ApiError, error_responses
from service.models import ARTIFACT_MEDIA, ArtifactName, RenderRequest, SceneInfo
from service.scenes import render_image, scene_info

router = APIRouter(prefix="/v1/scenes", tags=["scenes"])


def _scene(request: Request, scene_id: str, tenant: str):
    js = request.app.state.store
    owned_scene(scene_id, tenant, js)
    job_id = js.scene_job(scene_id)
    return js.scene_dir(scene_id), (js.get(job_id) if job_id else None)


@router.get("/{scene_id}", response_model=SceneInfo, summary="Scene metadata and the artifacts available now",
            responses=error_responses(401, 404))
def get_scene(scene_id: str, request: Request, tenant: str = Depends(require_tenant)) -> SceneInfo:
    scene_dir, job = _scene(request, scene_id, tenant)
    return scene_info(scene_id, scene_dir, job)


@router.get("/{scene_id}/graph", summary="The scene graph: nodes, classes, per-frame poses and validity",
            responses={200: {"content": {"application/json": {"schema": {"type": "object"}}},
                             "description": "the scene graph as JSON (graph.json)"},
                       **error_responses(401, 404, 409, 503)})
def get_graph(scene_id: str, request: Request, tenant: str = Depends(require_tenant)):
    scene_dir, _ = _scene(request, scene_id, tenant)
    f = scene_dir / "graph.json"
    if f.is_file():
        try:
            return JSONResponse(json.loads(f.read_text()))
        except ValueError:
            pass  # being written: fall back to the live scene
    scene = request.app.state.scene_cache.get(scene_dir)
    return JSONResponse(scene.graph_json())


@router.get("/{scene_id}/artifacts/{name}", summary="Download an artifact",
            description="scene.ply (Gaussians), graph.json, preview.mp4 (training frames re-rendered), metrics.json. "
                        "404 until the job has written it.",
            responses={200: {"content": {m: {"schema": {"type": "string", "format": "binary"}}
                                         for m in sorted(set(ARTIFACT_MEDIA.values()))},
                             "description": "the file"}, **error_responses(401, 404, 422)})
def get_artifact(scene_id: str, name: ArtifactName, request: Request, tenant: str = Depends(require_tenant)):
    scene_dir, _ = _scene(request, scene_id, tenant)
    f = scene_dir / name.value  # name is one of the enum's values: no client-controlled path
    if not f.is_file():
        raise ApiError(404, "artifact_not_found", f"{name.value} has not been written (yet)")
    return FileResponse(f, media_type=ARTIFACT_MEDIA[name.value], filename=f"{scene_id}-{name.value}")


@router.post("/{scene_id}/render", summary="Render one view (PNG or JPEG)",
             description="Renders at ``timestamp_us`` (within the scene's range) through ``world_from_camera``; the "
                         "latest checkpoint answers while the job trains (409 before the first one).",
             responses={200: {"content": {"image/png": {"schema": {"type": "string", "format": "binary"}},
                                          "image/jpeg": {"schema": {"type": "string", "format": "binary"}}},
                              "description": "the encoded image"},
                        **error_responses(401, 404, 409, 422, 503)})
async def render(scene_id: str, body: RenderRequest, request: Request, tenant: str = Depends(require_tenant)):
    state = request.app.state
    scene_dir, _ = await run_in_threadpool(_scene, request, scene_id, tenant)
    try:
        scene = await run_in_threadpool(state.scene_cache.get, scene_dir)
        data, media = await run_in_threadpool(render_image, scene, body, state.config.render_max_pixels,
                                              state.scene_cache.render_lock)
    except ApiError as exc:
        state.metrics.renders.labels(str(exc.status)).inc()
        raise
    state.metrics.renders.labels("200").inc()
    return Response(content=data, media_type=media)
