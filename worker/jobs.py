"""The job function RQ runs: one attempt of one reconstruction job.

``run_job(job_id, attempt)`` claims the job in the job-state hash (queued -> running, fenced by ``attempt``),
keeps its lease alive from a heartbeat thread, runs the engine (``agg.train.reconstruct`` by default,
``AGG_ENGINE`` to change it) with progress and cancellation callbacks, resuming from the scene's latest
checkpoint, writes ``preview.mp4``, and records the final state. A stale attempt (its lease expired and the job was
requeued, or it was cancelled) changes nothing: every write is fenced by the attempt number.
"""

from __future__ import annotations

import importlib
import inspect
import logging
import os
import socket
import threading
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path

import redis

from service.config import ServiceConfig
from service.jobstore import JobStore

log = logging.getLogger(__name__)

# Share of the progress bar given to the priors phase; training fills the rest.
PRIORS_SHARE = 0.15


@dataclass
class WorkerSettings:
    """What a job attempt needs besides the job itself (from ``ServiceConfig``; set by the runner)."""

    config: ServiceConfig = field(default_factory=ServiceConfig.from_env)
    worker_name: str = field(default_factory=lambda: f"{socket.gethostname()}:{os.getpid()}")
    progress_interval_s: float = 0.5  # at most one progress write per interval (phase changes always go)


SETTINGS: WorkerSettings | None = None  # set by worker.runner before it forks work horses


class Heartbeat(threading.Thread):
    """Renews the lease every lease/3 s; sets ``stop`` when cancellation is requested or the lease is lost.

    ``holds_lease()`` is the local check: False once a full lease period has passed since the start of the last
    successful renewal (the process was paused, or Redis was unreachable), because the reaper may then have given
    the job to another worker.
    """

    def __init__(self, store: JobStore, job_id: str, attempt: int, lease_s: float):
        super().__init__(daemon=True, name=f"lease-{job_id}")
        self.store, self.job_id, self.attempt, self.lease_s = store, job_id, attempt, lease_s
        self.stop, self.cancel, self.lost, self._done = (threading.Event(), threading.Event(), threading.Event(),
                                                         threading.Event())
        self.valid_until = time.monotonic() + lease_s

    def holds_lease(self) -> bool:
        if time.monotonic() > self.valid_until:
            self.lost.set()
            self.stop.set()
        return not self.lost.is_set()

    def run(self) -> None:
        while not self._done.wait(self.lease_s / 3):
            t0 = time.monotonic()
            try:
                res = self.store.renew(self.job_id, self.attempt, self.lease_s)
            except redis.RedisError as exc:
                log.warning("job %s: lease renewal failed (%s)", self.job_id, exc)
                self.holds_lease()
                continue
            if res != "lost":
                self.valid_until = t0 + self.lease_s
            if res == "cancel":
                self.cancel.set()
                self.stop.set()
            elif res == "lost":
                self.lost.set()
                self.stop.set()

    def close(self) -> None:
        self._done.set()


def load_engine(spec: str):
    """(function, Cancelled exception class or None) of a "module:function" spec."""
    module_name, _, func_name = spec.partition(":")
    module = importlib.import_module(module_name)
    fn = getattr(module, func_name or "reconstruct")
    cancelled = getattr(module, "Cancelled", None)
    if cancelled is None:
        cancelled = getattr(importlib.import_module(fn.__module__), "Cancelled", None)
    return fn, cancelled


def takes_device(fn) -> bool:
    """Whether an engine function accepts ``device`` (``agg.train:reconstruct`` does; a custom engine may not)."""
    try:
        params = inspect.signature(fn).parameters
    except (TypeError, ValueError):
        return False
    return "device" in params or any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values())


