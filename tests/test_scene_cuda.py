"""A saved scene served from a CUDA device (gsplat) against the same scene on the CPU: renders of every output,
and ``agg eval --device cuda``. Skipped without CUDA and gsplat."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from agg.cli import main
from agg.scene import Scene
from tests.scene_dirs import make_bundle, make_graph, psnr, write_scene_dir

pytestmark = pytest.mark.cuda

if not torch.cuda.is_available():
    pytest.skip("no CUDA device", allow_module_level=True)
pytest.importorskip("gsplat")


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    root = tmp_path_factory.mktemp("cuda_scenes")
    bundle, _ = make_bundle(root)
    return write_scene_dir(root, "s", bundle, make_graph(bundle), train_frames=[0, 1, 2, 3, 5]), bundle


def test_cuda_scene_renders_match_cpu(scene_dir):
    d, bundle = scene_dir
    cpu, gpu = Scene.load(d), Scene.load(d, device="cuda")
    assert gpu.graph.K.device.type == "cuda"
    for frame in (0, 4):
        t_us = int(bundle.timestamps_us[frame]) + 20_000  # between frames: interpolated agents too
        wfc, K = cpu.world_from_camera()[frame], cpu.K[min(frame, len(cpu.K) - 1)]
        a = cpu.render(t_us, wfc, K, cpu.width, cpu.height)
        b = gpu.render(t_us, wfc, K, gpu.width, gpu.height)
        assert psnr(a["rgb"], b["rgb"]) > 40.0
        assert np.abs(a["alpha"] - b["alpha"]).mean() < 2e-3
        solid = (a["alpha"] > 0.5) & (b["alpha"] > 0.5)
        rel = np.abs(a["depth"] - b["depth"])[solid] / a["depth"][solid]
        assert np.median(rel) < 1e-3
        assert (a["instance"] == b["instance"]).mean() > 0.99 and (a["instance"] > 0).any()


def test_eval_on_cuda_matches_cpu(scene_dir, capsys):
    d, _ = scene_dir
    results = {}
    for device in ("cpu", "cuda"):
        assert main(["eval", str(d), "--json", "--device", device]) == 0
        results[device] = json.loads(capsys.readouterr().out)
    a, b = results["cpu"], results["cuda"]
    assert a["n_gaussians"] == b["n_gaussians"] and a["n_test_frames"] == b["n_test_frames"] == 1
    assert abs(a["psnr"] - b["psnr"]) < 0.1
    assert b["render_fps"] > 0
