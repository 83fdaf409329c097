"""Functional core of adaptive topology evolution (paper Sec. 3.3, Algorithm 1): no graph, no optimiser.

- ``project``: world points -> pixels, camera depth and an in-image test (OpenCV pinhole); ``backproject``: the
  inverse (pixels at a z-depth -> world points).
- ``sample_features`` / ``prototype_bank`` / ``agent_like``: the semantic filter. The features F_t are the bundle's
  low-resolution PCA features [h, w, C]; a point at pixel (u, v) of the training resolution reads the cell at
  ``((u + 0.5) w / W - 0.5, (v + 0.5) h / H - 0.5)`` (bilinear). A point is agent-like when its best cosine
  similarity to B_rigid / B_non-rigid exceeds both its similarity to B_background and ``tau_sem``.
- ``cluster``: scikit-learn DBSCAN over world means.
- ``half_extents`` / ``inside_box``: box-frame extents of agent instances from their canonical Gaussians, and the
  point-in-(grown)-box test used to match clusters to existing agents.
- ``track_clusters``: constant-velocity Kalman tracking of the unmatched cluster centres over the frames
  (``agg.priors.kalman.track_points``: gated Hungarian association, RTS smoothing); ``stitch`` joins the
  fragments of one object; ``longest_run`` gives a track's longest run of consecutive hits over the frames that
  had statistics (the paper's age >= tau_life test).
- ``spawn_trajectory``: a track of cluster centroids (visible-surface samples) -> box centres
  (``box_centre_from_surface``), RTS-smoothed again -> ``trajectory_poses``: per-frame ``world_from_box``
  [T, 4, 4] and validity [T]; ``nearest_frame`` picks the frame each spawned Gaussian is canonicalised at.

Lengths are scene units throughout; the caller converts metric settings with the bundle's scale
(``metric = scale * scene_units``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components
from scipy.stats import chi2

from agg.priors.kalman import TrackHistory, smooth_sequence, track_points
from agg.priors.prototypes import CLASS_NAMES, cosine_scores


def project(means: np.ndarray, camera_from_world: np.ndarray, K: np.ndarray, width: int, height: int,  # noqa: N803
            near: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World points [N, 3] -> pixels uv [N, 2], camera z [N] and in-view [N] bool (z > near, inside the image)."""
    pc = means @ camera_from_world[:3, :3].T + camera_from_world[:3, 3]  # [N, 3]
    z = pc[:, 2]
    zs = np.where(z > near, z, 1.0)
    uv = (pc[:, :2] / zs[:, None]) @ K[:2, :2].T + K[:2, 2]  # [N, 2]
    vis = (z > near) & (uv[:, 0] >= -0.5) & (uv[:, 0] < width - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] < height - 0.5)
    return uv, z, vis


def backproject(uv: np.ndarray, z: np.ndarray, camera_from_world: np.ndarray, K: np.ndarray  # noqa: N803
                ) -> np.ndarray:
    """World points [N, 3] seen at pixels uv [N, 2] with camera z-depth z [N] (the inverse of ``project``)."""
    rays = np.concatenate([uv, np.ones((len(uv), 1))], 1) @ np.linalg.inv(K).T  # [N, 3], z = 1
    pc = rays * np.asarray(z, np.float64)[:, None]  # [N, 3] camera frame
    return (pc - camera_from_world[:3, 3]) @ camera_from_world[:3, :3]  # R^T (p - t)


def ray_cos3(uv: np.ndarray, K: np.ndarray) -> np.ndarray:  # noqa: N803
    """[N] cos^3 of the angle between the rays through pixels uv [N, 2] and the optical axis: the solid angle a
    pixel spans shrinks by it off axis, so a point read off it weighs that much less."""
    xy = (uv - K[:2, 2]) / np.diag(K)[:2]  # [N, 2] normalised image coordinates
    return (1.0 + (xy ** 2).sum(1)) ** -1.5


def pixel_at(image: np.ndarray, uv: np.ndarray, width: int, height: int) -> np.ndarray:
    """[N] values of a [height, width] image at the nearest pixel of each uv [N, 2] (clamped to the image)."""
    ui = np.clip(np.rint(uv[:, 0]), 0, width - 1).astype(np.int64)
    vi = np.clip(np.rint(uv[:, 1]), 0, height - 1).astype(np.int64)
    return np.asarray(image)[vi, ui]


