"""Deployment: ``docker compose config`` validates, the Dockerfiles are consistent, and ``agg serve`` runs the
API + a worker + its own redis-server on one machine (no Docker), loopback-only with a generated key."""

from __future__ import annotations

import importlib.util
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time

import httpx
import pytest
import yaml

from service.redis_local import free_port
from tests.service_helpers import ROOT, SAMPLE, STANDIN, wait_for

pytestmark = pytest.mark.timeout(90)


def compose_command() -> list[str] | None:
    for cmd in (["docker", "compose"], ["docker-compose"]):
        if shutil.which(cmd[0]) is None:
            continue
        try:
            if subprocess.run(cmd + ["version"], capture_output=True, timeout=20).returncode == 0:
                return cmd
        except (OSError, subprocess.TimeoutExpired):
            continue
    return None


def test_compose_config_validates(tmp_path):
    cmd = compose_command()
    if cmd is None:
        pytest.skip("neither 'docker compose' nor 'docker-compose' is installed")
    keys = tmp_path / "keys.txt"
    keys.write_text("ops:0123456789abcdef0123\n")
    env = {**os.environ, "AGG_API_KEYS_FILE": str(keys), "AGG_WORKERS": "3"}
    res = subprocess.run(cmd + ["-f", str(ROOT / "docker-compose.yml"), "--profile", "gpu", "config"], cwd=ROOT,
                         env=env, capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    cfg = yaml.safe_load(res.stdout)
    services = cfg["services"]
    assert {"redis", "api", "worker", "grpc", "worker-gpu"} <= set(services)
    redis_cmd = " ".join(services["redis"]["command"])
    assert "--appendonly yes" in redis_cmd and "--maxmemory-policy noeviction" in redis_cmd
    assert int(services["worker"]["deploy"]["replicas"]) == 3
    assert services["worker-gpu"]["profiles"] == ["gpu"]
    gpu = services["worker-gpu"]["deploy"]["resources"]["reservations"]["devices"][0]
    assert gpu["driver"] == "nvidia" and "gpu" in gpu["capabilities"]
    for name in ("api", "worker", "grpc", "worker-gpu"):
        mounts = services[name]["volumes"]
        assert any((m["source"] if isinstance(m, dict) else m.split(":")[0]) == "agg-data" for m in mounts), name
        assert services[name]["environment"]["AGG_DATA_DIR"] == "/data"
        assert services[name]["environment"]["AGG_REDIS_URL"] == "redis://redis:6379/0"
    assert "agg-data" in cfg["volumes"]


def test_dockerfiles_are_consistent():
    grpc_landed = (ROOT / "worker" / "grpc_server.py").exists()
    for name in ("Dockerfile.api", "Dockerfile.worker", "Dockerfile.worker-gpu"):
        text = (ROOT / "docker" / name).read_text()
        assert 'pip install "torch==2.13.0"' in text, name
        for src in re.findall(r"^COPY (\S+) ", text, flags=re.M):
            if src == "proto" and not grpc_landed:
                continue  # proto/ arrives with the gRPC servers
            assert (ROOT / src).exists(), f"{name}: COPY {src} does not exist"
        assert "USER agg" in text, name
    assert "whl/cpu" in (ROOT / "docker" / "Dockerfile.worker").read_text()
    gpu = (ROOT / "docker" / "Dockerfile.worker-gpu").read_text()
    assert "nvidia/cuda" in gpu and "gsplat" in gpu and "whl/cu" in gpu


def _read_until(proc, pattern: str, timeout: float) -> str:
    out, deadline = "", time.monotonic() + timeout
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            if proc.poll() is not None:
                break
            continue
        out += line
        if re.search(pattern, out):
            return out
    raise AssertionError(f"no {pattern!r} in the output of agg serve:\n{out}")


def _non_loopback_ip() -> str | None:
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.connect(("192.0.2.1", 9))  # no packet is sent; picks the outgoing interface
            ip = s.getsockname()[0]
        return None if ip.startswith("127.") else ip
    except OSError:
        return None


def test_agg_serve_runs_everything_on_one_machine(tmp_path):
    if shutil.which("redis-server") is None:
        pytest.skip("redis-server is not installed (bash scripts/install_service_deps.sh)")
    http, grpc = free_port(), free_port()
    env = {**os.environ, "AGG_ENGINE": STANDIN, "AGG_WRITE_PREVIEW": "0", "AGG_TEST_ENGINE_ITERS": "10",
           "AGG_TEST_ENGINE_SLEEP": "0.01", "PYTHONPATH": str(ROOT), "AGG_REDIS_URL": ""}
    proc = subprocess.Popen([sys.executable, "-m", "service.serve", "--http-port", str(http), "--grpc-port",
                             str(grpc), "--data-dir", str(tmp_path / "agg")], cwd=ROOT, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)
    try:
        out = _read_until(proc, r"API key \(tenant 'local'\): (\S+)", 60)
        key = re.search(r"API key \(tenant 'local'\): (\S+)", out).group(1)
        assert (tmp_path / "agg" / "generated-api-key").read_text() == f"local:{key}\n"
        assert oct((tmp_path / "agg" / "generated-api-key").stat().st_mode & 0o777) == "0o600"
        base = f"http://127.0.0.1:{http}"
        wait_for(lambda: _ok(base + "/readyz"), 30, what="the API")
        ip = _non_loopback_ip()
        if ip is not None:
            with pytest.raises(httpx.ConnectError):
                httpx.get(f"http://{ip}:{http}/healthz", timeout=2)
        with httpx.Client(base_url=base, headers={"Authorization": f"Bearer {key}"}, timeout=30) as c:
            assert c.get("/v1/jobs").status_code == 200
            wrong = {"Authorization": "Bearer nope-nope-nope-nope"}
            assert httpx.get(base + "/v1/jobs", headers=wrong).status_code == 401
            r = c.post("/v1/jobs", files={"video": ("dashcam.mp4", SAMPLE.read_bytes())}, data={"preset": "fast"})
            assert r.status_code == 202, r.text
            jid = r.json()["job_id"]
            job = wait_for(lambda: (j := c.get(f"/v1/jobs/{jid}").json())["state"] == "succeeded" and j, 60,
                           what="the local worker")
            assert job["history"][1]["worker"] == "local-1"
        assert (tmp_path / "agg" / "redis" / "appendonlydir").is_dir()  # its own redis, AOF on
        if importlib.util.find_spec("worker.grpc_server") is not None:
            with socket.create_connection(("127.0.0.1", grpc), timeout=5):
                pass
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            raise
    assert proc.returncode == 0
    redis_port = int(re.search(r"redis: redis://127\.0\.0\.1:(\d+)/0", out).group(1))
    with pytest.raises(OSError):  # its redis-server stopped with it
        socket.create_connection(("127.0.0.1", redis_port), timeout=2).close()


def _ok(url: str) -> bool:
    try:
        return httpx.get(url, timeout=2).status_code == 200
    except httpx.HTTPError:
        return False


def test_agg_serve_refuses_a_public_bind_without_keys(tmp_path):
    res = subprocess.run([sys.executable, "-m", "service.serve", "--host", "0.0.0.0", "--data-dir",
                          str(tmp_path / "agg"), "--http-port", str(free_port())], cwd=ROOT, capture_output=True,
                         text=True, timeout=60)
    assert res.returncode == 2 and "loopback only" in res.stderr
