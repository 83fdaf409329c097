"""Agent tracklets: connected components of the dynamic masks, lifted to 3D with depth, tracked with Kalman filters.

``track_agents(masks, depth, K, world_from_camera)`` turns per-frame dynamic masks into the bundle's tracklet prior
(``agg.io.bundle_priors.Tracklets``, box convention of docs/BUNDLE.md). The steps, and every threshold, are in
docs/PRIORS.md ("Agent tracklets"):

1. **Detections** per frame (``agg/priors/tracklet_detections.py``): OpenCV connected components of the mask,
   dropped below a minimum area; a component is cut at a thin neck (two agents joined by a strip of mask) and
   split where its depth is two-layered (an agent in front of another: bimodal log depth *and* a depth edge where
   the layers meet); parts of one object cut apart by a static occluder (nearby boxes at the same depth, the gap
   nearer where the depth sees it) are merged.
2. **Ground rule** (``agg/priors/tracklet_ground.py``): the road plane of the depth prior (per frame); a
   component whose footprint does not meet the road (contact above the horizon, or resting on an upright surface
   that is not the road) is no agent; side columns resting elsewhere, or standing far behind the footprint, are
   dropped.
3. **Lifting** (upright model): each column of a component is a vertical segment at the depth read near its
   contact (at most the road's depth there); a line ``1/d = a + b u`` through the column depths places every
   pixel (the visible 3D points); the depth statistic back-projects the pixel centroid to the *visible-surface
   centre* (the measurement).
4. **Tracking** (``agg/priors/kalman.py``): constant-velocity Kalman filters in world x, y, z, chi-square gating
   on the Mahalanobis distance plus an image-space gate, Hungarian assignment (plus a colour cue with frames); a
   track coasts (invalid) through up to ``max_missed`` missed frames and keeps its id; a track lost for longer
   is re-joined when it reappears within ``relink_max_gap`` frames where its motion predicts, in 3D and in the
   image; a detection off the track's path in the image (a blob taken where the agent's mask is missing) is
   dropped (``agg/priors/tracklet_paths.py``), and the tracks are re-joined again without the dropped ones;
   tracks with fewer than ``max(min_hits, min_track_fraction T)`` detections, or smaller than an agent at their
   road contact, are dropped; a gap of up to ``fill_max_gap`` frames inside a track is filled from the smoothed
   track (valid, confidence 0).
5. **Class** (rigid / non-rigid) from the tracked objects' image aspect ratio, **yaw** from the RTS-smoothed world
   velocity, and **amodal boxes** (``agg/priors/tracklet_boxes.py``): the visible points give the extents, a
   class-dependent size prior completes the unseen side (one size per rigid track), and the box is pushed away
   from the camera behind the visible faces; centres follow the RTS-smoothed track.

Scale-free: noise levels and gates are fractions of depth (or of the clip's median agent depth), so scene units
may be metres or the bundle's normalised units.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from scipy.stats import chi2

from agg.io.bundle_priors import Tracklets
from agg.priors.tracklet_detections import Candidate, frame_candidates
from agg.priors.kalman import relink, smooth_sequence, track_points
from agg.priors.tracklet_boxes import classify, track_boxes, track_yaws
from agg.priors.tracklet_paths import drop_strays
from agg.priors.tracklet_ground import ground_planes


class TrackletInputError(ValueError):
    """Bad input to ``track_agents`` (shapes, dtypes, non-finite poses) or a bad ``TrackConfig``."""


@dataclass(frozen=True)
class TrackConfig:
    """Tracklet extraction settings. Pixel sizes at the masks' resolution; ``*_sigma`` are fractions of depth."""

    # detections
    min_area_px: int = 6  # components below max(min_area_px, min_area_fraction * H * W) pixels are dropped
    min_area_fraction: float = 2e-4  # 160x96: 3 px; 1280x720: 184 px
    connectivity: int = 8  # 4 or 8 (OpenCV connected components)
    depth_percentile: float = 50.0  # depth statistic of a component (percentile of its pixels' upright depths)
    min_depth_confidence: float = 0.5  # with depth_confidence: lower pixels count as "no depth"
    min_depth_fraction: float = 0.05  # lifted when columns with a depth hold >= this fraction (and >= 3) of its px
    depth_outlier_ratio: float = 1.6  # column depths outside [d / r, d * r] of their median are ignored
    max_column_depth_ratio: float = 2.5  # columns deeper than this x the footprint's depth are dropped (a car's
    #                                      far end is < 2x its near corner's depth from 5 m on)
    plane_fit: bool = True  # visible points at the upright fit 1/d = a + b u of the column depths (False: raw depth)
    # ground rule (agg/priors/tracklet_ground.py): an agent stands on the road plane of the depth prior
    ground_rule: bool = True  # False: no road plane, no ground test (column depths from the prior only)
    contact_band: float = 0.25  # a column's depth: its valid depth in the lowest this x (box height) of the column
    contact_rows: float = 0.01  # the prior below a contact is read in this x H rows (>= 3)
    contact_ratio: float = 1.25  # ... GROUNDED when it is within this ratio of the road's depth there, ...
    occlusion_ratio: float = 1.1  # ... OCCLUDED when nearer than the component's own depth / this
    max_floating_fraction: float = 0.5  # footprint: more FLOATING pixels (by column) than this x those decided:
    #                                     not an agent
    split_depth_layers: bool = True  # split two-layered components (Otsu / widest gap of log depth + edge test)
    split_min_separation: float = 0.1  # ... when the layer means differ by >= this in log depth (10 %)
    split_min_contrast: float = 4.0  # ... and by >= this many pooled within-layer stds (Gaussian 2.7, uniform 3.5)
    split_edge_fraction: float = 0.7  # ... and the layers meet at a jump >= this * separation (above the noise)
    split_neck_ratio: float = 0.3  # cut a component at a column with <= this x the pixels of the tallest column on
    #                                 both sides (two agents joined by a thin strip of mask); 0 disables
    merge_parts: bool = True  # merge same-frame components at the same depth separated by a small gap
    merge_depth_ratio: float = 0.1  # |log d_a - log d_b| <= this
    merge_gap_fraction: float = 0.2  # gap <= this * the smaller extent (a pole, not the lane between two cars)
    merge_min_overlap: float = 0.7  # ... and their extents on the other axis overlap by >= this * the smaller
    # Kalman filter (agg/priors/kalman.py); the scale reference s = median depth of all lifted detections
    lateral_sigma: float = 0.03  # measurement std along camera x and y, fraction of the detection's depth
    depth_sigma: float = 0.08  # measurement std along camera z, fraction of depth
    border_sigma_factor: float = 4.0  # measurement stds x this for detections touching the image border
    accel_sigma: float = 0.01  # white-acceleration std per frame^2, fraction of s
    init_speed_sigma: float = 0.1  # velocity std of a new track per frame, fraction of s
    appearance_weight: float = 4.0  # with RGB frames: cost += this * (1 - Bhattacharyya coefficient of colours)
    appearance_bins: int = 4  # colour histogram bins per RGB channel (4: 64 bins)
    appearance_memory: float = 0.7  # a track's histogram: moving average keeping this much of the old one
    gate_probability: float = 0.999  # gate = chi2.ppf(p, 3) on the squared Mahalanobis distance (16.27)
    gate_box_margin: float = 0.5  # image gate: the predicted centre must project into the detection's box grown
    #                               by this x its size on each side + gate_box_min_margin; < 0 disables the gate
    gate_box_min_margin: float = 0.05  # fraction of the image width
    max_missed: int = 3  # consecutive missed frames before a track ends (2-frame occlusions keep the id)
    relink_max_gap: int = 8  # a track lost for longer than max_missed is re-joined when it reappears within this
    #                          many frames where its motion predicts (agg/priors/kalman.py ``relink``); < 2: never
    stray_window: int = 3  # a track's detection is checked against its others within this many frames (0: never)
    stray_offset: float = 0.5  # ... and dropped when its pixel centroid lies off their line through time by more
    #                            than this x their median box width (u) or height (v), ...
    stray_area_ratio: float = 0.25  # ... or its area is below this x their median area (a blob taken instead)
    min_hits: int = 3  # tracks with fewer detections are dropped ...
    min_track_fraction: float = 0.2  # ... or with fewer than this x T detections (mask flicker is short-lived)
    min_ground_area: float = 0.1  # ... or whose median area in camera heights^2 at their road contact is below
    #                               this (synthetic: people >= 0.33, cars >= 0.67; udacity: cars 1.6-3.1, a mask
    #                               blob on a lane marking near the camera 0.04); needs the road plane
    # class and box
    nonrigid_min_aspect: float = 1.3  # median 3D height / width of the track's detections above this: non-rigid
    rigid_length_width_ratio: float = 2.4  # rigid footprint: l >= ratio * w and w >= l / ratio (car ~4.5 / 1.85)
    extent_percentiles: tuple[float, float] = (5.0, 95.0)  # robust extents of the visible points
    yaw_min_speed_sigmas: float = 3.0  # velocity gives the yaw when |v_horizontal| > this * its std
    smooth_centres: bool = True  # box centres: the RTS-smoothed track of the amodal centres (False: per frame)
    fill_max_gap: int = 8  # a gap of up to this many frames inside a track (missed detections: an occluder, a
    #                        mask joined to the scenery) gets boxes from the smoothed track, valid with
    #                        confidence 0; 0: gaps stay invalid
    yaw_refinements: int = 2  # re-estimate yaw from the smoothed amodal centres this many times
    max_points: int = 4000  # visible points kept per detection (deterministic stride)

    def validate(self) -> None:
        def bad(msg: str) -> None:
            raise TrackletInputError(f"TrackConfig: {msg}")

        if self.min_area_px < 1 or not 0 <= self.min_area_fraction < 1:
            bad("min_area_px must be >= 1 and min_area_fraction in [0, 1)")
        if self.connectivity not in (4, 8):
            bad(f"connectivity must be 4 or 8, got {self.connectivity}")
        if not 0 <= self.depth_percentile <= 100:
            bad(f"depth_percentile must be in [0, 100], got {self.depth_percentile}")
        lo, hi = self.extent_percentiles
        if not 0 <= lo < hi <= 100:
            bad(f"extent_percentiles must satisfy 0 <= lo < hi <= 100, got {self.extent_percentiles}")
        for name in ("lateral_sigma", "depth_sigma", "border_sigma_factor", "accel_sigma", "init_speed_sigma",
                     "depth_outlier_ratio", "rigid_length_width_ratio", "nonrigid_min_aspect"):
            if not (np.isfinite(getattr(self, name)) and getattr(self, name) > 0):
                bad(f"{name} must be a finite value > 0, got {getattr(self, name)}")
        if self.depth_outlier_ratio <= 1 or self.max_column_depth_ratio <= 1:
            bad("depth_outlier_ratio and max_column_depth_ratio must be > 1")
        if not 0 < self.gate_probability < 1:
            bad(f"gate_probability must be in (0, 1), got {self.gate_probability}")
        if self.max_missed < 0 or self.min_hits < 1 or self.yaw_refinements < 0 or self.fill_max_gap < 0:
            bad("max_missed, yaw_refinements and fill_max_gap must be >= 0 and min_hits >= 1")
        if not 0 <= self.min_track_fraction <= 1 or self.min_ground_area < 0:
            bad("min_track_fraction must be in [0, 1] and min_ground_area >= 0")
        if self.appearance_weight < 0 or not 1 <= self.appearance_bins <= 16 or not 0 <= self.appearance_memory < 1:
            bad("appearance_weight must be >= 0, appearance_bins in [1, 16], appearance_memory in [0, 1)")
        if not (self.contact_ratio > 1 and self.occlusion_ratio >= 1 and 0 < self.contact_band <= 1
                and 0 <= self.contact_rows < 1 and 0 <= self.max_floating_fraction <= 1):
            bad("contact_ratio must be > 1, occlusion_ratio >= 1, contact_band in (0, 1], contact_rows in [0, 1), "
                "max_floating_fraction in [0, 1]")
        if self.max_points < 8:
            bad("max_points must be >= 8")
        if self.stray_window < 0 or not self.stray_offset > 0 or not 0 <= self.stray_area_ratio < 1:
            bad("stray_window must be >= 0, stray_offset > 0 and stray_area_ratio in [0, 1)")


