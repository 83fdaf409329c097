"""Helpers of the service tests: a live uvicorn server in a thread, worker subprocesses, polling.

Everything is real: redis-server (tests/redis_server.py), uvicorn on a random loopback port, ``python -m
worker.cli`` processes running RQ. The queue tests run the workers on ``tests.service_engine`` (the engine
contract's stand-in) until ``agg.train.reconstruct`` exists; tests/test_service_engine_e2e.py runs the real one.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from fractions import Fraction
from pathlib import Path

import httpx
import uvicorn

from service.app import create_app
from service.auth import KeyStore
from service.config import ServiceConfig
from service.redis_local import free_port

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "samples" / "dashcam.mp4"
KEYS = {"alice": "alice-key-0123456789abcdef", "bob": "bob-key-0123456789abcdef00"}
STANDIN = "tests.service_engine:reconstruct"


def keystore() -> KeyStore:
    return KeyStore.from_pairs(list(KEYS.items()))


def write_keys(path: Path) -> Path:
    path.write_text("".join(f"{t}:{k}\n" for t, k in KEYS.items()))
    return path


class LiveServer:
    """uvicorn serving ``create_app(config)`` on a random loopback port, in a daemon thread."""

    def __init__(self, config: ServiceConfig, **app_kwargs):
        self.config = config
        self.app = create_app(config, keystore(), **app_kwargs)
        self.port = free_port()
        self.server = uvicorn.Server(uvicorn.Config(self.app, host="127.0.0.1", port=self.port, log_level="warning",
                                                    lifespan="on"))
        self.thread = threading.Thread(target=self.server.run, daemon=True)

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def start(self) -> "LiveServer":
        self.thread.start()
        deadline = time.monotonic() + 15
        while not self.server.started:
            if time.monotonic() > deadline or not self.thread.is_alive():
                raise RuntimeError("uvicorn did not start")
            time.sleep(0.02)
        return self

    def stop(self) -> None:
        self.server.should_exit = True
        self.thread.join(10)

    def client(self, tenant: str | None = "alice", **kwargs) -> httpx.Client:
        headers = {"Authorization": f"Bearer {KEYS[tenant]}"} if tenant else {}
        kwargs.setdefault("timeout", 30)
        return httpx.Client(base_url=self.url, headers=headers, **kwargs)


def start_worker(config: ServiceConfig, name: str, *, iters: int = 20, sleep: float = 0.05, burst: bool = False,
                 extra_env: dict | None = None) -> subprocess.Popen:
    """``python -m worker.cli`` on the stand-in engine, in its own session (so the test can kill it)."""
    env = {**os.environ, **config.to_env(), "AGG_ENGINE": STANDIN, "AGG_WRITE_PREVIEW": "0",
           "AGG_TEST_ENGINE_ITERS": str(iters), "AGG_TEST_ENGINE_SLEEP": str(sleep), "PYTHONPATH": str(ROOT),
           **(extra_env or {})}
    args = [sys.executable, "-m", "worker.cli", "--redis-url", config.redis_url, "--data-dir",
            str(config.data_dir), "--name", name] + (["--burst"] if burst else [])
    log = open(Path(config.data_dir).parent / f"worker-{name}.log", "ab")  # noqa: SIM115 - the child owns it
    try:
        return subprocess.Popen(args, cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    finally:
        log.close()


def children(pid: int) -> list[int]:
    """Direct child pids of ``pid`` (from /proc)."""
    out = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                stat = (d / "stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                out.append(int(d.name))
    return out


def kill_tree(proc: subprocess.Popen, sig: int = signal.SIGKILL) -> list[int]:
    """Send ``sig`` to a worker and its work horses (which run in their own process groups); the pids hit."""
    pids = [proc.pid] + children(proc.pid)
    for pid in pids:
        try:
            os.kill(pid, sig)
        except ProcessLookupError:
            pass
    return pids


def stop_worker(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        kill_tree(proc, signal.SIGKILL)
        proc.wait(10)


def wait_for(predicate, timeout: float = 30.0, interval: float = 0.05, what: str = "condition"):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(interval)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


def service_config(tmp: Path, redis_url: str, **kw) -> ServiceConfig:
    base = dict(data_dir=tmp / "data", redis_url=redis_url, lease_s=2.0, reap_interval_s=0.3, checkpoint_every=5,
                write_preview=False, engine=STANDIN, max_upload_bytes=2_000_000, max_active_jobs=50,
                preset_timeouts={"tiny": 120, "fast": 600})
    base.update(kw)
    return ServiceConfig(**base)


def upload(client: httpx.Client, data: bytes | None = None, preset: str = "tiny", filename: str = "clip.mp4",
           **fields) -> httpx.Response:
    files = {"video": (filename, SAMPLE.read_bytes() if data is None else data, "video/mp4")}
    return client.post("/v1/jobs", files=files, data={"preset": preset, **fields})


def small_clip(path: Path, frames: int = 8, width: int = 320) -> Path:
    """The first ``frames`` frames of the sample clip at ``width`` px (H.264): a real, quick upload."""
    import av
    import numpy as np

    from agg.io.video import IngestConfig, read_video

    res = read_video(SAMPLE, IngestConfig(width=width, dtype="uint8", max_frames=frames))
    with av.open(str(path), "w") as c:
        s = c.add_stream("libx264" if "libx264" in av.codecs_available else "mpeg4", rate=Fraction(25))
        s.width, s.height, s.pix_fmt = res.size[0], res.size[1], "yuv420p"
        for f in res.frames:
            for p in s.encode(av.VideoFrame.from_ndarray(np.ascontiguousarray(f), format="rgb24")):
                c.mux(p)
        for p in s.encode(None):
            c.mux(p)
    return path
