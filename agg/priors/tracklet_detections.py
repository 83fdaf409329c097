"""Per-frame detections of the agent tracklets: mask components, neck cuts, depth-layer splits, merged parts, the
ground rule (``agg/priors/tracklet_ground.py``) and the upright 3D lifting.

Used by ``agg/priors/tracklets.py`` (``track_agents``); the rules and thresholds (``TrackConfig`` fields) are in
docs/PRIORS.md ("Agent tracklets"). Pixel (row i, column j) is the image point (u, v) = (j, i) (OpenCV).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.ndimage import distance_transform_edt
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components

from agg.priors.tracklet_ground import (FLOATING, GROUNDED, UNKNOWN, column_bottoms, column_medians,
                                        contact_verdicts, road_inverse_depth)


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
    on_ground: bool | None = None  # ground rule: True stands on the road, False does not, None: not decided
    ground_area: float = float("nan")  # pixel area / (footprint row - horizon row)^2: area in camera heights^2


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


def _split_necks(rows: np.ndarray, cols: np.ndarray, labels: list[int], min_area: int, cfg,
                 levels: int = 2) -> list[tuple[np.ndarray, np.ndarray]]:
    """Cut a component at a thin neck between two tall parts (two agents side by side joined by a strip of mask
    on the road): the column whose pixel count is the smallest fraction of the tallest column on *both* sides;
    cut when that fraction is <= ``split_neck_ratio`` and each side keeps >= min_area pixels and >= 3 columns.
    A leg gap or a car's underbody removes far less than that. Recursive (at most 2 levels)."""
    whole = [(rows, cols)]
    if cfg.split_neck_ratio <= 0 or levels <= 0 or len(rows) < 2 * min_area:
        return whole
    ucol, inv = np.unique(cols, return_inverse=True)
    if len(ucol) < 7:
        return whole
    thick = np.zeros(ucol[-1] - ucol[0] + 1)  # [w] pixels per column (0 in a gap)
    np.add.at(thick, cols - ucol[0], 1)
    left, right = np.maximum.accumulate(thick), np.maximum.accumulate(thick[::-1])[::-1]
    j = np.arange(3, len(thick) - 3)  # 3 columns at least on each side
    ratio = thick[j] / np.minimum(left[j - 1], right[j + 1])
    k = int(j[np.argmin(ratio)])
    if ratio.min() > cfg.split_neck_ratio:
        return whole
    a = cols - ucol[0] < k
    if a.sum() < min_area or (~a).sum() < min_area:
        return whole
    return [part for sel in (a, ~a) for part in _split_necks(rows[sel], cols[sel], labels, min_area, cfg, levels - 1)]


def _gap_in_front(box_a, box_b, horizontal: bool, depth: np.ndarray, ok_map: np.ndarray, mask: np.ndarray,
                  d: float, cfg) -> bool:
    """Whether the unmasked pixels between two boxes (x0, y0, x1, y1) that have depth are nearer than d (by
    ``occlusion_ratio``): an occluder in front; True when none of them has depth (cannot tell)."""
    (ax0, ay0, ax1, ay1), (bx0, by0, bx1, by1) = box_a, box_b
    if horizontal:
        x0, x1 = sorted((min(ax1, bx1), max(ax0, bx0)))
        y0, y1 = max(ay0, by0), min(ay1, by1)
    else:
        y0, y1 = sorted((min(ay1, by1), max(ay0, by0)))
        x0, x1 = max(ax0, bx0), min(ax1, bx1)
    sel = ok_map[y0:y1, x0:x1] & ~mask[y0:y1, x0:x1]
    if sel.sum() < 3:
        return True
    return bool(np.median(depth[y0:y1, x0:x1][sel]) < d / cfg.occlusion_ratio)


