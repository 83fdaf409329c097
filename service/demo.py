"""``agg demo``: the README's main command — the whole service on this machine, end to end.

1. Starts ``agg serve`` as a child process in its own session: a private redis-server on a free loopback port,
   one job worker, gRPC and the HTTP API on free loopback ports, a generated API key; everything under
   ``OUT/service/`` (emptied at the start of each run; its log is ``OUT/service.log``).
2. Uploads the bundled clip ``samples/dashcam.mp4`` with its OpenCV calibration over HTTP (``POST /v1/jobs``,
   preset ``fast``).
3. Follows the job's Server-Sent Events with a progress bar (phase, iteration, training PSNR, the engine's ETA).
4. Renders over gRPC (``worker.grpc_client.AggClient``) the camera of a held-out frame (interpolated between its
   neighbouring training frames, as the evaluation does) and the same camera shifted 1 m to the left, into
   ``OUT/heldout_view.png`` and ``OUT/novel_view.png``. Metres become scene units through the scene's
   ``scale`` (a video's is the engine's estimate from the camera height over the road, taken as 1.5 m;
   ``--camera-height-m`` measures the height in the rendered depth instead).
5. Prints the novel-view metrics (``GET /v1/scenes/{id}/artifacts/metrics.json``, also saved as
   ``OUT/metrics.json``).
6. Stops the service: SIGTERM to ``agg serve``, which stops the API, gRPC, its worker and Redis. On Ctrl-C or
   SIGTERM the job is cancelled first; any process of the service's tree still alive after the grace period is
   killed. ``--keep-running`` leaves the service up (its URL and key are printed) until Ctrl-C.

Registered as ``agg demo`` through the ``agg.commands`` entry-point group (the engine imports nothing from here).
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import httpx

from service.embedded import DemoError, EmbeddedService
from service.jobstore import TERMINAL

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "samples" / "dashcam.mp4"
SAMPLE_CALIBRATION = ROOT / "samples" / "dashcam_intrinsics.yml"
# Frames of the bundled clip (38 in all) kept by default: every one (measured: docs/BENCHMARKS.md, "agg demo").
DEFAULT_MAX_FRAMES = 38


@dataclass
class DemoConfig:
    """What ``agg demo`` does (the command-line flags)."""

    video: Path = SAMPLE
    calibration: Path | None = SAMPLE_CALIBRATION  # OpenCV K/dist file sent with the upload (None: estimated)
    preset: str = "fast"
    max_frames: int | None = DEFAULT_MAX_FRAMES
    out: Path = Path("runs/demo")
    shift_m: float = 1.0  # the novel camera: the held-out camera moved this far to its left
    camera_height_m: float | None = None  # metres to scene units: None uses the scene's scale (SceneInfo.scale);
    # a height measures the camera's height above the road in the rendered depth and takes it to be this
    keep_running: bool = False
    startup_timeout_s: float = 180.0


# ----------------------------------------------------------------------------------------------- HTTP steps


def check(r: httpx.Response, what: str) -> dict:
    if r.status_code >= 400:
        try:
            body = r.json()
            detail = f"{body.get('code')}: {body.get('message')}"
        except ValueError:
            detail = r.text[:300]
        raise DemoError(f"{what}: HTTP {r.status_code} {detail}")
    return r.json() if r.content else {}


def upload(http: httpx.Client, cfg: DemoConfig) -> dict:
    """POST /v1/jobs (multipart: video, preset, max_frames, calibration); the 202 body."""
    data = {"preset": cfg.preset}
    if cfg.max_frames:
        data["max_frames"] = str(cfg.max_frames)
    with open(cfg.video, "rb") as video:
        files = {"video": (cfg.video.name, video, "application/octet-stream")}
        if cfg.calibration is not None:
            files["calibration"] = (cfg.calibration.name, cfg.calibration.read_bytes(), "application/x-yaml")
        return check(http.post("/v1/jobs", data=data, files=files, timeout=300), "upload")


def _fmt_s(s) -> str:
    s = int(max(float(s), 0))
    return f"{s // 60}:{s % 60:02d}"


def describe(event: dict) -> tuple[str, str] | None:
    """(bar description, postfix) of one job event; None for events that do not change them (topology
    reports)."""
    if event.get("type") == "state":
        return event.get("state", "?"), ""
    if event.get("stage") == "priors" or event.get("phase") == "priors":
        done, total = event.get("done"), event.get("total")
        return f"priors: {event.get('step', '')}", f"{done}/{total}" if total else ""
    if event.get("stage") == "eval" or event.get("phase") == "eval":
        return "evaluating", ""
    if event.get("phase") == "preview":
        return "writing preview.mp4", ""
    if event.get("iteration") is not None:
        parts = [f"it {event['iteration']}/{event.get('total', '?')}"]
        tracking = event.get("tracking")
        if isinstance(tracking, dict):  # a camera-tracking round: the iteration count stands still meanwhile
            parts.append(f"tracking cameras {tracking.get('step')}/{tracking.get('steps')}")
        if event.get("psnr") is not None:
            parts.append(f"PSNR {float(event['psnr']):.1f} dB")
        if event.get("n_gaussians") is not None:
            parts.append(f"{int(event['n_gaussians']):,} G")
        if event.get("eta_s") is not None:
            parts.append(f"ETA {_fmt_s(event['eta_s'])}")
        return f"training ({event.get('phase', '')})", ", ".join(parts)
    return None


def sse_events(http: httpx.Client, job_id: str, last_id: str | None):
    """(id, event dict) from ``GET /v1/jobs/{id}/events`` until the stream ends (None when it answers 204)."""
    headers = {"Last-Event-ID": last_id} if last_id else {}
    with http.stream("GET", f"/v1/jobs/{job_id}/events", headers=headers,
                     timeout=httpx.Timeout(30.0, read=60.0)) as resp:
        if resp.status_code == 204:
            return
        if resp.status_code >= 400:
            resp.read()
            check(resp, "events")
        cur: dict[str, str] = {}
        for line in resp.iter_lines():
            if not line:
                if "data" in cur:
                    yield cur.get("id"), json.loads(cur["data"])
                cur = {}
            elif not line.startswith(":"):
                k, _, v = line.partition(":")
                cur[k] = v.removeprefix(" ")


def follow(http: httpx.Client, job_id: str) -> dict:
    """A tqdm bar fed by the job's SSE stream (reconnecting with Last-Event-ID); the final job record."""
    from tqdm import tqdm

    last_id, failures = None, 0
    with tqdm(total=100, desc="queued", bar_format="{desc}: {percentage:3.0f}%|{bar}| {elapsed}{postfix}",
              dynamic_ncols=True, mininterval=0.5) as bar:
        while True:
            try:
                for event_id, ev in sse_events(http, job_id, last_id):
                    last_id, failures = event_id, 0
                    shown = describe(ev)
                    bar.n = max(bar.n, round(100 * float(ev.get("progress") or 0.0), 1))
                    if shown is not None:
                        bar.set_description_str(shown[0], refresh=False)
                        bar.set_postfix_str(shown[1], refresh=False)
                    bar.refresh()
            except (httpx.TransportError, httpx.RemoteProtocolError) as exc:
                failures += 1
                if failures > 10:
                    raise DemoError(f"lost the event stream: {exc}") from None
                time.sleep(1.0)
            job = check(http.get(f"/v1/jobs/{job_id}"), "job status")
            if job["state"] in TERMINAL:
                return job


