"""AGG against the fixed-topology baseline and each ablation on the synthetic suite, plus KITTI and the preset trade.

    python bench/agg_suite.py synth [--seeds 0,1,2] [--noise 0,0.25,0.5,1.0] [--variants agg,baseline,...]
    python bench/agg_suite.py kitti [--data ../shared/data/kitti06_51] [--preset fast] [--set tracking.NAME=V]
    python bench/agg_suite.py presets [--presets fast,balanced] [--seed 0]
    python bench/agg_suite.py real --data BUNDLE [--tag NAME] [--variants agg,no-tick-tock,...] [--set seed=1]
    python bench/agg_suite.py probe --set iterations=4000 [--set lr.agent_boost=1] [--set tracking=none] [--seeds 0]
                                    [--set evolution.every=5000] [--set tracking.levels=4,2,1]
                                    [--noise 1.0] [--agent-noise 0.5] [--oracle-agents]
                                    # no --set needed with --agent-noise or --oracle-agents
    python bench/agg_suite.py rescore           # region / agent-pose / topology scores of runs whose scenes are on disk
    python bench/agg_suite.py report            # tables -> docs/BENCHMARKS.md section, plots -> docs/*.png

Synthetic runs: ``SceneConfig(seed, frames=24, 320x192)`` with ``NoiseConfig(camera_translation_max=noise,
missed=1, false=1)`` (the most visible moving car is missing from the priors, one false agent is planted), trained
at ``--preset`` (default balanced). Every run's result is a JSON file under ``--work`` (default
bench/out/agg_suite), so interrupted suites resume and ``report`` reads whatever has finished.
Variants: ``agg`` (everything on), ``baseline`` (``--ablate all``: the fixed-topology GSG baseline, same code),
``no-tick-tock``, ``no-semantic``, ``no-topology``; ``tick-tock-only``, ``semantic-only`` and ``topology-only`` (the
baseline plus one component, for how the components interact).
``probe`` runs the same synthetic variants at ``--preset`` with training options replaced (``--set NAME=VALUE``,
``lr.NAME`` for a learning-rate field; milestones scale with ``iterations``), to ask what a component's worth
depends on. Its records are kind "probe" and stay out of the suite's tables. ``--agent-noise`` adds noise to the
tracklet box centres too (the suite's priors keep them exact; only the cameras are noisy, as in the paper's stress
test), so a probe can ask what the agent rates are worth when the agent priors are wrong; with ``--agent-noise``
no ``--set`` is needed (the preset as it is, on noisy boxes). ``--oracle-agents`` hands the run priors with every
agent and no false one (the cameras as noisy as the suite's): what a scene graph gets when nothing is left for
topology evolution to correct: a measure of what correcting the agents can add. ``--boxes-follow-cameras``
lifts the tracklet boxes into the world through the noisy cameras, as the priors of a video are lifted
(``NoiseConfig.boxes_follow_cameras``: each box carries its frame's camera error; the suite keeps them exact).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import platform
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from agg_suite_scores import (agent_pose_scores, camera_scores, clip_camera_scores, load_graph,  # bench/ is on
                              prior_mask_scores, refined_alignment, region_scores, topology_scores)  # the path

ROOT = Path(__file__).resolve().parents[1]
SYNTHETIC_KINDS = ("synth", "preset", "probe")  # records of synthetic bundles, which have ground-truth scores
PRESET_NOISE = 0.5  # the preset trade runs on the seed's 0.5 m bundle
VARIANTS = {"agg": "", "baseline": "all", "no-tick-tock": "tick-tock", "no-semantic": "semantic",
            "no-topology": "topology",
            # the baseline plus one component (probes of how the components interact; no table of their own)
            "tick-tock-only": "semantic,topology", "semantic-only": "tick-tock,topology",
            "topology-only": "tick-tock,semantic"}


def bundle_dir(work: Path, seed: int, noise: float, agent_noise: float = 0.0, oracle: bool = False,
               follow: bool = False) -> Path:
    """Where ``synth_bundle`` keeps the bundle of these settings (the scripts that rescore scenes read it there)."""
    return work / "bundles" / (f"s{seed}_n{noise:g}" + (f"_a{agent_noise:g}" if agent_noise else "")
                               + ("_oracle" if oracle else "") + ("_fc" if follow else ""))


def synth_bundle(work: Path, seed: int, noise: float, frames: int, width: int, height: int,
                 agent_noise: float = 0.0, oracle: bool = False, follow: bool = False) -> Path:
    """The suite's bundle of ``seed`` with camera-centre noise ``noise`` (m); ``agent_noise`` (m, probes only) also
    moves every tracklet box centre by up to that much per frame (the suite itself keeps the boxes exact);
    ``oracle`` (probes only) keeps every agent in the priors and plants no false one (the same camera noise, whose
    draws are their own stream); ``follow`` (probes only) lifts the boxes through the noisy cameras."""
    from agg.synth.corrupt import NoiseConfig
    from agg.synth.scene import SceneConfig
    from agg.synth.suite import generate, write_bundle

    path = bundle_dir(work, seed, noise, agent_noise, oracle, follow)
    if not (path / "manifest.json").is_file():
        cfg = NoiseConfig(seed=seed, camera_translation_max=noise, agent_translation_max=agent_noise,
                          missed=0 if oracle else 1, false=0 if oracle else 1, boxes_follow_cameras=follow)
        gt, priors = generate(SceneConfig(seed=seed, frames=frames, width=width, height=height), cfg)
        tmp = path.with_name(f"{path.name}.tmp{os.getpid()}")  # runs started together race for one bundle:
        write_bundle(tmp, gt, priors, cfg, overwrite=True)  # each writes its own, the first rename wins
        try:
            tmp.rename(path)
        except OSError:
            shutil.rmtree(tmp)
    return path


def machine_info() -> dict:
    """What a run's floating-point results may depend on besides the code and the bundle: the CPU (torch and OpenCV
    pick SIMD kernels from its flags) and the numeric libraries' versions."""
    import cv2
    import torch

    info = Path("/proc/cpuinfo")
    lines = info.read_text().splitlines() if info.is_file() else []
    flags = next((ln for ln in lines if ln.startswith("flags")), "")
    model = next((ln.split(":", 1)[1].strip() for ln in lines if ln.startswith("model name")), platform.processor())
    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else None
    return {"cpu": model, "avx512": " avx512f" in flags, "torch": torch.__version__, "opencv": cv2.__version__,
            "numpy": np.__version__, "torch_threads": torch.get_num_threads(), "gpu": gpu}


