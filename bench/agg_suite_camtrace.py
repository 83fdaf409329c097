"""How chosen training cameras move during a suite run: their yaw and sideways centre error against ground truth.

    python bench/agg_suite_camtrace.py SEED --cameras 2,3 [--variants agg,no-tick-tock] [--noise 1.0]
                                       [--preset balanced] [--set NAME=VALUE ...] [--until N] [--every 20] [--work DIR]

Each variant trains the suite's synthetic bundle of SEED as ``bench/agg_suite.py probe`` would (same config, ``--set``
replacements included). After every ``--every`` steps, and on the steps either side of each camera-tracking round, it
prints the iteration, the phase and, for each camera, the yaw error (degrees, about the camera's y axis) and the
centre's error along the camera's x axis (metres, to the right), both against ground truth in the priors' world (the
suite's priors have exact rotations and noisy centres, so a yaw error is the refinement's: ``bench/agg_suite_frames.py``
gives every axis at the end of a run). The cameras are read between steps, so the run is the suite's. Written to
WORK/camtrace/NAME.jsonl as well (one line per reading, every axis).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from agg_suite import probe_config, synth_bundle  # bench/ is the script's folder
from agg_suite_curve import add_scene_args, reconstruct_until, suite_runs
from agg_suite_frames import camera_error


def trace(bundle_path: Path, scene_dir: Path, cfg, ablate: str, cameras: list[int], until: int | None, every: int,
          out_path: Path) -> None:
    from agg.io.bundle import SceneBundle
    from agg.train.trainer import Trainer

    gt = np.asarray(SceneBundle.load(bundle_path).gt.world_from_camera, np.float64)  # [T, 4, 4]
    out_path.parent.mkdir(parents=True, exist_ok=True)
    fh = out_path.open("w")

    class Watched(Trainer):
        def step(self) -> dict:
            row = super().step()
            it = row["iteration"]
            rounds = self.tracking.at if self.tracking is not None else ()
            if it % every and not any(abs(it - a) <= 1 for a in rounds) and it != until:
                return row
            with torch.no_grad():
                cams = self.graph.camera.world_from_camera().numpy().astype(np.float64)  # [T, 4, 4]
            errs = {c: camera_error(gt[c], cams[c]) for c in cameras}
            fh.write(json.dumps({"iteration": it, "phase": row["phase"], **{
                str(c): {"rotation_deg": r.round(3).tolist(), "centre_m": x.round(3).tolist()}
                for c, (r, x) in errs.items()}}) + "\n")
            print(f"  {it:5d} {row['phase']:6s} " + "  ".join(
                f"camera {c}: yaw {r[1]:+.2f} deg, right {x[0]:+.2f} m" for c, (r, x) in errs.items()), flush=True)
            return row

    try:
        reconstruct_until(Watched, bundle_path, scene_dir, cfg, ablate, until)
    finally:
        fh.close()


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_scene_args(p, "agg,no-tick-tock")
    p.add_argument("--cameras", required=True, help="training frames to follow, comma-separated")
    p.add_argument("--until", type=int, default=None)
    p.add_argument("--every", type=int, default=20)
    args = p.parse_args(argv)
    work = Path(args.work)
    cfg, tag = probe_config(args.preset, args.set)
    bundle = synth_bundle(work, args.seed, args.noise, args.frames, args.width, args.height)
    cameras = [int(c) for c in args.cameras.split(",")]
    for name, ablate in suite_runs(args, "camtrace", tag):
        print(name, flush=True)
        trace(bundle, work / "scenes" / name, cfg, ablate, cameras, args.until, max(args.every, 1),
              work / "camtrace" / f"{name}.jsonl")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
