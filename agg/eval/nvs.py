"""Novel-view evaluation: render held-out frames through interpolated poses and score them against the video.

A held-out (test) frame was never optimised, so its camera pose is interpolated from the refined poses of the
neighbouring train frames, and so are the refined agent box poses and validities (``agg.eval.interpolate``:
slerp rotation, lerp translation, nearest held at the ends). The graph is rendered at the test frame with those
overrides (``SceneGraph.render(frame, world_from_camera=..., agent_poses=..., agent_valid=...)``; the frame
still sets the continuous time of non-rigid deformation) and compared with the bundle's frame (float RGB, or
uint8 scaled to [0, 1]).

Aggregation (the keys of the returned dict):

- ``psnr``, ``ssim``, ``lpips``: means over test frames of the per-frame values (PSNR is the mean of per-frame
  PSNRs, not the PSNR of the pooled MSE). ``lpips`` is None when no local LPIPS weights are configured
  (``lpips_note`` says why).
- ``psnr_agents``, ``ssim_agents``: over the agent pixels of all test frames pooled (one MSE over every agent
  pixel of every test frame; the SSIM map averaged over the same pixels). Agent pixels come from ``agent_masks``
  [T, H, W] when given, else the bundle's ground-truth dynamic masks (``bundle.gt.dynamic_masks``, every agent
  instance), else none (then both are None); ``agent_mask_source`` says which ("argument", "gt_dynamic_masks",
  "none").
- The ego vehicle's pixels (the bundle's ``ego_mask``, ``agg.eval.ego``) are never scored: PSNR and SSIM are
  over the other pixels, SSIM's windows and LPIPS see the frame's own pixels there (the render's are replaced),
  and agent masks lose them. ``ego_pixel_share`` is the share of the image left out (0.0 without an ego mask).
- ``render_fps``: test frames per second of the ``render`` calls alone (no metric time), after one warm-up render.
- ``split`` ("nvs"), ``n_test_frames``, ``n_gaussians``, ``n_agents``; ``per_frame``: one dict per frame (frame,
  psnr, ssim, lpips, psnr_agents, ssim_agents, agent_pixels, pixels: the pixels scored).
"""

from __future__ import annotations

import time
from collections.abc import Sequence

import numpy as np
import torch

from agg.device import synchronize
from agg.eval.ego import scene_pixels, with_ego_from
from agg.eval.interpolate import interpolate_agents, interpolate_camera
from agg.eval.metrics import Lpips, as_image, psnr, psnr_from_mse, squared_error, ssim, ssim_sum


def pick_frames(frames: Sequence[int], max_frames: int | None) -> list[int]:
    """``frames`` sorted, or ``max_frames`` of them evenly spaced (first and last included)."""
    frames = sorted(int(f) for f in frames)
    if max_frames is None or len(frames) <= max_frames:
        return frames
    if max_frames < 1:
        raise ValueError(f"max_frames must be >= 1, got {max_frames}")
    idx = np.unique(np.round(np.linspace(0, len(frames) - 1, max_frames)).astype(int))
    return [frames[i] for i in idx]


def _agent_masks(bundle, agent_masks) -> tuple[np.ndarray | None, str]:
    if agent_masks is not None:
        return np.asarray(agent_masks, bool), "argument"
    gt = bundle.gt
    masks = gt.dynamic_masks if gt is not None else None
    if masks is not None:
        return masks, "gt_dynamic_masks"
    return None, "none"


def fit_image(img: torch.Tensor, height: int, width: int, mode: str = "area") -> torch.Tensor:
    """[h, w, C] -> [height, width, C] (``area`` for images, ``nearest`` for masks); unchanged when it fits."""
    if tuple(img.shape[:2]) == (height, width):
        return img
    x = img.permute(2, 0, 1)[None].float()
    return torch.nn.functional.interpolate(x, size=(height, width), mode=mode)[0].permute(1, 2, 0)


def held_out_overrides(graph, train_frames: Sequence[int], frame: int,
                       agent_tables: list | None = None) -> tuple[torch.Tensor, dict, dict]:
    """(world_from_camera [4, 4], agent_poses {track id: [4, 4]}, agent_valid {track id: bool}) at ``frame``,
    interpolated from the refined poses of ``train_frames``."""
    with torch.no_grad():
        cams = graph.camera.world_from_camera().detach()  # [T, 4, 4]
    cam = interpolate_camera(cams, train_frames, frame)
    poses, valid = {}, {}
    for ids, wfb, ok in agent_tables if agent_tables is not None else agent_pose_tables(graph):
        p, v = interpolate_agents(wfb, ok, train_frames, frame)
        for j, tid in enumerate(ids):
            poses[tid], valid[tid] = p[j], bool(v[j])
    return cam, poses, valid


