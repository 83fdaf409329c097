"""The README's main command, ``agg demo``, runs the whole service end to end and cleans up after itself; the
renderer demo (``agg demo-render``) fits a frame of the bundled clip.

Everything is real: ``agg demo`` starts ``agg serve`` (its own redis-server, worker, gRPC and uvicorn), uploads
a clip cut from samples/dashcam.mp4 with the sample's calibration, trains it with the ``tiny`` preset, renders a
novel view over gRPC and prints the metrics.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from tests.service_helpers import small_clip

ROOT = Path(__file__).resolve().parents[1]
CALIBRATION = ROOT / "samples" / "dashcam_intrinsics.yml"


def service_processes(data_dir: Path) -> list[int]:
    """Live processes started for the service under ``data_dir`` (agg serve, worker, work horse, redis-server):
    they all carry ``AGG_DATA_DIR=<data_dir>`` in their environment."""
    needle = f"AGG_DATA_DIR={data_dir.resolve()}".encode()
    found = []
    for d in Path("/proc").glob("[0-9]*"):
        try:
            if needle in (d / "environ").read_bytes().split(b"\0"):
                found.append(int(d.name))
        except OSError:
            continue
    return found


def demo_cmd(out: Path, clip: Path, *extra: str) -> list[str]:
    return [sys.executable, "-m", "agg.cli", "demo", "--preset", "tiny", "--max-frames", "5", "--video", str(clip),
            "--calibration", str(CALIBRATION), "--out", str(out), *extra]


def redis_installed() -> bool:
    from shutil import which

    return which("redis-server") is not None


needs_redis = pytest.mark.skipif(not redis_installed(), reason="redis-server is not installed "
                                                               "(bash scripts/install_service_deps.sh)")


@needs_redis
@pytest.mark.timeout(200)
def test_demo_end_to_end(tmp_path):
    out = tmp_path / "demo"
    clip = small_clip(tmp_path / "clip.mp4")
    t0 = time.monotonic()
    proc = subprocess.run(demo_cmd(out, clip), check=False, cwd=ROOT, capture_output=True, text=True, timeout=180)
    wall = time.monotonic() - t0
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]
    # the steps, the progress bar fed by SSE, and the printed metrics
    for line in ("[1/5] starting the service", "[2/5] uploading clip.mp4", "[4/5] rendering a novel view over gRPC",
                 "novel-view metrics", "psnr:", "demo finished"):
        assert line in proc.stdout, line
    assert "training (" in proc.stderr and "PSNR" in proc.stderr and "succeeded" in proc.stderr
    metrics = json.loads((out / "metrics.json").read_text())
    assert np.isfinite(metrics["psnr"]) and metrics["n_test_frames"] >= 1
    assert f"psnr: {round(metrics['psnr'], 4)}" in proc.stdout
    # the novel view: a real image at the training size, neither blank nor a copy of the held-out view
    novel = np.asarray(Image.open(out / "novel_view.png").convert("RGB"), np.float32) / 255  # [H, W, 3]
    heldout = np.asarray(Image.open(out / "heldout_view.png").convert("RGB"), np.float32) / 255
    assert novel.shape == heldout.shape == (90, 160, 3)
    assert novel.std() > 0.03 and 0.02 < novel.mean() < 0.98
    assert np.abs(novel - heldout).mean() > 0.005  # the camera moved
    # the service ran and is gone: scene artifacts on disk, no process left, the ports closed
    scenes = list((out / "service" / "scenes").iterdir())
    assert len(scenes) == 1 and (scenes[0] / "model.pt").is_file()
    assert service_processes(out / "service") == []
    print(f"agg demo (tiny, 5 frames of 160x90): {wall:.1f} s")


@needs_redis
@pytest.mark.timeout(150)
def test_demo_ctrl_c_stops_everything(tmp_path):
    """Ctrl-C while the job trains: the demo cancels it and stops the service. The signal is sent once the demo
    says it follows the job ("[3/5]") and the job's scene folder exists, so it lands while the job runs (the
    tiny job takes several seconds); both pipes are drained meanwhile."""
    import threading

    out = tmp_path / "demo"
    clip = small_clip(tmp_path / "clip.mp4")
    # a shell runs background jobs with SIGINT ignored, and Python keeps an ignored SIGINT: give the demo Ctrl-C
    # back, however the test run was started
    proc = subprocess.Popen(demo_cmd(out, clip), cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    lines: dict[str, list[str]] = {"out": [], "err": []}
    following = threading.Event()

    def drain(name, stream):
        for line in stream:
            lines[name].append(line)
            if name == "out" and line.startswith("[3/5]"):
                following.set()

    readers = [threading.Thread(target=drain, args=(n, s), daemon=True)
               for n, s in (("out", proc.stdout), ("err", proc.stderr))]
    for r in readers:
        r.start()
    scenes = out / "service" / "scenes"
    try:
        deadline = time.monotonic() + 90
        while not (following.is_set() and scenes.is_dir() and any(scenes.iterdir())):
            assert proc.poll() is None and time.monotonic() < deadline, "the job never started"
            time.sleep(0.05)
        assert service_processes(out / "service")  # the service runs ...
        proc.send_signal(signal.SIGINT)  # ... until Ctrl-C
        proc.wait(timeout=60)
    finally:
        if proc.poll() is None:  # the demo did not stop: kill it and the service it started (no orphans)
            proc.kill()
            proc.wait()
            for pid in service_processes(out / "service"):
                os.kill(pid, signal.SIGKILL)
        for r in readers:
            r.join(timeout=10)
    stderr = "".join(lines["err"])
    assert proc.returncode == 130, stderr[-2000:]
    assert "interrupted: stopping the service" in stderr
    assert service_processes(out / "service") == []
    assert not (out / "novel_view.png").exists()


def test_demo_render_fits_the_sample_frame(tmp_path):
    out = tmp_path / "demo"
    proc = subprocess.run(
        [sys.executable, "-m", "agg.cli", "demo-render", "--steps", "60", "--gaussians", "3000", "--width", "128",
         "--out", str(out)],
        check=False, cwd=ROOT, capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["backend"] == "cpu" and metrics["width"] == 128 and metrics["height"] == 72
    assert metrics["psnr_db"] > 25.0
    panel = Image.open(out / "fit.png")
    assert panel.size == (3 * 128, 72)
    assert "fitting 3000 Gaussians" in proc.stderr  # the progress bar


def test_demo_is_a_plugin_command():
    """``agg demo`` comes from service/ through the agg.commands entry points; the engine imports no service."""
    from agg.cli import build_parser

    sub = next(a for a in build_parser()._actions if a.dest == "command")
    assert {"demo", "demo-render", "serve", "worker"} <= set(sub.choices)
    assert sub.choices["demo"].get_default("func").__module__ == "service.demo"
    src = "\n".join(p.read_text() for p in (ROOT / "agg").rglob("*.py"))
    assert "from service" not in src and "import service" not in src and "from worker" not in src
