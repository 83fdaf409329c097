"""Faults with real processes: a worker killed with SIGKILL mid-training, a paused (zombie) worker that wakes up
after its job moved on, and a Redis restart (AOF) with jobs queued. The engine is the contract's stand-in
(tests/service_engine.py: checkpoints every 5 iterations, logs "pid iteration" per iteration)."""

from __future__ import annotations

import signal
import time
from collections import Counter

import httpx
import pytest
import torch

from service.jobstore import JobStore
from tests.redis_server import rclient, redis_proc  # noqa: F401 - fixtures
from tests.service_helpers import (
    LiveServer,
    children,
    kill_tree,
    service_config,
    start_worker,
    stop_worker,
    upload,
    wait_for,
)

pytestmark = pytest.mark.timeout(90)


@pytest.fixture(scope="module")
def server(redis_proc, tmp_path_factory):  # noqa: F811
    srv = LiveServer(service_config(tmp_path_factory.mktemp("faults"), redis_proc.url, lease_s=1.5)).start()
    yield srv
    srv.stop()


@pytest.fixture
def store(server, rclient):  # noqa: F811
    return JobStore.from_config(rclient, server.config)


def iterations(scene_dir) -> list[tuple[int, int]]:
    """(pid, iteration) lines of the stand-in engine's log."""
    lines = (scene_dir / "iterations.log").read_text().split("\n")
    return [tuple(int(x) for x in ln.split()) for ln in lines if ln.strip()]


def assert_single_finish(history: list[dict]) -> None:
    finals = [h for h in history if h["state"] in ("succeeded", "failed", "cancelled")]
    assert len(finals) == 1, history


def test_killed_worker_is_replaced_and_resumes_from_checkpoint(server, store):
    cfg = server.config
    a = start_worker(cfg, "wA", iters=60, sleep=0.08)
    b = None
    try:
        with server.client("alice") as c:
            jid = upload(c).json()["job_id"]
        wait_for(lambda: (store.get(jid)["iteration"] or 0) >= 13, 30, what="wA to pass a checkpoint")
        hit = kill_tree(a)  # the worker and its work horse, as when the machine dies
        a.wait(10)
        assert len(hit) == 2
        b = start_worker(cfg, "wB", iters=60, sleep=0.02)
        job = wait_for(lambda: (j := store.get(jid))["state"] == "succeeded" and j, 40, what="wB to finish")
        history = store.history(jid)
        assert [(h["state"], h["attempt"], h["worker"]) for h in history] == [
            ("queued", 1, ""), ("running", 1, "wA"), ("queued", 1, "wA"), ("running", 2, "wB"), ("succeeded", 2, "wB")]
        assert "stopped renewing the lease" in history[2]["reason"]
        assert_single_finish(history)
        assert job["attempt"] == 2 and job["progress"] == 1.0
        # wB resumed from wA's last checkpoint: no iteration lost, none before the checkpoint redone
        log = iterations(store.scene_dir(job["scene_id"]))
        pids = list(dict.fromkeys(p for p, _ in log))
        assert len(pids) == 2
        first = [i for p, i in log if p == pids[0]]
        second = [i for p, i in log if p == pids[1]]
        resumed = job["summary"]["resumed_from"]
        assert resumed >= 10 and resumed % 5 == 0 and second[0] == resumed <= first[-1] + 1
        assert first == list(range(first[-1] + 1)) and second == list(range(resumed, 60))
    finally:
        stop_worker(a)
        if b is not None:
            stop_worker(b)


def test_paused_worker_cannot_finish_a_job_it_lost(server, store):
    cfg = server.config
    a = start_worker(cfg, "wA", iters=60, sleep=0.05)
    b = None
    try:
        with server.client("alice") as c:
            jid = upload(c).json()["job_id"]
        wait_for(lambda: (store.get(jid)["iteration"] or 0) >= 7, 30, what="wA to train")
        paused = kill_tree(a, signal.SIGSTOP)
        b = start_worker(cfg, "wB", iters=60, sleep=0.02)
        job = wait_for(lambda: (j := store.get(jid))["state"] == "succeeded" and j, 40, what="wB to finish")
        scene_dir = store.scene_dir(job["scene_id"])
        lines_before = Counter(p for p, _ in iterations(scene_dir))
        for pid in paused:
            os_kill(pid, signal.SIGCONT)
        horse = [p for p in paused if p != a.pid]
        wait_for(lambda: not children(a.pid), 20, what="wA's work horse to give up")
        time.sleep(0.3)
        history = store.history(jid)
        assert_single_finish(history)
        assert store.get(jid)["state"] == "succeeded" and history[-1]["worker"] == "wB"
        assert torch.load(scene_dir / "checkpoint.pt")["iteration"] == 60  # the zombie wrote no checkpoint
        lines_after = Counter(p for p, _ in iterations(scene_dir))
        assert all(lines_after[p] - lines_before[p] <= 1 for p in horse)  # at most the iteration it was paused in
    finally:
        stop_worker(a)
        if b is not None:
            stop_worker(b)


def os_kill(pid: int, sig: int) -> None:
    import os

    try:
        os.kill(pid, sig)
    except ProcessLookupError:
        pass


def test_queued_jobs_survive_a_redis_restart(server, store, redis_proc):  # noqa: F811
    with server.client("alice") as c:
        ids = [upload(c).json()["job_id"] for _ in range(2)]
        redis_proc.stop(kill=True)  # SIGKILL: only what the AOF holds survives
        # while Redis is down: 503 with a code, never a 500 or a hang; nothing left behind
        r = c.get("/v1/jobs")
        assert (r.status_code, r.json()["code"]) == (503, "backend_unavailable") and r.headers["retry-after"] == "5"
        before = set(server.config.uploads_dir.iterdir())
        r = upload(c)
        assert (r.status_code, r.json()["code"]) == (503, "backend_unavailable")
        assert set(server.config.uploads_dir.iterdir()) == before
        assert httpx.get(server.url + "/readyz").status_code == 503 and httpx.get(server.url + "/healthz").is_success
        assert "agg_redis_up 0.0" in httpx.get(server.url + "/metrics").text
        redis_proc.start()
        listed = wait_for(lambda: _try(lambda: c.get("/v1/jobs").json()), 10, what="the API to reconnect")
        assert sorted(j["job_id"] for j in listed["jobs"]) == sorted(ids)
        assert all(j["state"] == "queued" for j in listed["jobs"])
    fresh = JobStore.from_config(redis_proc.client(), server.config)
    assert sorted(fresh.queue.job_ids) == sorted(f"{j}-a1" for j in ids)
    w = start_worker(server.config, "wR", iters=5, sleep=0.01, burst=True)
    assert w.wait(60) == 0
    for jid in ids:
        assert fresh.get(jid)["state"] == "succeeded"
        assert [h["state"] for h in fresh.history(jid)] == ["queued", "running", "succeeded"]


def _try(fn):
    try:
        return fn()
    except Exception:  # noqa: BLE001 - retried by wait_for
        return None
