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


def test_auto_is_cuda_when_torch_sees_it():
    want = "cuda" if torch.cuda.is_available() else "cpu"
    assert resolve_device("auto").type == want


def test_workers_train_on_the_configured_device():
    from service.config import ServiceConfig
    from tests import service_engine
    from agg.train import reconstruct
    from worker.jobs import takes_device

    assert ServiceConfig().train_device == "auto"
    cfg = ServiceConfig.from_env({"AGG_TRAIN_DEVICE": "cuda:1"})
    assert cfg.train_device == "cuda:1" and cfg.to_env()["AGG_TRAIN_DEVICE"] == "cuda:1"
    assert ServiceConfig.from_env(cfg.to_env()).train_device == "cuda:1"  # agg serve -> its workers
    assert takes_device(reconstruct) and takes_device(lambda *a, **kw: None)
    assert not takes_device(service_engine.reconstruct)  # an engine without the argument never gets it


def test_a_worker_with_a_bad_device_stops_before_taking_jobs(capsys):
    from worker.cli import main as worker_main

    assert worker_main(["--train-device", "gpu", "--redis-url", "redis://127.0.0.1:1/0", "--burst"]) == 2
    assert "agg worker: error: unknown torch device 'gpu'" in capsys.readouterr().err
    assert worker_main(["--grpc-device", "mps", "--redis-url", "redis://127.0.0.1:1/0", "--burst"]) == 2
    assert "device 'mps'" in capsys.readouterr().err
