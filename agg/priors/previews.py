"""PNG previews of a bundle's priors, for a person to look at: what was estimated, and where it is wrong.

``write_previews(bundle, out_dir)`` writes, for whatever the bundle holds:

- ``masks.png``: evenly spaced frames with the dynamic mask in red and the tracklets' pixel boxes and ids;
- ``trajectory.png``: the camera path seen from above (world x against z, the first camera looking up the page),
  coloured by pose source, with the ground-truth path aligned by Sim(3) when the bundle has one;
- ``tracklets.png``: each track's world centre seen from above over the camera path, and its frames of validity;
- ``depth.png``: dense depth (inverse depth colour map) of the same frames as ``masks.png``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from agg.io.bundle import SceneBundle
from agg.priors.tracklets import filled_entries

_SOURCE_COLOURS = {"sfm": "tab:blue", "given": "tab:blue", "gt": "tab:blue", "interpolated": "tab:orange",
                   "vo": "tab:purple"}


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: Path) -> Path:
    plt = _plt()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def _top_view(ax) -> None:
    """Axes of a plot seen from above: world x (right) against z (forward), equal scale."""
    ax.set_xlabel("x (right)")
    ax.set_ylabel("z (forward)")
    ax.set_aspect("equal", adjustable="datalim")


def preview_frames(num_frames: int, count: int = 6) -> list[int]:
    """Up to ``count`` evenly spaced frame indices, first and last included."""
    return sorted(set(np.linspace(0, num_frames - 1, min(count, num_frames)).round().astype(int).tolist()))


def _track_colour(k: int) -> tuple[float, float, float]:
    import matplotlib

    return matplotlib.colormaps["tab10"](k % 10)[:3]


def project_boxes(boxes: np.ndarray, camera_from_world: np.ndarray, K: np.ndarray) -> np.ndarray:  # noqa: N803
    """Pixel rectangles [K, 4] (x0, y0, x1, y1) of 3D boxes [K, 7] (docs/BUNDLE.md), NaN where a box is absent
    or behind the camera. A centre-only box (NaN size) gets a zero-size rectangle at its projected centre."""
    out = np.full((len(boxes), 4), np.nan)
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float)  # [8, 3]
    for k, b in enumerate(np.asarray(boxes, float)):
        if not np.isfinite(b[:3]).all():
            continue
        lhw = np.array([b[3], b[5], b[4]])  # box axes: x length, y height, z width
        if np.isfinite(lhw).all() and np.isfinite(b[6]):
            ca, sa = np.cos(b[6]), np.sin(b[6])
            r = np.array([[ca, 0, sa], [0, 1, 0], [-sa, 0, ca]])
            pts = b[:3] + (0.5 * signs * lhw) @ r.T  # [8, 3] world
        else:
            pts = b[None, :3]
        cam = pts @ camera_from_world[:3, :3].T + camera_from_world[:3, 3]
        if np.any(cam[:, 2] <= 1e-3):
            continue
        uv = cam @ K.T
        uv = uv[:, :2] / uv[:, 2:3]
        out[k] = (*uv.min(0), *uv.max(0))
    return out


def write_previews(bundle: SceneBundle, out_dir: str | Path, count: int = 6) -> list[Path]:
    """Write the previews that the bundle's parts allow; returns the written paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    idx = preview_frames(bundle.num_frames, count)
    written = []
    if bundle.has("dynamic_masks"):
        written.append(_masks_png(bundle, idx, out / "masks.png"))
    if bundle.has("poses"):
        written.append(_trajectory_png(bundle, out / "trajectory.png"))
    if bundle.has("tracklets"):
        written.append(_tracklets_png(bundle, out / "tracklets.png"))
    if bundle.has("depth_dense"):
        written.append(_depth_png(bundle, idx, out / "depth.png"))
    return written