def depth_at(depth: np.ndarray, uv: np.ndarray, width: int, height: int) -> np.ndarray:
    """[N] prior depth (0 = none) of a [height, width] depth map at the nearest pixel of each uv [N, 2]."""
    return pixel_at(np.asarray(depth, np.float32), uv, width, height)


def sample_features(features: np.ndarray, uv: np.ndarray, width: int, height: int) -> np.ndarray:
    """Bilinear samples [M, C] of a low-resolution feature map [h, w, C] at training-resolution pixels uv [M, 2]."""
    h, w = features.shape[:2]
    x = np.clip((uv[:, 0] + 0.5) * w / width - 0.5, 0, w - 1)
    y = np.clip((uv[:, 1] + 0.5) * h / height - 0.5, 0, h - 1)
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    f = np.asarray(features, np.float32)
    return ((1 - fx) * (1 - fy) * f[y0, x0] + fx * (1 - fy) * f[y0, x1] + (1 - fx) * fy * f[y1, x0]
            + fx * fy * f[y1, x1])


def prototype_bank(semantics) -> dict[str, np.ndarray] | None:
    """The prototype bank in the features' (PCA) space, or None when the bundle has none (or cannot map it)."""
    protos = semantics.prototypes if semantics is not None else None
    if not protos or any(k not in protos for k in CLASS_NAMES):
        return None
    if semantics.prototype_space == "pca":
        return {k: np.asarray(protos[k], np.float32).reshape(-1, semantics.features.shape[-1]) for k in CLASS_NAMES}
    if semantics.pca_basis is None or semantics.pca_mean is None:
        return None
    basis, mean = np.asarray(semantics.pca_basis, np.float64), np.asarray(semantics.pca_mean, np.float64)
    return {k: ((np.asarray(protos[k], np.float64).reshape(-1, len(mean)) - mean) @ basis).astype(np.float32)
            for k in CLASS_NAMES}


def agent_like(features: np.ndarray, bank: dict[str, np.ndarray], tau_sem: float) -> tuple[np.ndarray, np.ndarray]:
    """features [M, C] -> (agent-like [M] bool, non-rigid [M] bool: B_non-rigid beats B_rigid).

    Agent-like: max(P_rigid, P_non-rigid) > max(P_background, tau_sem) (Algorithm 1, line 4)."""
    if len(features) == 0:
        return np.zeros(0, bool), np.zeros(0, bool)
    s = cosine_scores(features, bank)  # [M, 3] background, rigid, non-rigid
    ag = s[:, 1:].max(1)
    return ag > np.maximum(s[:, 0], tau_sem), s[:, 2] > s[:, 1]


def cluster_centre(seen: np.ndarray, opacity: np.ndarray, surface: np.ndarray, known: np.ndarray,
                   min_samples: int) -> np.ndarray:
    """[3] where a frame sees a cluster: the opacity-weighted mean of its members' seen points [M, 3] over those
    on the observed surface whose pixel is on no known agent (``known``: in the prior dynamic masks). A smeared
    background Gaussian can project onto a prior car in front of or beside the missed one; read at that pixel's
    depth it lands on the prior car (seed 2 of the synthetic suite: 40 % of one cluster's members, 3 m off).
    With fewer than ``min_samples`` such members the known ones count again, then the off-surface ones."""
    for use in (surface & ~known, surface):
        if use.sum() >= min_samples:
            w = (opacity + 1e-6) * use
            return (seen * w[:, None]).sum(0) / w.sum()
    w = opacity + 1e-6
    return (seen * w[:, None]).sum(0) / w.sum()


def cluster(points: np.ndarray, eps: float, min_samples: int) -> np.ndarray:
    """DBSCAN labels [M] (-1 = noise) of world points [M, 3]."""
    from sklearn.cluster import DBSCAN

    if len(points) < max(min_samples, 1):
        return np.full(len(points), -1, np.int64)
    return DBSCAN(eps=float(eps), min_samples=int(min_samples)).fit(points).labels_.astype(np.int64)