@dataclass
class Detection:
    """One lifted mask component (or depth layer / merged parts) in one frame."""

    frame: int  # frame index i (0..T-1)
    bbox: np.ndarray  # [4] x0, y0, x1, y1 pixels, inclusive-exclusive (x1 = last column + 1)
    centre_world: np.ndarray  # [3] visible-surface centre, world frame (the Kalman measurement); NaN: no depth
    size: np.ndarray  # [3] visible extent (along the horizontal viewing direction, lateral, vertical); NaN: no depth
    area: int  # pixels
    label: int  # component label in that frame's OpenCV label map (the smallest one when parts were merged)
    labels: tuple[int, ...] = ()  # every component label it covers (merged parts)
    depth: float = float("nan")  # the depth statistic (camera z, scene units)
    depth_fraction: float = 0.0  # fraction of its pixels with valid depth
    centre_px: np.ndarray = field(default_factory=lambda: np.full(2, np.nan))  # [2] pixel centroid (u, v)
    on_ground: bool | None = None  # ground rule: False = not standing on the road (not tracked), None = undecided
    ground_area: float = float("nan")  # area in camera heights^2 at its road contact (NaN: no road plane)


@dataclass
class TrackResult:
    tracklets: Tracklets  # ids 1..K (= instance mask values), classes, boxes [K, T, 7], valid, confidence, labels
    boxes2d: np.ndarray  # [K, T, 4] float32 x0, y0, x1, y1 (inclusive-exclusive), NaN where invalid or filled
    centres2d: np.ndarray  # [K, T, 2] float32 pixel centroid (u, v) of the track's pixels, NaN where invalid or filled
    instance_masks: np.ndarray  # [T, H, W] int32: 0 = none, k + 1 = pixels of track k in that frame
    detections: list[list[Detection]]  # per frame, every detection (tracked or not)