def _merge_parts(parts: list[Candidate], depth_of: list[float], cfg, depth: np.ndarray, ok_map: np.ndarray,
                 mask: np.ndarray) -> list[Candidate]:
    """Union of same-frame parts at the same depth whose boxes are separated by a small gap (a static occluder):
    where the depth prior sees the gap, it must be nearer than the parts (a pole, not the road between two cars).
    Parts of one mask component (cut at a neck or a depth edge on purpose) are not merged again."""
    n = len(parts)
    joined = np.zeros((n, n), bool)  # [n, n] pairs to merge (a < b)
    boxes = [(p.cols.min(), p.rows.min(), p.cols.max() + 1, p.rows.max() + 1) for p in parts]
    for a in range(n):
        for b in range(a + 1, n):
            da, db = depth_of[a], depth_of[b]
            if set(parts[a].labels) & set(parts[b].labels):
                continue
            if not (np.isfinite(da) and np.isfinite(db)) or abs(np.log(da / db)) > cfg.merge_depth_ratio:
                continue
            (ax0, ay0, ax1, ay1), (bx0, by0, bx1, by1) = boxes[a], boxes[b]
            wa, wb, ha, hb = ax1 - ax0, bx1 - bx0, ay1 - ay0, by1 - by0
            gap_x, gap_y = max(ax0, bx0) - min(ax1, bx1), max(ay0, by0) - min(ay1, by1)  # < 0: overlap
            lap_x, lap_y = -gap_x / min(wa, wb), -gap_y / min(ha, hb)
            near_x = gap_x <= cfg.merge_gap_fraction * min(wa, wb) and lap_y >= cfg.merge_min_overlap
            near_y = gap_y <= cfg.merge_gap_fraction * min(ha, hb) and lap_x >= cfg.merge_min_overlap
            if (near_x or near_y) and _gap_in_front(boxes[a], boxes[b], near_x, depth, ok_map, mask,
                                                    min(da, db), cfg):
                joined[a, b] = True
    _, label = connected_components(csr_matrix(joined), directed=False)  # [n]
    out = []
    for g in range(label.max(initial=-1) + 1):
        ps = [parts[a] for a in np.flatnonzero(label == g)]
        out.append(Candidate(np.concatenate([p.rows for p in ps]), np.concatenate([p.cols for p in ps]),
                             sorted({lab for p in ps for lab in p.labels})))
    return out


def _percentile_extent(s: np.ndarray, cfg) -> float:
    lo, hi = cfg.extent_percentiles
    a, b = np.percentile(s, [lo, hi])
    return float((b - a) / ((hi - lo) / 100.0))


def _upright_depth(u: np.ndarray, d: np.ndarray, weight: np.ndarray, u_out: np.ndarray) -> np.ndarray:
    """Depth at columns u_out [m] of an upright surface, ``1/d = a + b u``: a trimmed weighted least-squares line
    through column depths d [k] at columns u [k] (an agent's faces are vertical, so its depth depends on the
    column only); a constant (the weighted median) with fewer than 3 columns."""
    y = 1.0 / d
    if len(u) < 3 or np.ptp(u) <= 0:
        order = np.argsort(y)
        cum = np.cumsum(weight[order])
        return np.full(len(u_out), 1.0 / y[order][np.searchsorted(cum, 0.5 * cum[-1])])
    uc = float(np.average(u, weights=weight))
    A = np.stack([np.ones_like(u), u - uc], 1)  # [k, 2]
    sw = np.sqrt(weight)
    keep = np.ones(len(y), bool)
    for _ in range(2):  # fit, drop residuals beyond 2.5 robust sigmas, refit
        coef = np.linalg.lstsq(A[keep] * sw[keep, None], y[keep] * sw[keep], rcond=None)[0]
        res = np.abs(y - A @ coef)
        keep = res <= 2.5 * (1.4826 * np.median(res[keep]) + 1e-12)
        if keep.sum() < 3:
            break
    inv = coef[0] + coef[1] * (u_out - uc)
    return 1.0 / np.clip(inv, y.min(), y.max())  # stay within the observed depth range


def _summary(c: Candidate) -> None:
    """Area, pixel box and centroid of c from its pixels."""
    c.area = int(len(c.rows))
    c.bbox = (int(c.cols.min()), int(c.rows.min()), int(c.cols.max()) + 1, int(c.rows.max()) + 1)
    c.centre_px = np.array([c.cols.mean(), c.rows.mean()])


def _drop_columns(c: Candidate, drop: np.ndarray, inv: np.ndarray, d_px: np.ndarray, ok: np.ndarray):
    """Remove the pixels of columns drop [m] (bool) from c; returns its per-pixel depth, validity and column index
    re-indexed to the kept columns."""
    keep_px = ~drop[inv]
    c.rows, c.cols = c.rows[keep_px], c.cols[keep_px]
    _summary(c)
    c.depth_fraction = float(ok[keep_px].mean())
    return d_px[keep_px], ok[keep_px], np.cumsum(~drop)[inv[keep_px]] - 1


