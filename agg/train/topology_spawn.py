"""Spawn planning of adaptive topology evolution (Algorithm 1, the unmatched clusters): which tracks become new agents,
with what pose prior, validity and member Gaussians. ``TopologyEvolution.evolve`` calls ``plan_spawns`` and does the
graph surgery itself.

The unmatched cluster centres are tracked over the frames that had gradient statistics (a held-out frame never has
any, and a track coasts through it without a miss); the fragments of one object (two clusters in one frame, a track
that restarts after two frames without a cluster) are joined (``topology_track.stitch``); a joined track whose
longest run over those frames reaches ``tau_life`` is planned, after its outlying centroids are dropped
(``topology_track.drop_outliers``), unless its box moves faster than any road user (``box_speed`` over
``max_speed_mps``), floats above the road (``road_contact``) or does not move in the video (``topology_motion``).
Its member rows are its clusters' Gaussians; with ``spawn_box_slack`` set (off by default) only those inside its box
(the guessed size grown by that slack) at the frame each is canonicalised at (``topology_track.inside_box``), the
others staying in the background, and a plan left with fewer than ``min_agent_gaussians`` rows is dropped
(``spawn_box_rows="all"``: every row, those outside pulled onto the box).
"""

from __future__ import annotations

import numpy as np

from agg.io.video import intrinsics_at
from agg.priors.kalman import smooth_sequence
from agg.priors.tracklet_ground import height_above_road
from agg.train import topology_motion as tm
from agg.train import topology_silhouette as ts
from agg.train import topology_track as tt
from agg.train import topology_view as tv