def engine_options(options: dict, input_path: str) -> dict:
    """``reconstruct`` keyword arguments from the upload options: ``max_frames``; ``intrinsics`` (the uploaded
    OpenCV calibration file, stored next to the video, or "fx,fy,cx,cy"), as ``agg priors`` takes them."""
    out = {}
    if options.get("max_frames"):
        out["max_frames"] = int(options["max_frames"])
    if options.get("calibration"):
        out["intrinsics"] = str(Path(input_path).parent / Path(options["calibration"]).name)
    elif options.get("intrinsics"):
        out["intrinsics"] = str(options["intrinsics"])
    return out


def _num(v) -> float:
    try:
        return float(v)
    except (TypeError, ValueError):
        return 0.0


def progress_fraction(event: dict) -> float:
    """Overall progress in [0, 1] from an engine event: the priors stages fill [0, PRIORS_SHARE) in order
    (``step`` = stage, ``done``/``total`` within it), training iterations the rest; other events give 0 (the
    store keeps the maximum, so they never move the bar back)."""
    total = _num(event.get("total"))
    if event.get("phase") == "priors" or event.get("stage") == "priors":
        from agg.priors.pipeline import STAGES

        frac = min(max(_num(event.get("done")) / total, 0.0), 1.0) if total > 0 else 0.0
        step = event.get("step")
        k = STAGES.index(step) if step in STAGES else 0
        return PRIORS_SHARE * (k + frac) / len(STAGES)
    if event.get("iteration") is None or total <= 0:
        return 0.0
    return PRIORS_SHARE + (1.0 - PRIORS_SHARE) * min(max(_num(event["iteration"]) / total, 0.0), 1.0)


class ProgressSink:
    """The engine's ``progress`` callable: throttled writes of progress events to the job store."""

    def __init__(self, store: JobStore, job_id: str, attempt: int, heartbeat: Heartbeat, interval_s: float):
        self.store, self.job_id, self.attempt, self.hb, self.interval_s = store, job_id, attempt, heartbeat, interval_s
        self._last, self._phase = 0.0, None

    def __call__(self, event: dict) -> None:
        now = time.monotonic()
        phase = event.get("phase")
        key = (phase, event.get("step"))
        if key == self._phase and now - self._last < self.interval_s and not event.get("final"):
            return
        self._last, self._phase = now, key
        try:
            if self.store.progress(self.job_id, self.attempt, progress_fraction(event), dict(event)) == "lost":
                self.hb.lost.set()
                self.hb.stop.set()
        except redis.RedisError as exc:  # progress is best effort; the lease decides the job's fate
            log.warning("job %s: progress write failed (%s)", self.job_id, exc)


def _connection() -> redis.Redis:
    try:
        from rq import get_current_job

        job = get_current_job()
        if job is not None:
            return job.connection
    except Exception:  # noqa: BLE001 - outside a work horse
        pass
    url = os.environ.get("AGG_REDIS_URL") or "redis://127.0.0.1:6379/0"
    return redis.Redis.from_url(url)


def run_job(job_id: str, attempt: int) -> str:
    """RQ entry point. Returns the final state written, or 'skipped' / 'lost' when this attempt had nothing to do."""
    settings = SETTINGS or WorkerSettings()
    store = JobStore.from_config(_connection(), settings.config)
    return execute(store, job_id, int(attempt), settings)


def execute(store: JobStore, job_id: str, attempt: int, settings: WorkerSettings) -> str:
    cfg, worker = settings.config, settings.worker_name
    t0 = time.monotonic()
    claim = store.start(job_id, attempt, worker, cfg.lease_s)
    if claim != "ok":
        log.info("job %s attempt %d: not started (%s)", job_id, attempt, claim)
        return "skipped"
    job = store.get(job_id)
    hb = Heartbeat(store, job_id, attempt, cfg.lease_s)
    hb.valid_until = t0 + cfg.lease_s  # the lease was granted after t0
    hb.start()
    try:
        state, error, summary = _run_engine(store, job, attempt, settings, hb)
    finally:
        hb.close()
    if hb.lost.is_set() and state != "succeeded":
        log.warning("job %s attempt %d lost its lease; leaving the job to the attempt that owns it", job_id, attempt)
        return "lost"
    res = store.finish(job_id, attempt, state, worker, error=error, summary=summary)
    if res != "ok":
        log.warning("job %s attempt %d: result not recorded (%s): another attempt owns the job", job_id, attempt, res)
        return "lost"
    discard_upload(job["input_path"], cfg)
    return state


