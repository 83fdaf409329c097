"""``agg worker``: consume reconstruction jobs from the Redis queue (CPU or GPU), optionally serve gRPC.

Registered as an ``agg`` sub-command through the ``agg.commands`` entry-point group (``register``); also runs as
``python -m worker.cli``.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "worker", help="run a job worker (reconstruction jobs from Redis; optional gRPC renders)",
        description="Consume jobs from the Redis queue and run the engine on them. Settings default to the AGG_* "
                    "environment variables (docs/SERVICE.md). Several workers, on several machines, may share "
                    "one Redis and one --data-dir (a shared volume).")
    add_arguments(p)
    p.set_defaults(func=main_args)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--redis-url", help="redis://host:port/db [AGG_REDIS_URL]")
    p.add_argument("--data-dir", type=Path, help="shared uploads/scenes folder [AGG_DATA_DIR]")
    p.add_argument("--queue", help="RQ queue name [AGG_QUEUE, default agg]")
    p.add_argument("--name", help="worker name in the job history (default host:pid)")
    p.add_argument("--engine", help="engine 'module:function' [AGG_ENGINE, default agg.train:reconstruct]")
    p.add_argument("--checkpoint-every", type=int, help="iterations between checkpoints [AGG_CHECKPOINT_EVERY]")
    p.add_argument("--lease-s", type=float, help="job lease in seconds [AGG_LEASE_S, default 30]")
    p.add_argument("--burst", action="store_true", help="exit when the queue is empty")
    p.add_argument("--grpc-port", type=int, help="also serve the gRPC services on this port (needs --api-keys)")
    p.add_argument("--grpc-host", default="0.0.0.0", help="gRPC bind address (default 0.0.0.0)")
    p.add_argument("--api-keys", type=Path, help="tenant:key file for gRPC [AGG_API_KEYS]")
    p.add_argument("--train-device", help="torch device jobs train on: auto (CUDA when torch sees it), cpu, cuda:N "
                                          "[AGG_TRAIN_DEVICE, default auto]")
    p.add_argument("--grpc-device", default="cpu", help="torch device of gRPC renders (cpu, cuda:0, ...)")
    p.add_argument("--no-jobs", action="store_true", help="serve gRPC only, consume no jobs")


def main_args(args: argparse.Namespace) -> int:
    from agg.device import resolve_device
    from service.config import ServiceConfig
    from worker.runner import run_worker

    config = ServiceConfig.from_env(redis_url=args.redis_url, data_dir=args.data_dir, queue=args.queue,
                                    engine=args.engine, checkpoint_every=args.checkpoint_every,
                                    lease_s=args.lease_s, api_keys_file=args.api_keys,
                                    train_device=args.train_device)
    try:  # bad device names stop the worker before it takes a job
        device = str(resolve_device(args.grpc_device))
        train = resolve_device(config.train_device)
    except ValueError as exc:
        print(f"agg worker: error: {exc}", file=sys.stderr)
        return 2
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    logging.getLogger("agg.worker").info("jobs train on %s (%s)", train, config.train_device)
    return run_worker(config, name=args.name, burst=args.burst, jobs=not args.no_jobs, grpc_port=args.grpc_port,
                      grpc_host=args.grpc_host, api_keys=args.api_keys, device=device)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="agg worker")
    add_arguments(parser)
    return main_args(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