REPORT_FILES = ("priors_summary.json",)  # what ``agg priors`` measured (its timings change from run to run)
REPORT_DIRS = ("previews",)  # ... and its PNG previews: neither is training input


def bundle_digest(path: Path) -> str | None:
    """SHA-256 (16 hex digits) over a bundle folder's files, names and contents, reports and previews left out:
    bundles are cached in the work folder and not tracked, so a record says which one it trained on (runs compared
    side by side must share it). Before 2026-12-04's thirty-fourth session the digest also read
    ``priors_summary.json``, so the same priors estimated twice got two digests."""
    path = Path(path)
    if not path.is_dir():
        return None
    h = hashlib.sha256()
    for f in sorted(p for p in path.rglob("*") if p.is_file() and p.name not in REPORT_FILES
                    and not set(p.relative_to(path).parts[:-1]) & set(REPORT_DIRS)):
        h.update(str(f.relative_to(path)).encode())
        h.update(f.read_bytes())
    return h.hexdigest()[:16]


def _log_topology(name: str, t0: float):
    """A progress callback that prints one line per topology evolution (a run's log then says what evolution did
    while it trains, also of a run stopped before its record is written)."""
    keys = ("candidates", "clusters", "spawned", "pruned", "floating", "static", "moving", "boxed")

    def progress(event: dict) -> None:
        if event.get("event") == "topology":
            r = event["report"]
            print(f"{name} {time.perf_counter() - t0:7.1f} s  iteration {r.get('iteration')}:",
                  json.dumps({k: r.get(k) for k in keys}), flush=True)
    return progress


