"""The job store: a job-state hash per job in Redis is the source of truth; RQ only carries "run attempt n".

Keys (prefix ``agg:``): ``job:{id}`` (hash), ``job:{id}:history`` (JSON entries: state, at, worker, attempt,
reason), ``job:{id}:events`` (stream, ``MAXLEN ~ stream_maxlen``), ``tenant:{t}:jobs`` (zset by creation time),
``tenant:{t}:active`` (queued + running ids, the quota), ``tenant:{t}:accepted`` (zset, the daily quota),
``tenant:{t}:uploading`` (uploads in flight), ``leases`` (zset: running job -> lease expiry), ``scene:{id}``
(hash: tenant, job_id, dir).

States: queued -> running -> succeeded | failed | cancelled; queued -> cancelled; running -> queued (the lease
expired: the worker died, ``reap``). Worker-side writes (start, renew, progress, finish) are Lua scripts fenced by
the attempt number, so an attempt that lost its lease can never finish the job (see docs/SERVICE.md). Creating a
job and requeueing it are WATCH/MULTI transactions that also push the RQ job, so a job is never in the hash as
queued without an RQ job to run it. Times are the Redis server's clock, in seconds.
"""

from __future__ import annotations

import json
import logging
import os
import re
import secrets
from pathlib import Path

import redis
from rq import Queue

from service import jobstore_lua as lua

log = logging.getLogger(__name__)

P = "agg:"
JOB_ID_RE = re.compile(r"^j[0-9a-f]{24}$")
SCENE_ID_RE = re.compile(r"^s[0-9a-f]{24}$")
EVENT_ID_RE = re.compile(r"^\d{1,20}-\d{1,20}$")
STATES = ("queued", "running", "succeeded", "failed", "cancelled")
TERMINAL = ("succeeded", "failed", "cancelled")
JOB_FUNC = "worker.jobs.run_job"
DAY_S = 86400


class QuotaExceeded(Exception):
    """The tenant has too many active jobs or too many jobs today; ``retry_after_s`` is a hint."""

    def __init__(self, message: str, retry_after_s: int = 60):
        super().__init__(message)
        self.retry_after_s = retry_after_s


def new_id(prefix: str) -> str:
    return prefix + secrets.token_hex(12)


def _k_job(job_id: str) -> str:
    return f"{P}job:{job_id}"


def _k_hist(job_id: str) -> str:
    return f"{P}job:{job_id}:history"


def _k_events(job_id: str) -> str:
    return f"{P}job:{job_id}:events"


def _k_tenant(tenant: str, what: str) -> str:
    return f"{P}tenant:{tenant}:{what}"


K_LEASES = P + "leases"


def events_key(job_id: str) -> str:
    """The Redis Stream of a job's events (for async readers such as the SSE endpoint)."""
    return _k_events(job_id)


def decode_event(fields: dict) -> dict:
    raw = fields.get(b"data") or fields.get("data") or b"{}"
    return json.loads(raw)