# --------------------------------------------------------------------------------------------------------------
# input checks


def _check_inputs(masks, depth, K, world_from_camera, frames, depth_confidence):
    m = np.asarray(masks)
    if m.ndim != 3 or min(m.shape) < 1:
        raise TrackletInputError(f"masks must be [T, H, W] with T, H, W >= 1, got shape {m.shape}")
    if not (m.dtype == bool or np.issubdtype(m.dtype, np.number)):
        raise TrackletInputError(f"masks must be bool or numeric, got dtype {m.dtype}")
    t, h, w = m.shape
    d = np.asarray(depth)
    if d.shape != (t, h, w) or not np.issubdtype(d.dtype, np.number):
        raise TrackletInputError(f"depth must be numeric [{t}, {h}, {w}] like the masks, got {d.shape} {d.dtype}")
    k = np.asarray(K, dtype=float)
    if k.shape != (3, 3) or not np.isfinite(k).all() or k[0, 0] <= 0 or k[1, 1] <= 0:
        raise TrackletInputError(f"K must be a finite [3, 3] pinhole matrix with fx, fy > 0, got {k.shape}")
    p = np.asarray(world_from_camera, dtype=float)
    if p.shape != (t, 4, 4) or not np.isfinite(p).all():
        raise TrackletInputError(f"world_from_camera must be finite [{t}, 4, 4], got {p.shape}")
    f = None
    if frames is not None:
        f = frames if hasattr(frames, "shape") else np.asarray(frames)  # keep a memmap lazy
        if tuple(f.shape[:3]) != (t, h, w) or len(f.shape) not in (3, 4) or (len(f.shape) == 4 and f.shape[3] != 3):
            raise TrackletInputError(f"frames must be RGB [{t}, {h}, {w}, 3] (or grey [{t}, {h}, {w}]) like the "
                                     f"masks, got {tuple(f.shape)}")
    c = None
    if depth_confidence is not None:
        c = np.asarray(depth_confidence)
        if c.shape != (t, h, w):
            raise TrackletInputError(f"depth_confidence must be [{t}, {h}, {w}], got {c.shape}")
    return m, d, k, p, f, c


