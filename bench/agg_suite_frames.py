"""Frame by frame: each camera's error against ground truth and each held-out frame's PSNR, before and after its
camera is fitted alone.

    python bench/agg_suite_frames.py SEED SCENE [SCENE ...] [--work bench/out/agg_suite] [--noise 1.0] [--fit 60]

SCENE names a folder under WORK/scenes (a run of ``bench/agg_suite.py`` whose scene is still on disk) trained on the
seed's bundle at ``--noise``. For every frame of the clip it prints the camera the scene renders that frame from (the
refined camera of a training frame; for a held-out frame the one ``agg eval`` interpolates from the training frames,
marked ``*``) against ground truth, in the priors' world (frame 0 is the gauge, so no alignment is taken out):

- the rotation error as a rotation vector in the camera's axes, in degrees: pitch (about x, right), yaw (about y,
  down) and roll (about z, forward);
- the centre error in the ground-truth camera's axes, in metres: right, down, forward.

For each held-out frame it adds the PSNR from ``metrics.json`` and, with ``--fit N``, the PSNR after N Adam steps
fit that frame's camera alone to its image (the scene frozen): a frame that stays low after the fit is the map's,
not the interpolated camera's. The suite's priors have exact rotations (its noise moves the camera centres only),
so every degree of rotation error is the refinement's.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np
import torch

from agg_suite import bundle_dir  # bench/ is the script's folder, so it is on the path
from agg_suite_depth import _fit_camera, add_finished_scene_args
from agg_suite_scores import load_graph


def camera_error(gt: np.ndarray, est: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(rotation vector [3] degrees, centre error [3] metres), both in the ground-truth camera's axes, of one
    camera-to-world pose ``est`` [4, 4] against ``gt`` [4, 4]."""
    rvec, _ = cv2.Rodrigues(gt[:3, :3].T @ est[:3, :3])
    return np.degrees(rvec[:, 0]), gt[:3, :3].T @ (est[:3, 3] - gt[:3, 3])


def frame_rows(scene_dir: Path, bundle_path: Path, fit: int = 0) -> list[dict]:
    """One row per frame of the clip (see the module doc)."""
    from agg.eval.nvs import agent_pose_tables, fit_image, held_out_overrides
    from agg.io.bundle import SceneBundle

    meta = json.loads((scene_dir / "scene.json").read_text())
    train = meta["train_frames"]
    metrics = json.loads((scene_dir / "metrics.json").read_text())
    held_psnr = {r["frame"]: r["psnr"] for r in metrics.get("per_frame", [])}
    bundle = SceneBundle.load(bundle_path)
    gt_poses = np.asarray(bundle.gt.world_from_camera, np.float64)  # [T, 4, 4]
    graph = load_graph(scene_dir)
    graph.eval()
    for p in graph.parameters():
        p.requires_grad_(False)
    tables = agent_pose_tables(graph)
    with torch.no_grad():
        refined = graph.camera.world_from_camera().numpy().astype(np.float64)  # [T, 4, 4]
    rows = []
    for f in range(bundle.num_frames):
        row = {"frame": f, "held_out": f not in train}
        cam = refined[f]
        if row["held_out"]:
            cam_t, poses, valid = held_out_overrides(graph, train, f, tables)
            cam = cam_t.detach().numpy().astype(np.float64)
            row["psnr"] = held_psnr.get(f)
            if fit > 0:
                with torch.no_grad():
                    h, w = graph.render(f, world_from_camera=cam_t, agent_poses=poses,
                                        agent_valid=valid).color.shape[:2]
                gt = fit_image(torch.as_tensor(np.asarray(bundle.frame(f), np.float32)), h, w)
                fitted = _fit_camera(graph, f, cam_t, poses, valid, gt, torch.ones(h, w, dtype=torch.bool), fit)
                with torch.no_grad():
                    pred = graph.render(f, world_from_camera=fitted, agent_poses=poses, agent_valid=valid).color
                row["psnr_fit"] = float(-10 * torch.log10(((pred.clamp(0, 1) - gt) ** 2).mean()))
        rot, centre = camera_error(gt_poses[f], cam)
        row["rotation_deg"], row["centre_m"] = rot.round(3).tolist(), centre.round(3).tolist()
        rows.append(row)
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_finished_scene_args(p)
    p.add_argument("--fit", type=int, default=60, help="Adam steps of the held-out camera fit (0: none)")
    args = p.parse_args(argv)
    work = Path(args.work)
    for name in args.scenes:
        print(name)
        for r in frame_rows(work / "scenes" / name, bundle_dir(work, args.seed, args.noise), args.fit):
            (pitch, yaw, roll), (right, down, fwd) = r["rotation_deg"], r["centre_m"]
            line = (f"  {r['frame']:3d}{'*' if r['held_out'] else ' '} pitch {pitch:+.2f} yaw {yaw:+.2f} roll "
                    f"{roll:+.2f} deg  centre {right:+.2f} {down:+.2f} {fwd:+.2f} m")
            if r.get("psnr") is not None:
                line += f"  PSNR {r['psnr']:.2f}" + (f" (camera fitted {r['psnr_fit']:.2f})" if "psnr_fit" in r else "")
            print(line, flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