class JobStore:
    """Jobs, their history and events, per-tenant listing and quotas, leases and scene ownership.

    ``JobStore(redis_client)`` is enough for readers (the gRPC servers); ``data_dir`` (default ``AGG_DATA_DIR``)
    locates scene folders; ``stream_maxlen``, ``max_attempts`` and ``retention_s`` matter to writers.
    """

    def __init__(self, client: redis.Redis, data_dir: str | Path | None = None, *, queue: str = "agg",
                 stream_maxlen: int = 2000, max_attempts: int = 3, retention_s: int = 30 * 86400):
        self.r = client
        env_dir = os.environ.get("AGG_DATA_DIR")
        self.data_dir = Path(data_dir) if data_dir is not None else (Path(env_dir) if env_dir else None)
        self.queue = Queue(queue, connection=client)
        self.stream_maxlen, self.max_attempts, self.retention_s = stream_maxlen, max_attempts, retention_s
        self._start = client.register_script(lua.START)
        self._renew = client.register_script(lua.RENEW)
        self._progress = client.register_script(lua.PROGRESS)
        self._finish = client.register_script(lua.FINISH)
        self._cancel = client.register_script(lua.CANCEL)

    @classmethod
    def from_config(cls, client: redis.Redis, config) -> "JobStore":
        return cls(client, config.data_dir, queue=config.queue, stream_maxlen=config.stream_maxlen,
                   max_attempts=config.max_attempts, retention_s=config.job_retention_s)

    # ----------------------------------------------------------------------------------------------- reading
    def now(self) -> float:
        s, us = self.r.time()
        return s + us / 1e6

    def get(self, job_id: str) -> dict | None:
        """The job as a dict (typed values), or None for an unknown or malformed id."""
        if not isinstance(job_id, str) or not JOB_ID_RE.match(job_id):
            return None
        raw = self.r.hgetall(_k_job(job_id))
        return _decode_job(raw) if raw else None

    def history(self, job_id: str) -> list[dict]:
        """The state transitions, oldest first: {state, at, worker, attempt, reason?}."""
        if not JOB_ID_RE.match(job_id or ""):
            return []
        return [json.loads(x) for x in self.r.lrange(_k_hist(job_id), 0, -1)]

    def list(self, tenant: str, limit: int = 100, offset: int = 0) -> list[dict]:
        """The tenant's jobs, newest first (ids whose hash has expired are dropped from the index)."""
        ids = [x.decode() for x in self.r.zrevrange(_k_tenant(tenant, "jobs"), offset, offset + limit - 1)]
        out, gone = [], []
        with self.r.pipeline(transaction=False) as pipe:
            for job_id in ids:
                pipe.hgetall(_k_job(job_id))
            for job_id, raw in zip(ids, pipe.execute(), strict=True):
                (out.append(_decode_job(raw)) if raw else gone.append(job_id))
        if gone:
            self.r.zrem(_k_tenant(tenant, "jobs"), *gone)
        return out

    def count(self, tenant: str) -> int:
        return int(self.r.zcard(_k_tenant(tenant, "jobs")))

    def events(self, job_id: str, after_id: str | None = None, block_ms: int = 0,
               count: int = 500) -> list[tuple[str, dict]]:
        """Stream entries after ``after_id`` (None: from the oldest kept), waiting up to ``block_ms`` (0: no wait)."""
        after = after_id or "0-0"
        if not JOB_ID_RE.match(job_id or "") or not EVENT_ID_RE.match(after):
            raise ValueError("malformed job id or event id")
        res = self.r.xread({_k_events(job_id): after}, count=count, block=block_ms if block_ms > 0 else None)
        return [(eid.decode(), decode_event(fields)) for _, entries in (res or []) for eid, fields in entries]

    def scene_dir(self, scene_id: str) -> Path:
        """The folder of a scene (``data_dir/scenes/{id}``, else the one recorded at creation)."""
        if not isinstance(scene_id, str) or not SCENE_ID_RE.match(scene_id):
            raise ValueError(f"malformed scene id {scene_id!r}")
        if self.data_dir is not None:
            return self.data_dir / "scenes" / scene_id
        recorded = self.r.hget(f"{P}scene:{scene_id}", "dir")
        if recorded is None:
            raise KeyError(scene_id)
        return Path(recorded.decode())

    def scene_tenant(self, scene_id: str) -> str | None:
        """The tenant owning ``scene_id``, or None (unknown or malformed id)."""
        if not isinstance(scene_id, str) or not SCENE_ID_RE.match(scene_id):
            return None
        t = self.r.hget(f"{P}scene:{scene_id}", "tenant")
        return t.decode() if t is not None else None

    def scene_job(self, scene_id: str) -> str | None:
        if not isinstance(scene_id, str) or not SCENE_ID_RE.match(scene_id):
            return None
        j = self.r.hget(f"{P}scene:{scene_id}", "job_id")
        return j.decode() if j is not None else None

    def scenes(self, tenant: str, limit: int = 100) -> list[dict]:
        """The tenant's scenes: {scene_id, job_id, state} of its jobs, newest first."""
        return [{"scene_id": j["scene_id"], "job_id": j["job_id"], "state": j["state"]}
                for j in self.list(tenant, limit=limit) if j.get("scene_id")]

    def queue_depth(self) -> int:
        return int(self.queue.count)

    def running_count(self) -> int:
        return int(self.r.zcard(K_LEASES))

    # ----------------------------------------------------------------------------------------------- quotas
    def check_quota(self, tenant: str, max_active: int, max_per_day: int, *, uploading_self: bool = False) -> None:
        """Raise QuotaExceeded when the tenant is at its active-job or daily limit (uploads in flight count)."""
        now = self.now()
        with self.r.pipeline(transaction=False) as pipe:
            pipe.scard(_k_tenant(tenant, "active"))
            pipe.get(_k_tenant(tenant, "uploading"))
            pipe.zcount(_k_tenant(tenant, "accepted"), now - DAY_S, "+inf")
            active, uploading, today = pipe.execute()
        uploading = max(int(uploading or 0) - int(uploading_self), 0)
        if int(active) + uploading >= max_active:
            raise QuotaExceeded(f"tenant has {int(active)} active job(s) and {uploading} upload(s) in flight; "
                                f"the limit is {max_active}", retry_after_s=30)
        if int(today) >= max_per_day:
            raise QuotaExceeded(f"tenant has submitted {int(today)} jobs in the last 24 h; the limit is "
                                f"{max_per_day}", retry_after_s=3600)

    def begin_upload(self, tenant: str) -> None:
        with self.r.pipeline() as pipe:
            pipe.incr(_k_tenant(tenant, "uploading"))
            pipe.expire(_k_tenant(tenant, "uploading"), 3600)
            pipe.execute()

    def end_upload(self, tenant: str) -> None:
        if int(self.r.decr(_k_tenant(tenant, "uploading"))) < 0:
            self.r.set(_k_tenant(tenant, "uploading"), 0, ex=3600)

    # ----------------------------------------------------------------------------------------------- writing
    def create(self, job_id: str, tenant: str, preset: str, *, input_path: str, timeout_s: int,
               options: dict | None = None, input_info: dict | None = None, max_active: int = 1 << 30,
               max_per_day: int = 1 << 30, scene_id: str | None = None) -> dict:
        """Record a queued job (attempt 1) and push its RQ job in one transaction; enforces the quotas."""
        if not JOB_ID_RE.match(job_id):
            raise ValueError(f"malformed job id {job_id!r}")
        scene_id = scene_id or new_id("s")
        active_k, accepted_k = _k_tenant(tenant, "active"), _k_tenant(tenant, "accepted")
        scene_dir = str((self.data_dir / "scenes" / scene_id).resolve()) if self.data_dir else ""
        with self.r.pipeline() as pipe:
            while True:
                try:
                    pipe.watch(active_k, accepted_k)
                    s, us = pipe.time()
                    now = s + us / 1e6
                    active = int(pipe.scard(active_k))
                    today = int(pipe.zcount(accepted_k, now - DAY_S, "+inf"))
                    if active >= max_active:
                        raise QuotaExceeded(f"tenant has {active} active job(s); the limit is {max_active}", 30)
                    if today >= max_per_day:
                        raise QuotaExceeded(f"tenant has submitted {today} jobs in the last 24 h; the limit is "
                                            f"{max_per_day}", 3600)
                    job = {"job_id": job_id, "tenant": tenant, "state": "queued", "progress": "0.000000",
                           "scene_id": scene_id, "error": "", "preset": preset, "created_at": f"{now:.6f}",
                           "updated_at": f"{now:.6f}", "attempt": "1", "worker": "", "cancel_requested": "0",
                           "input_path": input_path, "timeout_s": str(int(timeout_s)),
                           "options": json.dumps(options or {}), "input": json.dumps(input_info or {})}
                    pipe.multi()
                    pipe.hset(_k_job(job_id), mapping=job)
                    pipe.rpush(_k_hist(job_id), json.dumps({"state": "queued", "at": now, "worker": "",
                                                            "attempt": 1}))
                    pipe.xadd(_k_events(job_id), {"data": json.dumps({"type": "state", "state": "queued",
                                                                      "at": now, "progress": 0.0})},
                              maxlen=self.stream_maxlen, approximate=True)
                    pipe.zadd(_k_tenant(tenant, "jobs"), {job_id: now})
                    pipe.sadd(active_k, job_id)
                    pipe.zadd(accepted_k, {job_id: now})
                    pipe.zremrangebyscore(accepted_k, "-inf", now - DAY_S)
                    pipe.hset(f"{P}scene:{scene_id}", mapping={"tenant": tenant, "job_id": job_id, "dir": scene_dir})
                    self._enqueue(pipe, job_id, 1, timeout_s)
                    pipe.execute()
                    break
                except redis.WatchError:
                    continue
        return self.get(job_id)

    def _enqueue(self, pipe, job_id: str, attempt: int, timeout_s: int) -> None:
        self.queue.enqueue_call(JOB_FUNC, args=(job_id, attempt), timeout=int(timeout_s) + 60,
                                result_ttl=3600, failure_ttl=7 * 86400, job_id=f"{job_id}-a{attempt}",
                                description=f"agg job {job_id} attempt {attempt}", pipeline=pipe)

    def start(self, job_id: str, attempt: int, worker: str, lease_s: float) -> str:
        """queued -> running for ``attempt``; returns 'ok', or why not ('lost', 'cancelled', 'missing', ...)."""
        return self._start(keys=[_k_job(job_id), _k_hist(job_id), _k_events(job_id), K_LEASES],
                           args=[job_id, attempt, worker, lease_s, self.stream_maxlen]).decode()

    def renew(self, job_id: str, attempt: int, lease_s: float) -> str:
        """Extend the lease; 'run', 'cancel' (cancellation requested) or 'lost' (no longer this attempt's job)."""
        return self._renew(keys=[_k_job(job_id), K_LEASES], args=[job_id, attempt, lease_s]).decode()

    def progress(self, job_id: str, attempt: int, progress: float, event: dict) -> str:
        """Record progress (kept monotone) and append a progress event; 'ok' or 'lost'."""
        p = min(max(float(progress), 0.0), 1.0) if progress == progress else 0.0
        return self._progress(keys=[_k_job(job_id), _k_events(job_id)],
                              args=[attempt, f"{p:.6f}", json.dumps(_finite(event)), self.stream_maxlen]).decode()

    def finish(self, job_id: str, attempt: int, state: str, worker: str, *, error: str | None = None,
               summary: dict | None = None) -> str:
        """running -> succeeded | failed | cancelled, only for the current attempt; 'ok' or 'lost'."""
        if state not in TERMINAL:
            raise ValueError(f"not a final state: {state}")
        job = self.get(job_id)
        if job is None:
            return "missing"
        fields = {"error": (error or "")[:2000]}
        if summary is not None:
            text = json.dumps(_finite(summary))
            if len(text) > 100_000:  # keep the record small; the scene folder has the full metrics
                text = json.dumps({"note": "summary too large for the job record", "keys": sorted(summary)[:100]})
            fields["summary"] = text
        return self._finish(keys=[_k_job(job_id), _k_hist(job_id), _k_events(job_id), K_LEASES,
                                  _k_tenant(job["tenant"], "active")],
                            args=[job_id, attempt, state, worker, json.dumps(fields), self.stream_maxlen,
                                  self.retention_s]).decode()

    def request_cancel(self, job_id: str, who: str = "client") -> bool:
        """Cancel a queued job now, or ask a running one to stop; False when it had already finished."""
        job = self.get(job_id)
        if job is None:
            return False
        res = self._cancel(keys=[_k_job(job_id), _k_hist(job_id), _k_events(job_id),
                                 _k_tenant(job["tenant"], "active")],
                           args=[job_id, who, self.stream_maxlen, self.retention_s]).decode()
        if res == "cancelled_now":
            self.queue.remove(f"{job_id}-a{job['attempt']}")
        return res in ("cancelled_now", "cancelling")

    def reap(self) -> list[tuple[str, str]]:
        """Requeue running jobs whose lease expired (attempt + 1), or fail/cancel them; [(job_id, outcome)]."""
        now = self.now()
        done = []
        for raw_id in self.r.zrangebyscore(K_LEASES, "-inf", now):
            job_id = raw_id.decode()
            outcome = self._reap_one(job_id)
            if outcome:
                done.append((job_id, outcome))
        return done

    def _reap_one(self, job_id: str) -> str | None:
        key = _k_job(job_id)
        with self.r.pipeline() as pipe:
            while True:
                try:
                    pipe.watch(key)
                    s, us = pipe.time()
                    now = s + us / 1e6
                    h = {k.decode(): v.decode() for k, v in pipe.hgetall(key).items()}
                    if h.get("state") != "running":
                        pipe.multi()
                        pipe.zrem(K_LEASES, job_id)
                        pipe.execute()
                        return None
                    if float(h.get("lease_until") or 0) > now:
                        pipe.unwatch()
                        return None
                    attempt, worker = int(h["attempt"]), h.get("worker", "")
                    lost = f"worker {worker or '?'} stopped renewing the lease of attempt {attempt}"
                    if h.get("cancel_requested") == "1":
                        state, reason = "cancelled", lost + "; cancellation had been requested"
                    elif attempt >= self.max_attempts:
                        state, reason = "failed", lost + f"; giving up after {attempt} attempt(s)"
                    else:
                        state, reason = "queued", lost + "; requeued to resume from the latest checkpoint"
                    pipe.multi()
                    pipe.zrem(K_LEASES, job_id)
                    fields = {"state": state, "updated_at": f"{now:.6f}", "worker": "", "lease_until": ""}
                    if state == "queued":
                        fields["attempt"] = str(attempt + 1)
                        self._enqueue(pipe, job_id, attempt + 1, int(h.get("timeout_s") or 3600))
                    else:
                        fields.update({"finished_at": f"{now:.6f}", "error": reason})
                        pipe.srem(_k_tenant(h["tenant"], "active"), job_id)
                    pipe.hset(key, mapping=fields)
                    pipe.rpush(_k_hist(job_id), json.dumps({"state": state, "at": now, "worker": worker,
                                                            "attempt": attempt, "reason": reason}))
                    pipe.xadd(_k_events(job_id), {"data": json.dumps(
                        {"type": "state", "state": state, "at": now, "attempt": attempt, "reason": reason,
                         "progress": float(h.get("progress") or 0)})}, maxlen=self.stream_maxlen, approximate=True)
                    pipe.execute()
                    log.warning("job %s: %s -> %s", job_id, reason, state)
                    return state
                except redis.WatchError:
                    continue