# --------------------------------------------------------------------------------------------------------------
# the entry point


def _empty_result(t: int, h: int, w: int, detections) -> TrackResult:
    tr = Tracklets(ids=np.zeros(0, np.int64), classes=[], boxes=np.zeros((0, t, 7)), valid=np.zeros((0, t), bool),
                   confidence=np.zeros((0, t), np.float32), labels=[])
    return TrackResult(tr, np.zeros((0, t, 4), np.float32), np.zeros((0, t, 2), np.float32),
                       np.zeros((t, h, w), np.int32), detections)


def track_agents(masks: np.ndarray, depth: np.ndarray, K: np.ndarray, world_from_camera: np.ndarray,
                 config: TrackConfig = TrackConfig(), frames: np.ndarray | None = None,
                 depth_confidence: np.ndarray | None = None,
                 progress: Callable[[int], None] | None = None) -> TrackResult:
    """Agent tracklets from dynamic masks and depth.

    masks [T, H, W] bool / 0-1 (any value > 0 is dynamic); depth [T, H, W] camera z-depth in scene units (0 or
    non-finite = none); K [3, 3] at the masks' resolution; world_from_camera [T, 4, 4]; frames: the RGB video
    [T, H, W, 3] (uint8, or float in [0, 1]; grey [T, H, W] too) or None: when given, colour histograms of the
    detections join the association cost (``appearance_weight``); the Kalman time step is one frame;
    depth_confidence [T, H, W] in [0, 1] (pixels below ``config.min_depth_confidence`` count as no depth);
    progress: called with i after frame i's detections. Deterministic. Raises TrackletInputError on bad input.
    """
    config.validate()
    m, d, K, P, frames, conf = _check_inputs(masks, depth, K, world_from_camera, frames, depth_confidence)
    t, h, w = m.shape
    min_area = max(int(config.min_area_px), int(np.ceil(config.min_area_fraction * h * w)))
    K_inv = np.linalg.inv(K)
    planes = ground_planes(d, conf, m > 0, config.min_depth_confidence) if config.ground_rule else [None] * t
    cands: list[list[Candidate]] = []
    for i in range(t):
        image = None if frames is None else np.asarray(frames[i])
        cands.append(frame_candidates(m[i] > 0, d[i], None if conf is None else conf[i], image, K_inv, P[i],
                                      min_area, config, planes[i]))
        if progress is not None:
            progress(i)
    detections = [[_as_detection(c, i) for c in cs] for i, cs in enumerate(cands)]
    lifted = [[c for c in cs if c.lifted] for cs in cands]  # [T] lists: what the tracker sees
    all_depths = [c.depth for cs in lifted for c in cs]
    if not all_depths:
        return _empty_result(t, h, w, detections)
    s_ref = float(np.median(all_depths))
    dt = np.ones(t)
    n_bins = config.appearance_bins ** 3
    feats = None if frames is None else [np.array([c.appearance for c in cs]).reshape(len(cs), n_bins)
                                         for cs in lifted]
    accel_var, init_vel_var = (config.accel_sigma * s_ref) ** 2, (config.init_speed_sigma * s_ref) ** 2
    image_gate, gate = _image_gate(lifted, K, P, w, h, config), float(chi2.ppf(config.gate_probability, 3))
    histories = track_points([np.array([c.centre_world for c in cs]).reshape(-1, 3) for cs in lifted],
                             [np.array([c.cov_world for c in cs]).reshape(-1, 3, 3) for cs in lifted], dt,
                             accel_var=accel_var, init_vel_var=init_vel_var,
                             gate=gate, max_missed=config.max_missed,
                             feat_steps=feats, appearance_weight=config.appearance_weight,
                             appearance_memory=config.appearance_memory,
                             extra_gate=image_gate)
    histories = relink(histories, max_gap=config.relink_max_gap, gate=gate, accel_var=accel_var,
                       extra_gate=image_gate)
    # an agent's size is judged on every detection the tracker gave it (without its small strays a track of road
    # blobs would pass); its detection count without the strays
    histories = [drop_strays(hh, lifted, (h, w), config, accel_var, init_vel_var) for hh in histories
                 if _big_enough(hh, lifted, config)]
    # a track whose first or last detection was a stray may now meet its continuation (the blob was taken at the
    # start of the track that went on with the agent, so the first relink missed the pair)
    histories = relink(histories, max_gap=config.relink_max_gap, gate=gate, accel_var=accel_var,
                       extra_gate=image_gate)
    need = max(config.min_hits, int(np.ceil(config.min_track_fraction * t)))
    histories = [hh for hh in histories if hh.hits >= need]
    n = len(histories)
    if n == 0:
        return _empty_result(t, h, w, detections)
    boxes = np.full((n, t, 7), np.nan)
    valid = np.zeros((n, t), bool)
    confidence = np.zeros((n, t), np.float32)
    boxes2d = np.full((n, t, 4), np.nan, np.float32)
    centres2d = np.full((n, t, 2), np.nan, np.float32)
    instance = np.zeros((t, h, w), np.int32)
    classes: list[str] = []
    track_factor_hits = 2.0 * config.min_hits
    for k, hist in enumerate(histories):
        steps = np.nonzero(hist.assoc >= 0)[0]
        mine = {int(i): lifted[i][hist.assoc[i]] for i in steps}
        valid[k, steps] = True
        cls = classify(mine, K, (h, w), config)
        classes.append(cls)
        # yaw from the surface-centre track, boxes, then (yaw_refinements times) yaw again from the smoothed
        # track of the amodal box centres, which do not drift when the visible part of an agent changes
        yaw = track_yaws(hist.state, hist.cov, valid[k], P, config)
        for rnd in range(config.yaw_refinements + 1):
            fitted = track_boxes(mine, yaw, P, cls == "rigid", (h, w), config)
            z = np.full((t, 3), np.nan)
            r = np.repeat(np.eye(3)[None], t, 0)
            for i, c in mine.items():
                z[i], r[i] = fitted[i][:3], c.cov_world
            state, cov = smooth_sequence(z, r, accel_var=accel_var, init_vel_var=init_vel_var)
            if rnd < config.yaw_refinements:
                yaw = track_yaws(state, cov, valid[k], P, config)
        for i, c in mine.items():
            boxes[k, i] = fitted[i]
            if config.smooth_centres:  # the RTS-smoothed amodal centre
                boxes[k, i, :3] = state[i, :3]
            confidence[k, i] = c.depth_fraction * min(1.0, hist.hits / track_factor_hits)
            boxes2d[k, i] = c.bbox
            centres2d[k, i] = c.centre_px
            instance[i, c.rows, c.cols] = k + 1
        filled = fill_gaps(boxes[k], valid[k], state[:, :3] if config.smooth_centres else None,
                           config.fill_max_gap)
        valid[k, filled] = True  # confidence stays 0 there: no detection, a box from the track
    tracklets = Tracklets(ids=np.arange(1, n + 1, dtype=np.int64), classes=classes, boxes=boxes, valid=valid,
                          confidence=np.clip(confidence, 0, 1),
                          labels=["pedestrian" if c == "non-rigid" else "vehicle" for c in classes],
                          anchor="camera")  # each box lifted from its frame's camera through world_from_camera
    return TrackResult(tracklets, boxes2d, centres2d, instance, detections)