def discard_upload(input_path: str, cfg: ServiceConfig) -> None:
    """Delete a finished job's upload folder (the scene keeps its own bundle of the frames); only inside
    ``data_dir/uploads``."""
    import shutil

    folder = Path(input_path).resolve().parent
    root = cfg.uploads_dir.resolve()
    if folder.parent == root:
        shutil.rmtree(folder, ignore_errors=True)


def _run_engine(store: JobStore, job: dict, attempt: int, settings: WorkerSettings,
                hb: Heartbeat) -> tuple[str, str | None, dict | None]:
    """(final state, error message, summary) of one engine run."""
    from rq.timeouts import JobTimeoutException

    cfg = settings.config
    scene_dir = store.scene_dir(job["scene_id"])
    scene_dir.mkdir(parents=True, exist_ok=True)
    try:
        fn, cancelled_exc = load_engine(cfg.engine)
    except (ImportError, AttributeError) as exc:
        return "failed", f"the reconstruction engine {cfg.engine!r} is not available: {exc}", None
    sink = ProgressSink(store, job["job_id"], attempt, hb, settings.progress_interval_s)
    # The preset's time limit is cooperative (the engine stops between iterations, its checkpoint intact); RQ's
    # hard timeout, 60 s later, only catches an engine that stopped polling.
    deadline = time.monotonic() + float(job.get("timeout_s") or 3600)

    def should_stop() -> bool:
        return not hb.holds_lease() or hb.stop.is_set() or time.monotonic() > deadline

    kwargs = dict(progress=sink, should_stop=should_stop, checkpoint_ok=hb.holds_lease, resume=True,
                  checkpoint_every=cfg.checkpoint_every)
    if takes_device(fn):  # the job trains where the worker was told to (AGG_TRAIN_DEVICE, default auto)
        from agg.device import resolve_device

        try:
            kwargs["device"] = str(resolve_device(cfg.train_device))
        except ValueError as exc:
            return "failed", f"AGG_TRAIN_DEVICE: {exc}", None
    kwargs.update(engine_options(job.get("options") or {}, job["input_path"]))
    timed_out = f"timed out after {job.get('timeout_s')} s (the limit of preset {job['preset']!r})"
    try:
        summary = fn(job["input_path"], str(scene_dir), job["preset"], **kwargs)
    except JobTimeoutException:
        return "failed", timed_out, None
    except Exception as exc:  # noqa: BLE001 - every failure becomes the job's error
        if cancelled_exc is not None and isinstance(exc, cancelled_exc) or should_stop():
            if hb.cancel.is_set():
                return "cancelled", "cancelled by the client", None
            if hb.lost.is_set():
                return "failed", "stopped: the worker lost the job's lease", None
            return "failed", timed_out, None
        if isinstance(exc, ValueError):  # the engine's input errors (agg.io.errors) are all ValueErrors
            return "failed", f"invalid input: {exc}", None
        log.error("job %s failed:\n%s", job["job_id"], traceback.format_exc())
        return "failed", f"internal error: {type(exc).__name__}: {exc}", None
    if hb.cancel.is_set():
        return "cancelled", "cancelled by the client", None
    summary = summary if isinstance(summary, dict) else {}
    if cfg.write_preview and not (scene_dir / "preview.mp4").exists() and (scene_dir / "model.pt").exists():
        try:
            sink({"phase": "preview", "iteration": 0, "total": 1, "final": True})
            from worker.preview import write_preview

            write_preview(scene_dir)
        except Exception as exc:  # noqa: BLE001 - a missing preview does not fail the job
            log.warning("job %s: preview.mp4 not written: %s", job["job_id"], exc)
            summary["preview_error"] = f"{type(exc).__name__}: {exc}"
    return "succeeded", None, summary