def half_extents(canonical_means: np.ndarray, instance: np.ndarray, k: int, quantile: float = 0.98,
                 minimum: float = 0.0) -> np.ndarray:
    """[k, 3] box-frame half extents of k instances: the ``quantile`` of |canonical mean| per axis (0 if empty)."""
    out = np.zeros((k, 3))
    for j in range(k):
        m = np.abs(canonical_means[instance == j])
        if len(m):
            out[j] = np.quantile(m, quantile, axis=0)
    return np.maximum(out, minimum)


def tracklet_half_extents(tracklets) -> dict[int, np.ndarray]:
    """{track id: [3] box-frame half extents (x = l, y = h, z = w)} from the median size of each tracklet's valid
    boxes; centre-only tracks (NaN sizes) are left out."""
    out: dict[int, np.ndarray] = {}
    if tracklets is None:
        return out
    for k, tid in enumerate(np.asarray(tracklets.ids).tolist()):
        half = 0.5 * tracklets.box_size(k)  # [3]
        if np.all(np.isfinite(half) & (half > 0)):
            out[int(tid)] = half
    return out


def inside_box(points: np.ndarray, world_from_box: np.ndarray, half: np.ndarray) -> np.ndarray:
    """[M] bool: world points [M, 3] inside the box ``world_from_box`` [4, 4] (or one pose per point, [M, 4, 4]) of
    half extents [3]."""
    local = np.einsum("...ji,...j->...i", world_from_box[..., :3, :3], points - world_from_box[..., :3, 3])  # R^T(p-c)
    return np.all(np.abs(local) <= half, axis=1)


@dataclass(frozen=True)
class TrackParams:
    """Constant-velocity tracking of cluster centres (scene units, per frame)."""

    meas_sigma: float  # centroid measurement std
    accel_sigma: float  # white-acceleration std per frame^2
    init_vel_sigma: float  # std of the unknown initial velocity
    gate_prob: float = 0.99  # chi-square gate (3 dof) on the squared Mahalanobis distance
    max_missed: int = 1  # consecutive frames a track may coast


def track_clusters(centres: list[np.ndarray], p: TrackParams, observed: np.ndarray | None = None
                   ) -> list[TrackHistory]:
    """Track cluster centres over T frames (centres[t]: [n_t, 3], empty where a frame has none or no statistics).
    ``observed`` [T] bool marks the frames that had statistics (a held-out frame never does): a track coasts
    through the others without counting a miss. Returns every track ever started
    (``agg.priors.kalman.TrackHistory``, in order of creation)."""
    r_steps = [np.tile(np.eye(3) * p.meas_sigma ** 2, (len(c), 1, 1)) for c in centres]
    return track_points([np.asarray(c, float).reshape(-1, 3) for c in centres], r_steps, np.ones(len(centres)),
                        accel_var=p.accel_sigma ** 2, init_vel_var=p.init_vel_sigma ** 2,
                        gate=float(chi2.ppf(p.gate_prob, 3)), max_missed=p.max_missed, observed=observed)


def longest_run(hit: np.ndarray, observed: np.ndarray | None = None) -> tuple[int, int]:
    """(length, start) of the longest run of True in hit [T] (consecutive frames with a measurement). Frames
    where ``observed`` [T] is False (no statistics: held out) neither count nor break a run."""
    hit = np.asarray(hit, bool)
    frames = np.arange(len(hit)) if observed is None else np.flatnonzero(observed)
    best, start, run, run_start = 0, -1, 0, 0
    for i in frames:
        if hit[i]:
            if run == 0:
                run_start = int(i)
            run += 1
            if run > best:
                best, start = run, run_start
        else:
            run = 0
    return best, start


