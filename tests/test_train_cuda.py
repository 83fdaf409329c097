"""Training on a CUDA device (gsplat when installed): a tiny reconstruction on CUDA against the same on the CPU, and
checkpoints that move between devices (a job started on a GPU worker resumes on a CPU one, and back). Skipped
without CUDA."""

from __future__ import annotations

import math

import pytest
import torch

from agg.scene import Scene
from agg.synth.corrupt import NoiseConfig
from agg.synth.scene import SceneConfig
from agg.synth.suite import generate, write_bundle
from agg.train import reconstruct
from agg.train.trainer import Cancelled

pytestmark = pytest.mark.cuda

if not torch.cuda.is_available():
    pytest.skip("no CUDA device", allow_module_level=True)


@pytest.fixture(scope="module")
def bundle(tmp_path_factory):
    path = tmp_path_factory.mktemp("cuda_train") / "bundle"
    noise = NoiseConfig(camera_translation_max=0.1)
    gt, priors = generate(SceneConfig(seed=2, frames=10, width=128, height=80), noise)
    write_bundle(path, gt, priors, noise)
    return path


def test_tiny_reconstruction_on_cuda_matches_cpu(bundle, tmp_path):
    cpu = reconstruct(bundle, tmp_path / "cpu", "tiny")
    gpu = reconstruct(bundle, tmp_path / "gpu", "tiny", device="cuda")
    assert (cpu["device"], gpu["device"]) == ("cpu", "cuda")
    assert gpu["iterations"] == cpu["iterations"] and gpu["nodes"] == cpu["nodes"]
    for s in (cpu, gpu):
        assert math.isfinite(s["metrics"]["psnr"]) and math.isfinite(s["final_train_psnr"])
    # different rasterisers (gsplat / the CPU kernels) and float orderings: close, not equal
    assert abs(gpu["metrics"]["psnr"] - cpu["metrics"]["psnr"]) < 1.5
    assert gpu["n_gaussians"] > gpu["initial"]["n_gaussians"] * 0.5  # pruning on CUDA left the scene standing
    # (that densification gets dL/dmeans2d from gsplat is tested in test_render_cuda.py)
    scene = Scene.load(tmp_path / "gpu")  # a model trained on CUDA serves from the CPU
    assert scene.graph.K.device.type == "cpu"


@pytest.mark.parametrize("first, second", [("cuda", "cpu"), ("cpu", "cuda")])
def test_a_checkpoint_resumes_on_the_other_device(bundle, tmp_path, first, second):
    polls = {"n": 0}

    def stop() -> bool:
        polls["n"] += 1
        return polls["n"] > 45

    with pytest.raises(Cancelled):
        reconstruct(bundle, tmp_path / "s", "tiny", device=first, should_stop=stop, checkpoint_every=20,
                    evaluate=False)
    state = torch.load(tmp_path / "s" / "checkpoint.pt", map_location="cpu", weights_only=False)
    assert 0 < state["iteration"] < 80
    done = reconstruct(bundle, tmp_path / "s", "tiny", device=second)
    assert done["device"] == second and done["iterations"] == 80
    assert math.isfinite(done["metrics"]["psnr"])
