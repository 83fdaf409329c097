"""The HTTP API on a live uvicorn server and a real redis-server: uploads, auth, isolation, quotas, SSE, cancel."""

from __future__ import annotations

import json
import shutil
import threading
import time

import httpx
import pytest

from service.jobstore import JobStore
from tests.redis_server import rclient, redis_proc  # noqa: F401 - fixtures
from tests.service_helpers import KEYS, SAMPLE, LiveServer, service_config, upload

pytestmark = pytest.mark.timeout(60)
VIDEO = SAMPLE.read_bytes()


@pytest.fixture(scope="module")
def server(redis_proc, tmp_path_factory):  # noqa: F811
    srv = LiveServer(service_config(tmp_path_factory.mktemp("http"), redis_proc.url), sse_block_ms=200).start()
    yield srv
    srv.stop()


@pytest.fixture
def alice(server, rclient):  # noqa: F811 - rclient empties Redis before each test
    for d in server.config.uploads_dir.iterdir():
        shutil.rmtree(d)
    with server.client("alice") as c:
        yield c


@pytest.fixture
def store(server, rclient):  # noqa: F811
    return JobStore.from_config(rclient, server.config)


def nothing_queued(server, store):
    assert store.queue.count == 0 and store.list("alice") == []
    assert not any(server.config.uploads_dir.iterdir()), "a refused upload left files behind"


def test_health_ready_metrics(server, alice):
    assert httpx.get(server.url + "/healthz").json() == {"status": "ok"}
    assert httpx.get(server.url + "/readyz").json() == {"status": "ready", "redis": True, "queue_depth": 0}
    alice.get("/v1/jobs")
    text = httpx.get(server.url + "/metrics").text
    assert 'agg_http_requests_total{method="GET",route="/v1/jobs",status="200"}' in text
    assert "agg_queue_depth 0.0" in text and "agg_redis_up 1.0" in text


def test_valid_upload_is_queued(server, alice, store):
    r = upload(alice, max_frames="10", intrinsics="1000,1000,640,360", filename="my clip.mp4")
    assert r.status_code == 202, r.text
    job_id = r.json()["job_id"]
    assert r.headers["location"] == f"/v1/jobs/{job_id}" and r.json()["state"] == "queued"
    job = alice.get(r.headers["location"]).json()
    assert job["state"] == "queued" and job["progress"] == 0.0 and job["preset"] == "tiny"
    assert job["input"] == {"container": "mp4", "frames": 38, "width": 1280, "height": 720, "fps": 25.0,
                            "bytes": SAMPLE.stat().st_size}
    assert [h["state"] for h in job["history"]] == ["queued"]
    stored = store.get(job_id)
    assert stored["options"] == {"max_frames": 10, "intrinsics": "1000.0,1000.0,640.0,360.0"}
    assert stored["input_path"].endswith(f"uploads/{job_id}/video.mp4")  # never the client's name
    assert (server.config.uploads_dir / job_id / "video.mp4").read_bytes() == SAMPLE.read_bytes()
    assert store.queue.job_ids == [f"{job_id}-a1"]
    listed = alice.get("/v1/jobs").json()
    assert listed["total"] == 1 and listed["jobs"][0]["job_id"] == job_id


def test_upload_with_calibration_file(server, alice, store):
    calib = (SAMPLE.parent / "dashcam_intrinsics.yml").read_bytes()
    r = alice.post("/v1/jobs", files={"video": ("clip.mp4", VIDEO), "calibration": ("cam.yml", calib)},
                   data={"preset": "tiny"})
    assert r.status_code == 202, r.text
    job_id = r.json()["job_id"]
    assert store.get(job_id)["options"] == {"calibration": "calibration.yml"}
    assert (server.config.uploads_dir / job_id / "calibration.yml").read_bytes() == calib


def _multipart(parts: list[tuple[str, str | None, bytes]], boundary: str = "b0undary") -> tuple[bytes, dict]:
    body = b""
    for name, filename, data in parts:
        disp = f'form-data; name="{name}"' + (f'; filename="{filename}"' if filename is not None else "")
        body += f"--{boundary}\r\nContent-Disposition: {disp}\r\n\r\n".encode() + data + b"\r\n"
    return body + f"--{boundary}--\r\n".encode(), {"Content-Type": f"multipart/form-data; boundary={boundary}"}


