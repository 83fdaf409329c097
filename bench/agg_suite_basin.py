"""Is a training camera's error the tracker's or the map's? The tracking loss around chosen cameras during a suite run.

    python bench/agg_suite_basin.py SEED --cameras 2,3 --at 333,667 [--variants agg,no-tick-tock] [--noise 1.0]
                                    [--preset balanced] [--set NAME=VALUE ...] [--work DIR] [--save]
                                    [--saved [--round-set tracking.NAME=VALUE ...]]

Each variant trains the suite's synthetic bundle of SEED as ``bench/agg_suite.py probe`` would (same config, ``--set``
replacements included). After each ``--at`` iteration (a camera-tracking milestone reads the map that round starts
from), the Gaussians are held fixed and, for each camera, it reports:

- the tracking loss of that frame (a tracking step's: L_photo, plus Eq. 3 with M_bg when the semantic loss is on) at
  each level of the preset's tracking, rendered through four poses: the camera's current one (``now``), ground truth
  (``gt``), the ground-truth rotation at the current centre (``gt_rotation``) and the current rotation at the
  ground-truth centre (``gt_centre``);
- a tracking round of that camera alone (the preset's levels, steps and rates), started from ``now`` and from ``gt``:
  the yaw and sideways error it ends at, its whole rotation and centre error, and its last loss.

If the map scores the ground truth above the current pose, or a round started at the ground truth walks away from it,
the error is the map's: no tracker would fix it. If the ground truth scores lower and a round from ``now`` stays put,
it is the tracker's. The run's state is put back after each reading, so the run goes on as the suite's. Errors are
in the ground-truth camera's axes (``bench/agg_suite_frames.py``). Written to WORK/basin/NAME.jsonl as well.

``--save`` also writes the graph at each ``--at`` to WORK/basin/NAME_itN.pt. ``--saved`` trains nothing: it reads
those graphs again, with the rounds' tracking settings replaced by ``--round-set`` (``tracking.NAME=VALUE``, as
``agg_suite.py probe --set``), and writes WORK/basin/NAME_TAG.jsonl, so other trackers can be tried on the same maps.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np
import torch

from agg_suite import probe_config, synth_bundle  # bench/ is the script's folder
from agg_suite_curve import add_scene_args, reconstruct_until, suite_runs
from agg_suite_frames import camera_error

POSES = ("now", "gt", "gt_rotation", "gt_centre")


def set_pose(camera, frame: int, world_from_camera: np.ndarray) -> None:
    """Set ``camera``'s correction of ``frame`` so that it renders from ``world_from_camera`` [4, 4]."""
    prior = camera.prior[frame].detach().double().numpy()  # [4, 4]
    corr = np.linalg.inv(prior) @ world_from_camera  # prior_camera_from_refined_camera
    rvec, _ = cv2.Rodrigues(corr[:3, :3])
    with torch.no_grad():
        camera.omega[frame] = torch.as_tensor(rvec[:, 0], dtype=camera.omega.dtype)
        camera.tau[frame] = torch.as_tensor(corr[:3, 3], dtype=camera.tau.dtype)


