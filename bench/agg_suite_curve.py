"""When, during training, a variant's held-out background error opens up: the depth-band scores of
``bench/agg_suite_depth.py`` taken every ``--every`` iterations of a suite run, on the graph as it trains.

    python bench/agg_suite_curve.py SEED [--variants agg,no-tick-tock] [--noise 1.0] [--agent-noise 0]
                                    [--preset balanced] [--set NAME=VALUE ...] [--every 100] [--work DIR]

Each variant trains the suite's synthetic bundle of SEED exactly as ``bench/agg_suite.py probe`` would (same config,
``--set`` replacements included); the scores are read between two training steps, with no gradient and without
touching the training state, so the run is the suite's run (checked on the ``tiny`` preset: the same loss curve, bit
for bit, with and without the scores). One JSON line per evaluation goes to stdout and to WORK/curves/NAME.jsonl:
``iteration``, ``phase`` (of the step just taken), ``n_background``, the training cameras' mean centre error against
ground truth (``camera_m``; ``camera_sim3_m`` after the Sim(3) alignment, whose ``sim3_scale`` is ground truth per
scene unit) and the ``test`` / ``train`` scores (PSNR outside the ground-truth agent masks: all, by ground-truth
depth band, the bottom third, and the near road's median relative depth error).
"""

from __future__ import annotations

import argparse
import importlib
import json
from pathlib import Path

from agg_suite import ROOT, VARIANTS, probe_config, synth_bundle  # bench/ is the script's folder
from agg_suite_depth import graph_depth_errors
from agg_suite_scores import camera_scores


def train_with_curve(bundle_path: Path, scene_dir: Path, cfg, ablate: str, every: int, out_path: Path | None,
                     echo: bool = True) -> list[dict]:
    """Reconstruct ``bundle_path`` into ``scene_dir`` (no final evaluation) and return the score rows taken every
    ``every`` iterations (also appended to ``out_path``)."""
    from agg.io.bundle import SceneBundle

    from agg.train.trainer import Trainer

    bundle = SceneBundle.load(bundle_path)
    held: list = []

    class Watched(Trainer):  # the trainer ``reconstruct`` builds, kept for the callback
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            held.append(self)

    rows: list[dict] = []
    if out_path is not None:
        out_path.parent.mkdir(parents=True, exist_ok=True)
        out_path.write_text("")

    def progress(event: dict) -> None:
        it = event.get("iteration")
        if event.get("stage") != "train" or not held or it is None or it % every:
            return
        t = held[-1]
        cams = camera_scores(t.graph, scene_dir, bundle_path)["refined"]
        row = {"iteration": it, "phase": event["phase"], "n_background": len(t.graph.background),
               "camera_m": round(cams["mean_m"], 4), "camera_sim3_m": round(cams["sim3_mean_m"], 4),
               "sim3_scale": round(cams["sim3_scale"], 4),
               **graph_depth_errors(t.graph, bundle, t.data.train_frames, t.data.test_frames, bands_only=True)}
        rows.append(row)
        if out_path is not None:
            with out_path.open("a") as fh:
                fh.write(json.dumps(row) + "\n")
        if echo:
            print(json.dumps(row), flush=True)

    reconstruct_with(Watched, bundle_path, scene_dir, cfg, ablate, progress=progress)
    return rows


def reconstruct_with(trainer_cls, bundle_path: Path, scene_dir: Path, cfg, ablate: str, **kwargs) -> None:
    """``reconstruct`` the bundle from scratch (no final evaluation) with ``trainer_cls``, a subclass of the
    trainer that watches the run, in place of the trainer it builds."""
    rec = importlib.import_module("agg.train.reconstruct")  # the module (agg.train's ``reconstruct`` is the function)
    original = rec.Trainer
    rec.Trainer = trainer_cls
    try:
        rec.reconstruct(bundle_path, scene_dir, cfg, resume=False, ablate=ablate, evaluate=False, **kwargs)
    finally:
        rec.Trainer = original


def reconstruct_until(trainer_cls, bundle_path: Path, scene_dir: Path, cfg, ablate: str, until: int | None) -> None:
    """``reconstruct_with``, stopped as a cancelled job stops (checkpoint written) once the trainer has taken
    ``until`` steps; ``None`` runs to the end."""
    from agg.train.trainer import Cancelled

    held: list = []

    class Held(trainer_cls):  # the trainer ``reconstruct`` builds, kept for the stop test
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            held.append(self)

    try:
        reconstruct_with(Held, bundle_path, scene_dir, cfg, ablate,
                         should_stop=lambda: until is not None and bool(held) and held[-1].iteration >= until)
    except Cancelled:
        pass


def add_scene_args(p: argparse.ArgumentParser, variants: str) -> None:
    """The arguments that pick a suite run to watch: the seed, variants, noise, preset, ``--set`` replacements and
    the bundle's size, as ``bench/agg_suite.py probe`` takes them."""
    p.add_argument("seed", type=int)
    p.add_argument("--variants", default=variants)
    p.add_argument("--noise", type=float, default=1.0)
    p.add_argument("--preset", default="balanced")
    p.add_argument("--set", action="append", default=[], help="NAME=VALUE, as bench/agg_suite.py probe")
    p.add_argument("--frames", type=int, default=24)
    p.add_argument("--width", type=int, default=320)
    p.add_argument("--height", type=int, default=192)
    p.add_argument("--work", default=str(ROOT / "bench" / "out" / "agg_suite"))


def suite_runs(args: argparse.Namespace, prefix: str, tag: str, agent_noise: float = 0.0):
    """(name, ablation) of each of ``args.variants`` in turn, the name as ``prefix_sSEED_nNOISE[_aAGENT]_VARIANT_PRESET
    [_TAG]`` (``tag`` from ``probe_config``); an unknown variant ends the script when its turn comes."""
    for variant in args.variants.split(","):
        if variant not in VARIANTS:
            raise SystemExit(f"unknown variant {variant!r} (one of {', '.join(VARIANTS)})")
        yield (f"{prefix}_s{args.seed}_n{args.noise:g}" + (f"_a{agent_noise:g}" if agent_noise else "")
               + f"_{variant}_{args.preset}" + (f"_{tag}" if tag else "")), VARIANTS[variant]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_scene_args(p, "agg,no-tick-tock")
    p.add_argument("--agent-noise", type=float, default=0.0)
    p.add_argument("--every", type=int, default=100)
    args = p.parse_args(argv)
    work = Path(args.work)
    cfg, tag = probe_config(args.preset, args.set)
    bundle = synth_bundle(work, args.seed, args.noise, args.frames, args.width, args.height, args.agent_noise)
    for name, ablate in suite_runs(args, "curve", tag, args.agent_noise):
        train_with_curve(bundle, work / "scenes" / name, cfg, ablate, args.every, work / "curves" / f"{name}.jsonl")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
