"""Per-frame detections of the agent tracklets: mask components, depth-layer splits, merged parts, 3D lifting.

Used by ``agg/priors/tracklets.py`` (``track_agents``); the rules and thresholds (``TrackConfig`` fields) are in
docs/PRIORS.md ("Agent tracklets"). Pixel (row i, column j) is the image point (u, v) = (j, i) (OpenCV).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.ndimage import distance_transform_edt


@dataclass
class Candidate:
    """A detection with the data the tracker and the box fit need (internal; ``Detection`` is the public view)."""

    rows: np.ndarray  # [n] pixel rows
    cols: np.ndarray  # [n] pixel columns
    labels: list[int]  # OpenCV component labels covered
    bbox: tuple[int, int, int, int] = (0, 0, 0, 0)  # x0, y0, x1, y1 inclusive-exclusive
    area: int = 0
    centre_px: np.ndarray = field(default_factory=lambda: np.full(2, np.nan))  # [2] (u, v) pixel centroid
    lifted: bool = False  # enough valid depth to be placed in 3D
    depth: float = float("nan")  # the depth statistic (camera z)
    depth_fraction: float = 0.0
    centre_world: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))  # [3] visible-surface centre
    cov_world: np.ndarray = field(default_factory=lambda: np.full((3, 3), np.nan))  # [3, 3] measurement covariance
    points_world: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # [m, 3] visible points
    size: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))  # [3] visible extent (view, lateral, up)
    appearance: np.ndarray | None = None  # [bins^3] normalised RGB histogram of its pixels (with an image)


def _valid_depth(d: np.ndarray, c: np.ndarray | None, min_conf: float) -> np.ndarray:
    ok = np.isfinite(d) & (d > 0)
    if c is not None:
        ok &= np.asarray(c, float) >= min_conf
    return ok


def _layer_splits(logd: np.ndarray, min_count: float, cfg) -> list[tuple[float, float]]:
    """Candidate (threshold, separation) pairs splitting log depths [n] into a near and a far layer: Otsu's
    threshold and the widest gap between sorted values, each kept when both layers have >= min_count values and
    their means differ by >= ``split_min_separation`` and >= ``split_min_contrast`` pooled within-layer stds."""
    x = np.sort(logd)
    n = len(x)
    min_count = max(int(np.ceil(min_count)), 2)
    if n < 2 * min_count:
        return []
    cs = np.cumsum(x)
    j = np.arange(min_count, n - min_count + 1)  # size of the near layer
    m1 = cs[j - 1] / j
    m2 = (cs[-1] - cs[j - 1]) / (n - j)
    otsu = int(j[np.argmax(j * (n - j) * (m2 - m1) ** 2)])
    gap = int(j[np.argmax(x[j] - x[j - 1])])
    out = []
    for best in dict.fromkeys((otsu, gap)):
        near, far = x[:best], x[best:]
        sep = float(far.mean() - near.mean())
        pooled = float(np.sqrt((near.var() * len(near) + far.var() * len(far)) / n))
        if sep >= cfg.split_min_separation and sep >= cfg.split_min_contrast * max(pooled, 1e-12):
            out.append((float(0.5 * (near[-1] + far[0])), sep))
    return out


def _depth_edge(grid: np.ndarray, logd: np.ndarray) -> tuple[float, float]:
    """Median |log-depth jump| between 4-neighbours of different layers and of the same layer (NaN if none).
    grid [h, w]: -1 = no depth, 0 = near, 1 = far; logd [h, w]."""
    across, within = [], []
    for a, b, la, lb in ((grid[:, :-1], grid[:, 1:], logd[:, :-1], logd[:, 1:]),
                         (grid[:-1], grid[1:], logd[:-1], logd[1:])):
        both = (a >= 0) & (b >= 0)
        jump = np.abs(la - lb)
        across.append(jump[both & (a != b)])
        within.append(jump[both & (a == b)])
    across, within = np.concatenate(across), np.concatenate(within)
    med = lambda v: float(np.median(v)) if len(v) else float("nan")  # noqa: E731
    return med(across), med(within)


def _split_layers(rows, cols, d, ok, labels, min_area, cfg, levels: int = 2) -> list[Candidate]:
    """Recursively split a pixel group into two depth layers when its depth is bimodal (``_layer_splits``) *and*
    the layers meet at a depth discontinuity (an occlusion edge, not a slanted surface such as a car's side): the median
    jump between neighbouring pixels of different layers must exceed the median jump within a layer by
    ``split_edge_fraction`` of the layer separation. Pixels without depth join the layer of the nearest pixel
    with depth."""
    whole = [Candidate(rows, cols, list(labels))]
    if not cfg.split_depth_layers or levels <= 0 or len(rows) < 2 * min_area or ok.sum() < 8:
        return whole
    logd = np.log(d[ok])
    y0, x0 = rows.min(), cols.min()
    r, c = rows - y0, cols - x0
    shape = (r.max() + 1, c.max() + 1)
    lgrid = np.zeros(shape)
    lgrid[r[ok], c[ok]] = logd
    for thr, sep in _layer_splits(logd, min_area * ok.mean(), cfg):
        grid = np.full(shape, -1, np.int64)
        grid[r[ok], c[ok]] = (logd > thr).astype(np.int64)
        across, within = _depth_edge(grid, lgrid)
        jump = across - (within if np.isfinite(within) else 0.0)
        if not np.isfinite(across) or jump >= cfg.split_edge_fraction * sep:
            break
    else:
        return whole
    # nearest pixel with depth, for every pixel of the crop
    idx = distance_transform_edt(grid < 0, return_distances=False, return_indices=True)  # [2, h, w]
    far = grid[idx[0][r, c], idx[1][r, c]] == 1  # [n]
    if far.sum() < min_area or (~far).sum() < min_area:
        return whole
    out = []
    for sel in (~far, far):
        out += _split_layers(rows[sel], cols[sel], d[sel], ok[sel], labels, min_area, cfg, levels - 1)
    return out


def _merge_parts(parts: list[Candidate], depth_of: list[float], cfg) -> list[Candidate]:
    """Union of same-frame parts at the same depth whose boxes are separated by a small gap (a static occluder)."""
    n = len(parts)
    parent = list(range(n))

    def find(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    boxes = [(p.cols.min(), p.rows.min(), p.cols.max() + 1, p.rows.max() + 1) for p in parts]
    for a in range(n):
        for b in range(a + 1, n):
            da, db = depth_of[a], depth_of[b]
            if not (np.isfinite(da) and np.isfinite(db)) or abs(np.log(da / db)) > cfg.merge_depth_ratio:
                continue
            (ax0, ay0, ax1, ay1), (bx0, by0, bx1, by1) = boxes[a], boxes[b]
            wa, wb, ha, hb = ax1 - ax0, bx1 - bx0, ay1 - ay0, by1 - by0
            gap_x, gap_y = max(ax0, bx0) - min(ax1, bx1), max(ay0, by0) - min(ay1, by1)  # < 0: overlap
            lap_x, lap_y = -gap_x / min(wa, wb), -gap_y / min(ha, hb)
            near_x = gap_x <= cfg.merge_gap_fraction * min(wa, wb) and lap_y >= cfg.merge_min_overlap
            near_y = gap_y <= cfg.merge_gap_fraction * min(ha, hb) and lap_x >= cfg.merge_min_overlap
            if near_x or near_y:
                parent[find(b)] = find(a)
    groups: dict[int, list[int]] = {}
    for a in range(n):
        groups.setdefault(find(a), []).append(a)
    out = []
    for members in groups.values():
        ps = [parts[a] for a in members]
        out.append(Candidate(np.concatenate([p.rows for p in ps]), np.concatenate([p.cols for p in ps]),
                             sorted({lab for p in ps for lab in p.labels})))
    return out


def _percentile_extent(s: np.ndarray, cfg) -> float:
    lo, hi = cfg.extent_percentiles
    a, b = np.percentile(s, [lo, hi])
    return float((b - a) / ((hi - lo) / 100.0))


def _plane_depth(u: np.ndarray, v: np.ndarray, d: np.ndarray, u_out: np.ndarray, v_out: np.ndarray) -> np.ndarray:
    """Depth at (u_out, v_out) [m] from a trimmed least-squares plane 1/d = a + b u + c v through samples [n]."""
    uc, vc = u.mean(), v.mean()
    A = np.stack([np.ones_like(u), u - uc, v - vc], 1)  # [n, 3]
    y = 1.0 / d
    keep = np.ones(len(y), bool)
    for _ in range(2):  # fit, drop residuals beyond 2.5 robust sigmas, refit
        coef = np.linalg.lstsq(A[keep], y[keep], rcond=None)[0]
        res = np.abs(y - A @ coef)
        sigma = 1.4826 * np.median(res[keep]) + 1e-12
        keep = res <= 2.5 * sigma
        if keep.sum() < 3:
            break
    inv = coef[0] + coef[1] * (u_out - uc) + coef[2] * (v_out - vc)
    lo, hi = 1.0 / d.max(), 1.0 / d.min()  # stay within the observed depth range
    return 1.0 / np.clip(inv, lo, hi)


def _lift(c: Candidate, depth: np.ndarray, ok_map: np.ndarray, K_inv: np.ndarray, world_from_camera: np.ndarray,
          cfg) -> Candidate:
    """Fill the 2D summary of c, and its 3D fields when it has enough valid depth."""
    rows, cols = c.rows, c.cols
    c.area = int(len(rows))
    x0, y0, x1, y1 = int(cols.min()), int(rows.min()), int(cols.max()) + 1, int(rows.max()) + 1
    c.bbox = (x0, y0, x1, y1)
    c.centre_px = np.array([cols.mean(), rows.mean()])
    d = depth[rows, cols].astype(float)
    ok = ok_map[rows, cols]
    c.depth_fraction = float(ok.mean())
    if ok.sum() < max(3, cfg.min_depth_fraction * c.area):
        return c
    stat = float(np.percentile(d[ok], cfg.depth_percentile))
    ok &= (d >= stat / cfg.depth_outlier_ratio) & (d <= stat * cfg.depth_outlier_ratio)
    c.depth, c.lifted = stat, True
    R, t = world_from_camera[:3, :3], world_from_camera[:3, 3]
    ray = K_inv @ np.array([c.centre_px[0], c.centre_px[1], 1.0])
    c.centre_world = R @ (ray * stat) + t
    h, w = depth.shape
    cut = x0 == 0 or y0 == 0 or x1 == w or y1 == h  # cut by the image border: its visible centre is biased
    f = cfg.border_sigma_factor if cut else 1.0
    cov_cam = np.diag([(f * cfg.lateral_sigma * stat) ** 2] * 2 + [(f * cfg.depth_sigma * stat) ** 2])
    c.cov_world = R @ cov_cam @ R.T
    # visible points: every pixel of c back-projected with a robust plane fit of its inverse depth (exact for a
    # planar surface, smooths per-pixel noise), or with the raw depth of its inlier pixels (plane_fit=False)
    if cfg.plane_fit:
        sel = np.arange(0, c.area, max(1, int(np.ceil(c.area / cfg.max_points))))
        u, v = cols[sel].astype(float), rows[sel].astype(float)
        z = _plane_depth(cols[ok].astype(float), rows[ok].astype(float), d[ok], u, v)
    else:
        sel = np.nonzero(ok)[0]
        sel = sel[::max(1, int(np.ceil(len(sel) / cfg.max_points)))]
        u, v, z = cols[sel].astype(float), rows[sel].astype(float), d[sel]
    pts_cam = (K_inv @ np.stack([u, v, np.ones_like(u)], 0)) * z[None]  # [3, m]
    c.points_world = (R @ pts_cam).T + t  # [m, 3]
    view = c.centre_world - t
    view = np.array([view[0], 0.0, view[2]])
    view = view / max(np.linalg.norm(view), 1e-12)
    lateral = np.array([view[2], 0.0, -view[0]])
    c.size = np.array([_percentile_extent(c.points_world @ ax, cfg)
                       for ax in (view, lateral, np.array([0.0, 1.0, 0.0]))])
    return c


def colour_histogram(image: np.ndarray, rows: np.ndarray, cols: np.ndarray, bins: int) -> np.ndarray:
    """[bins^3] normalised RGB histogram of the pixels (image [H, W, 3] or [H, W], uint8 or float in [0, 1])."""
    px = image[rows, cols].astype(np.float64)  # [n, 3] or [n]
    if not np.issubdtype(image.dtype, np.integer):
        px = px * 255.0
    px = px.reshape(len(rows), -1)
    if px.shape[1] == 1:
        px = np.repeat(px, 3, 1)
    q = np.clip((px * bins / 256.0).astype(np.int64), 0, bins - 1)  # [n, 3]
    hist = np.bincount((q[:, 0] * bins + q[:, 1]) * bins + q[:, 2], minlength=bins ** 3).astype(np.float64)
    return hist / max(hist.sum(), 1.0)


def frame_candidates(mask: np.ndarray, depth: np.ndarray, conf: np.ndarray | None, image: np.ndarray | None,
                     K_inv: np.ndarray, world_from_camera: np.ndarray, min_area: int, cfg) -> list[Candidate]:
    """Detections of one frame: mask [H, W] bool, depth [H, W], conf [H, W] or None, image [H, W, 3] or None,
    K_inv [3, 3], world_from_camera [4, 4]."""
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=cfg.connectivity)
    ok_map = _valid_depth(depth, conf, cfg.min_depth_confidence)  # [H, W]
    parts: list[Candidate] = []
    for lab in range(1, n):
        x, y, w, h, area = (int(v) for v in stats[lab])
        if area < min_area:
            continue
        rr, cc = np.nonzero(labels[y:y + h, x:x + w] == lab)
        rr, cc = rr + y, cc + x
        parts += _split_layers(rr, cc, depth[rr, cc].astype(float), ok_map[rr, cc], [lab], min_area, cfg)
    parts = [p for p in parts if len(p.rows) >= min_area]
    if cfg.merge_parts and len(parts) > 1:
        stat = []
        for p in parts:
            ok = ok_map[p.rows, p.cols]
            enough = ok.sum() >= max(3, cfg.min_depth_fraction * len(p.rows))
            stat.append(float(np.percentile(depth[p.rows, p.cols][ok], cfg.depth_percentile)) if enough
                        else float("nan"))
        parts = _merge_parts(parts, stat, cfg)
    out = [_lift(p, depth, ok_map, K_inv, world_from_camera, cfg) for p in parts]
    if image is not None:
        for p in out:
            p.appearance = colour_histogram(image, p.rows, p.cols, cfg.appearance_bins)
    out.sort(key=lambda p: (min(p.labels), p.bbox[1], p.bbox[0]))
    return out