def stitch(states: list[np.ndarray], hits: list[np.ndarray], merge_dist: float, max_gap: int,
           observed: np.ndarray | None = None) -> list[list[int]]:
    """Groups (lists of indices) of track fragments that follow one object.

    states[i] [T, 6]: fragment i's smoothed (x, y, z, vx, vy, vz), NaN outside its life; hits[i]: its number of
    measurements. One object often yields several fragments: two clusters in one frame (its front and its
    smear), or a track that ends where the object's gradients faded for two frames and restarts after. Two
    fragments with at least 2 hits each are joined when they overlap in time and their median distance there is
    at most ``merge_dist``, or when at most ``max_gap`` frames lie between the end of one and the start of the
    other (counting only ``observed`` frames, [T] bool, when given) and each one's constant-velocity
    extrapolation across the gap lands within ``merge_dist`` of the other's end (mean of the two). Groups are
    the connected components, in order of their first fragment."""
    n = len(states)
    joined = np.zeros((n, n), bool)  # [n, n] same-object pairs (a < b)
    life = [np.flatnonzero(~np.isnan(s[:, 0])) for s in states]
    ok = [hits[i] >= 2 and len(life[i]) > 0 for i in range(n)]
    for a in range(n):
        for b in range(a + 1, n):
            if not (ok[a] and ok[b]):
                continue
            both = np.intersect1d(life[a], life[b])
            if len(both):
                d = float(np.median(np.linalg.norm(states[a][both, :3] - states[b][both, :3], axis=1)))
            else:
                (x, y) = (a, b) if life[a][-1] < life[b][0] else (b, a)
                end, start = int(life[x][-1]), int(life[y][0])
                gap = start - end
                if (gap - 1 if observed is None else int(np.count_nonzero(observed[end + 1:start]))) > max_gap:
                    continue
                fwd = states[x][end, :3] + states[x][end, 3:] * gap
                back = states[y][start, :3] - states[y][start, 3:] * gap
                d = 0.5 * float(np.linalg.norm(fwd - states[y][start, :3]) + np.linalg.norm(back - states[x][end, :3]))
            joined[a, b] = d <= merge_dist
    _, label = connected_components(csr_matrix(joined), directed=False)  # [n]
    groups = [np.flatnonzero(label == g).tolist() for g in range(label.max(initial=-1) + 1)]
    return sorted(groups, key=lambda g: min(int(life[i][0]) if len(life[i]) else 1 << 30 for i in g))


def drop_outliers(z: np.ndarray, meas_sigma: float, accel_sigma: float, init_vel_sigma: float,
                  max_residual: float, max_fraction: float = 1 / 3) -> np.ndarray:
    """z [T, 3] (NaN where missing) with its outliers set to NaN: while the worst residual from the RTS-smoothed
    track (acceleration std ``accel_sigma``: a steady path) exceeds ``max_residual``, that row goes, up to
    ``max_fraction`` of the rows. A cluster that also took in Gaussians off the object (smear in front of the
    surface, a neighbour) pulls its centroid metres away; the object's other frames outvote it."""
    z = np.array(z, float)
    r = np.tile(np.eye(3) * meas_sigma ** 2, (len(z), 1, 1))
    budget = int(np.count_nonzero(~np.isnan(z[:, 0])) * max_fraction)
    for _ in range(budget):
        state, _ = smooth_sequence(z, r, accel_var=accel_sigma ** 2, init_vel_var=init_vel_sigma ** 2)
        res = np.linalg.norm(z - state[:, :3], axis=1)  # [T], NaN where missing
        if not np.any(res > max_residual):
            break
        z[int(np.nanargmax(res))] = np.nan
    return z


