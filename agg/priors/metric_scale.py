"""How many metres one scene unit is: the engine's metric thresholds on bundles without metric priors.

Training has settings in metres: topology evolution's DBSCAN radius (2.5 m, the paper's), its Kalman noise, the
size of a spawned car (4.5 x 1.8 x 1.6 m), the static test of a demoted agent; the pose-translation learning rates
(the paper's rates are metres per step); the deformation network's position scale (about a pedestrian's half
height). A bundle with metric priors (KITTI ground-truth poses, the synthetic suite) says ``metric = scale x
scene_units`` and that is the answer. A monocular video has no metres: its poses are normalised so the median
sparse depth is 1 (docs/PRIORS.md), which on the dashcam sample is about 107 m. Reading its units as metres made
the DBSCAN radius 2.5 median depths and a spawned car 4.5 median depths long.

So a bundle that is not metric gets an *estimate* from the road: a level camera at height h over a flat road sees
the road's inverse depth as ``w = (v - v_horizon) / (fy h)`` (``agg.priors.tracklet_ground``), so the road plane
of the depth prior gives h in scene units, and a dashcam or a car roof camera is ``ASSUMED_CAMERA_HEIGHT_M`` above
the road (1.2-1.7 m for the cameras of driving datasets: KITTI 1.65 m, a windscreen dashcam about 1.3 m), so one
scene unit is ``ASSUMED_CAMERA_HEIGHT_M / h`` metres, to within about 20 %. It only sets thresholds and rates; no
metric number is reported from it (docs/BUNDLE.md: a bundle that is not metric reports none).

Sources, in order: ``"metric"`` (the bundle is metric: ``scale``), ``"camera_height"`` (the road plane of the dense
depth prior, else of the sparse depth rows, median over the frames that have one), ``"bundle_scale"`` (no depth or
no road found: the bundle's ``scale``, the old reading; ``scene.json``'s ``metric_scale.source`` says so).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

ASSUMED_CAMERA_HEIGHT_M = 1.5  # metres over the road of a driving camera (module doc)
MAX_FRAMES = 32  # frames whose road plane is fitted (evenly spaced): enough for a median, bounded time


@dataclass(frozen=True)
class MetricScale:
    metres_per_unit: float  # one scene unit is this many metres
    source: str  # "metric" | "camera_height" | "bundle_scale" (| "none": a Trainer without a bundle reads 1)
    camera_height_units: float | None = None  # the road plane's camera height (scene units), where fitted
    frames_with_road: int = 0  # frames whose own road plane was found

    def __post_init__(self):
        if not (math.isfinite(self.metres_per_unit) and self.metres_per_unit > 0):
            raise ValueError(f"metres_per_unit must be positive and finite, got {self.metres_per_unit}")

    @property
    def units_per_metre(self) -> float:
        return 1.0 / self.metres_per_unit

    def as_dict(self) -> dict:
        return asdict(self)


def sampled_frames(num_frames: int) -> list[int]:
    """Up to ``MAX_FRAMES`` evenly spaced frame indices."""
    return [int(i) for i in np.unique(np.linspace(0, num_frames - 1, min(MAX_FRAMES, num_frames)).astype(int))]


def camera_height_from_depth(depth, fy: float, frames: list[int], masks=None, conf=None,
                             min_conf: float = 0.3) -> tuple[float | None, int]:
    """Median camera height over the road (scene units) over ``frames``, and how many of them had a road plane;
    (None, 0) when none had. ``depth[i]``: frame i's [H, W] z-depth (0 / non-finite: none; an array, a memmap or a
    dict of the frames); ``masks[i]`` [H, W]: dynamic pixels (> 0.5; they do not vote); ``conf[i]`` [H, W]."""
    from agg.priors.depth import fit_ground_plane
    from agg.priors.tracklet_ground import camera_height, road_rows

    heights = []
    for i in frames:
        mask = None if masks is None else np.asarray(masks[i]) > 0.5
        rows = road_rows(depth[i], None if conf is None else conf[i], mask, min_conf)  # [k, 4] u, v, z, 1
        if len(rows) < 3:
            continue
        h, w = np.shape(depth[i])
        plane = fit_ground_plane(rows[:, :2], 1.0 / rows[:, 2], w, h)
        if plane is None or not plane[1] > 0:
            continue
        height = camera_height(plane, fy)
        if math.isfinite(height) and height > 0:
            heights.append(height)
    if not heights:
        return None, 0
    return float(np.median(heights)), len(heights)


def _sparse_depth_images(bundle, frames: list[int]) -> dict[int, np.ndarray]:
    """{frame: [H, W] float32}: each given frame's sparse depth rows drawn at their pixels (0 elsewhere)."""
    h, w = bundle.height, bundle.width
    out = {}
    for i in frames:
        img = np.zeros((h, w), np.float32)
        rows = np.asarray(bundle.sparse_depth(i))  # [k, 4] u, v, z, confidence
        if len(rows):
            u, v = np.round(rows[:, 0]).astype(int), np.round(rows[:, 1]).astype(int)
            ok = (u >= 0) & (u < w) & (v >= 0) & (v < h) & np.isfinite(rows[:, 2]) & (rows[:, 2] > 0)
            img[v[ok], u[ok]] = rows[ok, 2]
        out[i] = img
    return out


def estimate_metric_scale(bundle) -> MetricScale:
    """Metres per scene unit of a ``SceneBundle`` (module doc)."""
    if bundle.metric:
        return MetricScale(float(bundle.scale), "metric")
    fy = float(np.asarray(bundle.intrinsics)[0][1, 1])
    frames = sampled_frames(bundle.num_frames)
    masks = bundle.dynamic_masks if bundle.has("dynamic_masks") else None  # read frame by frame
    height, n = None, 0
    if bundle.has("depth_dense"):
        height, n = camera_height_from_depth(bundle.dense_depth, fy, frames, masks, bundle.dense_depth_confidence)
    if height is None and bundle.has("depth_sparse"):
        height, n = camera_height_from_depth(_sparse_depth_images(bundle, frames), fy, frames, masks)
    if height is None:
        return MetricScale(float(bundle.scale), "bundle_scale")
    return MetricScale(ASSUMED_CAMERA_HEIGHT_M / height, "camera_height", height, n)


__all__ = ["MetricScale", "estimate_metric_scale", "camera_height_from_depth", "sampled_frames",
           "ASSUMED_CAMERA_HEIGHT_M"]