def filled_entries(tracklets: Tracklets) -> np.ndarray:
    """[K, T] bool: the entries ``fill_gaps`` made (valid with confidence 0: a box from the track, no detection);
    all False without confidences."""
    valid = np.asarray(tracklets.valid, bool)
    if tracklets.confidence is None:
        return np.zeros_like(valid)
    return valid & (np.asarray(tracklets.confidence) == 0)


def fill_gaps(boxes: np.ndarray, valid: np.ndarray, centres: np.ndarray | None, max_gap: int) -> np.ndarray:
    """Fill the gaps of one track in place: boxes [T, 7] (NaN where invalid), valid [T]; centres [T, 3] the
    smoothed track (NaN outside it) or None. A run of at most ``max_gap`` invalid frames between two valid ones
    gets the smoothed centre (else the linear interpolation of the two boxes' centres), sizes interpolated
    linearly (one size for a rigid track) and the yaw interpolated along the shorter way round. Returns the
    indices [F] of the filled frames; ``valid`` is left to the caller."""
    have = np.nonzero(valid)[0]
    filled = []
    for a, b in zip(have[:-1], have[1:]):
        if not 1 < b - a <= max_gap + 1:
            continue
        for i in range(a + 1, b):
            f = (i - a) / (b - a)
            box = (1 - f) * boxes[a] + f * boxes[b]  # [7] centre and sizes
            if centres is not None and np.isfinite(centres[i]).all():
                box[:3] = centres[i]
            dyaw = (boxes[b, 6] - boxes[a, 6] + np.pi) % (2 * np.pi) - np.pi
            box[6] = boxes[a, 6] + f * dyaw
            boxes[i] = box
            filled.append(i)
    return np.asarray(filled, dtype=np.int64)


