"""``--device``: names of torch devices given by users are checked once, with a clear error (CPU machines)."""

from __future__ import annotations

import json

import pytest
import torch

from agg.cli import main
from agg.device import resolve_device
from tests.scene_dirs import make_bundle, make_graph, write_scene_dir


def test_cpu_names_resolve():
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device(torch.device("cpu")).type == "cpu"


@pytest.mark.parametrize("spec, words", [("gpu", "unknown torch device"), ("mps", "only cpu and cuda"),
                                         ("cuda:x", "unknown torch device")])
def test_bad_names_say_why(spec, words):
    with pytest.raises(ValueError, match=words):
        resolve_device(spec)


@pytest.mark.skipif(torch.cuda.is_available(), reason="a CUDA device is visible")
def test_cuda_without_a_device_says_why():
    with pytest.raises(ValueError, match="CPU build|no CUDA device"):
        resolve_device("cuda")


@pytest.mark.skipif(torch.cuda.is_available(), reason="a CUDA device is visible")
def test_reconstruct_on_a_missing_device_fails_before_any_work(tmp_path, capsys):
    bundle, _ = make_bundle(tmp_path)
    assert main(["reconstruct", str(bundle.path), "-o", str(tmp_path / "s"), "--device", "cuda"]) == 2
    assert "agg reconstruct: error: device 'cuda'" in capsys.readouterr().err
    assert not (tmp_path / "s").exists()


def test_eval_and_render_reject_bad_devices_before_loading(tmp_path, capsys):
    bundle, _ = make_bundle(tmp_path)
    d = write_scene_dir(tmp_path, "s", bundle, make_graph(bundle), train_frames=[0, 1, 2, 3, 5])
    assert main(["eval", str(d), "--device", "gpu"]) == 2
    assert "agg eval: error: unknown torch device 'gpu'" in capsys.readouterr().err
    assert main(["render", str(d), "--frame", "0", "--device", "mps", "-o", str(tmp_path / "x.png")]) == 2
    assert "agg render: error: device 'mps'" in capsys.readouterr().err
    assert not (tmp_path / "x.png").exists() and not (d / "metrics.json").exists()
    assert main(["eval", str(d), "--device", "cpu", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["n_test_frames"] == 1 and out["psnr"] > 15.0
