"""Subprocess entry that runs pycolmap structure-from-motion in isolation.

Run as a *script* (``python _sfm_worker.py JOB_DIR``; ``run_worker`` launches it): the child imports only the
standard library, numpy and pycolmap, so OpenCV (used by the parent process to write the PNGs and for the
checks) never shares a process with pycolmap. The parent imports this module for ``run_worker`` only (pycolmap
is imported inside ``run_job``). GUIDE.md: the two in one process crashed with
``free(): invalid pointer`` while writing PNGs.

Input ``JOB_DIR/job.json`` (written by ``agg.priors.poses``)::

    image_dir: folder of PNGs, names: image names in input order,
    camera_model: COLMAP model name (SIMPLE_PINHOLE, PINHOLE, FULL_OPENCV),
    camera_params: list of floats in COLMAP's convention (pixel centre of the top-left pixel at (0.5, 0.5)),
    refine_focal, refine_principal_point, refine_extra_params: bools,
    overlap, max_num_features, init_max_forward_motion, init_min_tri_angle, num_threads, random_seed,
    min_num_matches, abs_pose_min_num_inliers

Output ``JOB_DIR/result.npz``: for the largest model only (empty arrays if none)::

    registered: [N] bool, cam_from_world: [N, 3, 4] (COLMAP cam_from_world, OpenCV axes),
    camera_params: [P] float64 (COLMAP convention), points_xyz: [M, 3], points_rgb: [M, 3] uint8,
    points_error: [M] px, obs_frame: [K] int, obs_point: [K] int (row in points_xyz),
    obs_uv: [K, 2] keypoint in COLMAP pixel convention (distorted image)

and ``JOB_DIR/result.json`` with timings (s), model sizes and a status string.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np


def _largest_model(recs: dict) -> object | None:
    best, best_n = None, -1
    for rec in recs.values():
        n = rec.num_reg_images()
        if n > best_n:
            best, best_n = rec, n
    return best


def run_job(job_dir: Path) -> dict:
    import pycolmap

    job = json.loads((job_dir / "job.json").read_text())
    names: list[str] = job["names"]
    db = job_dir / "database.db"
    reuse = bool(job.get("reuse_database")) and db.exists()  # a re-run of the mapper only (new seed)
    if db.exists() and not reuse:
        db.unlink()
    out = job_dir / f"sparse_{int(job.get('random_seed', 0))}"
    out.mkdir(exist_ok=True)
    info: dict = {"status": "ok", "timings_s": {}, "model_sizes": []}
    nthreads = int(job.get("num_threads", -1))

    if not reuse:
        # --- feature extraction (CPU SIFT, one shared camera with the given parameters)
        t0 = time.perf_counter()
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = job["camera_model"]
        reader.camera_params = ",".join(f"{p:.10g}" for p in job["camera_params"])
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.use_gpu = False
        extraction.num_threads = nthreads
        extraction.sift.max_num_features = int(job.get("max_num_features", 8192))
        pycolmap.extract_features(
            db, job["image_dir"], image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
            reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu,
        )
        info["timings_s"]["feature_extraction"] = time.perf_counter() - t0

        # --- sequential matching with a true N-frame overlap, no loop detection (it needs a vocabulary download)
        t0 = time.perf_counter()
        matching = pycolmap.FeatureMatchingOptions()
        matching.use_gpu = False
        matching.num_threads = nthreads
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = int(job.get("overlap", 10))
        pairing.quadratic_overlap = False
        pairing.loop_detection = False
        pairing.num_threads = nthreads
        pycolmap.match_sequential(db, matching_options=matching, pairing_options=pairing, device=pycolmap.Device.cpu)
        info["timings_s"]["matching"] = time.perf_counter() - t0

    # --- incremental mapping with loosened start-up thresholds for forward motion
    t0 = time.perf_counter()
    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = nthreads
    opts.random_seed = int(job.get("random_seed", 0))
    opts.min_num_matches = int(job.get("min_num_matches", 15))
    opts.extract_colors = True
    opts.ba_refine_focal_length = bool(job["refine_focal"])
    opts.ba_refine_principal_point = bool(job["refine_principal_point"])
    opts.ba_refine_extra_params = bool(job["refine_extra_params"])
    m = opts.mapper
    m.init_max_forward_motion = float(job.get("init_max_forward_motion", 1.0))
    m.init_min_tri_angle = float(job.get("init_min_tri_angle", 4.0))
    m.abs_pose_refine_focal_length = bool(job["refine_focal"])
    m.abs_pose_refine_extra_params = bool(job["refine_extra_params"])
    m.abs_pose_min_num_inliers = int(job.get("abs_pose_min_num_inliers", 30))
    m.num_threads = nthreads
    m.random_seed = int(job.get("random_seed", 0))
    opts.mapper = m
    recs = pycolmap.incremental_mapping(db, job["image_dir"], out, options=opts)
    info["timings_s"]["mapping"] = time.perf_counter() - t0
    info["model_sizes"] = sorted((r.num_reg_images() for r in recs.values()), reverse=True)

    n = len(names)
    index = {name: i for i, name in enumerate(names)}
    registered = np.zeros(n, bool)
    cam_from_world = np.tile(np.eye(4)[:3], (n, 1, 1))
    rec = _largest_model(recs)
    pts_xyz = np.zeros((0, 3))
    pts_rgb = np.zeros((0, 3), np.uint8)
    pts_err = np.zeros(0)
    obs_frame, obs_point, obs_uv = [], [], []
    camera_params = np.asarray(job["camera_params"], float)
    if rec is None:
        info["status"] = "no_model"
    else:
        cam = next(iter(rec.cameras.values()))
        camera_params = np.asarray(cam.params, float)
        for image in rec.images.values():
            if not image.has_pose:
                continue
            i = index[image.name]
            registered[i] = True
            cam_from_world[i] = np.asarray(image.cam_from_world().matrix(), float)
        pid_to_row = {}
        xyz, rgb, err = [], [], []
        for pid, p in rec.points3D.items():
            pid_to_row[pid] = len(xyz)
            xyz.append(np.asarray(p.xyz, float))
            rgb.append(np.asarray(p.color, np.uint8))
            err.append(float(p.error))
            for el in p.track.elements:
                image = rec.images[el.image_id]
                obs_frame.append(index[image.name])
                obs_point.append(pid_to_row[pid])
                obs_uv.append(np.asarray(image.points2D[el.point2D_idx].xy, float))
        if xyz:
            pts_xyz, pts_rgb, pts_err = np.stack(xyz), np.stack(rgb), np.asarray(err)
    np.savez(
        job_dir / "result.npz",
        registered=registered, cam_from_world=cam_from_world, camera_params=camera_params,
        points_xyz=pts_xyz, points_rgb=pts_rgb, points_error=pts_err,
        obs_frame=np.asarray(obs_frame, np.int64), obs_point=np.asarray(obs_point, np.int64),
        obs_uv=np.asarray(obs_uv, float).reshape(-1, 2),
    )
    (job_dir / "result.json").write_text(json.dumps(info))
    return info


def run_worker(job_dir: Path, job: dict, timeout_s: float) -> tuple[dict | None, dict]:
    """Parent side: run this file in a child process on ``job``; returns (result arrays or None, info)."""
    job_dir = Path(job_dir)
    for stale in ("result.npz", "result.json"):
        (job_dir / stale).unlink(missing_ok=True)
    (job_dir / "job.json").write_text(json.dumps(job))
    try:
        proc = subprocess.run([sys.executable, str(Path(__file__).resolve()), str(job_dir)], capture_output=True,
                              text=True, timeout=timeout_s)
    except subprocess.TimeoutExpired:
        return None, {"status": "timeout"}
    if proc.returncode != 0 or not (job_dir / "result.npz").exists():
        return None, {"status": f"worker failed (exit {proc.returncode})", "stderr_tail": proc.stderr[-2000:]}
    with np.load(job_dir / "result.npz") as z:
        arrays = {k: z[k] for k in z.files}
    return arrays, json.loads((job_dir / "result.json").read_text())


if __name__ == "__main__":
    if len(sys.argv) != 2:
        print("usage: _sfm_worker.py JOB_DIR", file=sys.stderr)
        sys.exit(2)
    run_job(Path(sys.argv[1]))