def agent_pose_tables(graph) -> list[tuple[list[int], torch.Tensor, torch.Tensor]]:
    """Per agent node: (track ids [K], refined world_from_box [T, K, 4, 4], valid [T, K])."""
    out = []
    with torch.no_grad():
        for node in graph.agent_nodes():
            wfb = torch.stack([node.world_from_box(i).detach() for i in range(node.num_frames)])
            out.append((node.track_ids.tolist(), wfb, node.valid.clone()))
    return out


def evaluate(graph, bundle, test_frames: Sequence[int], train_frames: Sequence[int], *, agent_masks=None,
             lpips: Lpips | None = None, max_frames: int | None = None, images=None) -> dict:
    """Novel-view metrics of ``graph`` on the held-out ``test_frames`` of ``bundle`` (see the module docstring):
    ``psnr`` is the mean over frames of per-frame PSNR, ``psnr_agents`` the PSNR of all agent pixels pooled.

    ``max_frames`` caps the number of test frames (evenly spaced); ``lpips`` defaults to ``Lpips()`` (the
    ``AGG_LPIPS_WEIGHTS`` file, or None with a note). ``images`` [T, H, W, 3] (float in [0, 1] or uint8) are the
    frames to compare with, e.g. the training-resolution frames; by default the bundle's. Frames and masks of
    another size than the graph's render are resampled to it (area for frames, nearest for masks)."""
    if bundle.num_frames != graph.num_frames:
        raise ValueError(f"bundle has {bundle.num_frames} frames, graph {graph.num_frames}")
    frames = pick_frames(test_frames, max_frames)
    train = sorted(int(f) for f in train_frames)
    if not frames:
        raise ValueError("no test frames")
    lpips = lpips if lpips is not None else Lpips()
    masks, source = _agent_masks(bundle, agent_masks)
    tables = agent_pose_tables(graph)
    device = graph.K.device

    was_training = graph.training
    graph.eval()
    renders, render_s = [], 0.0
    try:
        with torch.no_grad():
            cam, poses, valid = held_out_overrides(graph, train, frames[0], tables)
            graph.render(frames[0], world_from_camera=cam, agent_poses=poses, agent_valid=valid)  # warm-up
            for frame in frames:
                cam, poses, valid = held_out_overrides(graph, train, frame, tables)
                synchronize(device)
                t0 = time.perf_counter()
                out = graph.render(frame, world_from_camera=cam, agent_poses=poses, agent_valid=valid)
                synchronize(device)
                render_s += time.perf_counter() - t0
                renders.append(out.color.detach().clamp(0.0, 1.0).cpu())  # [H, W, 3]
            n_gaussians = int(graph.compose(frames[0])["means"].shape[0])
    finally:
        graph.train(was_training)

    per_frame = []
    sse = n_err = 0.0
    ssum = n_ssim = 0.0
    height, width = renders[0].shape[:2]
    scene = scene_pixels(bundle, width, height)  # [H, W] bool, or None: every pixel is scored
    for frame, pred in zip(frames, renders):
        gt = as_image(images[frame] if images is not None else bundle.frame(frame))
        gt = fit_image(gt, height, width, "area")  # [H, W, 3] float in [0, 1]
        seen = with_ego_from(gt, pred, scene)  # [H, W, 3] the render, with the frame's own ego pixels
        row = {"frame": frame, "psnr": psnr(pred, gt, scene), "ssim": ssim(seen, gt, scene),
               "lpips": lpips(seen, gt), "psnr_agents": None, "ssim_agents": None, "agent_pixels": None,
               "pixels": height * width if scene is None else int(scene.sum())}
        if masks is not None:
            m = fit_image(torch.as_tensor(np.array(masks[frame], bool))[..., None], height, width, "nearest")
            m = m[..., 0].numpy() > 0.5  # [H, W]
            if scene is not None:
                m &= scene.numpy()
            row["agent_pixels"] = int(m.sum())
            if m.any():
                e, n = squared_error(pred, gt, m)
                sse, n_err = sse + e, n_err + n
                row["psnr_agents"] = psnr_from_mse(e / n)
                s, n = ssim_sum(seen, gt, m)
                ssum, n_ssim = ssum + s, n_ssim + n
                row["ssim_agents"] = s / n
        per_frame.append(row)

    lp = [r["lpips"] for r in per_frame]
    return {
        "psnr": float(np.mean([r["psnr"] for r in per_frame])),
        "ssim": float(np.mean([r["ssim"] for r in per_frame])),
        "lpips": float(np.mean(lp)) if lpips.available else None,
        "psnr_agents": psnr_from_mse(sse / n_err) if n_err else None,
        "ssim_agents": ssum / n_ssim if n_ssim else None,
        "split": "nvs",
        "n_test_frames": len(frames),
        "render_fps": len(frames) / max(render_s, 1e-9),
        "n_gaussians": n_gaussians,
        "n_agents": int(sum(n.num_instances for n in graph.agent_nodes())),
        "ego_pixel_share": 0.0 if scene is None else float(1.0 - scene.float().mean()),
        "per_frame": per_frame,
        "agent_mask_source": source,
        "lpips_note": lpips.note,
    }