def _run(args, name: str, input_path, preset, row: dict, **kwargs) -> dict | None:
    """Reconstruct ``input_path`` (at ``preset``, a name or a TrainConfig) into work/scenes/NAME and record
    work/runs/NAME.json (``row`` plus wall time, metrics and summary); None when that record exists and ``--force``
    is off."""
    from agg.train import reconstruct

    work = Path(args.work)
    out = work / "runs" / f"{name}.json"
    if out.is_file() and not args.force:
        return None
    digest = bundle_digest(input_path)  # taken before training: which input this record trained on
    t0 = time.perf_counter()
    summary = reconstruct(input_path, work / "scenes" / name, preset, resume=False, device=args.device,
                          progress=_log_topology(name, t0), **kwargs)
    row = {**row, "preset": preset if isinstance(preset, str) else preset.name, "device": args.device,
           "wall_s": round(time.perf_counter() - t0, 1), "machine": machine_info(), "bundle": digest,
           "metrics": summary.get("metrics"), "summary": summary}
    if row["kind"] in SYNTHETIC_KINDS:  # score the missed and false agents, the cameras and the regions
        graph = load_graph(work / "scenes" / name)
        row["topology"] = topology_scores(graph, input_path, refined_alignment(graph, work / "scenes" / name,
                                                                               input_path))
        row["cameras"] = camera_scores(graph, work / "scenes" / name, input_path)
        row["regions"] = region_scores(work / "scenes" / name)
        row["agent_poses"] = agent_pose_scores(graph, input_path)
    elif row["kind"] == "real":
        row["prior_masks"] = prior_mask_scores(work / "scenes" / name)
    if row["kind"] in ("kitti", "real") and (cameras := clip_camera_scores(work / "scenes" / name)) is not None:
        row["cameras"] = cameras
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(row, indent=1))
    print(name, f"{row['wall_s']} s", "PSNR", row["metrics"]["psnr"], "agents", row["metrics"]["psnr_agents"],
          flush=True)
    return row


def _synthetic_cases(args, agent_noise: float = 0.0, oracle: bool = False, follow: bool = False):
    """(seed, noise, variant, bundle path) for every case of ``--seeds`` x ``--noise`` x ``--variants``."""
    for seed in [int(s) for s in args.seeds.split(",")]:
        for noise in [float(n) for n in args.noise.split(",")]:
            for variant in args.variants.split(","):
                yield seed, noise, variant, synth_bundle(Path(args.work), seed, noise, args.frames, args.width,
                                                         args.height, agent_noise, oracle, follow)


def run_synth(args) -> None:
    for seed, noise, variant, bundle in _synthetic_cases(args):
        row = _run(args, f"synth_s{seed}_n{noise:g}_{variant}_{args.preset}", bundle, args.preset,
                   {"kind": "synth", "seed": seed, "noise": noise, "variant": variant}, ablate=VARIANTS[variant])
        if row is not None:
            print("  topology:", row["topology"]["missed_match"], flush=True)


PROBE_PARTS = ("lr", "evolution", "tracking")  # --set PART.NAME=VALUE reaches a field of TrainConfig.PART


def _probe_value(kind: type, value: str):
    """A --set VALUE read as ``kind``: ``none`` is None, a bool is true/false, a tuple is comma-separated ints."""
    if value.lower() == "none":
        return None
    if kind is bool:
        if value.lower() not in ("true", "false"):
            raise SystemExit(f"--set: {value!r} is not true or false")
        return value.lower() == "true"
    if kind is tuple:
        return tuple(int(v) for v in value.split(","))
    if kind is type(None):  # an optional setting that is off by default: a number switches it on
        try:
            return float(value)
        except ValueError:
            raise SystemExit(f"--set: {value!r} is not a number") from None
    return kind(value)


