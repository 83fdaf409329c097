"""The whole service as one child process on this machine, for ``agg demo`` (service/demo.py) and the load bench
(bench/service_load.py): ``agg serve`` (``python -m service.serve``) in its own session, on free loopback ports,
with its own Redis and data folder and one generated API key, and its stop, which kills whatever of its process
tree outlives the grace period."""

from __future__ import annotations

import os
import secrets
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx

from service.redis_local import free_port

ROOT = Path(__file__).resolve().parents[1]
MARKER = ".agg-demo"  # marks OUT/service as the demo's own folder (it is emptied at each start)


class DemoError(RuntimeError):
    """A step of the demo failed; the message says which and why."""


# ----------------------------------------------------------------------------------------------- processes


def _stat(pid: int) -> tuple[int, str] | None:
    """(parent pid, start time) of a live process from /proc, or None."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None
    return int(fields[1]), fields[19]


def process_tree(root: int) -> dict[int, str]:
    """{pid: start time} of ``root`` and all its descendants (Linux /proc; just the root elsewhere)."""
    parents: dict[int, list[int]] = {}
    for d in Path("/proc").glob("[0-9]*"):
        st = _stat(int(d.name))
        if st is not None:
            parents.setdefault(st[0], []).append(int(d.name))
    out, todo = {}, [root]
    while todo:
        pid = todo.pop()
        st = _stat(pid)
        if st is None or pid in out:
            continue
        out[pid] = st[1]
        todo += parents.get(pid, [])
    return out


def kill_survivors(tree: dict[int, str]) -> list[int]:
    """SIGKILL the processes of ``tree`` that are still alive (same pid *and* start time); the pids killed."""
    killed = []
    for pid, started in tree.items():
        st = _stat(pid)
        if st is not None and st[1] == started:
            try:
                os.kill(pid, signal.SIGKILL)
                killed.append(pid)
            except ProcessLookupError:
                pass
    return killed


class EmbeddedService:
    """``agg serve`` (``python -m service.serve``) in its own session, on free loopback ports, with one key.

    ``fresh``: empty ``data_dir`` first and generate a key (tenant ``demo``); else restart the service over an
    earlier run's folder (its Redis AOF keeps the jobs and scene owners; its ``api-keys.txt`` the key).
    """

    def __init__(self, data_dir: Path, log_path: Path, *, workers: int = 1, fresh: bool = True):
        self.data_dir, self.log_path = data_dir.resolve(), log_path.resolve()
        self.workers, self.fresh = int(workers), fresh
        self.key = secrets.token_urlsafe(24)
        self.http_port, self.grpc_port = free_port(), free_port()
        self.proc: subprocess.Popen | None = None

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.http_port}"

    @property
    def grpc_address(self) -> str:
        return f"127.0.0.1:{self.grpc_port}"

    def start(self) -> EmbeddedService:
        keys = self.data_dir / "api-keys.txt"
        if self.data_dir.exists() and not (self.data_dir / MARKER).is_file():
            raise DemoError(f"{self.data_dir} exists and is not a demo folder; choose another --out")
        if not self.fresh:
            if not keys.is_file():
                raise DemoError(f"{self.data_dir} has no api-keys.txt: not the folder of an earlier agg demo run")
            self.key = keys.read_text().strip().partition(":")[2]
        else:
            if self.data_dir.exists():
                shutil.rmtree(self.data_dir)
            self.data_dir.mkdir(parents=True)
            (self.data_dir / MARKER).write_text("created by agg demo; emptied at each run\n")
            fd = os.open(keys, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
            with os.fdopen(fd, "w") as fh:
                fh.write(f"demo:{self.key}\n")
        # Our own Redis and data folder whatever the caller's environment says.
        env = {k: v for k, v in os.environ.items() if k not in ("AGG_REDIS_URL", "AGG_API_KEYS")}
        env["AGG_DATA_DIR"] = str(self.data_dir)
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))
        args = [sys.executable, "-m", "service.serve", "--http-port", str(self.http_port), "--grpc-port",
                str(self.grpc_port), "--data-dir", str(self.data_dir), "--api-keys", str(keys),
                "--host", "127.0.0.1", "--workers", str(self.workers)]
        with open(self.log_path, "ab" if not self.fresh else "wb") as log:
            self.proc = subprocess.Popen(args, cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT,
                                         stdin=subprocess.DEVNULL, start_new_session=True)
        return self

    def log_tail(self, n: int = 15) -> str:
        try:
            return "\n".join(self.log_path.read_text(errors="replace").splitlines()[-n:])
        except OSError:
            return ""

    def wait_ready(self, timeout_s: float) -> None:
        """Until ``/readyz`` answers 200 (Redis up, API serving; gRPC starts before the API)."""
        deadline = time.monotonic() + timeout_s
        with httpx.Client(base_url=self.url, timeout=2.0) as c:
            while time.monotonic() < deadline:
                if self.proc.poll() is not None:
                    raise DemoError(f"agg serve exited with {self.proc.returncode}:\n{self.log_tail()}")
                try:
                    if c.get("/readyz").status_code == 200:
                        return
                except httpx.HTTPError:
                    pass
                time.sleep(0.25)
        raise DemoError(f"the service did not become ready within {timeout_s:.0f} s:\n{self.log_tail()}")

    def stop(self, grace_s: float = 30.0) -> list[int]:
        """SIGTERM ``agg serve`` (it stops the API, gRPC, the worker, then Redis), wait, then SIGKILL whatever
        of its process tree (work horse, worker, redis-server) is still alive; the pids that had to be killed."""
        if self.proc is None:
            return []
        tree = process_tree(self.proc.pid)
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(grace_s)
            except subprocess.TimeoutExpired:
                pass
        killed = kill_survivors(tree)
        if self.proc.poll() is None:
            self.proc.wait(5)
        return killed

    def kill_jobs(self) -> None:
        """SIGKILL the work horses (grandchildren of ``agg serve``: a job still in its priors phase ignores a
        cancellation until training starts), so that the workers can stop at once."""
        if self.proc is None:
            return
        tree = process_tree(self.proc.pid)
        children = [p for p in tree if p != self.proc.pid and (_stat(p) or (0,))[0] == self.proc.pid]
        for child in children:  # the worker (its horse below it) and redis-server (no children)
            kill_survivors({p: t for p, t in process_tree(child).items() if p != child})
