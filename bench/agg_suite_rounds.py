"""What each camera-tracking round does to the training cameras, against ground truth.

    python bench/agg_suite_rounds.py SEED [--noise 1.0] [--preset fast] [--set NAME=VALUE ...] [--until N]
    python bench/agg_suite_rounds.py --bundle BUNDLE --name NAME [--preset fast] [--set ...] [--until N]

Trains the suite's synthetic bundle of SEED (or any BUNDLE that has ground-truth poses, e.g. kitti06_51's priors) as
``bench/agg_suite.py probe`` / ``real`` would, AGG with every component, and stops after ``--until`` steps (default:
just after the last tracking round). Before and after each round it reads the training cameras and prints their
error after the Sim(3) alignment to ground truth (mean centre error in metres, mean rotation error in degrees), how
far the round moved them (median centre shift in metres, median turn in degrees), and what a gate that compares each
frame's loss at the training size (``TrackingConfig.gate``), or at the round's finest level, would keep. Written to
WORK/rounds/NAME.json as well.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from agg_suite import probe_config, synth_bundle  # bench/ is the script's folder
from agg_suite_curve import add_scene_args, reconstruct_until
from agg_suite_scores import sim3_scores


def cameras_now(graph, frames: list[int]) -> np.ndarray:
    """The refined camera-to-world poses [F, 4, 4] (float64) of ``frames``."""
    with torch.no_grad():
        cams = graph.camera.world_from_camera().numpy().astype(np.float64)  # [T, 4, 4]
    return cams[frames]


def moved(before: np.ndarray, after: np.ndarray, metres_per_unit: float) -> dict:
    """Median centre shift (metres) and turn (degrees) from ``before`` to ``after`` [F, 4, 4]."""
    from agg.eval.trajectory import rotation_angle_deg

    shift = np.linalg.norm(after[:, :3, 3] - before[:, :3, 3], axis=1) * metres_per_unit  # [F]
    turn = rotation_angle_deg(np.transpose(before[:, :3, :3], (0, 2, 1)) @ after[:, :3, :3])  # [F]
    return {"shift_median_m": float(np.median(shift)), "shift_max_m": float(shift.max()),
            "turn_median_deg": float(np.median(turn))}


def watch(bundle_path: Path, scene_dir: Path, cfg, until: int | None, out_path: Path) -> list[dict]:
    """Train with every tracking round read on either side: the trainer's ``track_cameras`` is wrapped for the run
    (the round itself, and so the run, is unchanged)."""
    import agg.train.trainer as trainer_module
    from agg.io.bundle import SceneBundle
    from agg.train.camera_tracking import full_size_losses, level_inputs

    gt_all = np.asarray(SceneBundle.load(bundle_path).gt.world_from_camera, np.float64)  # [T, 4, 4]
    rows: list[dict] = []
    held: list = []
    original = trainer_module.track_cameras

    class Watched(trainer_module.Trainer):  # kept for its iteration and metric scale
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            held.append(self)

    def watched_round(graph, images, frames, config, extent, **kwargs):
        frames = list(frames)
        finest = config.levels[-1]  # the finest level the round optimises (1 where it reaches the training size)
        inputs = {level: level_inputs(graph, images, kwargs.get("attention"), frames, level) for level in {1, finest}}

        def losses(level: int) -> np.ndarray:  # [F] each frame's tracking loss at 1/level of the training size
            return np.array(full_size_losses(graph, frames, inputs[level], kwargs["ssim_weight"],
                                             kwargs["lambda_sem"], kwargs["delta"]))

        before, loss0, fine0 = cameras_now(graph, frames), losses(1), losses(finest)
        report = original(graph, images, frames, config, extent, **kwargs)
        if report is None:
            return None
        after, loss1, fine1 = cameras_now(graph, frames), losses(1), losses(finest)
        better, fine_better = loss1 < loss0, fine1 < fine0  # [F] each
        gated = np.where(better[:, None, None], after, before)  # [F, 4, 4]
        fine_gated = np.where(fine_better[:, None, None], after, before)  # [F, 4, 4]
        gt = gt_all[frames]
        mpu = held[-1].metric.metres_per_unit
        row = {"iteration": held[-1].iteration, "before": {**sim3_scores(before, gt), "metres_per_unit": mpu},
               "after": {**sim3_scores(after, gt), "metres_per_unit": mpu}, "moved": moved(before, after, mpu),
               "full_size_loss": [float(loss0.mean()), float(loss1.mean())],
               "frames_better": int(better.sum()), "frames": int(len(better)),
               "gated": {**sim3_scores(gated, gt), "metres_per_unit": mpu}, "levels": report["levels"],
               "finest_level": finest, "finest_loss": [float(fine0.mean()), float(fine1.mean())],
               "frames_better_finest": int(fine_better.sum()),
               "gated_finest": {**sim3_scores(fine_gated, gt), "metres_per_unit": mpu}}
        rows.append(row)
        print(f"  round at {row['iteration']}: {row['before']['sim3_mean_m']:.4f} m / "
              f"{row['before']['sim3_rotation_deg']:.3f} deg -> {row['after']['sim3_mean_m']:.4f} m / "
              f"{row['after']['sim3_rotation_deg']:.3f} deg; moved {row['moved']['shift_median_m']:.4f} m, "
              f"{row['moved']['turn_median_deg']:.3f} deg; full-size loss {loss0.mean():.4f} -> "
              f"{loss1.mean():.4f}, {row['frames_better']}/{row['frames']} frames better; gated "
              f"{row['gated']['sim3_mean_m']:.4f} m / {row['gated']['sim3_rotation_deg']:.3f} deg; at level {finest} "
              f"{row['frames_better_finest']} frames better, gated there {row['gated_finest']['sim3_mean_m']:.4f} m",
              flush=True)
        return report

    trainer_module.track_cameras = watched_round
    try:
        reconstruct_until(Watched, bundle_path, scene_dir, cfg, "", until)
    finally:
        trainer_module.track_cameras = original
    out_path.parent.mkdir(parents=True, exist_ok=True)
    out_path.write_text(json.dumps(rows, indent=1) + "\n")
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_scene_args(p, "agg")
    p.add_argument("--bundle", default=None, help="a bundle with ground-truth poses instead of the synthetic one")
    p.add_argument("--name", default=None, help="the run's name with --bundle")
    p.add_argument("--until", type=int, default=None)
    args = p.parse_args(argv)
    work = Path(args.work)
    cfg, tag = probe_config(args.preset, args.set)
    until = args.until
    if until is None and cfg.tracking is not None:
        until = cfg.tracking.scaled(cfg.scale).at[-1] + 1
    if args.bundle:
        bundle, name = Path(args.bundle), args.name or Path(args.bundle).name
    else:
        bundle = synth_bundle(work, args.seed, args.noise, args.frames, args.width, args.height)
        name = f"rounds_s{args.seed}_n{args.noise:g}_{args.preset}"
    name += f"_{tag}" if tag else ""
    watch(bundle, work / "scenes" / name, cfg, until, work / "rounds" / f"{name}.json")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
