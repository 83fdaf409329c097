"""Load benchmark of the embedded service (``agg serve``): concurrent gRPC renders and upload throughput.

    python bench/service_load.py --reuse runs/demo          # the scene the last `agg demo` trained (fast preset)
    python bench/service_load.py --preset tiny              # train a scene first, through the service

1. The service: with ``--reuse OUT`` it restarts ``agg serve`` over the folder of an earlier ``agg demo --out OUT``
   run (its Redis AOF keeps the scene's owner, its ``api-keys.txt`` the key); otherwise it starts a fresh one under
   ``--work``, uploads the bundled clip with ``--preset`` and waits for the job to succeed, then restarts the
   service. Either way the measured service runs with no job worker (``--workers 0``): nothing trains during the
   measurements, and uploaded jobs stay queued until cancelled.
2. Renders: ``--clients`` threads, each with its own gRPC channel (``worker.grpc_client.AggClient``), make
   ``--calls`` unary ``Render`` calls each: one camera, the refined camera of a random training frame at that
   frame's timestamp, intrinsics scaled to ``--width`` x ``--height``, RGB as PNG. One call before the clock
   starts loads the scene into the server's cache. Latency p50 / p90 / p99 / max, throughput, errors by code.
3. Uploads: a ``--upload-mb`` video (the sample clip's frames re-encoded lossless and repeated, cached under
   ``--work``) is posted ``--upload-reps`` times (``POST /v1/jobs``: streamed to disk, sniffed and fully
   test-decoded, then queued; each job is cancelled at once), and a body of random bytes of the same size once
   (streamed to disk, then refused with 415: the transfer alone). MB/s = file size / time to the answer.

Prints a summary and writes it as JSON (``--json``, default ``WORK/service_load.json``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import threading
import time
from datetime import date
from fractions import Fraction
from pathlib import Path

import grpc
import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from service.demo import SAMPLE, SAMPLE_CALIBRATION, DemoConfig, check, upload
from service.embedded import EmbeddedService


def percentile(values: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(values, dtype=np.float64), q)) if values else float("nan")


# ----------------------------------------------------------------------------------------------- the service


def train_scene(work: Path, preset: str, max_frames: int) -> Path:
    """A fresh embedded service under ``work/service`` trains the sample clip; returns that data folder."""
    svc = EmbeddedService(work / "service", work / "service.log", workers=1)
    try:
        svc.start().wait_ready(180)
        with httpx.Client(base_url=svc.url, headers={"Authorization": f"Bearer {svc.key}"}, timeout=60) as http:
            job = upload(http, DemoConfig(preset=preset, max_frames=max_frames, calibration=SAMPLE_CALIBRATION))
            print(f"training scene {job['scene_id']} (preset {preset}, {max_frames} frames) ...", flush=True)
            t0 = time.monotonic()
            while (state := check(http.get(f"/v1/jobs/{job['job_id']}"), "job")["state"]) not in (
                    "succeeded", "failed", "cancelled"):
                time.sleep(2.0)
            if state != "succeeded":
                raise SystemExit(f"the training job ended {state}; see {svc.log_path}")
            print(f"trained in {time.monotonic() - t0:.0f} s", flush=True)
    finally:
        svc.stop()
    return work / "service"


def find_scene(address: str, key: str) -> str:
    """The newest finished scene of the key's tenant (gRPC ListScenes)."""
    from worker.grpc_client import AggClient
    from worker.grpc_proto import scene_pb2

    with AggClient(address, key) as c:
        scenes = c.scenes.ListScenes(scene_pb2.ListScenesRequest(), metadata=c.metadata, timeout=60).scenes
    done = [s.scene_id for s in scenes if s.status == "done"]
    if not done:
        raise SystemExit("no finished scene in this service (run `agg demo` first, or drop --reuse)")
    return done[-1]


# ----------------------------------------------------------------------------------------------- renders


