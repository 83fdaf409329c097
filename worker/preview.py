"""``preview.mp4`` of a finished scene: every training frame re-rendered through its refined camera (H.264)."""

from __future__ import annotations

import json
from fractions import Fraction
from pathlib import Path

import numpy as np


def write_preview(scene_dir: str | Path, out: str | Path | None = None, max_frames: int = 600,
                  max_width: int = 960) -> Path:
    """Render ``model.pt`` at each frame (at most ``max_frames``, at most ``max_width`` wide) into an MP4."""
    import av
    import torch

    from agg.graph import SceneGraph

    scene_dir = Path(scene_dir)
    out = Path(out) if out else scene_dir / "preview.mp4"
    state = torch.load(scene_dir / "model.pt", map_location="cpu", weights_only=False)
    graph = SceneGraph.from_state(state["graph"]).eval()
    meta = json.loads((scene_dir / "scene.json").read_text()) if (scene_dir / "scene.json").is_file() else {}
    t = graph.num_frames
    stamps = np.asarray(meta.get("timestamps_us") or [], dtype=np.float64)
    fps = 10.0
    if stamps.size >= 2 and stamps[-1] > stamps[0]:
        fps = float(np.clip((stamps.size - 1) / ((stamps[-1] - stamps[0]) / 1e6), 1.0, 60.0))
    scale = min(1.0, max_width / graph.width)
    w, h = max(2, int(graph.width * scale) // 2 * 2), max(2, int(graph.height * scale) // 2 * 2)
    tmp = out.with_suffix(".part.mp4")
    with av.open(str(tmp), "w") as container:
        stream = container.add_stream("libx264" if "libx264" in av.codecs_available else "mpeg4",
                                      rate=Fraction(round(fps * 1000), 1000))
        stream.width, stream.height, stream.pix_fmt = w, h, "yuv420p"
        with torch.no_grad():
            for i in range(min(t, max_frames)):
                img = graph.render(i, t=i / max(t - 1, 1)).color[..., :3].clamp(0, 1)  # [H, W, 3]
                rgb = (img.cpu().numpy() * 255 + 0.5).astype(np.uint8)
                if rgb.shape[:2] != (h, w):
                    import cv2

                    rgb = cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA)
                for packet in stream.encode(av.VideoFrame.from_ndarray(rgb, format="rgb24")):
                    container.mux(packet)
        for packet in stream.encode(None):
            container.mux(packet)
    tmp.replace(out)
    return out