def visible_surface_offset(half: np.ndarray, camera: np.ndarray, inside=None, samples: int = 24) -> np.ndarray:
    """[3] box-frame offset from a box's centre to the centroid of its visible surface as Gaussians sample it.

    half [3]: half extents along the box axes; camera [3]: the camera centre in the box frame. A face is visible
    when the camera lies outside its plane. Densification refines Gaussians to the views' angular resolution, so
    a surface element dA at distance r holds them in proportion to the solid angle it subtends, ``dA cos(theta)
    / r^2``: each visible face is sampled on a ``samples`` x ``samples`` grid with those weights. Near a car this
    matters: on seed 2 of the synthetic suite an area-weighted (orthographic) model missed the centroid of the
    car's pixels by 0.5 m in depth at 7 m and by 1 m the other way at 5.5 m. (One frame's pixels add a
    ``1 / cos^3`` of the angle off the optical axis; with that term the spawned car of seed 2 was within 1 m on 0.46
    of its frames instead of all of them, and on the unit scene of tests/test_topology.py, with its fit of then on
    near-black frames, 1.0-1.07 m off instead of 0.85-0.95 m: the Gaussians of a car that crosses the image follow
    no single frame's grid.)
    ``inside``: optional test of box-frame points [P, 3] -> bool [P], the points that project inside the image.
    A car cut off by the image edge shows only part of its faces, and only the samples inside count (with none
    inside, all do). Subtracting the (rotated) offset from a measured visible centroid recovers the box centre."""
    camera = np.asarray(camera, np.float64)
    grid = (np.arange(samples) + 0.5) / samples * 2.0 - 1.0  # [S] cell centres in [-1, 1]
    pts, wts = [], []
    for a in range(3):
        b, c = [i for i in range(3) if i != a]
        for sign in (-1.0, 1.0):
            if sign * camera[a] <= half[a]:
                continue  # the camera is behind this face's plane
            face = np.zeros((samples, samples, 3))
            face[..., a] = sign * half[a]
            face[..., b] = grid[:, None] * half[b]
            face[..., c] = grid[None, :] * half[c]
            face = face.reshape(-1, 3)  # [S*S, 3]
            ray = camera - face
            r = np.linalg.norm(ray, axis=1)
            pts.append(face)
            wts.append(4.0 * half[b] * half[c] / samples ** 2 * sign * ray[:, a] / r ** 3)  # dA cos / r^2
    if not pts:
        return np.zeros(3)  # the camera is inside the box
    p, w = np.concatenate(pts), np.concatenate(wts)  # [P, 3], [P]
    if inside is not None:
        keep = np.asarray(inside(p), bool)
        if keep.any():
            p, w = p[keep], w[keep]
    return (p * w[:, None]).sum(0) / w.sum()


def visible_centroid(centre: np.ndarray, yaw: float, half: np.ndarray, camera_centre: np.ndarray,
                     in_image=None) -> np.ndarray:
    """[3] world centroid of the visible surface of the box (``centre``, ``yaw``, ``half``) seen from
    ``camera_centre``; ``in_image``: optional test of world points [P, 3] -> bool [P] (the part in view)."""
    rot = pose_from_yaw(np.zeros(3), yaw)[:3, :3]
    centre = np.asarray(centre, np.float64)
    inside = None if in_image is None else (lambda p: in_image(p @ rot.T + centre))
    return centre + rot @ visible_surface_offset(half, rot.T @ (np.asarray(camera_centre) - centre), inside)


def box_centre_from_surface(centroid: np.ndarray, camera_centre: np.ndarray, yaw: float, half: np.ndarray,
                            iterations: int = 3) -> np.ndarray:
    """Box centre [3] whose whole visible surface (seen from ``camera_centre``) has the measured ``centroid``."""
    centroid = np.asarray(centroid, np.float64)
    centre = centroid.copy()
    for _ in range(iterations):
        centre = centre + (centroid - visible_centroid(centre, yaw, half, camera_centre))
    return centre


def edge_aware_measurements(centres: np.ndarray, centroids: dict[int, np.ndarray], yaws: np.ndarray,
                            camera_centres: np.ndarray, half: np.ndarray, in_image, sigma: float, step: float
                            ) -> tuple[np.ndarray, np.ndarray]:
    """One Gauss-Newton linearisation of the measured visible centroids about the box centres [T, 3] (NaN rows
    are skipped), with the image edges in the model: ``h_t(c) = visible_centroid(c, ..., in_image(t, .))``.
    A box cut off by the image edge barely moves its visible centroid along the cut direction, so the Jacobian
    J_t (central differences of ``step``) is nearly singular there and the centre must not be read off the
    centroid in that direction; the pseudo-measurement carries that as covariance. Returns z [T, 3] (NaN where
    no centroid) and its covariance R [T, 3, 3]: ``R = (J^T J / sigma^2 + I / sigma_max^2)^-1`` and
    ``z = c + R J^T (m - h(c)) / sigma^2``, with ``sigma_max = 100 sigma`` bounding the uncertainty."""
    n = len(centres)
    z = np.full((n, 3), np.nan)
    r = np.tile(np.eye(3) * sigma ** 2, (n, 1, 1))
    for t, m in centroids.items():
        c = centres[t]
        if np.isnan(c).any():
            continue

        def h(x: np.ndarray, t: int = t) -> np.ndarray:
            return visible_centroid(x, yaws[t], half, camera_centres[t], lambda p: in_image(t, p))

        jac = np.stack([(h(c + e) - h(c - e)) / (2 * step) for e in np.eye(3) * step], 1)  # [3, 3]: dh / dc
        info = jac.T @ jac / sigma ** 2 + np.eye(3) / (100 * sigma) ** 2
        r[t] = np.linalg.inv(info)
        z[t] = c + r[t] @ jac.T @ (np.asarray(m) - h(c)) / sigma ** 2
    return z, r