def probe_config(preset: str, sets: list[str]):
    """The preset with ``NAME=VALUE`` replacements (``lr.NAME`` for a learning-rate field, ``evolution.NAME`` for a
    topology-evolution one, ``tracking.NAME`` for camera tracking; ``none`` switches off an optional part or
    setting, ``true`` / ``false`` set a switch, ``4,2,1`` a tuple), and a tag naming them."""
    from dataclasses import fields, replace

    from agg.train.config import get_preset

    cfg = get_preset(preset)
    tags = []
    for item in sets:
        name, _, value = item.partition("=")
        part, _, field = name.rpartition(".")
        if part and part not in PROBE_PARTS:
            raise SystemExit(f"--set {item!r}: no part {part!r} (one of {', '.join(PROBE_PARTS)})")
        target = getattr(cfg, part) if part else cfg
        if target is None:
            raise SystemExit(f"--set {item!r}: {part} is off in this preset or an earlier --set")
        kinds = {f.name: type(getattr(target, f.name)) for f in fields(target)}
        if field not in kinds or not value:
            raise SystemExit(f"--set {item!r}: no option {name!r} (NAME=VALUE)")
        new = replace(target, **{field: _probe_value(kinds[field], value)})  # tracking=none
        cfg = replace(cfg, **{part: new}) if part else new
        tags.append(f"{field}{value.replace(',', '-')}")
    return cfg, "_".join(tags)


def run_probe(args) -> None:
    a, oracle, follow = args.agent_noise, args.oracle_agents, args.boxes_follow_cameras
    if not args.set and not a and not oracle and not follow:
        raise SystemExit("probe needs at least one --set NAME=VALUE, --agent-noise, --oracle-agents or "
                         "--boxes-follow-cameras")
    cfg, tag = probe_config(args.preset, args.set)
    for seed, noise, variant, bundle in _synthetic_cases(args, a, oracle, follow):
        _run(args, f"probe_s{seed}_n{noise:g}" + (f"_a{a:g}" if a else "") + ("_oracle" if oracle else "")
             + ("_fc" if follow else "") + f"_{variant}_{args.preset}" + (f"_{tag}" if tag else ""),
             bundle, cfg, {"kind": "probe", "seed": seed, "noise": noise, "variant": variant, "set": args.set,
                           "agent_noise": a, "oracle_agents": oracle, "boxes_follow_cameras": follow},
             ablate=VARIANTS[variant])


def run_rescore(args) -> None:
    """Add the region, agent-pose and topology scores to finished records whose scene directory is still on
    disk, and the camera scores to KITTI and real-clip records whose bundle has ground-truth cameras."""
    work = Path(args.work)
    for path in sorted((work / "runs").glob("*.json")):
        row = json.loads(path.read_text())
        scene = work / "scenes" / path.stem
        if row["kind"] == "real" and (scene / "model.pt").is_file():
            row["prior_masks"] = prior_mask_scores(scene)
            path.write_text(json.dumps(row, indent=1))
            print(path.stem, row["prior_masks"], flush=True)
        if row["kind"] in ("kitti", "real") and (scene / "model.pt").is_file() and (
                cameras := clip_camera_scores(scene)) is not None:
            row["cameras"] = cameras
            path.write_text(json.dumps(row, indent=1))
            print(path.stem, {k: round(v["sim3_mean_m"], 3) for k, v in row["cameras"].items()}, flush=True)
        if row["kind"] in SYNTHETIC_KINDS and (scene / "metrics.json").is_file():
            if json.loads((scene / "metrics.json").read_text())["psnr"] != row["metrics"]["psnr"]:
                print(path.stem, "skipped: the scene on disk is not the one this record scored", flush=True)
                continue
            row["regions"] = region_scores(scene)
            bundle = synth_bundle(work, row["seed"], row["noise"], args.frames, args.width, args.height,
                                  row.get("agent_noise", 0.0), row.get("oracle_agents", False),
                                  row.get("boxes_follow_cameras", False))
            graph = load_graph(scene)
            row["agent_poses"] = agent_pose_scores(graph, bundle)
            if row.get("topology") is not None:
                row["topology"] = topology_scores(graph, bundle, refined_alignment(graph, scene, bundle))
            path.write_text(json.dumps(row, indent=1))
            print(path.stem, row["regions"], {k: v for k, v in (row["agent_poses"] or {}).items()
                                              if k != "per_agent"}, flush=True)