def _grid(n: int, aspect: float):
    plt = _plt()
    cols = 2 if n > 1 else 1
    rows = (n + cols - 1) // cols
    width = 12.0
    fig, axes = plt.subplots(rows, cols, figsize=(width, width / cols / aspect * rows + 0.4 * rows), squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    return plt, fig, axes.ravel()


def _masks_png(bundle: SceneBundle, idx: list[int], path: Path) -> Path:
    plt, fig, axes = _grid(len(idx), bundle.width / bundle.height)
    masks = bundle.dynamic_masks
    tr = bundle.tracklets if bundle.has("poses") else None
    filled = filled_entries(tr) if tr is not None else None  # [K, T] boxes filled across a gap: dashed
    for ax, i in zip(axes, idx):
        img = bundle.frame(i).copy()  # [H, W, 3]
        m = np.asarray(masks[i]) > 0
        img[m] = 0.45 * img[m] + 0.55 * np.array([1.0, 0.1, 0.1])
        ax.imshow(img)
        if tr is not None:
            valid = np.asarray(tr.valid[:, i])
            rects = project_boxes(np.asarray(tr.boxes[:, i]), bundle.camera_from_world[i], bundle.intrinsics[i])
            for k in np.flatnonzero(valid & np.isfinite(rects).all(1)):
                x0, y0, x1, y1 = rects[k]
                ax.add_patch(plt.Rectangle((x0, y0), max(x1 - x0, 2), max(y1 - y0, 2), fill=False, lw=1.5,
                                           ec=_track_colour(k), ls="--" if filled[k, i] else "-"))
                ax.text(x0, y0 - 2, f"{tr.ids[k]} {tr.classes[k]}", color=_track_colour(k), fontsize=8,
                        weight="bold")
        ax.set_xlim(-0.5, bundle.width - 0.5)
        ax.set_ylim(bundle.height - 0.5, -0.5)
        cover = 100.0 * float(m.mean())
        ax.set_title(f"frame {i}  (mask {cover:.1f} % of pixels)", fontsize=9)
        ax.axis("off")
    fig.suptitle("dynamic masks (red) and tracklets", fontsize=11)
    return _save(fig, path)


def _trajectory_png(bundle: SceneBundle, path: Path) -> Path:
    plt = _plt()
    poses = bundle.world_from_camera
    c = poses[:, :3, 3]
    sources = bundle.pose_source or ["?"] * len(c)
    fig, ax = plt.subplots(figsize=(6, 6))
    ax.plot(c[:, 0], c[:, 2], "-", color="0.6", lw=1, zorder=1)
    for s in sorted(set(sources)):
        m = np.array([x == s for x in sources])
        ax.scatter(c[m, 0], c[m, 2], s=14, color=_SOURCE_COLOURS.get(s, "tab:gray"), label=f"{s} ({m.sum()})",
                   zorder=2)
    title = "camera path from above (scene units)"
    gt = bundle.gt
    if gt is not None and gt.has("poses"):
        from agg.eval.trajectory import align_sim3, evaluate_trajectory

        sim = align_sim3(poses, gt.world_from_camera)
        inv = np.linalg.inv(sim.rotation) / sim.scale  # GT drawn in the estimate's frame
        g = (gt.world_from_camera[:, :3, 3] - sim.translation) @ inv.T
        ax.plot(g[:, 0], g[:, 2], "--", color="k", lw=1, label="ground truth (Sim(3)-aligned)")
        m = evaluate_trajectory(poses, gt.world_from_camera)
        unit = " m" if gt.metric else " (gt units)"
        title += f"\nATE {m.ate_rmse:.3g}{unit}, {m.ate_percent_of_path:.2f} % of the path"
    for i in (0, len(c) - 1):
        ax.annotate(f"frame {i}", (c[i, 0], c[i, 2]), fontsize=8)
    _top_view(ax)
    ax.legend(fontsize=8)
    ax.set_title(title, fontsize=10)
    return _save(fig, path)


def _tracklets_png(bundle: SceneBundle, path: Path) -> Path:
    plt = _plt()
    tr = bundle.tracklets
    c = bundle.world_from_camera[:, :3, 3]
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(12, 5), gridspec_kw={"width_ratios": [1, 1.4]})
    ax.plot(c[:, 0], c[:, 2], "-", color="0.5", lw=2, label="camera")
    gap_filled = filled_entries(tr)  # [K, T]
    for k in range(len(tr.ids)):
        v = np.asarray(tr.valid[k])
        b = np.asarray(tr.boxes[k])[v]
        ax.plot(b[:, 0], b[:, 2], ".-", color=_track_colour(k), ms=4, label=f"track {tr.ids[k]} ({tr.classes[k]})")
        filled = gap_filled[k]
        ax2.plot(np.flatnonzero(v & ~filled), np.full((v & ~filled).sum(), k), "s", color=_track_colour(k), ms=4)
        ax2.plot(np.flatnonzero(filled), np.full(filled.sum(), k), "s", mfc="none", color=_track_colour(k), ms=4)
    _top_view(ax)
    ax.set_title("track centres from above", fontsize=10)
    if len(tr.ids):
        ax.legend(fontsize=7)
    ax2.set_yticks(range(len(tr.ids)), [str(i) for i in tr.ids])
    ax2.set_xlim(-0.5, bundle.num_frames - 0.5)
    ax2.set_xlabel("frame")
    ax2.set_ylabel("track id")
    ax2.set_title("frames where each track is valid (hollow: filled across a gap)", fontsize=10)
    return _save(fig, path)


def _depth_png(bundle: SceneBundle, idx: list[int], path: Path) -> Path:
    plt, fig, axes = _grid(len(idx), bundle.width / bundle.height)
    dense = bundle.dense_depth
    for ax, i in zip(axes, idx):
        d = np.asarray(dense[i], dtype=np.float32)
        inv = np.where(d > 0, 1.0 / np.maximum(d, 1e-6), np.nan)
        ax.imshow(inv, cmap="turbo")
        ax.set_title(f"frame {i}: inverse depth ({100.0 * float((d > 0).mean()):.0f} % covered)", fontsize=9)
        ax.axis("off")
    fig.suptitle("dense depth prior", fontsize=11)
    return _save(fig, path)