def plan_spawns(evo, graph, unmatched: list[list[dict]], means: np.ndarray, taken: np.ndarray,
                observed: np.ndarray, report: dict) -> list[dict]:
    """Track the unmatched clusters over the frames that had statistics (``observed``), join the fragments
    of one object (``tt.stitch``); every joined track with a long enough run becomes a spawn plan (pose prior,
    member rows and the frame each member is canonicalised at). ``evo``: the ``TopologyEvolution`` (its config,
    scene unit, intrinsics, image size, prototype bank, features and prior dynamic masks)."""
    cfg, u = evo.config, evo.unit
    params = tt.TrackParams(meas_sigma=cfg.track_meas_sigma_m * u, accel_sigma=cfg.track_accel_sigma_m * u,
                            init_vel_sigma=cfg.track_init_vel_sigma_m * u, max_missed=cfg.track_max_missed)
    centres = [np.array([c["centre"] for c in frame]).reshape(-1, 3) for frame in unmatched]
    histories = tt.track_clusters(centres, params, observed)
    groups = tt.stitch([h.state for h in histories], [h.hits for h in histories], cfg.eps_m * u,
                       cfg.stitch_gap_frames, observed)
    report["tracks"] = len(groups)
    plans, claimed, runs = [], taken.copy(), []
    frames: dict[int, ts.FrameCells] = {}  # frame -> its feature cells, shared by every track's silhouettes
    cfw = graph.camera.camera_from_world().detach().cpu().numpy().astype(np.float64)  # [T, 4, 4]
    cam_centres = np.linalg.inv(cfw)[:, :3, 3]  # [T, 3]
    n_frames = len(cfw)
    r = np.tile(np.eye(3) * params.meas_sigma ** 2, (n_frames, 1, 1))  # [T, 3, 3]
    motion_cache: dict = {}  # the flow residuals of this evolution's cameras, computed for the first tested spawn

    def in_image(i: int, points: np.ndarray) -> np.ndarray:
        k = intrinsics_at(evo.K, i)
        return tt.project(points, cfw[i], k, evo.width, evo.height, cfg.near_m * u)[2]

    for group in groups:
        per_frame: dict[int, list[dict]] = {}  # frame -> the group's clusters there
        for i in group:
            for t in np.flatnonzero(histories[i].assoc >= 0):
                per_frame.setdefault(int(t), []).append(unmatched[t][int(histories[i].assoc[t])])
        hit = np.zeros(n_frames, bool)
        hit[list(per_frame)] = True
        run, _ = tt.longest_run(hit, observed)
        runs.append(int(run))
        if run < cfg.tau_life:
            continue
        clusters = [(t, c) for t in sorted(per_frame) for c in per_frame[t]]
        rows = np.unique(np.concatenate([c["members"] for _, c in clusters]))
        rows = rows[~claimed[rows]]
        if len(rows) < max(cfg.min_agent_gaussians, 1):
            continue
        centroids = {t: np.average([c["centre"] for c in cs], axis=0, weights=[len(c["members"]) for c in cs])
                     for t, cs in per_frame.items()}  # frame -> [3], member-weighted over its clusters
        fallback = tt.ground_axis_yaw(means[rows])
        nonrigid = float(np.mean([c["nonrigid"] for _, c in clusters]))
        cls = "non-rigid" if nonrigid > 0.5 else "rigid"
        half = spawn_half(graph, cls, cfg, u, evo.box_half)
        in_view, evidence = tv.box_visibility(evo, cfw, half)
        if cfg.silhouette and evo.bank is not None and evo.depth is not None:
            centroids = {t: silhouette_or(evo, t, c, cfw[t], half, report, frames)
                         for t, c in centroids.items()}
        z = np.full((n_frames, 3), np.nan)
        for t, c in centroids.items():
            z[t] = c
        z = tt.drop_outliers(z, params.meas_sigma, cfg.smooth_accel_sigma_m * u, params.init_vel_sigma,
                             cfg.outlier_m * u)
        centroids = {t: c for t, c in centroids.items() if not np.isnan(z[t, 0])}
        state, _ = smooth_sequence(z, r, accel_var=params.accel_sigma ** 2,
                                   init_vel_var=params.init_vel_sigma ** 2)  # [T, 6]
        poses, valid = tt.spawn_trajectory(
            state, centroids, cam_centres, half, in_view, fallback, meas_sigma=params.meas_sigma,
            accel_sigma=cfg.smooth_accel_sigma_m * u, init_vel_sigma=params.init_vel_sigma,
            min_speed=cfg.min_speed_m * u, extend=cfg.extend_frames, evidence=evidence, in_image=in_image)
        speed = box_speed(poses, valid, evo.frame_seconds)  # scene units per second, or None
        if speed is not None and cfg.max_speed_mps is not None and speed / u > cfg.max_speed_mps:
            report["fast"].append(round(speed / u, 1))  # faster than any road user: no agent
            continue
        contact = road_contact(evo, poses, valid, half, cfw)
        if contact is not None and contact[0] > 1.0:  # its box floats above (or sinks below) the road: no agent
            report["floating"].append(round(contact[1], 2))
            continue
        moving = tm.spawn_motion(evo, poses, valid, half, cfw, observed, motion_cache)
        if moving is not None:  # its box must move in the video (topology_motion)
            kept = moving >= cfg.motion.min_share
            report["moving" if kept else "static"].append(round(moving, 3))
            if not kept:
                continue
        frame_of = tt.nearest_frame(means[rows], rows, [(t, c["members"]) for t, c in clusters], poses)
        box = None
        if cfg.spawn_box_slack is not None:  # a box for the agent's object; which rows it takes: spawn_box_rows
            box = half * (1.0 + cfg.spawn_box_slack)
            inside = tt.inside_box(means[rows], poses[frame_of], box)
            report["boxed"].append(round(float(inside.mean()), 3))
            if cfg.spawn_box_rows == "inside":  # the others stay in the background
                rows, frame_of = rows[inside], frame_of[inside]
                if len(rows) < max(cfg.min_agent_gaussians, 1):
                    continue
        claimed[rows] = True
        plans.append({"rows": rows, "frame_of": frame_of, "poses": poses, "valid": valid, "class": cls,
                      "half": half, "box": box})
    # the longest run of each (joined) track over the frames with statistics, longest first
    report["track_runs"] = sorted(runs, reverse=True)[:8]
    return plans


