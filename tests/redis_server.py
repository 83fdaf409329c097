"""Fixtures for the service tests: a real redis-server on a random loopback port (never the machine's 6379).

Import the fixtures into a test module (``from tests.redis_server import redis_proc, rclient``). Tests skip when
``redis-server`` is not installed (``bash scripts/install_service_deps.sh`` installs it).
"""

from __future__ import annotations

import pytest

from service.redis_local import RedisNotInstalled, RedisProcess


@pytest.fixture(scope="module")
def redis_proc(tmp_path_factory):
    """One redis-server per test module (AOF on, appendfsync always so a SIGKILL loses nothing)."""
    try:
        proc = RedisProcess(tmp_path_factory.mktemp("redis"), appendfsync="always")
    except RedisNotInstalled as exc:
        pytest.skip(str(exc))
    proc.start()
    yield proc
    proc.stop(kill=True)


@pytest.fixture
def rclient(redis_proc):
    """A client of the module's server, emptied before each test."""
    c = redis_proc.client()
    c.flushall()
    yield c
    c.close()