def run_kitti(args) -> None:
    """kitti06_51 from its frames (priors estimated in the run), with its estimated poses and with ground truth;
    ``--set`` options as for ``probe`` name the records after them (the report's table reads ``--work``'s
    top-level records, so keep option runs in a work folder of their own)."""
    cfg, tag = probe_config(args.preset, args.set) if args.set else (args.preset, "")
    for gt in (False, True):
        _run(args, f"kitti_{args.preset}_{'gt' if gt else 'est'}" + (f"_{tag}" if tag else ""), args.data, cfg,
             {"kind": "kitti", "gt_poses": gt, "set": args.set}, gt_poses=gt)


def run_real(args) -> None:
    """Each variant on one real input (a bundle whose priors were estimated once, so every variant trains on the
    same priors), with ``--set`` options and training seeds when given: there is no ground truth beyond the frames,
    so the records hold the held-out metrics alone."""
    cfg, tag = probe_config(args.preset, args.set) if args.set else (args.preset, "")
    data = Path(args.data)
    name = args.tag or data.name
    for variant in args.variants.split(","):
        _run(args, f"real_{name}_{variant}_{args.preset}" + (f"_{tag}" if tag else ""), data, cfg,
             {"kind": "real", "data": name, "variant": variant, "set": args.set}, ablate=VARIANTS[variant])


def run_presets(args) -> None:
    for preset in args.presets.split(","):
        bundle = synth_bundle(Path(args.work), args.seed, PRESET_NOISE, args.frames, args.width, args.height)
        _run(args, f"preset_{preset}_s{args.seed}", bundle, preset,
             {"kind": "preset", "seed": args.seed, "noise": PRESET_NOISE})


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("what", choices=["synth", "probe", "kitti", "real", "presets", "rescore", "report"])
    p.add_argument("--work", default=str(ROOT / "bench" / "out" / "agg_suite"))
    p.add_argument("--seeds", default="0,1,2")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--noise", default="0,0.25,0.5,1.0")
    p.add_argument("--variants", default="agg,baseline")
    p.add_argument("--preset", default="balanced")
    p.add_argument("--presets", default="fast,balanced")
    p.add_argument("--frames", type=int, default=24)
    p.add_argument("--width", type=int, default=320)
    p.add_argument("--height", type=int, default=192)
    p.add_argument("--data", default=str(ROOT.parent / "shared" / "data" / "kitti06_51"))
    p.add_argument("--set", action="append", default=[], help="probe: NAME=VALUE (lr.NAME for a learning rate)")
    p.add_argument("--agent-noise", type=float, default=0.0,
                   help="probe: also move each tracklet box centre by up to this many metres per frame")
    p.add_argument("--oracle-agents", action="store_true",
                   help="probe: priors with every agent and no false one (the same camera noise)")
    p.add_argument("--boxes-follow-cameras", action="store_true",
                   help="probe: tracklet boxes lifted through the noisy cameras (each carries its frame's error)")
    p.add_argument("--tag", default=None, help="real: the name its records carry (default: the folder's)")
    p.add_argument("--force", action="store_true")
    p.add_argument("--device", default="cpu", help="torch device training runs on (cpu, cuda, ...)")
    args = p.parse_args(argv)
    if (args.agent_noise or args.boxes_follow_cameras) and args.what != "probe":
        p.error("--agent-noise and --boxes-follow-cameras are for probe only (the suite's records keep the tracklet "
                "boxes exact)")
    if args.what == "report":
        from bench.agg_suite_report import write_report

        write_report(Path(args.work), ROOT / "docs", machine=f"{platform.processor() or platform.machine()}")
        return 0
    commands = {"synth": run_synth, "probe": run_probe, "rescore": run_rescore, "kitti": run_kitti,
                "real": run_real, "presets": run_presets}
    commands[args.what](args)
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    sys.exit(main())