def _lift(c: Candidate, depth: np.ndarray, ok_map: np.ndarray, K_inv: np.ndarray, world_from_camera: np.ndarray,
          cfg, plane: np.ndarray | None = None) -> Candidate:
    """Fill the 2D summary of c, its ground verdict, and its 3D fields when it stands on the ground (or no road
    plane is known) and has depth. plane: the frame's road plane (a, b, c) of inverse depth, or None.

    Ground rule: the verdicts (``contact_verdicts``) of its footprint, the columns whose contact lies in its
    lowest ``contact_band``, decide: more FLOATING than ``max_floating_fraction`` (by pixels), and c is no agent
    (``on_ground`` False, not lifted); else FLOATING columns anywhere (a blob merged at the side) are dropped.
    Columns standing deeper than ``max_column_depth_ratio`` x the footprint's depth are dropped too (a tree line
    above and behind an agent, joined to its mask): a GROUNDED or UNKNOWN column stands where the road is at its
    contact, another at its own depth.
    Upright model: each column of c is a vertical segment at the depth read near its contact (the lowest
    ``contact_band`` of c's height in that column; else the road's depth at a GROUNDED contact; else the column's
    valid depth), at most the road's depth at its contact (an object seen there is not under the road), and an
    upright line ``1/d = a + b u`` through those column depths gives every pixel's depth."""
    _summary(c)
    d_px = depth[c.rows, c.cols].astype(float)
    ok = ok_map[c.rows, c.cols]
    c.depth_fraction = float(ok.mean())
    ucol, bottom, inv = column_bottoms(c.rows, c.cols)  # [m], [m], [n]
    band = max(1, int(round(cfg.contact_band * (c.bbox[3] - c.bbox[1]))))
    own = column_medians(d_px, inv, ok & (c.rows > bottom[inv] - band), len(ucol))  # [m] depth at the contact
    ground = plane is not None and cfg.ground_rule
    road = np.full(len(ucol), np.inf)  # [m] the road's depth at each contact (inf: none)
    verdict = np.full(len(ucol), UNKNOWN)
    if ground:
        verdict = contact_verdicts(ucol, bottom, own, depth, ok_map, plane, cfg)  # [m]
        counts = np.bincount(inv, minlength=len(ucol))  # [m] pixels per column
        known = (bottom >= bottom.max() - band + 1) & (verdict != UNKNOWN)  # decided columns of the footprint
        floating = verdict == FLOATING
        if (known.any() and counts[known & floating].sum() > cfg.max_floating_fraction * counts[known].sum()) \
                or (~floating[inv]).sum() < 3:
            c.on_ground = False
            return c
        c.on_ground = True if known.any() else None
        if floating.any():  # drop the columns that rest on something else (a blob merged at the side)
            d_px, ok, inv = _drop_columns(c, floating, inv, d_px, ok)
            ucol, bottom, own, verdict = ucol[~floating], bottom[~floating], own[~floating], verdict[~floating]
        w_road = road_inverse_depth(plane, ucol.astype(float), bottom + 0.5)
        road = np.where(w_road > 0, 1.0 / np.where(w_road > 0, w_road, 1.0), np.inf)
        fill = (verdict == GROUNDED) & ~np.isfinite(own)  # no depth of its own: the road's at the contact
        own[fill] = road[fill]
    rest = ~np.isfinite(own)
    if rest.any():
        own[rest] = column_medians(d_px, inv, ok, len(ucol))[rest]
    own = np.minimum(own, road)  # nothing seen below the horizon is under the road
    counts = np.bincount(inv, minlength=len(ucol))
    have = np.isfinite(own) & (own > 0)
    foot = have & (bottom >= bottom.max() - band + 1)
    if foot.any():  # columns standing far behind the footprint belong to something else (a tree line behind)
        reach = np.where((verdict == GROUNDED) | (verdict == UNKNOWN), road, own)  # where their contact is
        reach = np.where(np.isfinite(reach), reach, own)  # on the road (visible or assumed), else their depth
        far = reach > cfg.max_column_depth_ratio * np.median(np.repeat(own[foot], counts[foot]))
        if far.any() and (~far[inv]).sum() >= 3:
            d_px, ok, inv = _drop_columns(c, far, inv, d_px, ok)
            ucol, bottom, own, have, road = ucol[~far], bottom[~far], own[~far], have[~far], road[~far]
            counts = np.bincount(inv, minlength=len(ucol))
    if ground:
        w_foot = 1.0 / float(np.median(road[bottom >= bottom.max() - band + 1]))  # the road at the footprint
        if w_foot > 0:  # an agent of 3D area A there covers A / h_cam^2 x (v_foot - v_horizon)^2 pixels
            c.ground_area = float(c.area * (plane[1] / w_foot) ** 2)
    if counts[have].sum() < max(3, cfg.min_depth_fraction * c.area) or (ok.sum() < 3 and not c.on_ground):
        return c
    med = float(np.median(np.repeat(own[have], counts[have])))
    have &= (own >= med / cfg.depth_outlier_ratio) & (own <= med * cfg.depth_outlier_ratio)
    col_depth = _upright_depth(ucol[have].astype(float), own[have], counts[have].astype(float), ucol.astype(float))
    z_px = col_depth[inv]  # [n] every pixel at its column's depth
    stat = float(np.percentile(z_px, cfg.depth_percentile))
    c.depth, c.lifted = stat, True
    R, t = world_from_camera[:3, :3], world_from_camera[:3, 3]
    ray = K_inv @ np.array([c.centre_px[0], c.centre_px[1], 1.0])
    c.centre_world = R @ (ray * stat) + t
    h, w = depth.shape
    x0, y0, x1, y1 = c.bbox
    cut = x0 == 0 or y0 == 0 or x1 == w or y1 == h  # cut by the image border: its visible centre is biased
    f = cfg.border_sigma_factor if cut else 1.0
    cov_cam = np.diag([(f * cfg.lateral_sigma * stat) ** 2] * 2 + [(f * cfg.depth_sigma * stat) ** 2])
    c.cov_world = R @ cov_cam @ R.T
    # visible points: every pixel back-projected at its column's upright depth (plane_fit), or the raw depth of
    # its valid pixels near that depth (plane_fit=False)
    if cfg.plane_fit:
        sel = np.arange(0, c.area, max(1, int(np.ceil(c.area / cfg.max_points))))
        u, v, z = c.cols[sel].astype(float), c.rows[sel].astype(float), z_px[sel]
    else:
        sel = np.nonzero(ok & (d_px >= z_px / cfg.depth_outlier_ratio) & (d_px <= z_px * cfg.depth_outlier_ratio))[0]
        sel = sel if len(sel) >= 3 else np.arange(c.area)
        sel = sel[::max(1, int(np.ceil(len(sel) / cfg.max_points)))]
        u, v = c.cols[sel].astype(float), c.rows[sel].astype(float)
        z = np.where(ok[sel], d_px[sel], z_px[sel])
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
                     K_inv: np.ndarray, world_from_camera: np.ndarray, min_area: int, cfg,
                     plane: np.ndarray | None = None) -> list[Candidate]:
    """Detections of one frame: mask [H, W] bool, depth [H, W], conf [H, W] or None, image [H, W, 3] or None,
    K_inv [3, 3], world_from_camera [4, 4], plane: the road plane (a, b, c) of inverse depth or None."""
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=cfg.connectivity)
    ok_map = _valid_depth(depth, conf, cfg.min_depth_confidence)  # [H, W]
    parts: list[Candidate] = []
    for lab in range(1, n):
        x, y, w, h, area = (int(v) for v in stats[lab])
        if area < min_area:
            continue
        rr, cc = np.nonzero(labels[y:y + h, x:x + w] == lab)
        rr, cc = rr + y, cc + x
        for r2, c2 in _split_necks(rr, cc, [lab], min_area, cfg):
            parts += _split_layers(r2, c2, depth[r2, c2].astype(float), ok_map[r2, c2], [lab], min_area, cfg)
    parts = [p for p in parts if len(p.rows) >= min_area]
    if cfg.merge_parts and len(parts) > 1:
        stat = []
        for p in parts:
            ok = ok_map[p.rows, p.cols]
            enough = ok.sum() >= max(3, cfg.min_depth_fraction * len(p.rows))
            stat.append(float(np.percentile(depth[p.rows, p.cols][ok], cfg.depth_percentile)) if enough
                        else float("nan"))
        parts = _merge_parts(parts, stat, cfg, depth, ok_map, mask)
    out = [_lift(p, depth, ok_map, K_inv, world_from_camera, cfg, plane) for p in parts]
    if image is not None:
        for p in out:
            p.appearance = colour_histogram(image, p.rows, p.cols, cfg.appearance_bins)
    out.sort(key=lambda p: (min(p.labels), p.bbox[1], p.bbox[0]))
    return out
