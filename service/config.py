"""Service configuration: one typed dataclass, filled from ``AGG_*`` environment variables or the ``agg serve`` flags.

Every process of a deployment (API, workers, gRPC) reads the same variables, so docker-compose sets them once.
Sizes are bytes, durations seconds.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field, fields, replace
from pathlib import Path

# Training wall-clock limit of one attempt per preset (RQ job timeout); overridable with AGG_PRESET_TIMEOUTS.
DEFAULT_PRESET_TIMEOUTS = {"tiny": 900, "fast": 3 * 3600, "balanced": 6 * 3600, "quality": 12 * 3600,
                           "paper": 48 * 3600}


def parse_timeouts(spec: str) -> dict[str, int]:
    """``"tiny=900,fast=10800"`` -> {"tiny": 900, "fast": 10800}; raises ValueError on a malformed entry."""
    out: dict[str, int] = {}
    for item in filter(None, (s.strip() for s in spec.split(","))):
        name, _, value = item.partition("=")
        if not name or not value or int(value) <= 0:
            raise ValueError(f"preset timeout {item!r}: expected NAME=SECONDS with SECONDS > 0")
        out[name.strip()] = int(value)
    return out


@dataclass
class ServiceConfig:
    """Settings shared by the API, the workers and ``agg serve`` (env variable in brackets)."""

    data_dir: Path = Path("data")  # shared path for uploads and scenes [AGG_DATA_DIR]
    redis_url: str | None = None  # redis://host:port/db [AGG_REDIS_URL]; None: ``agg serve`` starts one
    queue: str = "agg"  # RQ queue name [AGG_QUEUE]
    api_keys_file: Path | None = None  # lines "tenant:key" [AGG_API_KEYS]
    max_upload_bytes: int = 1 << 30  # video part size limit, 413 beyond [AGG_MAX_UPLOAD_BYTES]
    max_active_jobs: int = 4  # per tenant: queued + running + uploads in flight, 429 beyond [AGG_MAX_ACTIVE_JOBS]
    max_jobs_per_day: int = 200  # per tenant: accepted uploads in a rolling day, 429 beyond [AGG_MAX_JOBS_PER_DAY]
    max_frames_limit: int = 5000  # largest accepted ``max_frames`` option
    # the accepted presets and the time limit (s) of one attempt of each [AGG_PRESET_TIMEOUTS]
    preset_timeouts: dict[str, int] = field(default_factory=lambda: dict(DEFAULT_PRESET_TIMEOUTS))
    stream_maxlen: int = 2000  # progress events kept per job (XADD MAXLEN ~) [AGG_STREAM_MAXLEN]
    lease_s: float = 30.0  # a running job whose lease is not renewed for this long is requeued [AGG_LEASE_S]
    reap_interval_s: float = 5.0  # how often workers and the API look for expired leases [AGG_REAP_INTERVAL_S]
    max_attempts: int = 3  # attempts before a job that keeps losing its worker fails [AGG_MAX_ATTEMPTS]
    checkpoint_every: int = 200  # engine checkpoint period in iterations [AGG_CHECKPOINT_EVERY]
    engine: str = "agg.train:reconstruct"  # "module:function" the worker runs [AGG_ENGINE]
    # torch device jobs train on: auto (the first CUDA device when torch sees one, else cpu), cpu, cuda, cuda:N;
    # given to engines whose function takes ``device`` [AGG_TRAIN_DEVICE]
    train_device: str = "auto"
    write_preview: bool = True  # render preview.mp4 after a job succeeds [AGG_WRITE_PREVIEW]
    render_max_pixels: int = 4096 * 2160  # HTTP render size limit (width * height) [AGG_RENDER_MAX_PIXELS]
    render_cache_size: int = 2  # loaded scenes kept by the API for renders [AGG_RENDER_CACHE]
    job_retention_s: int = 30 * 86400  # finished jobs' Redis keys expire after this [AGG_JOB_RETENTION_S]

    @property
    def presets(self) -> list[str]:
        return sorted(self.preset_timeouts)

    @property
    def uploads_dir(self) -> Path:
        return Path(self.data_dir) / "uploads"

    @property
    def scenes_dir(self) -> Path:
        return Path(self.data_dir) / "scenes"

    @classmethod
    def from_env(cls, env: dict[str, str] | None = None, **overrides) -> "ServiceConfig":
        """Defaults, then ``AGG_*`` variables, then ``overrides`` (None values are ignored)."""
        env = os.environ if env is None else env
        values: dict = {}
        names = {f.name: f for f in fields(cls)}
        env_names = {"data_dir": "AGG_DATA_DIR", "redis_url": "AGG_REDIS_URL", "queue": "AGG_QUEUE",
                     "api_keys_file": "AGG_API_KEYS", "max_upload_bytes": "AGG_MAX_UPLOAD_BYTES",
                     "max_active_jobs": "AGG_MAX_ACTIVE_JOBS", "max_jobs_per_day": "AGG_MAX_JOBS_PER_DAY",
                     "max_frames_limit": "AGG_MAX_FRAMES_LIMIT", "preset_timeouts": "AGG_PRESET_TIMEOUTS",
                     "stream_maxlen": "AGG_STREAM_MAXLEN", "lease_s": "AGG_LEASE_S",
                     "reap_interval_s": "AGG_REAP_INTERVAL_S", "max_attempts": "AGG_MAX_ATTEMPTS",
                     "checkpoint_every": "AGG_CHECKPOINT_EVERY", "engine": "AGG_ENGINE",
                     "train_device": "AGG_TRAIN_DEVICE", "write_preview": "AGG_WRITE_PREVIEW",
                     "render_max_pixels": "AGG_RENDER_MAX_PIXELS",
                     "render_cache_size": "AGG_RENDER_CACHE", "job_retention_s": "AGG_JOB_RETENTION_S"}
        for name, var in env_names.items():
            raw = env.get(var)
            if raw is None or raw == "":
                continue
            values[name] = _convert(name, raw, names[name].type)
        values.update({k: v for k, v in overrides.items() if v is not None})
        cfg = cls(**values)
        cfg.data_dir = Path(cfg.data_dir)
        return cfg

    def to_env(self) -> dict[str, str]:
        """The variables that reproduce this config in a child process (``agg serve`` -> its worker)."""
        out = {"AGG_DATA_DIR": str(Path(self.data_dir).resolve()), "AGG_QUEUE": self.queue,
               "AGG_MAX_UPLOAD_BYTES": str(self.max_upload_bytes),
               "AGG_PRESET_TIMEOUTS": ",".join(f"{k}={v}" for k, v in self.preset_timeouts.items()),
               "AGG_STREAM_MAXLEN": str(self.stream_maxlen), "AGG_LEASE_S": str(self.lease_s),
               "AGG_REAP_INTERVAL_S": str(self.reap_interval_s), "AGG_MAX_ATTEMPTS": str(self.max_attempts),
               "AGG_CHECKPOINT_EVERY": str(self.checkpoint_every), "AGG_ENGINE": self.engine,
               "AGG_TRAIN_DEVICE": self.train_device, "AGG_WRITE_PREVIEW": "1" if self.write_preview else "0",
               "AGG_JOB_RETENTION_S": str(self.job_retention_s)}
        if self.redis_url:
            out["AGG_REDIS_URL"] = self.redis_url
        return out

    def with_(self, **changes) -> "ServiceConfig":
        return replace(self, **changes)


def _convert(name: str, raw: str, annotation) -> object:
    if name == "preset_timeouts":
        return parse_timeouts(raw)
    text = str(annotation)
    if name in ("data_dir", "api_keys_file"):
        return Path(raw)
    if name == "write_preview":
        return raw.strip().lower() not in ("0", "false", "no", "off")
    if text.startswith("int"):
        return int(raw)
    if text.startswith("float"):
        return float(raw)
    return raw
