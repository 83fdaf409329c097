"""Camera-pose prior from a monocular video: pycolmap SfM, outlier checks, OpenCV visual-odometry fallback.

``estimate_poses``: frames are resized and written as PNGs with OpenCV here; pycolmap runs in a separate process
(``_sfm_worker.py``; the two in one process crashed, GUIDE.md) with CPU SIFT, sequential matching over a true
N-frame overlap, no loop detection and loosened start-up thresholds; the largest model is kept. Registered
poses are checked (``agg.priors.pose_checks``: OpenCV essential matrices on consecutive pairs, per frame and as
a clip-level "bend", and smoothness against slerp/lerp of the neighbours), outliers and unregistered frames are
interpolated (constant velocity beyond the ends), and OpenCV essential-matrix VO (``visual_odometry``) replaces SfM
when too few frames register. World = first camera (``world_from_camera[0] = I``), OpenCV axes; the scale is normalised
so the median sparse depth is 1 (VO: mean step 1). Details, thresholds and the confidence rule: docs/PRIORS.md.
"""

from __future__ import annotations

import tempfile
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Sequence

import numpy as np

from agg.priors._sfm_worker import run_worker
from agg.priors.intrinsics import CameraIntrinsics, intrinsics_for_frames
from agg.priors.pose_checks import (
    PoseEstimationError,
    epipolar_check,
    find_pose_outliers,
    interpolate_poses,
    track_corners,
    two_view_motion,
)


@dataclass(frozen=True)
class PoseConfig:
    """Settings of ``estimate_poses``. Angles in degrees; ``image_scale`` is a resize factor."""

    image_scale: float = 1.0  # SfM/VO work resolution relative to the input
    min_work_width: int = 640  # ... but never below this width (nor above the input's): small frames stay sharp
    overlap: int = 10  # sequential matching window (frames)
    max_num_features: int = 8192
    init_max_forward_motion: float = 1.0
    init_min_tri_angle: float = 4.0
    refine_intrinsics: bool | None = None  # None: refine focal only when intrinsics were not given
    num_threads: int = 1  # SIFT, matching and mapping. 1: the same clip gives bit-identical poses (pycolmap 4.2,
    #                      fixed random_seed). -1 (all cores) is faster (51 KITTI frames, 2 cores: 91 s against
    #                      128 s at full resolution, 25 s against 31 s at half) but each of the three stages then
    #                      varies from run to run
    random_seed: int = 0
    max_sfm_attempts: int = 4  # mapper runs (new seed each) while the bend check or registration fails: with
    #                             all cores the mapper was not deterministic, and bent models (~25 deg) came back
    #                             in about 1 of 4 runs on synthetic 320x192 clips
    sfm_timeout_s: float = 1800.0
    min_registered_fraction: float = 0.5  # below this, VO replaces SfM
    outlier_min_deg: float = 5.0
    outlier_k: float = 5.0
    epipolar_max_deg: float = 3.0  # per-pair rotation disagreement with the essential matrix
    epipolar_max_t_deg: float = 45.0  # per-pair direction-of-travel disagreement: at most 5.3 deg on KITTI 06 and
    #                                  the dashcam clip, 26 deg on synthetic 320x192 clips, 65-78 deg where the
    #                                  last frame of a 14-frame clip was registered a step too far
    epipolar_min_flow_px: float = 2.0  # ... checked only where the pair's median flow defines a direction
    max_bend_deg: float = 3.0  # clip-level accumulated disagreement (E chains themselves drift ~1 deg on KITTI)
    normalize_scale: bool = True
    use_sfm: bool = True  # False: VO only
    vo_min_flow_px: float = 0.5  # median flow below this: the camera is treated as stationary
    vo_max_corners: int = 2000

    @staticmethod
    def preset(name: str) -> "PoseConfig":
        """"accurate": full resolution (128 s for 51 KITTI frames on 2 cores, one thread); "fast": half
        resolution, at least ``min_work_width`` pixels wide (SfM at 160x96 drifted 12 % of the path on synthetic
        320x192 clips; at 320x192 it stayed under 0.6 %)."""
        presets = {"accurate": PoseConfig(), "fast": PoseConfig(image_scale=0.5)}
        if name not in presets:
            raise PoseEstimationError(f"unknown preset {name!r}; choose from {sorted(presets)}")
        return presets[name]