def _finite(obj):
    """JSON-safe copy: NaN/inf floats become None, numpy scalars become Python numbers."""
    if isinstance(obj, dict):
        return {str(k): _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    if hasattr(obj, "tolist") and callable(obj.tolist):  # numpy / torch scalars and arrays
        return _finite(obj.tolist())
    if isinstance(obj, float) and obj != obj or obj in (float("inf"), float("-inf")):
        return None
    if isinstance(obj, (str, int, float, bool)) or obj is None:
        return obj
    return str(obj)


def _decode_job(raw: dict) -> dict:
    h = {k.decode(): v.decode() for k, v in raw.items()}

    def num(name, cast=float):
        v = h.get(name)
        return cast(v) if v not in (None, "") else None

    return {"job_id": h["job_id"], "tenant": h["tenant"], "state": h["state"], "progress": num("progress") or 0.0,
            "scene_id": h.get("scene_id") or None, "error": h.get("error") or None, "preset": h.get("preset"),
            "created_at": num("created_at"), "updated_at": num("updated_at"), "started_at": num("started_at"),
            "finished_at": num("finished_at"), "attempt": num("attempt", int) or 1, "worker": h.get("worker") or None,
            "lease_until": num("lease_until"), "cancel_requested": h.get("cancel_requested") == "1",
            "phase": h.get("phase") or None, "iteration": num("iteration", _int), "total": num("total", _int),
            "timeout_s": num("timeout_s", int), "input_path": h.get("input_path"),
            "options": json.loads(h.get("options") or "{}"), "input": json.loads(h.get("input") or "{}"),
            "summary": json.loads(h["summary"]) if h.get("summary") else None}


def _int(v: str) -> int | None:
    try:
        return int(float(v))
    except ValueError:
        return None
