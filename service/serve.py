"""``agg serve``: the API, one worker and the gRPC servers on one machine, without Docker.

Stable interface: ``agg serve --http-port P --grpc-port G --data-dir DIR --api-keys FILE``. Without ``--redis-url``
(or ``AGG_REDIS_URL``) it starts a private redis-server (AOF in ``DIR/redis``) when one is installed. Without
``--api-keys`` it generates one key, prints it (and writes it to ``DIR/generated-api-key``, mode 0600), and binds
to loopback only.
"""

from __future__ import annotations

import argparse
import ipaddress
import logging
import os
import signal
import subprocess
import sys
from pathlib import Path

log = logging.getLogger("agg.serve")


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "serve", help="run the HTTP API, a worker and gRPC on this machine (no Docker needed)",
        description="Run the AGG service on one machine: the HTTP API, --workers job workers and the gRPC "
                    "render/scene/job services. Needs redis-server (installed by scripts/install_service_deps.sh) "
                    "unless --redis-url points at a running Redis. See docs/SERVICE.md.")
    add_arguments(p)
    p.set_defaults(func=run_serve)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--http-port", type=int, default=8000, help="HTTP port (default 8000)")
    p.add_argument("--grpc-port", type=int, default=50051, help="gRPC port (default 50051; 0 disables gRPC)")
    p.add_argument("--data-dir", type=Path, default=None, help="uploads, scenes and Redis data [AGG_DATA_DIR, "
                                                                "default ./agg-data]")
    p.add_argument("--api-keys", type=Path, default=None, help="file of 'tenant:key' lines [AGG_API_KEYS]; "
                                                               "without it: one generated key, loopback only")
    p.add_argument("--redis-url", default=None, help="use this Redis instead of starting one [AGG_REDIS_URL]")
    p.add_argument("--host", default=None, help="bind address (default 0.0.0.0 with --api-keys, else 127.0.0.1)")
    p.add_argument("--workers", type=int, default=1, help="local job workers (default 1; 0 for none)")
    p.add_argument("--engine", default=None, help="engine 'module:function' [AGG_ENGINE]")


def _is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def run_serve(args: argparse.Namespace) -> int:
    import uvicorn

    from service.app import create_app
    from service.auth import KeyFileError, KeyStore
    from service.config import ServiceConfig
    from service.jobstore import JobStore
    from service.redis_local import RedisNotInstalled, RedisProcess, free_port

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    config = ServiceConfig.from_env(redis_url=args.redis_url, api_keys_file=args.api_keys, engine=args.engine,
                                    data_dir=args.data_dir)
    if args.data_dir is None and not os.environ.get("AGG_DATA_DIR"):
        config.data_dir = Path("agg-data")
    config.data_dir = config.data_dir.resolve()
    config.data_dir.mkdir(parents=True, exist_ok=True)

    generated = None
    if config.api_keys_file:
        try:
            keystore = KeyStore.from_file(config.api_keys_file)
        except KeyFileError as exc:
            print(f"agg serve: {exc}", file=sys.stderr)
            return 2
        host = args.host or "0.0.0.0"
    else:
        keystore, generated = KeyStore.generate("local")
        host = args.host or "127.0.0.1"
        if not _is_loopback(host):
            print("agg serve: without --api-keys the service binds to loopback only; pass --api-keys FILE to "
                  f"listen on {host}", file=sys.stderr)
            return 2
        key_file = config.data_dir / "generated-api-key"
        fd = os.open(key_file, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "w") as fh:
            fh.write(f"local:{generated}\n")

    redis_proc = None
    if not config.redis_url:
        try:
            redis_proc = RedisProcess(config.data_dir / "redis", free_port()).start()
        except RedisNotInstalled as exc:
            print(f"agg serve: {exc}", file=sys.stderr)
            return 2
        config.redis_url = redis_proc.url
        log.info("started redis-server on %s (AOF in %s)", redis_proc.url, redis_proc.dir)

    workers: list[subprocess.Popen] = []
    grpc_server = None
    try:
        env = {**os.environ, **config.to_env()}
        for i in range(max(args.workers, 0)):
            workers.append(subprocess.Popen([sys.executable, "-m", "worker.cli", "--redis-url", config.redis_url,
                                             "--data-dir", str(config.data_dir), "--name", f"local-{i + 1}"],
                                            env=env))
        app = create_app(config, keystore)
        if args.grpc_port:
            import redis as redis_lib

            from worker.runner import start_grpc

            store = JobStore.from_config(redis_lib.Redis.from_url(config.redis_url), config)
            try:
                grpc_server = start_grpc(args.grpc_port, host, keystore.tenant_for, store)
            except ImportError as exc:
                log.error("gRPC not started: %s", exc)
                args.grpc_port = 0
        _banner(host, args.http_port, args.grpc_port, config, generated, len(workers))
        # uvicorn shuts down gracefully on SIGINT/SIGTERM, then re-raises the signal: turn both into
        # KeyboardInterrupt so the workers and redis-server are stopped below.
        signal.signal(signal.SIGTERM, _interrupt)
        try:
            uvicorn.Server(uvicorn.Config(app, host=host, port=args.http_port, log_level="info")).run()
        except KeyboardInterrupt:
            pass
        return 0
    finally:
        if grpc_server is not None:
            grpc_server.stop(grace=2)
        for w in workers:
            if w.poll() is None:
                w.send_signal(signal.SIGTERM)
        for w in workers:
            try:
                w.wait(timeout=15)
            except subprocess.TimeoutExpired:
                w.kill()  # its job's lease expires and the job is requeued at the next start
        if redis_proc is not None:
            redis_proc.stop()


def _interrupt(signum, frame) -> None:
    raise KeyboardInterrupt


def _banner(host: str, http_port: int, grpc_port: int, config, key: str | None, n_workers: int) -> None:
    shown = "127.0.0.1" if host in ("0.0.0.0", "::") else host
    lines = [f"AGG service: http://{shown}:{http_port}  (OpenAPI docs at /docs)",
             f"  gRPC: {shown}:{grpc_port}" if grpc_port else "  gRPC: off",
             f"  data: {config.data_dir}   redis: {config.redis_url}   workers: {n_workers}"]
    if key:
        lines += [f"  API key (tenant 'local'): {key}",
                  f"  (also in {config.data_dir / 'generated-api-key'}; bound to loopback only)",
                  f"  curl -H 'Authorization: Bearer {key}' -F video=@samples/dashcam.mp4 -F preset=fast "
                  f"http://{shown}:{http_port}/v1/jobs"]
    print("\n".join(lines), flush=True)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="agg serve")
    add_arguments(parser)
    return run_serve(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