def pose(rotation: np.ndarray, centre: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = rotation, centre
    return out


def read_basin(g, images, attention, cfg, tracking, extent: float, gt: np.ndarray, cameras: list[int]) -> dict:
    """The reading of one map (see the module doc): graph ``g``, training images [T, H, W, 3], M_bg [T, H, W] or
    None, the TrainConfig, the rounds' TrackingConfig and the scene extent. Every parameter, flag and gradient of
    ``g`` is put back."""
    from agg.train.camera_tracking import frame_loss, level_inputs, track_cameras

    cam = g.camera
    saved = [(p, p.detach().clone(), p.requires_grad, p.grad) for p in g.parameters()]
    for p in g.parameters():
        p.requires_grad_(False)
    kw = dict(ssim_weight=cfg.ssim_weight, lambda_sem=cfg.lambda_sem, delta=cfg.delta)
    out = {}
    try:
        with torch.no_grad():
            now = cam.world_from_camera().double().numpy()  # [T, 4, 4]
        for c in cameras:
            poses = {"now": now[c], "gt": gt[c], "gt_rotation": pose(gt[c][:3, :3], now[c][:3, 3]),
                     "gt_centre": pose(now[c][:3, :3], gt[c][:3, 3])}
            inputs = [level_inputs(g, images, attention, [c], level) for level in tracking.levels]
            losses = {}
            for name in POSES:
                set_pose(cam, c, poses[name])
                row = []
                for targets, maps, ks in inputs:
                    with torch.no_grad():
                        row.append(float(frame_loss(g, c, targets[c], None if maps is None else maps[c], ks[c],
                                                    **kw)))
                losses[name] = row
            rounds = {}
            for start in ("now", "gt"):
                set_pose(cam, c, poses[start])
                report = track_cameras(g, images, [c], tracking, extent, attention=attention, **kw)
                for p in (cam.omega, cam.tau):
                    p.requires_grad_(False)
                with torch.no_grad():
                    end = cam.world_from_camera([c])[0].double().numpy()
                rvec, centre = camera_error(gt[c], end)
                rounds[start] = {"rotation_deg": rvec.round(3).tolist(), "centre_m": centre.round(3).tolist(),
                                 "loss_last": report["levels"][-1]["loss_last"]}
            rvec, centre = camera_error(gt[c], now[c])
            out[str(c)] = {"rotation_deg": rvec.round(3).tolist(), "centre_m": centre.round(3).tolist(),
                           "levels": list(tracking.levels), "loss": losses, "round": rounds}
    finally:
        with torch.no_grad():
            for p, value, flag, grad in saved:
                p.copy_(value)
                p.requires_grad_(flag)
                p.grad = grad
    return out


def print_reading(it: int, phase: str, reading: dict) -> None:
    for c, r in reading.items():
        print(f"  {it:5d} {phase:6s} camera {c}: yaw {r['rotation_deg'][1]:+.2f} deg, right {r['centre_m'][0]:+.2f} m",
              flush=True)
        for name in POSES:
            values = " ".join(f"L{lv} {v:.5f}" for lv, v in zip(r["levels"], r["loss"][name]))
            print(f"      loss at {name:11s} {values}", flush=True)
        for start, e in r["round"].items():
            print(f"      round from {start:3s}: yaw {e['rotation_deg'][1]:+.2f} deg, right {e['centre_m'][0]:+.2f} m, "
                  f"|rot| {np.linalg.norm(e['rotation_deg']):.2f} deg, |centre| {np.linalg.norm(e['centre_m']):.2f} m, "
                  f"last loss {e['loss_last']:.5f}", flush=True)


def watch(bundle_path: Path, scene_dir: Path, cfg, ablate: str, cameras: list[int], at: list[int],
          out_path: Path, save: bool) -> None:
    from agg.io.bundle import SceneBundle
    from agg.train.camera_tracking import TrackingConfig
    from agg.train.trainer import Trainer

    gt = np.asarray(SceneBundle.load(bundle_path).gt.world_from_camera, np.float64)  # [T, 4, 4]
    out_path.parent.mkdir(parents=True, exist_ok=True)
    fh = out_path.open("w")

    class Watched(Trainer):
        def step(self) -> dict:
            row = super().step()
            it = row["iteration"]
            if it in at:
                tracking = self.tracking or TrackingConfig()
                attention = self.data.m_bg if self.cfg.semantic else None
                reading = read_basin(self.graph, self.data.images, attention, self.cfg, tracking, self.extent, gt,
                                     cameras)
                if save:
                    torch.save({"graph": self.graph.state(), "extent": self.extent, "iteration": it,
                                "phase": row["phase"]}, out_path.with_name(f"{out_path.stem}_it{it}.pt"))
                fh.write(json.dumps({"iteration": it, "phase": row["phase"], "cameras": reading}) + "\n")
                print_reading(it, row["phase"], reading)
            return row

    try:
        reconstruct_until(Watched, bundle_path, scene_dir, cfg, ablate, max(at))
    finally:
        fh.close()


def reread(bundle_path: Path, cfg, ablate: str, cameras: list[int], at: list[int], stem: Path, tracking,
           out_path: Path) -> None:
    """The readings of the graphs ``--save`` wrote (STEM_itN.pt), with the rounds' settings ``tracking``."""
    from agg.graph import SceneGraph
    from agg.io.bundle import SceneBundle
    from agg.train.data import load_train_data

    cfg = cfg.with_ablation(ablate)
    bundle = SceneBundle.load(bundle_path)
    gt = np.asarray(bundle.gt.world_from_camera, np.float64)  # [T, 4, 4]
    data = load_train_data(bundle, cfg.max_width, cfg.attention_norm, cfg.eval_every, cfg.semantic_min_contrast)
    attention = data.m_bg if cfg.semantic else None
    with out_path.open("w") as fh:
        for it in at:
            state = torch.load(stem.with_name(f"{stem.name}_it{it}.pt"), map_location="cpu", weights_only=False)
            g = SceneGraph.from_state(state["graph"])
            reading = read_basin(g, data.images, attention, cfg, tracking, state["extent"], gt, cameras)
            fh.write(json.dumps({"iteration": it, "phase": state["phase"], "cameras": reading}) + "\n")
            print_reading(it, state["phase"], reading)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_scene_args(p, "agg,no-tick-tock")
    p.add_argument("--cameras", required=True, help="training frames to read, comma-separated (not frame 0)")
    p.add_argument("--at", required=True, help="iterations to read at, comma-separated")
    p.add_argument("--save", action="store_true", help="write the graph at each --at (for --saved)")
    p.add_argument("--saved", action="store_true", help="read the graphs --save wrote instead of training")
    p.add_argument("--round-set", action="append", default=[], help="tracking.NAME=VALUE for the rounds (--saved)")
    args = p.parse_args(argv)
    work = Path(args.work)
    cfg, tag = probe_config(args.preset, args.set)
    if args.round_set and not args.saved:
        raise SystemExit("--round-set reads saved graphs: add --saved")
    if any(not item.startswith("tracking.") for item in args.round_set):
        raise SystemExit("--round-set: only tracking.NAME=VALUE")
    from agg.train.camera_tracking import TrackingConfig

    round_cfg, round_tag = probe_config(args.preset, args.round_set)
    tracking = (round_cfg.tracking or TrackingConfig()).scaled(cfg.scale)
    bundle = synth_bundle(work, args.seed, args.noise, args.frames, args.width, args.height)
    cameras = [int(c) for c in args.cameras.split(",")]
    if 0 in cameras:
        raise SystemExit("--cameras: frame 0 is the gauge and never moves")
    at = sorted(int(a) for a in args.at.split(","))
    for name, ablate in suite_runs(args, "basin", tag):
        out = work / "basin" / f"{name}.jsonl"
        if args.saved:
            print(name + (f" {round_tag}" if round_tag else ""), flush=True)
            reread(bundle, cfg, ablate, cameras, at, out.with_suffix(""), tracking,
                   out.with_name(f"{name}_{round_tag or 'same'}.jsonl"))
        else:
            print(name, flush=True)
            watch(bundle, work / "scenes" / name, cfg, ablate, cameras, at, out, args.save)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