def yaw_from_heading(dx: float, dz: float) -> float:
    """Box yaw (rotation about world y, docs/BUNDLE.md) whose +x axis points along the ground direction (dx, dz)."""
    return float(np.arctan2(-dz, dx))


def pose_from_yaw(centre: np.ndarray, yaw: float) -> np.ndarray:
    """[4, 4] world_from_box with rotation R_y(yaw) and the given centre [3]."""
    c, s = np.cos(yaw), np.sin(yaw)
    p = np.eye(4)
    p[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    p[:3, 3] = centre
    return p


def ground_axis_yaw(points: np.ndarray) -> float:
    """Yaw of the principal ground-plane (x, z) axis of points [M, 3] (a static agent's heading, up to sign)."""
    if len(points) < 2:
        return 0.0
    xz = points[:, [0, 2]] - points[:, [0, 2]].mean(0)
    _, _, vt = np.linalg.svd(xz, full_matrices=False)
    return yaw_from_heading(vt[0, 0], vt[0, 1])


def cell_centre_pixels(xs: np.ndarray, ys: np.ndarray, w: int, h: int, width: int, height: int
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Training-resolution pixel (column, row) index arrays of the centres of the cells (xs, ys) of a [h, w]
    feature map over a [height, width] image."""
    px = np.clip(((np.asarray(xs) + 0.5) * width / w).astype(np.int64), 0, width - 1)
    py = np.clip(((np.asarray(ys) + 0.5) * height / h).astype(np.int64), 0, height - 1)
    return px, py


def trajectory_poses(state: np.ndarray, *, min_speed: float, extend: int,
                     in_view, fallback_yaw: float, evidence=None) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame box poses from a smoothed track.

    state [T, 6] (x, y, z, vx, vy, vz per frame; NaN outside the track's first..last hit). Inside the track's
    life the centre is the smoothed position (coasted across gaps); up to ``extend`` frames before / after it the
    centre is extrapolated with the end velocity and the frame counts as valid while ``in_view(frame,
    world_from_box [4, 4]) -> bool`` holds (the box there, at that frame's yaw). With ``evidence(frame,
    world_from_box) -> bool`` the extrapolation goes on past ``extend`` frames for as long as every frame is in
    view and shows evidence of the agent there (agent-like features where its box would be: the clusters only
    saw the car where its background gradients stood out, the features see it wherever it is visible). Beyond
    that the pose is held constant (invalid). The yaw follows the smoothed ground velocity (x, z) where the speed
    is at least ``min_speed`` per frame (directions opposing the median one are flipped: a noisy slow track must
    not turn around), is held from the nearest such frame elsewhere, and is ``fallback_yaw`` when the track never
    moves that fast.
    Returns world_from_box [T, 4, 4] and valid [T] bool."""
    n = len(state)
    speed = np.linalg.norm(state[:, [3, 5]], axis=1)  # [T], NaN outside life
    moving = np.flatnonzero(np.nan_to_num(speed) >= min_speed)
    yaw = np.full(n, fallback_yaw)
    if len(moving):
        unit = state[moving][:, [3, 5]] / speed[moving, None]
        ref = np.median(unit, axis=0)
        for j, i in enumerate(moving):
            yaw_i = yaw_from_heading(*unit[j])
            yaw[i] = yaw_i if unit[j] @ ref >= 0 or len(moving) == 1 else yaw_from_heading(*-unit[j])
        nearest = moving[np.abs(np.arange(n)[:, None] - moving[None]).argmin(1)]
        yaw = yaw[nearest]
    life = np.flatnonzero(~np.isnan(state[:, 0]))
    first, last = int(life[0]), int(life[-1])
    centre = np.full((n, 3), np.nan)
    centre[first:last + 1] = state[first:last + 1, :3]
    valid = np.zeros(n, bool)
    valid[first:last + 1] = True
    for direction, end in ((-1, first), (1, last)):
        v = state[end, 3:]
        i, steps, held = end + direction, 1, extend
        while 0 <= i < n:
            c = state[end, :3] + v * direction * steps
            pose = pose_from_yaw(c, yaw[i])
            seen = in_view(i, pose)
            if steps <= extend and seen:
                valid[i] = True
            elif steps > extend and held == steps - 1 and seen and evidence is not None and evidence(i, pose):
                valid[i], held = True, steps
            centre[i] = c if steps <= held else state[end, :3] + v * direction * held
            i, steps = i + direction, steps + 1
    poses = np.stack([pose_from_yaw(centre[i], yaw[i]) for i in range(n)])
    return poses, valid


def spawn_trajectory(state: np.ndarray, centroids: dict[int, np.ndarray], camera_centres: np.ndarray,
                     half: np.ndarray, in_view, fallback_yaw: float, *, meas_sigma: float, accel_sigma: float,
                     init_vel_sigma: float, min_speed: float, extend: int, evidence=None, in_image=None,
                     edge_passes: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Pose prior of a spawned agent: world_from_box [T, 4, 4] and valid [T].

    ``state`` [T, 6] is the tracker's smoothed track of the cluster centroids ``centroids`` {frame: [3]}, which
    sample the agent's visible surface, not its centre. Each centroid is moved back to the centre of a box of
    half extents ``half`` (heading from the track, seen from ``camera_centres`` [T, 3]: ``box_centre_from_
    surface``), the corrected centres are RTS-smoothed again with the smaller ``accel_sigma`` (a steady
    heading), and ``trajectory_poses`` turns the result into poses (``evidence``: see there).
    ``in_image(t, points [P, 3]) -> bool [P]``: which world points frame t's image holds. With it, ``edge_passes``
    Gauss-Newton passes re-read the centroids with the part of the box outside the image left out
    (``edge_aware_measurements``) and smooth again: a car leaving at the image edge is then placed by the
    directions its visible part does fix and by its track elsewhere."""
    poses, _ = trajectory_poses(state, min_speed=min_speed, extend=extend, in_view=in_view,
                                fallback_yaw=fallback_yaw)
    yaws = np.arctan2(poses[:, 0, 2], poses[:, 0, 0])  # [T]
    z = np.full((len(state), 3), np.nan)
    for t, c in centroids.items():
        z[t] = box_centre_from_surface(c, camera_centres[t], yaws[t], half)
    kw = {"accel_var": accel_sigma ** 2, "init_vel_var": init_vel_sigma ** 2}
    smooth, _ = smooth_sequence(z, np.tile(np.eye(3) * meas_sigma ** 2, (len(state), 1, 1)), **kw)
    for _ in range(edge_passes if in_image is not None else 0):
        z, r = edge_aware_measurements(smooth[:, :3], centroids, yaws, camera_centres, half, in_image, meas_sigma,
                                       0.25 * float(np.min(half)))
        smooth, _ = smooth_sequence(z, r, **kw)
    return trajectory_poses(smooth, min_speed=min_speed, extend=extend, in_view=in_view, fallback_yaw=fallback_yaw,
                            evidence=evidence)


def nearest_frame(points: np.ndarray, rows: np.ndarray, members: list[tuple[int, np.ndarray]],
                  poses: np.ndarray) -> np.ndarray:
    """[M] frame at which each of the rows (world points [M, 3]) enters its agent's canonical frame: among the
    frames whose cluster holds the row (``members``: (frame, rows)), the one whose box centre is nearest."""
    frame_of = np.zeros(len(rows), np.int64)
    best = np.full(len(rows), np.inf)
    for t, m in members:
        d = np.where(np.isin(rows, m), np.linalg.norm(points - poses[t, :3, 3], axis=1), np.inf)
        better = d < best
        frame_of[better], best[better] = t, d[better]
    return frame_of
