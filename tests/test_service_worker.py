"""Real workers (``python -m worker.cli`` processes running RQ) with the live API: upload -> SSE -> done, cancel,
per-preset time limit. The engine is the contract's stand-in (tests/service_engine.py)."""

from __future__ import annotations

import json

import pytest

from service.jobstore import JobStore
from tests.redis_server import rclient, redis_proc  # noqa: F401 - fixtures
from tests.service_helpers import LiveServer, service_config, start_worker, stop_worker, upload, wait_for

pytestmark = pytest.mark.timeout(60)


@pytest.fixture(scope="module")
def server(redis_proc, tmp_path_factory):  # noqa: F811
    cfg = service_config(tmp_path_factory.mktemp("worker"), redis_proc.url,
                         preset_timeouts={"tiny": 120, "fast": 600, "short": 1})
    srv = LiveServer(cfg, sse_block_ms=200).start()
    yield srv
    srv.stop()


@pytest.fixture
def store(server, rclient):  # noqa: F811
    return JobStore.from_config(rclient, server.config)


def sse_events(client, path: str, headers=None) -> list[dict]:
    out = []
    with client.stream("GET", path, headers=headers or {}) as r:
        assert r.status_code == 200
        cur = {}
        for line in r.iter_lines():
            if not line:
                if "data" in cur:
                    out.append({"id": cur.get("id"), "event": cur.get("event"), **json.loads(cur["data"])})
                cur = {}
            elif not line.startswith(":"):
                k, _, v = line.partition(":")
                cur[k] = v.strip()
    return out


def test_upload_progress_done(server, store):
    worker = start_worker(server.config, "w-e2e", iters=24, sleep=0.05)
    try:
        with server.client("alice") as c:
            created = upload(c, max_frames="12", intrinsics="1000,1000,640,360").json()
            jid, scene = created["job_id"], created["scene_id"]
            events = sse_events(c, f"/v1/jobs/{jid}/events")
            states = [e["state"] for e in events if e["event"] == "state"]
            assert states == ["queued", "running", "succeeded"]
            progress = [e["progress"] for e in events if e["event"] == "progress"]
            assert len(progress) >= 2 and progress == sorted(progress) and 0 < progress[0] < progress[-1] <= 1
            job = c.get(f"/v1/jobs/{jid}").json()
            assert job["state"] == "succeeded" and job["progress"] == 1.0 and job["scene_id"] == scene
            assert [h["state"] for h in job["history"]] == ["queued", "running", "succeeded"]
            assert job["history"][1]["worker"] == "w-e2e" and job["error"] is None
            assert job["summary"] == {"iterations": 24, "resumed_from": 0}
            info = c.get(f"/v1/scenes/{scene}").json()
            assert info["status"] == "ready" and info["num_frames"] == 38
            assert set(info["artifacts"]) == {"graph.json", "metrics.json"}
            assert c.get(f"/v1/scenes/{scene}/artifacts/metrics.json").json() == {"iterations": 24, "resumed_from": 0}
            assert c.get(f"/v1/scenes/{scene}/graph").json()["nodes"][0]["class"] == "background"
            # the upload options reach the engine as reconstruct(..., max_frames=, intrinsics=)
            meta = json.loads((store.scene_dir(scene) / "scene.json").read_text())
            assert meta["options"] == {"max_frames": 12, "intrinsics": "1000.0,1000.0,640.0,360.0"}
            assert not (server.config.uploads_dir / jid).exists()  # the upload is deleted once the job ends
    finally:
        stop_worker(worker)


def test_cancel_running_job(server, store):
    worker = start_worker(server.config, "w-cancel", iters=400, sleep=0.05)
    try:
        with server.client("alice") as c:
            jid = upload(c).json()["job_id"]
            wait_for(lambda: (store.get(jid)["iteration"] or 0) >= 3, 30, what="training to start")
            r = c.post(f"/v1/jobs/{jid}/cancel")
            assert r.status_code == 202 and r.json()["state"] == "running" and r.json()["cancel_requested"]
            job = wait_for(lambda: (j := c.get(f"/v1/jobs/{jid}").json())["state"] == "cancelled" and j, 15,
                           what="the worker to stop")
            assert job["error"] == "cancelled by the client"
            assert [(h["state"], h["worker"]) for h in job["history"]] == [
                ("queued", ""), ("running", "w-cancel"), ("cancelled", "w-cancel")]
            scene_dir = store.scene_dir(job["scene_id"])
            done = len((scene_dir / "iterations.log").read_text().splitlines())
            assert done < 400 and (scene_dir / "checkpoint.pt").is_file()
            assert c.post(f"/v1/jobs/{jid}/cancel").status_code == 409
    finally:
        stop_worker(worker)


def test_preset_time_limit(server, store):
    worker = start_worker(server.config, "w-timeout", iters=400, sleep=0.05)
    try:
        with server.client("alice") as c:
            jid = upload(c, preset="short").json()["job_id"]  # "short" allows 1 s per attempt
            job = wait_for(lambda: (j := c.get(f"/v1/jobs/{jid}").json())["state"] in ("failed", "succeeded") and j,
                           30, what="the time limit")
            assert job["state"] == "failed" and "timed out after 1 s" in job["error"]
            assert [h["state"] for h in job["history"]] == ["queued", "running", "failed"]
    finally:
        stop_worker(worker)