# ----------------------------------------------------------------------------------------------- gRPC step


def camera_height_units(depth, alpha, K) -> float | None:
    """Height of the camera above the road in scene units, from a rendered view: the median of
    ``Y = depth * (v - cy) / fy`` (camera y points down) over the bottom fifth of the image, middle half of the
    columns, where alpha > 0.5; assumes a roughly level camera looking along a flat road. None when too few pixels
    qualify or the answer is not positive. ``depth``, ``alpha``: [H, W]; ``K``: [3, 3]."""
    import numpy as np

    h, w = depth.shape
    r0, c0, c1 = int(h * 0.8), w // 4, 3 * w // 4
    v = np.arange(r0, h, dtype=np.float64)[:, None]  # [h', 1]
    y = depth[r0:, c0:c1] * (v - K[1, 2]) / K[1, 1]  # [h', w'] height below the camera
    ok = (alpha[r0:, c0:c1] > 0.5) & (depth[r0:, c0:c1] > 0) & (v > K[1, 2])
    if ok.sum() < 20:
        return None
    height = float(np.median(y[ok]))
    return height if height > 0 else None


def render_views(address: str, key: str, scene_id: str, shift_m: float, out: Path,
                 camera_height_m: float | None = None) -> dict:
    """Render over gRPC a held-out frame's camera and the same camera ``shift_m`` metres to its left; PNGs in
    ``out``. Metres become scene units through GetScene's ``scale`` (metres per unit: exact for metric priors, else
    the engine's estimate from the camera height over the road, agg/priors/metric_scale.py). With
    ``camera_height_m`` the camera's height above the road is measured in the held-out view's depth
    (``camera_height_units``) and taken to be that many metres instead; without a usable road it falls back to the
    scale.
    Returns {frame, timestamp_us, shift_units, units_per_m_source, paths, size, mean/std of the novel view}."""
    import numpy as np
    import torch
    from PIL import Image

    from agg.eval.interpolate import interpolate_camera
    from worker.grpc_client import AggClient
    from worker.grpc_convert import pose_from_proto, pose_to_proto
    from worker.grpc_proto import common_pb2

    with AggClient(address, key) as client:
        info = client.scene(scene_id)
        test = list(info.test_frames) or [len(info.timestamps_us) // 2]
        frame = int(test[len(test) // 2])
        ts = info.timestamps_us[frame]
        cam = info.cameras[0]
        poses = np.stack([pose_from_proto(p.pose, f"pose {i}") for i, p in enumerate(cam.poses)])  # [T, 4, 4]
        train = list(info.train_frames) or [frame]
        heldout = interpolate_camera(torch.from_numpy(poses), train, frame).double().numpy()  # [4, 4]

        def spec(name: str, pose) -> common_pb2.CameraSpec:
            return common_pb2.CameraSpec(name=name, intrinsics=cam.intrinsics, world_from_camera=pose_to_proto(pose))

        first = client.render(scene_id, ts, [spec("heldout", heldout)], depth=True, alpha=True)[0]
        i = cam.intrinsics
        K = np.array([[i.fx, 0, i.cx], [0, i.fy, i.cy], [0, 0, 1]])
        height = camera_height_units(first["depth"], first["alpha"], K) if camera_height_m else None
        if height is not None:
            units_per_m, source = height / camera_height_m, f"camera {camera_height_m:g} m above the road"
        else:
            units_per_m, source = 1.0 / (info.scale or 1.0), f"scene's scale, {info.scale or 1.0:.4g} m per unit"
        units = shift_m * units_per_m
        novel = heldout.copy()
        novel[:3, 3] -= heldout[:3, 0] * units  # camera x points right: minus x is left
        second = client.render(scene_id, ts, [spec("novel", novel)])[0]
    paths = {"heldout": out / "heldout_view.png", "novel": out / "novel_view.png"}
    Image.fromarray(first["rgb"]).save(paths["heldout"])
    Image.fromarray(second["rgb"]).save(paths["novel"])
    rgb = second["rgb"].astype(np.float32) / 255.0
    return {"frame": frame, "timestamp_us": int(ts), "shift_units": units, "units_per_m_source": source,
            "width": int(i.width), "height": int(i.height), "paths": paths, "mean": float(rgb.mean()),
            "std": float(rgb.std())}


# ----------------------------------------------------------------------------------------------- the command


def print_metrics(metrics: dict, summary: dict | None) -> None:
    """The scalar novel-view metrics and the job's training summary, one line each."""
    print("novel-view metrics (held-out frames, metrics.json):")
    for k, v in metrics.items():
        if isinstance(v, (int, float, str)) or v is None:
            print(f"  {k}: {round(v, 4) if isinstance(v, float) else v}")
    if summary:
        keep = ("iterations", "n_gaussians", "n_agents", "agents_spawned", "agents_pruned", "final_train_psnr",
                "seconds_priors", "seconds_train", "seconds_total")
        print("training: " + ", ".join(f"{k} {summary[k]}" for k in keep if summary.get(k) is not None))
        gate = summary.get("semantic") or {}
        if gate.get("active") is False:
            print(f"semantic loss: off, {gate.get('reason')}")
        tracking = summary.get("camera_tracking") or {}
        if tracking.get("active") is False:
            print(f"camera tracking rounds: off, {tracking.get('reason')}")


def _raise_interrupt(signum, frame) -> None:
    raise KeyboardInterrupt


def run_demo(cfg: DemoConfig) -> int:
    """The six steps of the module docstring; 0 on success, 1 on a failed step, 130 when interrupted."""
    for path, what in ((cfg.video, "video"), (cfg.calibration, "calibration")):
        if path is not None and not Path(path).is_file():
            print(f"agg demo: {what} {path} not found", file=sys.stderr)
            return 2
    out = cfg.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    for stale in ("novel_view.png", "heldout_view.png", "metrics.json"):
        (out / stale).unlink(missing_ok=True)
    previous = signal.signal(signal.SIGTERM, _raise_interrupt)
    service = EmbeddedService(out / "service", out / "service.log")
    http: httpx.Client | None = None
    job_id, job_ended, finished = None, False, False
    t0 = time.perf_counter()
    try:
        print(f"[1/5] starting the service (agg serve; log: {service.log_path})", flush=True)
        service.start().wait_ready(cfg.startup_timeout_s)
        print(f"      HTTP {service.url}   gRPC {service.grpc_address}   data {service.data_dir}", flush=True)
        http = httpx.Client(base_url=service.url, headers={"Authorization": f"Bearer {service.key}"}, timeout=60)
        size_mb = cfg.video.stat().st_size / 1e6
        print(f"[2/5] uploading {cfg.video.name} ({size_mb:.1f} MB, preset {cfg.preset}, max_frames "
              f"{cfg.max_frames or 'all'}{', with ' + cfg.calibration.name if cfg.calibration else ''})", flush=True)
        created = upload(http, cfg)
        job_id, scene_id = created["job_id"], created["scene_id"]
        print(f"      job {job_id}, scene {scene_id}", flush=True)
        print("[3/5] reconstructing (progress from the job's event stream)", flush=True)
        job = follow(http, job_id)
        job_ended = True
        if job["state"] != "succeeded":
            raise DemoError(f"the job ended {job['state']}: {job.get('error')}")
        print(f"[4/5] rendering a novel view over gRPC ({service.grpc_address})", flush=True)
        view = render_views(service.grpc_address, service.key, scene_id, cfg.shift_m, out, cfg.camera_height_m)
        print(f"      held-out frame {view['frame']} (t = {view['timestamp_us']} us), its camera moved {cfg.shift_m:g} m "
              f"left = {view['shift_units']:.4f} scene units (scale from the {view['units_per_m_source']}), "
              f"{view['width']}x{view['height']}:\n      {view['paths']['novel']} (the unmoved camera: "
              f"{view['paths']['heldout'].name})", flush=True)
        print("[5/5] metrics", flush=True)
        metrics = check(http.get(f"/v1/scenes/{scene_id}/artifacts/metrics.json"), "metrics")
        (out / "metrics.json").write_text(json.dumps(metrics, indent=1))
        print_metrics(metrics, job.get("summary"))
        print(f"demo finished in {time.perf_counter() - t0:.0f} s", flush=True)
        finished = True
        if cfg.keep_running:
            print(f"\nthe service keeps running: HTTP {service.url} (docs at /docs), gRPC {service.grpc_address}\n"
                  f"  API key: {service.key}   scene: {scene_id}\n  Ctrl-C to stop it", flush=True)
            while service.proc.poll() is None:
                time.sleep(1.0)
            print(f"agg serve exited with {service.proc.returncode}", file=sys.stderr)
        return 0
    except KeyboardInterrupt:
        if finished:  # --keep-running: Ctrl-C is how it ends
            print("\nstopping the service", file=sys.stderr, flush=True)
            return 0
        print("\ninterrupted: stopping the service", file=sys.stderr, flush=True)
        if job_id is not None and not job_ended and http is not None:
            _cancel(http, job_id, service)
        return 130
    except (DemoError, httpx.HTTPError) as exc:
        print(f"agg demo: {exc}", file=sys.stderr)
        return 1
    finally:
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # let the shutdown finish (it is bounded by timeouts)
        try:
            if http is not None:
                http.close()
            killed = service.stop()
            if killed:
                print(f"(killed {len(killed)} process(es) that did not stop in time)", file=sys.stderr)
        finally:
            signal.signal(signal.SIGINT, signal.default_int_handler)
            signal.signal(signal.SIGTERM, previous)


def _cancel(http: httpx.Client, job_id: str, service: EmbeddedService, wait_s: float = 10.0) -> None:
    """Ask the service to cancel the job and wait briefly for it to stop; then kill its work horse if needed."""
    try:
        http.post(f"/v1/jobs/{job_id}/cancel", timeout=5)
        deadline = time.monotonic() + wait_s
        while time.monotonic() < deadline:
            if http.get(f"/v1/jobs/{job_id}", timeout=5).json().get("state") in TERMINAL:
                return
            time.sleep(0.3)
    except (httpx.HTTPError, ValueError, KeyboardInterrupt):
        pass
    service.kill_jobs()


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "demo", help="the whole service end to end: upload the sample clip, train, render a novel view over gRPC",
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--preset", default="fast", help="training preset (default fast)")
    p.add_argument("--max-frames", type=int, default=DEFAULT_MAX_FRAMES,
                   help=f"frames of the clip to use (default {DEFAULT_MAX_FRAMES}; 0 = all)")
    p.add_argument("--keep-running", action="store_true", help="leave the service up afterwards (Ctrl-C stops it)")
    p.add_argument("--video", type=Path, default=SAMPLE, help="the clip to upload (default the bundled sample)")
    p.add_argument("--calibration", type=Path, default=None,
                   help="OpenCV calibration file sent with the upload (default: the sample's, with the sample)")
    p.add_argument("--no-calibration", action="store_true", help="send no calibration (intrinsics estimated)")
    p.add_argument("--shift-m", type=float, default=1.0, help="novel camera: metres left of the held-out camera")
    p.add_argument("--camera-height-m", type=float, default=None,
                   help="height of the camera above the road, measured in the rendered depth to convert metres to "
                        "scene units (default: the scene's own scale, estimated by the engine for a video)")
    p.add_argument("--out", type=Path, default=Path("runs/demo"), help="output folder (default runs/demo)")
    p.set_defaults(func=main_args)


def main_args(args: argparse.Namespace) -> int:
    calibration = args.calibration
    if calibration is None and Path(args.video).resolve() == SAMPLE:
        calibration = SAMPLE_CALIBRATION
    if args.no_calibration:
        calibration = None
    return run_demo(DemoConfig(video=Path(args.video), calibration=calibration, preset=args.preset,
                               max_frames=args.max_frames or None, out=Path(args.out), shift_m=args.shift_m,
                               camera_height_m=args.camera_height_m, keep_running=args.keep_running))