@dataclass
class SparsePoints:
    """Sparse SfM points in the result's world frame, with per-frame observations.

    ``obs_uv`` are keypoints in the *undistorted pinhole* image at the input resolution (OpenCV pixel
    convention) and ``obs_depth`` the z of the point in that frame's camera (world units), so a sparse depth
    map for frame i is ``obs_uv[obs_frame == i]`` with ``obs_depth[obs_frame == i]``.
    """

    xyz: np.ndarray  # [M, 3] world
    rgb: np.ndarray  # [M, 3] uint8
    error_px: np.ndarray  # [M] mean reprojection error at the work resolution
    obs_frame: np.ndarray  # [K] int frame index
    obs_point: np.ndarray  # [K] int row in xyz
    obs_uv: np.ndarray  # [K, 2] pixels
    obs_depth: np.ndarray  # [K] > 0

    def for_frame(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """(uv [k, 2], depth [k]) observed in frame i."""
        m = self.obs_frame == i
        return self.obs_uv[m], self.obs_depth[m]


@dataclass
class PoseResult:
    world_from_camera: np.ndarray  # [T, 4, 4] camera-to-world, OpenCV axes, frame 0 = I
    source: list[str]  # [T] "sfm" | "interpolated" | "vo"
    confidence: np.ndarray  # [T] in [0, 1]
    registered_fraction: float  # frames SfM registered (before outlier removal) / T
    intrinsics: CameraIntrinsics  # refined (or given) at the input resolution
    points: SparsePoints
    outliers: list[int]  # registered frames rejected by the checks (then interpolated)
    method: str  # "sfm" or "vo"
    scale_applied: float  # world units per SfM (or VO) unit
    timings_s: dict[str, float] = field(default_factory=dict)
    diagnostics: dict = field(default_factory=dict)


# ------------------------------------------------------------------------------------------ visual odometry
def visual_odometry(grays: np.ndarray, K: np.ndarray, dist=None, config: PoseConfig = PoseConfig()):  # noqa: N803
    """Chained essential-matrix VO. Returns ``world_from_camera`` [T, 4, 4] (frame 0 = I) and inliers [T].

    Scale: the first moving step has length 1; each later step's length is fixed by triangulation
    consistency - features detected in frame i and tracked to i-1 and i+1 are triangulated with both pairs,
    and the median depth ratio carries the scale from pair (i-1, i) to (i, i+1). Where that fails (too few
    common points) the previous step length is kept. A pair with median flow below ``vo_min_flow_px`` is
    treated as stationary (rotation only).
    """
    import cv2

    t_count = len(grays)
    motions = [two_view_motion(grays[i], grays[i + 1], K, dist, config.vo_max_corners) for i in range(t_count - 1)]
    kinv = np.linalg.inv(K)

    def depths_in_a(pa, pb, r, t):  # points seen at pa in camera a and pb in camera b=[r|t]; depths in a
        xa = (np.c_[pa, np.ones(len(pa))] @ kinv.T)[:, :2].T
        xb = (np.c_[pb, np.ones(len(pb))] @ kinv.T)[:, :2].T
        x = cv2.triangulatePoints(np.eye(3, 4), np.c_[r, t], xa, xb)
        return x[2] / x[3], (r @ (x[:3] / x[3]) + t[:, None])[2]

    scales = np.ones(t_count - 1)
    prev_scale = 1.0
    for i in range(t_count - 1):
        m = motions[i]
        if not m["ok"] or m["flow"] < config.vo_min_flow_px:
            scales[i] = 0.0
            continue
        scales[i] = prev_scale
        if i > 0 and scales[i - 1] > 0 and motions[i - 1]["ok"]:
            # corners of frame i tracked back to i-1 and forward to i+1, triangulated with both pairs
            p_i, (p_prev, p_next) = track_corners(grays[i], [grays[i - 1], grays[i + 1]], K, dist,
                                                  config.vo_max_corners)
            if len(p_i) >= 20:
                mp = motions[i - 1]  # cam_i_from_cam_{i-1}: unit t times scales[i-1]
                _, z_prev = depths_in_a(p_prev, p_i, mp["R"], mp["t"] * scales[i - 1])
                z_next, _ = depths_in_a(p_i, p_next, m["R"], m["t"])
                ok = (z_prev > 0) & (z_next > 0) & np.isfinite(z_prev) & np.isfinite(z_next)
                if ok.sum() >= 10:
                    scales[i] = float(np.median(z_prev[ok] / z_next[ok]))
        prev_scale = scales[i]
    world_from_camera = np.tile(np.eye(4), (t_count, 1, 1))
    inliers = np.zeros(t_count, int)
    for i, m in enumerate(motions):
        b_from_a = np.eye(4)
        b_from_a[:3, :3] = m["R"] if m["ok"] else np.eye(3)
        b_from_a[:3, 3] = m["t"] * scales[i]
        world_from_camera[i + 1] = world_from_camera[i] @ np.linalg.inv(b_from_a)
        inliers[i + 1] = m["inliers"]
    inliers[0] = inliers[1] if t_count > 1 else 0
    return world_from_camera, inliers


# -------------------------------------------------------------------------------------------- orchestration
def _load_frames(frames, scale: float, min_width: int = 0) -> tuple[list[np.ndarray], tuple[int, int]]:
    """Frames (array [T,H,W(,3)] uint8 / float in [0,1] RGB, or image paths) -> list of uint8 BGR/gray at the
    work resolution, and the input size (W, H)."""
    import cv2

    if isinstance(frames, np.ndarray):
        if frames.ndim not in (3, 4) or (frames.ndim == 4 and frames.shape[-1] not in (1, 3)):
            raise PoseEstimationError(f"frames must be [T, H, W] or [T, H, W, 3], got {frames.shape}")
        arr = frames if frames.dtype == np.uint8 else np.clip(np.asarray(frames, float) * 255 + 0.5, 0, 255).astype(np.uint8)
        imgs = [a[..., ::-1] if a.ndim == 3 and a.shape[-1] == 3 else a.reshape(a.shape[:2]) for a in arr]
    else:
        imgs = []
        for p in frames:
            img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
            if img is None:
                raise PoseEstimationError(f"cannot read image {p}")
            imgs.append(img if img.dtype == np.uint8 else cv2.convertScaleAbs(img, alpha=255.0 / img.max()))
    if len(imgs) < 2:
        raise PoseEstimationError(f"need at least 2 frames, got {len(imgs)}")
    h, w = imgs[0].shape[:2]
    if any(im.shape[:2] != (h, w) for im in imgs):
        raise PoseEstimationError("all frames must have the same size")
    scale = min(1.0, max(scale, min_width / w))
    if scale != 1.0:
        size = (max(1, round(w * scale)), max(1, round(h * scale)))
        imgs = [cv2.resize(im, size, interpolation=cv2.INTER_AREA) for im in imgs]
    return [np.ascontiguousarray(im) for im in imgs], (w, h)


def estimate_poses(frames: np.ndarray | Sequence, K=None, config: PoseConfig | None = None,  # noqa: N803, C901
                   dist=None, work_dir: str | Path | None = None) -> PoseResult:
    """Camera poses, refined intrinsics and sparse points for a monocular clip (see module docstring).

    frames: [T, H, W, 3] RGB (uint8, or float in [0, 1]), [T, H, W] grayscale, or a list of image paths.
    K: 3x3 pixels (OpenCV convention) or ``CameraIntrinsics`` or None (default field of view, refined).
    dist: OpenCV (k1, k2, p1, p2, k3) when K is an array.
    """
    import cv2

    cfg = config or PoseConfig()
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    imgs, (w, h) = _load_frames(frames, cfg.image_scale, cfg.min_work_width)
    n = len(imgs)
    intr = intrinsics_for_frames(K, dist, w, h)
    refine = intr.source != "given" if cfg.refine_intrinsics is None else cfg.refine_intrinsics
    wh, ww = imgs[0].shape[:2]
    work = intr.resized(ww, wh)
    grays = [im if im.ndim == 2 else cv2.cvtColor(im, cv2.COLOR_BGR2GRAY) for im in imgs]
    Kw, dw = work.K, (work.dist if work.has_distortion else None)  # noqa: N806
    diag: dict = {"sfm_attempts": []}
    tmp = tempfile.TemporaryDirectory(prefix="agg_sfm_") if work_dir is None else None
    job_dir = Path(tmp.name if tmp else work_dir)
    try:
        image_dir = job_dir / "images"
        image_dir.mkdir(parents=True, exist_ok=True)
        names = [f"{i:06d}.png" for i in range(n)]
        for name, im in zip(names, imgs):
            cv2.imwrite(str(image_dir / name), im)
        timings["prepare"] = time.perf_counter() - t0

        best = None
        if cfg.use_sfm:
            model, params = work.to_colmap(refine)
            job = dict(image_dir=str(image_dir), names=names, camera_model=model, camera_params=params,
                       refine_focal=refine, refine_principal_point=False, refine_extra_params=False,
                       overlap=cfg.overlap, max_num_features=cfg.max_num_features,
                       init_max_forward_motion=cfg.init_max_forward_motion,
                       init_min_tri_angle=cfg.init_min_tri_angle, num_threads=cfg.num_threads)
            for attempt in range(max(1, cfg.max_sfm_attempts)):
                arrays, info = run_worker(job_dir, {**job, "random_seed": cfg.random_seed + attempt,
                                                  "reuse_database": attempt > 0}, cfg.sfm_timeout_s)
                for k, v in info.get("timings_s", {}).items():
                    timings[k] = timings.get(k, 0.0) + v
                rec = {"status": info.get("status"), "model_sizes": info.get("model_sizes", [])}
                diag["sfm_attempts"].append(rec)
                if arrays is None or not arrays["registered"].any():
                    break
                tc = time.perf_counter()
                reg = arrays["registered"]
                cfw = np.tile(np.eye(4), (n, 1, 1))
                cfw[:, :3] = arrays["cam_from_world"]
                wfc = np.linalg.inv(cfw)
                epi = epipolar_check(grays, wfc, reg, Kw, dw, cfg)
                timings["checks"] = timings.get("checks", 0.0) + time.perf_counter() - tc
                rec.update(registered=int(reg.sum()), bend_deg=epi["bend_deg"])
                # keep the attempt with most registered frames, then the smallest bend; retry a bent or thin model
                if best is None or (reg.sum(), -epi["bend_deg"]) > (best[0]["registered"].sum(), -best[2]["bend_deg"]):
                    best = (arrays, wfc, epi)
                if epi["bend_deg"] <= cfg.max_bend_deg and reg.sum() >= cfg.min_registered_fraction * n:
                    break
        tc = time.perf_counter()
        use_sfm_result = best is not None and best[0]["registered"].sum() >= cfg.min_registered_fraction * n
        if use_sfm_result:
            result = _finish_sfm(best, n, intr, work, refine, cfg, grays, (w, h))
        else:
            result = _finish_vo(grays, Kw, dw, intr, cfg)
        stage = "checks" if use_sfm_result else "vo"
        timings[stage] = timings.get(stage, 0.0) + time.perf_counter() - tc
    finally:
        if tmp:
            tmp.cleanup()
    timings["total"] = time.perf_counter() - t0
    result.timings_s = timings
    result.diagnostics.update(diag)
    return result


def _finish_sfm(best, n, intr, work, refine, cfg, grays, size) -> PoseResult:
    arrays, wfc, epi = best
    reg = arrays["registered"].copy()
    model, _ = work.to_colmap(refine)
    intr_out = work.from_colmap(model, arrays["camera_params"], refine).resized(*size)
    xyz = arrays["points_xyz"]
    obs_f, obs_p = arrays["obs_frame"], arrays["obs_point"]
    cfw = np.linalg.inv(wfc)
    z = np.einsum("kij,kj->ki", cfw[obs_f, :3, :3], xyz[obs_p]) + cfw[obs_f, :3, 3]  # [K, 3] camera coords
    depth_ref = float(np.median(z[:, 2])) if len(z) else 0.0
    # checks: epipolar outliers first, then smoothness on what is left
    valid = reg.copy()
    valid[epi["outliers"]] = False
    smooth = find_pose_outliers(wfc, valid, cfg, depth_ref)
    valid[smooth] = False
    outliers = sorted(set(epi["outliers"]) | set(smooth))
    if not valid.any():
        valid = reg.copy()
        outliers = []
    poses = interpolate_poses(wfc, valid)
    # world = first camera, then scale normalisation by the median observation depth
    anchor = np.linalg.inv(poses[0])
    poses = anchor @ poses
    xyz_w = xyz @ anchor[:3, :3].T + anchor[:3, 3]
    scale = 1.0 / depth_ref if cfg.normalize_scale and depth_ref > 0 else 1.0
    poses[:, :3, 3] *= scale
    xyz_w = xyz_w * scale
    # observations -> undistorted pinhole pixels at the input resolution, with depths
    uv = arrays["obs_uv"] - 0.5
    if work.has_distortion and len(uv):
        import cv2

        uv = cv2.undistortPoints(uv.reshape(-1, 1, 2), work.K, work.dist, P=work.K).reshape(-1, 2)
    sx, sy = size[0] / work.width, size[1] / work.height
    uv = np.c_[(uv[:, 0] + 0.5) * sx - 0.5, (uv[:, 1] + 0.5) * sy - 0.5]
    keep = reg[obs_f] & valid[obs_f] & (z[:, 2] > 0)  # observations from rejected frames are dropped
    points = SparsePoints(xyz=xyz_w, rgb=arrays["points_rgb"], error_px=arrays["points_error"],
                          obs_frame=obs_f[keep], obs_point=obs_p[keep], obs_uv=uv[keep],
                          obs_depth=z[keep, 2] * scale)
    counts = np.bincount(points.obs_frame, minlength=n)
    source, conf = [], np.zeros(n)
    vidx = np.flatnonzero(valid)
    for i in range(n):
        if valid[i]:
            source.append("sfm")
            bad = [epi["bad_pairs"][j] for j in (i - 1, i) if 0 <= j < n - 1]
            conf[i] = min(1.0, counts[i] / 200.0) * (0.5 if any(bad) else 1.0)
        else:
            source.append("interpolated")
            conf[i] = 0.5 / max(1, int(np.min(np.abs(vidx - i))))
    return PoseResult(
        world_from_camera=poses, source=source, confidence=conf, registered_fraction=float(reg.mean()),
        intrinsics=intr_out if refine else replace(intr_out, fx=intr.fx, fy=intr.fy, cx=intr.cx, cy=intr.cy),
        points=points, outliers=outliers, method="sfm", scale_applied=scale,
        diagnostics={"epipolar_pair_deg": epi["pair_deg"].tolist(),
                     "epipolar_pair_t_deg": epi["pair_t_deg"].tolist(), "bend_deg": epi["bend_deg"],
                     "median_depth_sfm_units": depth_ref, "intrinsics_in": asdict(intr) | {"dist": intr.dist.tolist()}},
    )


def _finish_vo(grays, Kw, dw, intr, cfg) -> PoseResult:  # noqa: N803
    n = len(grays)
    poses, inliers = visual_odometry(np.asarray(grays), Kw, dw, cfg)
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    scale = 1.0 / float(steps[steps > 0].mean()) if cfg.normalize_scale and np.any(steps > 0) else 1.0
    poses[:, :3, 3] *= scale
    empty = np.zeros((0,), int)
    points = SparsePoints(np.zeros((0, 3)), np.zeros((0, 3), np.uint8), np.zeros(0), empty, empty,
                          np.zeros((0, 2)), np.zeros(0))
    return PoseResult(world_from_camera=poses, source=["vo"] * n, confidence=0.3 * np.minimum(1.0, inliers / 200.0),
                      registered_fraction=0.0, intrinsics=intr, points=points, outliers=[], method="vo",
                      scale_applied=scale)


def write_kitti_poses(path: str | Path, world_from_camera: np.ndarray) -> None:
    """Write poses [T, 4, 4] (or [T, 3, 4]) as KITTI text: one row-major 3x4 matrix per line, input order."""
    p = np.asarray(world_from_camera, float)
    if p.ndim != 3 or p.shape[1:] not in ((4, 4), (3, 4)):
        raise PoseEstimationError(f"poses must be [T, 4, 4] or [T, 3, 4], got {p.shape}")
    rows = p[:, :3, :4].reshape(len(p), 12)
    Path(path).write_text("".join(" ".join(f"{v:.9e}" for v in r) + "\n" for r in rows))