def box_speed(poses: np.ndarray, valid: np.ndarray, frame_seconds: float | None) -> float | None:
    """Median speed (scene units per second) of a box with poses [T, 4, 4] over its consecutive valid [T] frames;
    None without a frame interval or without two consecutive valid frames."""
    idx = np.flatnonzero(valid)
    consecutive = np.diff(idx) == 1  # [V - 1]
    if frame_seconds is None or not consecutive.any():
        return None
    steps = np.linalg.norm(poses[idx[1:], :3, 3] - poses[idx[:-1], :3, 3], axis=1)[consecutive]
    return float(np.median(steps)) / frame_seconds


def silhouette_or(evo, t: int, centroid: np.ndarray, camera_from_world: np.ndarray, half: np.ndarray,
                  report: dict, frames: dict) -> np.ndarray:
    """Frame t's visible-surface centroid of the agent at ``centroid`` (the member-weighted cluster centroid, a
    world point [3] on it) read off its semantic silhouette (``topology_silhouette``), or ``centroid`` itself
    where there is none. Counts both in ``report["silhouette"]`` ([from the silhouette, kept]). ``frames``:
    frame -> ``FrameCells``, filled on first use."""
    cfg = evo.config
    k = intrinsics_at(evo.K, t)
    if t not in frames:
        frames[t] = ts.frame_cells(evo.semantics.features[t], evo.bank, cfg.tau_sem, evo.depth[t], camera_from_world,
                                   k, None if evo.dynamic is None else evo.dynamic[t])
    found = ts.silhouette_centroid(centroid, frames[t], camera_from_world, k, 2.0 * float(np.linalg.norm(half)),
                                   near=cfg.near_m * evo.unit)
    report["silhouette"][found is None] += 1
    return centroid if found is None else found[0]


def road_contact(evo, poses: np.ndarray, valid: np.ndarray, half: np.ndarray,
                 camera_from_world: np.ndarray) -> tuple[float, float] | None:
    """How far a planned box is from standing on the road: (median over its valid frames of the height of its
    bottom over the depth prior's road plane divided by the tolerance at its distance, median height in metres).
    Frames without a road plane or with the bottom behind the camera do not count; None when none is left (or
    the check is off). Agents stand on the road; the built-in features also call trees and a hillside agent-like,
    and on the dashcam sample such spawns floated 4-29 m above it (docs/TRAINING.md)."""
    cfg, u = evo.config, evo.unit
    planes = evo.road_planes()
    if planes is None or cfg.ground_tolerance_m is None or cfg.ground_tolerance_per_m is None:
        return None
    ratios, heights = [], []
    for t in np.flatnonzero(valid):
        if planes[t] is None:
            continue
        bottom = poses[t, :3, 3] + poses[t, :3, 1] * half[1]  # the box's y axis points down
        pc = camera_from_world[t, :3, :3] @ bottom + camera_from_world[t, :3, 3]  # [3]
        if pc[2] <= cfg.near_m * u:
            continue
        h = float(height_above_road(planes[t], intrinsics_at(evo.K, t), pc[None])[0])
        ratios.append(abs(h) / ((cfg.ground_tolerance_m + cfg.ground_tolerance_per_m * pc[2] / u) * u))
        heights.append(h / u)
    return (float(np.median(ratios)), float(np.median(heights))) if ratios else None


def spawn_half(graph, cls: str, cfg, unit: float, box_half: dict | None = None) -> np.ndarray:
    """Box-frame half extents (x = l, y = h, z = w) assumed for a new agent of class ``cls``: the median box of
    the graph's instances of that class whose size is known (``box_half``: track id -> [3]), else the median of
    their canonical extents, else the configured metric size."""
    node = graph.rigid if cls == "rigid" else getattr(graph, "nonrigid", None)
    ids = node.track_ids.tolist() if node is not None else []
    known = [box_half[int(t)] for t in ids if box_half and int(t) in box_half]  # sizes from tracklets or spawns
    if known:
        return np.median(np.stack(known), 0)
    if node is not None and node.num_instances > 0 and len(node.gaussians) > 0:
        half = tt.half_extents(node.gaussians.means.detach().cpu().numpy(), node.instance.cpu().numpy(),
                               node.num_instances)
        half = half[(half > 0).all(1)]
        if len(half):
            return np.median(half, 0)
    l, w, h = cfg.rigid_size_m if cls == "rigid" else cfg.nonrigid_size_m
    return 0.5 * np.array([l, h, w]) * unit