def _big_enough(hist, lifted: list[list[Candidate]], cfg: TrackConfig) -> bool:
    """The median area of a track's detections in camera heights^2 (where the road plane gives it) is at least
    ``min_ground_area``."""
    area = [lifted[i][j].ground_area for i, j in enumerate(hist.assoc) if j >= 0]
    area = [a for a in area if np.isfinite(a)]
    return not area or float(np.median(area)) >= cfg.min_ground_area


def _image_gate(lifted: list[list[Candidate]], K: np.ndarray, world_from_camera: np.ndarray, width: int,
                height: int, cfg: TrackConfig):
    """extra_gate(step, predicted world position [3]) -> [N] bool: its projection lies in each detection's grown
    box, which is open beyond the image border it touches (None when ``gate_box_margin`` < 0)."""
    if cfg.gate_box_margin < 0:
        return None
    grown = []
    for cs in lifted:
        b = np.array([c.bbox for c in cs], float).reshape(-1, 4)  # [N, 4]
        size = np.stack([b[:, 2] - b[:, 0], b[:, 3] - b[:, 1]], 1)  # [N, 2]
        m = cfg.gate_box_margin * size + cfg.gate_box_min_margin * width  # [N, 2]
        g = np.concatenate([b[:, :2] - m, b[:, 2:] + m], 1)
        g[b[:, 0] <= 0, 0], g[b[:, 1] <= 0, 1] = -np.inf, -np.inf  # cut by the border: open on that side
        g[b[:, 2] >= width, 2], g[b[:, 3] >= height, 3] = np.inf, np.inf
        grown.append(g)
    camera_from_world = np.linalg.inv(world_from_camera)  # [T, 4, 4]

    def gate(i: int, x: np.ndarray) -> np.ndarray:
        p = camera_from_world[i, :3, :3] @ x + camera_from_world[i, :3, 3]
        if p[2] <= 0:
            return np.zeros(len(grown[i]), bool)
        u, v = (K @ p)[:2] / p[2]
        g = grown[i]
        return (u >= g[:, 0]) & (u <= g[:, 2]) & (v >= g[:, 1]) & (v <= g[:, 3])

    return gate


def _as_detection(c: Candidate, frame: int) -> Detection:
    return Detection(frame=frame, bbox=np.asarray(c.bbox, float), centre_world=c.centre_world.copy(),
                     size=c.size.copy(), area=int(c.area), label=int(min(c.labels)), labels=tuple(c.labels),
                     depth=float(c.depth), depth_fraction=float(c.depth_fraction), centre_px=c.centre_px.copy(),
                     on_ground=c.on_ground, ground_area=float(c.ground_area))


__all__ = ["TrackConfig", "Detection", "TrackResult", "TrackletInputError", "track_agents"]
