"""Scene directories for the serving tests: a tiny synthetic bundle, its initial scene graph, saved as
``model.pt`` / ``checkpoint.pt`` with ``scene.json`` exactly as the worker writes them (COMMON scene-dir contract)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from agg.graph import SceneGraph
from agg.io.bundle import SceneBundle
from agg.priors.metric_scale import estimate_metric_scale
from agg.nodes.init import InitConfig
from agg.synth.corrupt import NoiseConfig
from agg.synth.scene import SceneConfig
from agg.synth.suite import generate, write_bundle

WIDTH, HEIGHT, FRAMES = 96, 64, 6


def make_bundle(root: Path, seed: int = 0) -> tuple[SceneBundle, object]:
    """A 6-frame 96x64 synthetic clip with exact priors (rigid and non-rigid agents), and its ground truth."""
    gt, priors = generate(SceneConfig(seed=seed, frames=FRAMES, width=WIDTH, height=HEIGHT), NoiseConfig())
    path = Path(root) / f"bundle{seed}"
    write_bundle(path, gt, priors, NoiseConfig())
    return SceneBundle.load(path), gt


def make_graph(bundle: SceneBundle) -> SceneGraph:
    """The initial graph (dense opaque points at their true depths render the clip well before any training)."""
    return SceneGraph.from_bundle(bundle, InitConfig(opacity=0.9))


def write_scene_dir(root: Path, scene_id: str, bundle: SceneBundle, graph: SceneGraph | None,
                    file: str = "model.pt", iteration: int = 0, train_frames: list[int] | None = None,
                    status: str = "done", metric_scale: dict | None = None) -> Path:
    """``root/scene_id`` with scene.json and, unless ``graph`` is None, the graph saved as ``file``.
    ``metric_scale``: scene.json's metres per unit (default: the bundle's estimate, as ``reconstruct`` writes it)."""
    d = Path(root) / scene_id
    d.mkdir(parents=True, exist_ok=True)
    t = bundle.num_frames
    train = list(range(t)) if train_frames is None else list(train_frames)
    meta = {"version": 1, "scene_id": scene_id, "bundle": str(bundle.path),
            "num_frames": t, "timestamps_us": [int(v) for v in bundle.timestamps_us], "width": bundle.width,
            "height": bundle.height, "K": np.asarray(bundle.intrinsics).tolist(), "train_frames": train,
            "test_frames": [i for i in range(t) if i not in train], "preset": "test", "status": status,
            "metric_scale": metric_scale or estimate_metric_scale(bundle).as_dict()}
    (d / "scene.json").write_text(json.dumps(meta))
    if graph is not None:
        torch.save({"graph": graph.state(), "iteration": iteration}, d / file)
    return d


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR in dB of two float images in [0, 1]."""
    mse = float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))
    return float(-10.0 * np.log10(max(mse, 1e-12)))
