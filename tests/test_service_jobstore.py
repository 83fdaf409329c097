"""The job store on a real redis-server: transitions, fencing, leases and requeue, cancellation, quotas, streams."""

from __future__ import annotations

import threading
import time

import pytest

from service.jobstore import JobStore, QuotaExceeded, new_id
from tests.redis_server import rclient, redis_proc  # noqa: F401 - fixtures

pytestmark = pytest.mark.timeout(60)


@pytest.fixture
def js(rclient, tmp_path):  # noqa: F811
    return JobStore(rclient, tmp_path, stream_maxlen=50, max_attempts=3)


def make(js, tenant="alice", **kw):
    return js.create(new_id("j"), tenant, "tiny", input_path="/in/video.mp4", timeout_s=60, **kw)


def states(js, job_id):
    return [(h["state"], h["attempt"]) for h in js.history(job_id)]


def test_lifecycle_and_history(js):
    job = make(js, options={"max_frames": 10})
    jid = job["job_id"]
    assert job["state"] == "queued" and job["attempt"] == 1 and job["progress"] == 0.0
    assert job["options"] == {"max_frames": 10} and job["scene_id"].startswith("s")
    assert js.queue.job_ids == [f"{jid}-a1"]
    assert js.start(jid, 1, "w1", 30) == "ok"
    assert js.start(jid, 1, "w2", 30) == "running"  # a second claim of the same attempt is refused
    assert js.progress(jid, 1, 0.4, {"iteration": 4, "total": 10, "phase": "joint", "loss": float("nan")}) == "ok"
    assert js.progress(jid, 1, 0.2, {"iteration": 2, "total": 10}) == "ok"
    got = js.get(jid)
    assert got["progress"] == pytest.approx(0.4) and got["iteration"] == 2 and got["worker"] == "w1"
    assert js.finish(jid, 1, "succeeded", "w1", summary={"psnr": 30.0}) == "ok"
    assert js.finish(jid, 1, "succeeded", "w1") == "lost"  # never finished twice
    got = js.get(jid)
    assert got["state"] == "succeeded" and got["progress"] == 1.0 and got["summary"] == {"psnr": 30.0}
    assert states(js, jid) == [("queued", 1), ("running", 1), ("succeeded", 1)]
    assert [h["worker"] for h in js.history(jid)] == ["", "w1", "w1"]
    kinds = [(e["type"], e.get("state")) for _, e in js.events(jid)]
    assert kinds[0] == ("state", "queued") and kinds[-1] == ("state", "succeeded") and ("progress", None) in kinds
    prog = [e for _, e in js.events(jid) if e["type"] == "progress"]
    assert prog[0]["loss"] is None and prog[0]["iteration"] == 4  # NaN is stored as null
    assert [e["progress"] for e in prog] == pytest.approx([0.4, 0.4])  # progress never goes back
    assert js.r.ttl(f"agg:job:{jid}") > 0  # finished jobs expire after the retention time
    assert js.scene_tenant(got["scene_id"]) == "alice" and js.scene_dir(got["scene_id"]).parent.name == "scenes"


def test_lease_expiry_requeues_and_fences_the_old_attempt(js):
    jid = make(js)["job_id"]
    assert js.start(jid, 1, "w1", 0.3) == "ok"
    assert js.reap() == []  # lease still valid
    time.sleep(0.45)
    assert js.reap() == [(jid, "queued")]
    job = js.get(jid)
    assert job["state"] == "queued" and job["attempt"] == 2 and job["worker"] is None
    assert js.queue.job_ids == [f"{jid}-a1", f"{jid}-a2"]
    # the first attempt wakes up: every write of it is refused
    assert js.renew(jid, 1, 30) == "lost" and js.progress(jid, 1, 0.9, {}) == "lost"
    assert js.finish(jid, 1, "succeeded", "w1") == "lost"
    assert js.start(jid, 1, "w1", 30) == "lost"
    assert js.start(jid, 2, "w2", 30) == "ok" and js.finish(jid, 2, "succeeded", "w2") == "ok"
    assert states(js, jid) == [("queued", 1), ("running", 1), ("queued", 1), ("running", 2), ("succeeded", 2)]
    assert "stopped renewing the lease" in js.history(jid)[2]["reason"]


