"""Torch device names given by users (``--device``, ``--grpc-device``): parsed once, with a clear error.

``resolve_device("cuda")`` fails with a ``ValueError`` that says why (no CUDA build, no visible device, index out of
range) instead of a torch error at the first tensor moved there; ``"auto"`` is the first CUDA device when torch sees
one, else the CPU.
"""

from __future__ import annotations

import torch


def resolve_device(spec: str | torch.device) -> torch.device:
    """``torch.device`` of ``spec`` ("cpu", "cuda", "cuda:1", "auto", ...) after checking that it can be used here."""
    if spec == "auto":
        return torch.device("cuda", 0) if torch.cuda.is_available() else torch.device("cpu")
    try:
        dev = torch.device(spec)
    except (RuntimeError, TypeError) as exc:
        raise ValueError(f"unknown torch device {str(spec)!r}: use cpu, cuda or cuda:N") from exc
    if dev.type == "cpu":
        return dev
    if dev.type != "cuda":
        raise ValueError(f"device {str(spec)!r}: only cpu and cuda are supported")
    if not torch.cuda.is_available():
        build = "this torch is a CPU build" if torch.version.cuda is None else "no CUDA device is visible"
        raise ValueError(f"device {str(spec)!r}: {build}")
    count = torch.cuda.device_count()
    if dev.index is not None and dev.index >= count:
        raise ValueError(f"device {str(spec)!r}: only {count} CUDA device{'s' if count > 1 else ''} visible")
    return dev


def synchronize(device: torch.device) -> None:
    """Wait for the work queued on ``device`` (a no-op on the CPU): wall-clock timings of CUDA work need it."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)