def render_load(address: str, key: str, scene_id: str, clients: int, calls: int, width: int, height: int,
                seed: int = 0) -> dict:
    """``clients`` threads x ``calls`` Render calls; latencies (ms), throughput and errors."""
    from worker.grpc_client import AggClient
    from worker.grpc_proto import common_pb2

    with AggClient(address, key) as c:
        info = c.scene(scene_id)
        cam = info.cameras[0]
        sx, sy = width / cam.intrinsics.width, height / cam.intrinsics.height
        intr = common_pb2.PinholeIntrinsics(fx=cam.intrinsics.fx * sx, fy=cam.intrinsics.fy * sy,
                                            cx=(cam.intrinsics.cx + 0.5) * sx - 0.5,
                                            cy=(cam.intrinsics.cy + 0.5) * sy - 0.5, width=width, height=height)
        train = list(info.train_frames) or list(range(len(info.timestamps_us)))
        specs = {f: common_pb2.CameraSpec(name="load", intrinsics=intr, world_from_camera=cam.poses[f].pose)
                 for f in train}
        t0 = time.perf_counter()
        first = c.render(scene_id, info.timestamps_us[train[0]], [specs[train[0]]])[0]["rgb"]
        cold_ms = (time.perf_counter() - t0) * 1e3
        assert first.shape == (height, width, 3), first.shape

    latencies: list[float] = []
    errors: dict[str, int] = {}
    lock = threading.Lock()
    start = threading.Barrier(clients + 1)

    def client(i: int) -> None:
        rng = np.random.default_rng(seed + i)
        with AggClient(address, key, timeout_s=300) as c:
            mine, errs = [], {}
            start.wait()
            for _ in range(calls):
                f = int(rng.choice(train))
                t = time.perf_counter()
                try:
                    img = c.render(scene_id, info.timestamps_us[f], [specs[f]])[0]["rgb"]
                    if img.shape != (height, width, 3):
                        errs["wrong_shape"] = errs.get("wrong_shape", 0) + 1
                        continue
                    mine.append((time.perf_counter() - t) * 1e3)
                except grpc.RpcError as exc:
                    errs[exc.code().name] = errs.get(exc.code().name, 0) + 1
        with lock:
            latencies.extend(mine)
            for k, v in errs.items():
                errors[k] = errors.get(k, 0) + v

    threads = [threading.Thread(target=client, args=(i,), daemon=True) for i in range(clients)]
    for t in threads:
        t.start()
    start.wait()
    t0 = time.perf_counter()
    for t in threads:
        t.join()
    wall = time.perf_counter() - t0
    return {"clients": clients, "calls_per_client": calls, "width": width, "height": height, "encoding": "png",
            "ok": len(latencies), "errors": errors, "wall_s": round(wall, 2),
            "throughput_rps": round(len(latencies) / wall, 2), "cold_first_call_ms": round(cold_ms, 1),
            "latency_ms": {"p50": round(percentile(latencies, 50), 1), "p90": round(percentile(latencies, 90), 1),
                           "p99": round(percentile(latencies, 99), 1), "mean": round(statistics.fmean(latencies), 1)
                           if latencies else None, "max": round(max(latencies), 1) if latencies else None}}


# ----------------------------------------------------------------------------------------------- uploads


def big_video(path: Path, target_mb: float) -> Path:
    """The sample clip's frames (1280x720), lossless H.264, played forward and back until ``target_mb``."""
    if path.is_file() and path.stat().st_size >= 0.95 * target_mb * 1e6:
        return path
    import av

    from agg.io.video import IngestConfig, read_video

    frames = read_video(SAMPLE, IngestConfig(dtype="uint8")).frames  # [T, H, W, 3]
    order = list(range(len(frames))) + list(range(len(frames) - 2, 0, -1))
    tmp = path.with_suffix(".tmp.mp4")
    with av.open(str(tmp), "w") as c:
        s = c.add_stream("libx264", rate=Fraction(25), options={"crf": "0", "preset": "ultrafast"})
        s.width, s.height, s.pix_fmt = frames.shape[2], frames.shape[1], "yuv420p"
        i, written = 0, 0
        while written < target_mb * 1e6 and i < 5000:
            f = frames[order[i % len(order)]]
            for p in s.encode(av.VideoFrame.from_ndarray(np.ascontiguousarray(f), format="rgb24")):
                written += p.size
                c.mux(p)
            i += 1
        for p in s.encode(None):
            c.mux(p)
    os.replace(tmp, path)
    return path


def post_file(http: httpx.Client, path: Path, name: str) -> tuple[httpx.Response, float]:
    with open(path, "rb") as fh:
        t0 = time.perf_counter()
        r = http.post("/v1/jobs", data={"preset": "tiny"}, files={"video": (name, fh, "application/octet-stream")},
                      timeout=600)
        return r, time.perf_counter() - t0