def test_concurrent_reapers_requeue_once(js, redis_proc):  # noqa: F811
    jid = make(js)["job_id"]
    js.start(jid, 1, "w1", 0.2)
    time.sleep(0.3)
    stores = [JobStore(redis_proc.client(), js.data_dir) for _ in range(4)]
    results, barrier = [], threading.Barrier(4)

    def reap(s):
        barrier.wait()
        results.extend(s.reap())

    threads = [threading.Thread(target=reap, args=(s,)) for s in stores]
    [t.start() for t in threads]
    [t.join() for t in threads]
    assert results == [(jid, "queued")]
    assert js.queue.job_ids == [f"{jid}-a1", f"{jid}-a2"] and js.get(jid)["attempt"] == 2


def test_gives_up_after_max_attempts(js):
    jid = make(js)["job_id"]
    for attempt in (1, 2, 3):
        assert js.start(jid, attempt, f"w{attempt}", 0.1) == "ok"
        time.sleep(0.15)
        js.reap()
    job = js.get(jid)
    assert job["state"] == "failed" and "giving up after 3 attempt" in job["error"]
    assert [s for s, _ in states(js, jid)].count("running") == 3
    assert js.r.scard("agg:tenant:alice:active") == 0


def test_cancel_queued_running_and_finished(js):
    a = make(js)["job_id"]
    assert js.request_cancel(a) is True
    assert js.get(a)["state"] == "cancelled" and js.queue.job_ids == []
    assert js.start(a, 1, "w1", 30) == "cancelled"  # a worker that dequeues it anyway does nothing
    b = make(js)["job_id"]
    js.start(b, 1, "w1", 30)
    assert js.request_cancel(b) is True
    assert js.get(b)["state"] == "running" and js.get(b)["cancel_requested"] is True
    assert js.renew(b, 1, 30) == "cancel"
    assert js.finish(b, 1, "cancelled", "w1", error="cancelled by the client") == "ok"
    assert js.request_cancel(b) is False
    c = make(js)["job_id"]  # a worker that dies after cancellation was requested: cancelled, not requeued
    js.start(c, 1, "w1", 0.1)
    js.request_cancel(c)
    time.sleep(0.15)
    assert js.reap() == [(c, "cancelled")]
    assert js.request_cancel(new_id("j")) is False


def test_quotas_and_tenant_isolation(js):
    make(js, max_active=2)
    make(js, max_active=2)
    with pytest.raises(QuotaExceeded, match="2 active"):
        make(js, max_active=2)
    with pytest.raises(QuotaExceeded):
        js.check_quota("alice", 2, 100)
    js.check_quota("bob", 2, 100)
    js.begin_upload("bob")
    js.begin_upload("bob")
    with pytest.raises(QuotaExceeded, match="2 upload"):
        js.check_quota("bob", 2, 100)
    js.end_upload("bob")
    js.check_quota("bob", 2, 100)
    with pytest.raises(QuotaExceeded, match="24 h"):
        make(js, tenant="carol", max_per_day=0)
    assert len(js.list("alice")) == 2 and js.list("bob") == [] and js.list("carol") == []
    assert js.queue.count == 2  # refused jobs queue nothing


def test_event_stream_is_bounded_and_resumable(js):
    jid = make(js)["job_id"]
    js.start(jid, 1, "w1", 30)
    for i in range(400):
        js.progress(jid, 1, i / 400, {"iteration": i, "total": 400})
    assert js.r.xlen(f"agg:job:{jid}:events") <= 150  # MAXLEN ~ 50 (approximate trimming)
    evs = js.events(jid, count=1000)
    assert evs[-1][1]["iteration"] == 399
    mid = evs[len(evs) // 2][0]
    after = js.events(jid, mid, count=1000)
    assert [e for e, _ in after] == [e for e, _ in evs[len(evs) // 2 + 1:]]
    assert js.events(jid, evs[-1][0], block_ms=50) == []
    with pytest.raises(ValueError):
        js.events(jid, "not-an-id")
    assert js.get("../etc") is None and js.scene_tenant("../../x") is None
    with pytest.raises(ValueError):
        js.scene_dir("../../etc")
