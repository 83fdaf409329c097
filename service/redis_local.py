"""A private redis-server child process on a loopback port (``agg serve`` without ``--redis-url``; the tests).

Persistence is the append-only file (``appendonly yes``) in ``dir``, so queued jobs survive a restart; the
eviction policy is ``noeviction`` (a queue must never silently lose keys).
"""

from __future__ import annotations

import shutil
import socket
import subprocess
import time
from pathlib import Path

import redis


class RedisNotInstalled(RuntimeError):
    """No ``redis-server`` executable on PATH."""


def free_port(host: str = "127.0.0.1") -> int:
    with socket.socket() as s:
        s.bind((host, 0))
        return s.getsockname()[1]


class RedisProcess:
    """Start/stop/restart one redis-server; ``url`` and ``client()`` to talk to it."""

    def __init__(self, data_dir: str | Path, port: int | None = None, *, appendfsync: str = "everysec",
                 executable: str | None = None, log_file: str | Path | None = None):
        self.exe = executable or shutil.which("redis-server")
        if not self.exe:
            raise RedisNotInstalled("redis-server is not installed (bash scripts/install_service_deps.sh), "
                                    "or pass --redis-url")
        self.dir = Path(data_dir)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.port = port or free_port()
        self.appendfsync = appendfsync
        self.log_file = Path(log_file) if log_file else self.dir / "redis.log"
        self.proc: subprocess.Popen | None = None

    @property
    def url(self) -> str:
        return f"redis://127.0.0.1:{self.port}/0"

    def client(self, **kwargs) -> redis.Redis:
        return redis.Redis.from_url(self.url, **kwargs)

    def start(self, timeout_s: float = 10.0) -> "RedisProcess":
        args = [self.exe, "--port", str(self.port), "--bind", "127.0.0.1", "--dir", str(self.dir.resolve()),
                "--appendonly", "yes", "--appendfsync", self.appendfsync, "--save", "",
                "--maxmemory-policy", "noeviction", "--protected-mode", "yes",
                "--logfile", str(self.log_file.resolve()), "--daemonize", "no"]
        self.proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                     start_new_session=True)
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"redis-server exited with {self.proc.returncode}; see {self.log_file}")
            try:
                c = self.client(socket_connect_timeout=0.2)
                if c.ping() and c.info("persistence").get("loading", 0) == 0:
                    c.close()
                    return self
            except redis.exceptions.RedisError:
                pass
            time.sleep(0.05)
        raise RuntimeError(f"redis-server on port {self.port} did not answer within {timeout_s} s")

    def stop(self, kill: bool = False, timeout_s: float = 10.0) -> None:
        """SIGTERM (Redis flushes the AOF and exits) or, with ``kill``, SIGKILL."""
        if self.proc is None or self.proc.poll() is not None:
            return
        (self.proc.kill if kill else self.proc.terminate)()
        try:
            self.proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()

    def restart(self, kill: bool = False) -> "RedisProcess":
        self.stop(kill=kill)
        return self.start()

    def __enter__(self) -> "RedisProcess":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