def upload_load(url: str, key: str, work: Path, target_mb: float, reps: int) -> dict:
    video = big_video(work / f"upload_{int(target_mb)}mb.mp4", target_mb)
    junk = work / f"junk_{int(target_mb)}mb.bin"
    if not junk.is_file() or junk.stat().st_size != video.stat().st_size:
        junk.write_bytes(np.random.default_rng(0).integers(0, 256, video.stat().st_size, np.uint8).tobytes())
    mb = video.stat().st_size / 1e6
    accepted = []
    with httpx.Client(base_url=url, headers={"Authorization": f"Bearer {key}"}) as http:
        for _ in range(reps):
            r, dt = post_file(http, video, "big.mp4")
            created = check(r, "upload")
            accepted.append(dt)
            check(http.post(f"/v1/jobs/{created['job_id']}/cancel"), "cancel")
        job = check(http.get(f"/v1/jobs/{created['job_id']}"), "job")
        r, dt_junk = post_file(http, junk, "junk.mp4")
        if r.status_code != 415:
            raise SystemExit(f"random bytes answered {r.status_code}, expected 415: {r.text[:200]}")
    info = job.get("input") or {}
    return {"bytes": video.stat().st_size, "mb": round(mb, 1), "frames": info.get("frames"),
            "size": f"{info.get('width')}x{info.get('height')}", "reps": reps,
            "accepted_s": [round(t, 2) for t in accepted],
            "accepted_mb_s": round(mb / statistics.median(accepted), 1),
            "rejected_415_s": round(dt_junk, 2), "rejected_mb_s": round(mb / dt_junk, 1)}


# ----------------------------------------------------------------------------------------------- main


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--reuse", type=Path, help="the --out folder of an earlier `agg demo` run (e.g. runs/demo)")
    ap.add_argument("--preset", default="tiny", help="preset of the scene trained without --reuse (default tiny)")
    ap.add_argument("--max-frames", type=int, default=12, help="frames of that scene (default 12)")
    ap.add_argument("--work", type=Path, default=Path("runs/service_load"), help="scratch folder")
    ap.add_argument("--clients", type=int, default=8)
    ap.add_argument("--calls", type=int, default=50, help="Render calls per client")
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=192)
    ap.add_argument("--upload-mb", type=float, default=50.0)
    ap.add_argument("--upload-reps", type=int, default=3)
    ap.add_argument("--json", type=Path, help="write the results here (default WORK/service_load.json)")
    args = ap.parse_args(argv)

    work = args.work.resolve()
    work.mkdir(parents=True, exist_ok=True)
    if args.reuse:
        data_dir, log = args.reuse.resolve() / "service", args.reuse.resolve() / "service.log"
    else:
        data_dir, log = train_scene(work, args.preset, args.max_frames), work / "service.log"
    svc = EmbeddedService(data_dir, log, workers=0, fresh=False)
    try:
        svc.start().wait_ready(180)
        scene_id = find_scene(svc.grpc_address, svc.key)
        print(f"service up (no worker): HTTP {svc.url}, gRPC {svc.grpc_address}; scene {scene_id}", flush=True)
        renders = render_load(svc.grpc_address, svc.key, scene_id, args.clients, args.calls, args.width,
                              args.height)
        print(json.dumps(renders), flush=True)
        uploads = upload_load(svc.url, svc.key, work, args.upload_mb, args.upload_reps)
        print(json.dumps(uploads), flush=True)
    finally:
        svc.stop()
    import torch

    meta = json.loads(next((data_dir / "scenes").glob(f"{scene_id}/scene.json")).read_text())
    result = {"date": date.today().isoformat(), "host": platform.node(), "cpus": os.cpu_count(),
              "python": platform.python_version(), "torch": torch.__version__, "load_avg_1m": os.getloadavg()[0],
              "scene": {"id": scene_id, "preset": meta.get("preset"), "frames": meta.get("num_frames"),
                        "train_size": f"{meta.get('width')}x{meta.get('height')}",
                        "n_gaussians": (meta.get("summary") or {}).get("n_gaussians")},
              "renders": renders, "uploads": uploads}
    out = args.json or work / "service_load.json"
    out.write_text(json.dumps(result, indent=1))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
