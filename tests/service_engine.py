"""A stand-in for ``agg.train.reconstruct`` with the same contract, for the queue tests (``AGG_ENGINE``).

It is not a mock of the queue: the real worker, Redis and job store run it. It reads the uploaded video's frame
count with the real reader, "trains" for ``AGG_TEST_ENGINE_ITERS`` iterations of ``AGG_TEST_ENGINE_SLEEP``
seconds, checkpoints every ``checkpoint_every`` iterations with ``torch.save`` (atomic rename) when ``checkpoint_ok()``
allows, resumes from the checkpoint, polls ``should_stop`` every iteration, and appends "pid iteration" per iteration to
``scene_dir/iterations.log`` so a test can check that a resumed attempt continued from the checkpoint.
"""

from __future__ import annotations

import json
import os
from pathlib import Path


class Cancelled(Exception):
    """Raised when ``should_stop()`` turns true (the engine contract's ``agg.train.Cancelled``)."""


def reconstruct(input_path, scene_dir, preset="fast", *, progress=None, should_stop=None, resume=True,
                checkpoint_every=None, overrides=None, max_frames=None, intrinsics=None, checkpoint_ok=None) -> dict:
    import time

    import torch

    from agg.io.video import IngestConfig, read_video

    scene_dir = Path(scene_dir)
    total = int(os.environ.get("AGG_TEST_ENGINE_ITERS", "20"))
    pause = float(os.environ.get("AGG_TEST_ENGINE_SLEEP", "0.05"))
    every = int(checkpoint_every or 5)
    ckpt = scene_dir / "checkpoint.pt"
    start = int(torch.load(ckpt)["iteration"]) if resume and ckpt.is_file() else 0
    if start == 0:
        frames = read_video(input_path, IngestConfig(width=16, dtype="uint8")).frames
        (scene_dir / "scene.json").write_text(json.dumps({
            "version": 1, "scene_id": scene_dir.name, "num_frames": len(frames), "width": 16,
            "height": int(frames.shape[1]), "timestamps_us": [i * 40000 for i in range(len(frames))],
            "K": [[[16.0, 0, 7.5], [0, 16.0, 4.5], [0, 0, 1]]] * len(frames), "preset": preset,
            "status": "training",
            "options": {k: v for k, v in (("max_frames", max_frames), ("intrinsics", intrinsics)) if v is not None}}))
    log = open(scene_dir / "iterations.log", "a")  # noqa: SIM115
    try:
        for i in range(start, total):
            if should_stop is not None and should_stop():
                raise Cancelled(f"stopped at iteration {i}")
            time.sleep(pause)
            log.write(f"{os.getpid()} {i}\n")
            log.flush()
            # never write after losing the job (the next should_stop() ends this attempt)
            if (i + 1) % every == 0 and (checkpoint_ok is None or checkpoint_ok()):
                torch.save({"iteration": i + 1}, scene_dir / "checkpoint.tmp")
                os.replace(scene_dir / "checkpoint.tmp", ckpt)
            if progress is not None:
                progress({"iteration": i + 1, "total": total, "phase": "joint", "loss": 1.0 / (i + 1),
                          "psnr": 10.0 + i, "n_gaussians": 100, "agents_spawned": 0, "agents_pruned": 0,
                          "eta_s": pause * (total - i - 1), "stage": "train"})
    finally:
        log.close()
    (scene_dir / "metrics.json").write_text(json.dumps({"iterations": total, "resumed_from": start}))
    (scene_dir / "graph.json").write_text(json.dumps({"nodes": [{"id": 0, "class": "background"}]}))
    return {"iterations": total, "resumed_from": start}