@pytest.mark.parametrize("case, parts, status, code", [
    ("empty", [("video", "a.mp4", b""), ("preset", None, b"tiny")], 422, "empty_upload"),
    ("non-video", [("video", "a.mp4", b"<html>not a video</html>" * 50), ("preset", None, b"tiny")], 415,
     "not_a_video"),
    ("png", [("video", "a.mp4", b"\x89PNG\r\n\x1a\n" + b"\0" * 500), ("preset", None, b"tiny")], 415, "not_a_video"),
    ("truncated", [("video", "a.mp4", VIDEO[: len(VIDEO) // 2]), ("preset", None, b"tiny")], 422, "truncated_video"),
    ("traversal", [("video", "../../../etc/cron.d/x.mp4", VIDEO), ("preset", None, b"tiny")], 400,
     "invalid_filename"),
    ("backslash", [("video", "..\\..\\x.mp4", VIDEO), ("preset", None, b"tiny")], 400, "invalid_filename"),
    ("no video", [("preset", None, b"tiny")], 422, "missing_video"),
    ("bad preset", [("video", "a.mp4", VIDEO), ("preset", None, b"huge")], 422, "invalid_preset"),
    ("no preset", [("video", "a.mp4", VIDEO)], 422, "invalid_preset"),
    ("fx <= 0", [("video", "a.mp4", VIDEO), ("preset", None, b"tiny"), ("intrinsics", None, b"0,1000,640,360")],
     422, "invalid_intrinsics"),
    ("max_frames", [("video", "a.mp4", VIDEO), ("preset", None, b"tiny"), ("max_frames", None, b"1")], 422,
     "invalid_max_frames"),
    ("unknown field", [("video", "a.mp4", VIDEO), ("preset", None, b"tiny"), ("rm -rf", None, b"1")], 422,
     "unknown_field"),
    ("duplicate", [("video", "a.mp4", VIDEO), ("video", "b.mp4", VIDEO), ("preset", None, b"tiny")], 400,
     "duplicate_field"),
    ("bad calibration", [("video", "a.mp4", VIDEO), ("preset", None, b"tiny"),
                         ("calibration", "c.yml", b"%YAML:1.0\nfoo: 1\n")], 422, "invalid_calibration"),
])
def test_bad_uploads_are_refused(server, alice, store, case, parts, status, code):
    body, headers = _multipart(parts)
    r = alice.post("/v1/jobs", content=body, headers=headers)
    assert (r.status_code, r.json()["code"]) == (status, code), r.text
    assert r.json()["message"]
    nothing_queued(server, store)


def test_oversize_and_malformed_bodies(server, alice, store):
    big = VIDEO * 3  # 2.4 MB > the 2 MB limit of this server
    r = upload(alice, big)  # with Content-Length: refused before reading the body
    assert (r.status_code, r.json()["code"]) == (413, "upload_too_large")

    def chunks():  # no Content-Length: refused while streaming
        body, _ = _multipart([("preset", None, b"tiny"), ("video", "a.mp4", big)])
        for i in range(0, len(body), 65536):
            yield body[i:i + 65536]

    r = alice.post("/v1/jobs", content=chunks(), headers={"Content-Type": "multipart/form-data; boundary=b0undary"})
    assert (r.status_code, r.json()["code"]) == (413, "upload_too_large")
    r = alice.post("/v1/jobs", json={"video": "x", "preset": "tiny"})
    assert (r.status_code, r.json()["code"]) == (415, "expected_multipart")
    body, headers = _multipart([("video", "a.mp4", VIDEO), ("preset", None, b"tiny")])
    r = alice.post("/v1/jobs", content=body[:-30], headers=headers)  # no closing boundary
    assert (r.status_code, r.json()["code"]) == (400, "malformed_multipart")
    nothing_queued(server, store)


def test_auth(server, alice):
    job_id = upload(alice).json()["job_id"]
    routes = [("GET", "/v1/jobs"), ("POST", "/v1/jobs"), ("GET", f"/v1/jobs/{job_id}"),
              ("GET", f"/v1/jobs/{job_id}/events"), ("POST", f"/v1/jobs/{job_id}/cancel"),
              ("GET", "/v1/scenes/s000000000000000000000000"), ("POST", "/v1/scenes/s000000000000000000000000/render")]
    for headers in ({}, {"Authorization": "Bearer wrong-key-0123456789abc"},
                    {"Authorization": f"Basic {KEYS['alice']}"}, {"Authorization": "Bearer"}):
        for method, path in routes:
            r = httpx.request(method, server.url + path, headers=headers)
            assert r.status_code == 401, (method, path, headers, r.text)
            assert r.json()["code"] == "unauthorized" and r.headers["www-authenticate"] == "Bearer"
    assert alice.get(f"/v1/jobs/{job_id}").json()["state"] == "queued"  # nothing was cancelled


def test_other_tenants_ids_are_not_found(server, alice, store):
    job = upload(alice).json()
    scene = job["scene_id"]
    (store.scene_dir(scene)).mkdir(parents=True, exist_ok=True)
    (store.scene_dir(scene) / "metrics.json").write_text("{}")
    with server.client("bob") as bob:
        for method, path in [("GET", f"/v1/jobs/{job['job_id']}"), ("GET", f"/v1/jobs/{job['job_id']}/events"),
                             ("POST", f"/v1/jobs/{job['job_id']}/cancel"), ("GET", f"/v1/scenes/{scene}"),
                             ("GET", f"/v1/scenes/{scene}/graph"),
                             ("GET", f"/v1/scenes/{scene}/artifacts/metrics.json")]:
            r = bob.request(method, path)
            assert r.status_code == 404, (path, r.text)
            assert r.json()["code"] in ("job_not_found", "scene_not_found")
        r = bob.post(f"/v1/scenes/{scene}/render", json={"timestamp_us": 0, "world_from_camera": _eye()})
        assert r.status_code == 404
        assert bob.get("/v1/jobs").json() == {"jobs": [], "total": 0}
        mine = upload(bob).json()["job_id"]
        assert [j["job_id"] for j in bob.get("/v1/jobs").json()["jobs"]] == [mine]
    assert [j["job_id"] for j in alice.get("/v1/jobs").json()["jobs"]] == [job["job_id"]]
    assert alice.get(f"/v1/jobs/{mine}").status_code == 404
    assert alice.get(f"/v1/scenes/{scene}/artifacts/metrics.json").json() == {}


def test_quota(redis_proc, rclient, tmp_path):  # noqa: F811
    srv = LiveServer(service_config(tmp_path, redis_proc.url, max_active_jobs=2)).start()
    try:
        with srv.client("alice") as c:
            assert [upload(c).status_code for _ in range(2)] == [202, 202]
            r = upload(c)
            assert (r.status_code, r.json()["code"]) == (429, "quota_exceeded") and r.headers["retry-after"] == "30"
            with srv.client("bob") as bob:
                assert upload(bob).status_code == 202  # quotas are per tenant
            c.post(f"/v1/jobs/{c.get('/v1/jobs').json()['jobs'][0]['job_id']}/cancel")
            assert upload(c).status_code == 202  # a cancelled job frees its slot
    finally:
        srv.stop()


def _eye():
    return [[1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 1.0]]


def _sse(response) -> list[dict]:
    events, cur = [], {}
    for line in response.iter_lines():
        if not line:
            if "data" in cur:
                events.append(cur)
            cur = {}
        elif not line.startswith(":"):
            field, _, value = line.partition(":")
            cur[field] = value.strip()
    return events


def test_sse_resumes_from_last_event_id(server, alice, store):
    job = upload(alice).json()
    jid = job["job_id"]

    def fake_worker_writes():  # the worker-side store calls a real worker makes, without the engine
        store.start(jid, 1, "w-test", 30)
        for i in range(1, 11):
            store.progress(jid, 1, i / 10, {"iteration": i, "total": 10, "phase": "joint"})
            time.sleep(0.02)
        store.finish(jid, 1, "succeeded", "w-test")

    writer = threading.Thread(target=fake_worker_writes)
    with alice.stream("GET", f"/v1/jobs/{jid}/events") as r:
        assert r.status_code == 200 and r.headers["content-type"].startswith("text/event-stream")
        writer.start()
        full = _sse(r)
    writer.join()
    kinds = [(e["event"], json.loads(e["data"]).get("state")) for e in full]
    assert kinds[0] == ("state", "queued") and kinds[1] == ("state", "running") and kinds[-1] == ("state", "succeeded")
    assert [json.loads(e["data"])["iteration"] for e in full if e["event"] == "progress"] == list(range(1, 11))
    assert all(e["id"] for e in full)
    cut = full[5]["id"]
    with alice.stream("GET", f"/v1/jobs/{jid}/events", headers={"Last-Event-ID": cut}) as r:
        rest = _sse(r)
    assert [e["id"] for e in rest] == [e["id"] for e in full[6:]]
    assert alice.get(f"/v1/jobs/{jid}/events", headers={"Last-Event-ID": full[-1]["id"]}).status_code == 204
    r = alice.get(f"/v1/jobs/{jid}/events", headers={"Last-Event-ID": "garbage"})
    assert (r.status_code, r.json()["code"]) == (400, "invalid_event_id")
    assert alice.get(f"/v1/jobs/{jid}").json()["progress"] == 1.0


def test_cancel_queued_job(server, alice, store):
    jid = upload(alice).json()["job_id"]
    r = alice.post(f"/v1/jobs/{jid}/cancel")
    assert r.status_code == 202 and r.json() == {"job_id": jid, "state": "cancelled", "cancel_requested": True}
    assert store.queue.count == 0 and not (server.config.uploads_dir / jid).exists()
    r = alice.post(f"/v1/jobs/{jid}/cancel")
    assert (r.status_code, r.json()["code"]) == (409, "job_finished")
    assert [h["state"] for h in alice.get(f"/v1/jobs/{jid}").json()["history"]] == ["queued", "cancelled"]


def test_scene_endpoints(server, alice, store):
    job = upload(alice).json()
    scene = job["scene_id"]
    info = alice.get(f"/v1/scenes/{scene}").json()
    assert info["status"] == "pending" and info["artifacts"] == [] and info["renderable"] is False
    r = alice.get(f"/v1/scenes/{scene}/artifacts/scene.ply")
    assert (r.status_code, r.json()["code"]) == (404, "artifact_not_found")
    for bad in ("model.pt", "..%2F..%2Fetc%2Fpasswd", "checkpoint.pt"):
        assert alice.get(f"/v1/scenes/{scene}/artifacts/{bad}").status_code in (404, 422)
    d = store.scene_dir(scene)
    d.mkdir(parents=True)
    (d / "graph.json").write_text(json.dumps({"nodes": [{"id": 0, "class": "background"}]}))
    (d / "scene.json").write_text(json.dumps({"num_frames": 3, "width": 16, "height": 9, "timestamps_us": [0, 1, 2],
                                              "K": [[[9.0, 0, 8], [0, 9.0, 4], [0, 0, 1]]] * 3, "preset": "tiny"}))
    assert alice.get(f"/v1/scenes/{scene}/graph").json() == {"nodes": [{"id": 0, "class": "background"}]}
    r = alice.get(f"/v1/scenes/{scene}/artifacts/graph.json")
    assert r.status_code == 200 and r.headers["content-type"] == "application/json"
    info = alice.get(f"/v1/scenes/{scene}").json()
    assert info["num_frames"] == 3 and info["intrinsics"][0][0] == 9.0 and info["artifacts"] == ["graph.json"]
    r = alice.post(f"/v1/scenes/{scene}/render", json={"timestamp_us": 1, "world_from_camera": _eye()})
    assert r.status_code in (409, 503) and r.json()["code"] in ("scene_not_ready", "renderer_unavailable")


@pytest.mark.parametrize("body, where", [
    ('{"timestamp_us": 0, "world_from_camera": [[NaN,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}', "world_from_camera"),
    ('{"timestamp_us": 0, "world_from_camera": [[2,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}', "world_from_camera"),
    ('{"timestamp_us": 0, "world_from_camera": [[1,0,0],[0,1,0],[0,0,1]]}', "world_from_camera"),
    ('{"timestamp_us": 0, "world_from_camera": EYE, "width": 0}', "width"),
    ('{"timestamp_us": 0, "world_from_camera": EYE, "width": 100000}', "width"),
    ('{"timestamp_us": 0, "world_from_camera": EYE, "intrinsics": {"fx": 0, "fy": 5, "cx": 1, "cy": 1}}', "fx"),
    ('{"timestamp_us": 0, "world_from_camera": EYE, "intrinsics": {"fx": -3, "fy": 5, "cx": 1, "cy": 1}}', "fx"),
    ('{"timestamp_us": -5, "world_from_camera": EYE}', "timestamp_us"),
    ('{"timestamp_us": 0, "world_from_camera": EYE, "agent_poses": {"7": [[Infinity,0,0,0],[0,1,0,0],[0,0,1,0],'
     '[0,0,0,1]]}}', "agent_poses"),
    ('{"timestamp_us": 0, "world_from_camera": EYE, "agent_poses": {"car": EYE}}', "agent_poses"),
    ("not json", "body"),
])
def test_render_request_validation(server, alice, body, where):
    scene = upload(alice).json()["scene_id"]
    eye = json.dumps(_eye())
    r = alice.post(f"/v1/scenes/{scene}/render", content=body.replace("EYE", eye),
                   headers={"Content-Type": "application/json"})
    assert r.status_code == 422, r.text
    assert r.json()["code"] == "invalid_request" and where in r.json()["message"] + json.dumps(r.json()["details"])
