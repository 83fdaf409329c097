"""End to end on the real engine (``agg.train.reconstruct``): upload a clip cut from the bundled dashcam video ->
SSE progress -> the worker is killed with SIGKILL after a checkpoint -> another worker resumes from it ->
succeeded; then the artifacts, the scene graph and an HTTP render at a training timestamp (PSNR floor against
that frame). One engine run covers both the happy path and the worker death, to keep the suite short."""

from __future__ import annotations

import io
import json
import threading

import numpy as np
import pytest

from service.jobstore import JobStore
from tests.redis_server import redis_proc  # noqa: F401 - fixture
from tests.service_helpers import LiveServer, kill_tree, service_config, small_clip, start_worker, stop_worker, wait_for

train = pytest.importorskip("agg.train")
if not hasattr(train, "reconstruct"):
    pytest.skip("agg.train.reconstruct is not there yet", allow_module_level=True)
pytest.importorskip("agg.scene")

pytestmark = [pytest.mark.slow, pytest.mark.timeout(420)]
REAL = {"AGG_ENGINE": "agg.train:reconstruct", "AGG_WRITE_PREVIEW": "1"}


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return 10 * np.log10(1.0 / max(mse, 1e-12))


def test_real_engine_upload_progress_kill_resume_render(redis_proc, tmp_path):  # noqa: F811
    from PIL import Image

    cfg = service_config(tmp_path, redis_proc.url, engine=REAL["AGG_ENGINE"], checkpoint_every=10, lease_s=3.0,
                         write_preview=True, preset_timeouts={"tiny": 900})
    srv = LiveServer(cfg, sse_block_ms=500).start()
    store = JobStore.from_config(redis_proc.client(), cfg)
    a = start_worker(cfg, "wA", extra_env=REAL)
    b = None
    events: list[dict] = []
    try:
        with srv.client("alice") as c:
            r = c.post("/v1/jobs", files={"video": ("clip.mp4", small_clip(tmp_path / "clip.mp4", 10).read_bytes())},
                       data={"preset": "tiny", "max_frames": "8"})
            assert r.status_code == 202, r.text
            jid, scene = r.json()["job_id"], r.json()["scene_id"]
            scene_dir = store.scene_dir(scene)

            def follow():  # one SSE connection from upload to the end, across the requeue
                with srv.client("alice", timeout=None) as sc, sc.stream("GET", f"/v1/jobs/{jid}/events") as resp:
                    cur = {}
                    for line in resp.iter_lines():
                        if not line and "data" in cur:
                            events.append({"id": cur.get("id"), "event": cur.get("event"), **json.loads(cur["data"])})
                            cur = {}
                        elif line and not line.startswith(":"):
                            k, _, v = line.partition(":")
                            cur[k] = v.strip()

            reader = threading.Thread(target=follow, daemon=True)
            reader.start()
            wait_for(lambda: (store.get(jid)["iteration"] or 0) >= 20 and (scene_dir / "checkpoint.pt").is_file(),
                     300, interval=0.2, what="wA to train past a checkpoint")
            # while the job trains, renders come from the latest checkpoint
            meta = json.loads((scene_dir / "scene.json").read_text())
            eye = np.eye(4).tolist()
            r = c.post(f"/v1/scenes/{scene}/render", json={"timestamp_us": meta["timestamps_us"][0],
                                                           "world_from_camera": eye})
            assert r.status_code == 200 and r.headers["content-type"] == "image/png"
            kill_tree(a)
            a.wait(10)
            import torch

            ckpt_iter = int(torch.load(scene_dir / "checkpoint.pt", weights_only=False)["iteration"])
            b = start_worker(cfg, "wB", extra_env=REAL)
            job = wait_for(lambda: (j := c.get(f"/v1/jobs/{jid}").json())["state"] in ("succeeded", "failed") and j,
                           360, interval=0.5, what="wB to finish")
            assert job["state"] == "succeeded", job["error"]
            reader.join(30)
            assert [(h["state"], h["attempt"], h["worker"]) for h in job["history"]] == [
                ("queued", 1, ""), ("running", 1, "wA"), ("queued", 1, "wA"), ("running", 2, "wB"),
                ("succeeded", 2, "wB")]
            assert [e["state"] for e in events if e["event"] == "state"] == [
                "queued", "running", "queued", "running", "succeeded"]
            resumed = [e["iteration"] for e in events if e["event"] == "progress" and e.get("attempt") == 2
                       and e.get("stage") == "train"]
            assert resumed and min(resumed) > ckpt_iter >= 10  # attempt 2 continued from wA's checkpoint

            for name in ("scene.ply", "graph.json", "metrics.json", "preview.mp4"):
                assert c.get(f"/v1/scenes/{scene}/artifacts/{name}").status_code == 200, name
            from agg.io.video import read_video

            (tmp_path / "preview.mp4").write_bytes(c.get(f"/v1/scenes/{scene}/artifacts/preview.mp4").content)
            assert len(read_video(tmp_path / "preview.mp4").frames) == 8
            graph = c.get(f"/v1/scenes/{scene}/graph").json()
            assert {"camera", "background"} <= {n["id"] for n in graph["nodes"]}

            # a render at a training timestamp through the refined camera reaches a PSNR floor against the frame
            meta = json.loads((scene_dir / "scene.json").read_text())
            f = int(meta["train_frames"][0])
            body = {"timestamp_us": meta["timestamps_us"][f],
                    "world_from_camera": graph["cameras"]["world_from_camera"][f]}
            r = c.post(f"/v1/scenes/{scene}/render", json=body)
            assert r.status_code == 200 and r.headers["content-type"] == "image/png"
            img = np.asarray(Image.open(io.BytesIO(r.content)).convert("RGB"), np.float32) / 255  # [H, W, 3]
            from agg.io.bundle import SceneBundle
            from agg.train.data import resize_images

            frame = np.asarray(SceneBundle.load(meta["bundle"]).frame(f))  # [h, w, 3] float in [0, 1]
            frame = np.round(frame * 255).astype(np.uint8) if frame.dtype != np.uint8 else frame
            gt = resize_images(frame[None], meta["width"], meta["height"])[0].numpy()  # [H, W, 3] in [0, 1]
            assert psnr(img, gt) >= 10.0
            # the service draws exactly the engine's view of that training camera (only 8-bit quantisation differs)
            from agg.graph import SceneGraph

            g = SceneGraph.from_state(torch.load(scene_dir / "model.pt", weights_only=False)["graph"]).eval()
            with torch.no_grad():
                ref = g.render(f, t=f / max(g.num_frames - 1, 1)).color[..., :3].clamp(0, 1).numpy()
            assert psnr(img, ref) >= 35.0
            for bad, code in (({"timestamp_us": meta["timestamps_us"][-1] + 1}, "timestamp_out_of_range"),
                              ({"agent_poses": {"987654": np.eye(4).tolist()}}, "unknown_track")):
                r = c.post(f"/v1/scenes/{scene}/render", json={**body, **bad})
                assert (r.status_code, r.json()["code"]) == (422, code), r.text
    finally:
        stop_worker(a)
        if b is not None:
            stop_worker(b)
        srv.stop()
