"""Request dependencies: the caller's tenant (Bearer API key), the job store, and id checks that answer 404."""

from __future__ import annotations

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from service.errors import ApiError
from service.jobstore import JOB_ID_RE, SCENE_ID_RE, JobStore

bearer = HTTPBearer(auto_error=False, description="Authorization: Bearer KEY (keys are configured per tenant)")


def require_tenant(request: Request, creds: HTTPAuthorizationCredentials | None = Depends(bearer)) -> str:
    """The tenant of the presented key; 401 when the key is missing or unknown."""
    challenge = {"WWW-Authenticate": "Bearer"}
    if creds is None or creds.scheme.lower() != "bearer" or not creds.credentials:
        raise ApiError(401, "unauthorized", "missing API key: send 'Authorization: Bearer KEY'", challenge)
    tenant = request.app.state.keystore.tenant_for(creds.credentials)
    if tenant is None:
        raise ApiError(401, "unauthorized", "unknown API key", challenge)
    return tenant


def store(request: Request) -> JobStore:
    return request.app.state.store


def owned_job(job_id: str, tenant: str, js: JobStore) -> dict:
    """The job if it exists and belongs to ``tenant``; otherwise 404 (another tenant's id looks unknown)."""
    job = js.get(job_id) if JOB_ID_RE.match(job_id) else None
    if job is None or job["tenant"] != tenant:
        raise ApiError(404, "job_not_found", f"no job {job_id!r}")
    return job


def owned_scene(scene_id: str, tenant: str, js: JobStore) -> None:
    if not SCENE_ID_RE.match(scene_id) or js.scene_tenant(scene_id) != tenant:
        raise ApiError(404, "scene_not_found", f"no scene {scene_id!r}")
