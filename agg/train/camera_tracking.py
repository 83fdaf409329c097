"""Camera tracking: pose-only refinement of every training camera against the current map, coarse to fine.

The camera node's ordinary update is one Adam step on the frame rendered at that iteration, so a pose moves
about one learning rate per visit, and each frame is visited once every ``len(train_frames)`` iterations. At the
balanced preset that is a few centimetres over the whole run, against prior errors of up to a metre (the paper's
1.0 m stress test): on the synthetic suite (seed 0) the mean camera-centre error fell from 0.395 m to 0.378 m in
700 iterations. At 30x the per-step rate it was 0.31 m after 400 iterations, with training PSNR 2–3 dB lower,
because the map is refitted after every jump (docs/TRAINING.md).

So at a few milestones (``TrackingConfig.at``, at the paper's 30k-iteration scale) the trainer freezes every
Gaussian and runs a short tracking optimisation of the camera corrections alone, as a SLAM front end tracks
against its map:

- every training frame is rendered through its current pose and compared with its image, with the loss of a
  Tick step: L_photo, plus Eq. 3's background-attention term when the semantic loss is on (the camera follows
  the static scene, not the agents);
- coarse to fine: the render and the image are at ``1/level`` of the training size for each level in ``levels``
  (intrinsics scaled), which widens the basin of the photometric alignment from pixels to ``level`` pixels;
- one fresh Adam over the node's ``omega`` and ``tau`` (element-wise, so the frames are independent problems that
  share one step), ``steps`` steps per level; the rates are ``lr_translation x scene extent`` and
  ``lr_rotation`` radians, halved at each finer level;
- ``rotation_from`` (default 0) makes the levels before it move the centres alone: a sideways centre error looks
  much like a turn to the photometric loss, and a round that may turn from its first step can take it up as yaw
  (docs/TRAINING.md, "Yaw for a sideways error");
- ``gate`` (off by default) keeps a frame's new pose only where the round lowered its loss at the training size,
  and puts every other frame back: from good priors an ungated round moves the cameras away from the truth (most
  of it the coarse levels' splatting, below), and from a metre off the gate holds back the corrections as well
  (docs/TRAINING.md, "The tracking gate");
- ``render_full`` (the default) makes a coarse level splat at the training size and area-average the render,
  as the targets are averaged: splatted at the level's size, every Gaussian is dilated by the projection's 0.3 px^2
  at that size, so a map's sub-pixel Gaussians grow against the image and the coarse loss has its optimum
  elsewhere than the full-size one (docs/TRAINING.md, "Coarse levels that blur the full-size render");
- frame 0 stays fixed (the gauge) and held-out frames are never rendered, so their corrections are untouched;
- a cancellation between two steps puts the corrections back as they were before the round, so a resumed run
  tracks the round again from the same state.

Tracking only happens where the camera trains: in the warm-up, a Tick or the joint phase (never in a Tock), and
with Tick-Tock ablated at the same milestones. It does not touch the Gaussians, the densifier statistics or the
topology accumulators.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable, Sequence

import torch
from torch import Tensor

from agg.eval.ego import with_ego_from
from agg.eval.nvs import fit_image
from agg.io.video import intrinsics_at, scale_intrinsics
from agg.train.losses import photometric_loss, semantic_attention_loss


@dataclass(frozen=True)
class TrackingConfig:
    at: tuple[int, ...] = (2_500, 5_000, 10_000)  # paper-scale iterations (scaled like the milestones)
    levels: tuple[int, ...] = (4, 2, 1)  # downscale factors, coarse to fine, ending at the training size
    steps: int = 20  # Adam steps per level
    lr_translation: float = 2e-3  # x scene extent, per step at the coarsest level
    lr_rotation: float = 2e-3  # radians per step at the coarsest level
    rotation_from: int = 0  # the first level (index into levels) whose steps turn the cameras: the levels
    # before it move the centres alone (0: every level turns them)
    gate: bool = False  # a frame keeps the round's pose only if its loss at the training size went down; else it
    # goes back to the pose it had before the round
    render_full: bool = True  # a coarse level renders at the training size and area-averages the render to the
    # level's size (the full-size render blurred, as the targets are) instead of splatting at the level's size

    def scaled(self, scale: float) -> "TrackingConfig":
        return replace(self, at=tuple(max(1, int(round(a * scale))) for a in self.at))


def level_size(width: int, height: int, level: int) -> tuple[int, int]:
    """(w, h) of a tracking level: the training size divided by ``level``, at least 8 pixels."""
    return max(8, width // level), max(8, height // level)


def level_inputs(graph, images: Tensor, attention: Tensor | None, frames: Sequence[int], level: int):
    """(targets, maps, intrinsics) of one tracking level, each a dict frame -> tensor: the image [h, w, 3], M_bg
    [h, w] (maps is None without ``attention``) and K [3, 3], at ``level_size`` of the graph's training size."""
    width, height = graph.width, graph.height
    w, h = level_size(width, height, level)
    targets = {f: fit_image(images[f], h, w) for f in frames}  # [h, w, 3] each
    maps = ({f: fit_image(attention[f][..., None], h, w)[..., 0] for f in frames}
            if attention is not None else None)
    intrinsics = {}  # frame -> [3, 3] at this level
    for f in frames:
        k = intrinsics_at(graph.K, f)
        k_level = scale_intrinsics(k.detach().cpu().numpy(), (width, height), (w, h))
        intrinsics[f] = torch.as_tensor(k_level, dtype=k.dtype, device=k.device)
    return targets, maps, intrinsics


def level_weight(weight: Tensor | None, graph, level: int) -> Tensor | None:
    """[h, w] at a tracking level (``level_size``): 1 where every training pixel under the level's pixel has
    weight 1 in ``weight`` [H, W] (``TrainData.scene_weight``), else 0; None without one."""
    if weight is None:
        return None
    w, h = level_size(graph.width, graph.height, level)
    return (fit_image(weight[..., None], h, w)[..., 0] >= 1.0 - 1e-6).float()


def frame_loss(graph, frame: int, target: Tensor, attention: Tensor | None, K: Tensor, ssim_weight: float = 0.2,
               lambda_sem: float = 0.8, delta: float = 1e-6, render_size: tuple[int, int] | None = None,
               weight: Tensor | None = None) -> Tensor:
    """A tracking step's loss of one frame rendered through its current camera at ``target``'s size: L_photo,
    plus Eq. 3 with ``attention`` (M_bg) when given. target [h, w, 3]; attention [h, w]; K [3, 3] at the render's
    size: ``target``'s, or ``render_size`` (w, h), whose render is area-averaged to ``target``'s size; weight
    [h, w]: 0 on the ego vehicle's pixels (``level_weight``), left out of both terms, or None."""
    h, w = target.shape[:2]
    rw, rh = render_size if render_size is not None else (w, h)
    color = graph.render(frame, K=K, width=rw, height=rh).color  # [rh, rw, 3]
    color = with_ego_from(target, fit_image(color, h, w), weight)  # [h, w, 3]
    loss = photometric_loss(color, target, ssim_weight if min(w, h) >= 11 else 0.0, weight)
    if attention is not None:
        loss = loss + semantic_attention_loss(color, target, attention, lambda_sem, delta)
    return loss


def full_size_losses(graph, frames: Sequence[int], inputs, ssim_weight: float, lambda_sem: float,
                     delta: float, weight: Tensor | None = None) -> list[float]:
    """Each frame's ``frame_loss`` [F] through its current camera, no gradient; ``inputs`` is ``level_inputs``'s
    (targets, maps, intrinsics); ``weight`` [H, W] L_photo's pixel weight or None."""
    targets, maps, intrinsics = inputs
    with torch.no_grad():
        return [float(frame_loss(graph, f, targets[f], None if maps is None else maps[f], intrinsics[f],
                                 ssim_weight, lambda_sem, delta, weight=weight)) for f in frames]


def track_cameras(graph, images: Tensor, frames: Sequence[int], config: TrackingConfig, extent: float, *,
                  attention: Tensor | None = None, ssim_weight: float = 0.2, lambda_sem: float = 0.8,
                  delta: float = 1e-6, should_stop: Callable[[], bool] | None = None,
                  on_step: Callable[[int, int], None] | None = None, weight: Tensor | None = None) -> dict | None:
    """Refine ``graph.camera``'s corrections of ``frames`` against the frozen map; returns a report (the mean
    loss of the first and last step of each level). images [T, H, W, 3]; attention [T, H, W] (M_bg) or None;
    weight [H, W] L_photo's pixel weight (``TrainData.scene_weight``: 0 on the ego vehicle) or None.

    ``should_stop()`` is asked before every step; once it is True the corrections are put back as they were
    before the round and None is returned (the round can be run again from the start, e.g. after a resume).
    ``on_step(done, total)`` is called after every step: ``done`` of the round's ``len(levels) x steps``.
    The caller freezes the Gaussians (``requires_grad`` False); only ``omega`` and ``tau`` get gradients here."""
    cam = graph.camera
    params = [cam.omega, cam.tau]
    before = [p.detach().clone() for p in params]
    for p in params:
        p.requires_grad_(True)
    opt = torch.optim.Adam([{"params": [cam.omega], "lr": config.lr_rotation},
                            {"params": [cam.tau], "lr": config.lr_translation * extent}], eps=1e-15)
    report = {"levels": [], **({"render_full": True} if config.render_full else {})}
    full = level_inputs(graph, images, attention, frames, 1) if config.gate or config.render_full else None
    if config.gate:
        loss_before = full_size_losses(graph, frames, full, ssim_weight, lambda_sem, delta, weight)  # [F]
    for li, level in enumerate(config.levels):
        factor = 0.5 ** li
        opt.param_groups[0]["lr"] = config.lr_rotation * factor
        cam.omega.requires_grad_(li >= config.rotation_from)  # a centre-only level leaves omega without a gradient
        opt.param_groups[1]["lr"] = config.lr_translation * extent * factor
        targets, maps, intrinsics = level_inputs(graph, images, attention, frames, level)
        pixel_weight = level_weight(weight, graph, level)  # [h, w] or None
        render_size = None
        if config.render_full and level_size(graph.width, graph.height, level) != (graph.width, graph.height):
            render_size = (graph.width, graph.height)  # splat at the training size, compare blurred
            intrinsics = full[2]  # frame -> [3, 3] at that size
        first = last = 0.0
        for step in range(config.steps):
            if should_stop is not None and should_stop():
                with torch.no_grad():
                    for p, b in zip(params, before):
                        p.copy_(b)
                        p.grad = None
                return None
            opt.zero_grad(set_to_none=True)
            total = 0.0
            for f in frames:
                loss = frame_loss(graph, f, targets[f], None if maps is None else maps[f], intrinsics[f],
                                  ssim_weight, lambda_sem, delta, render_size, pixel_weight)
                loss.backward()
                total += float(loss.detach())
            opt.step()
            if on_step is not None:
                on_step(li * config.steps + step + 1, len(config.levels) * config.steps)
            mean = total / max(len(frames), 1)
            first = mean if step == 0 else first
            last = mean
        report["levels"].append({"level": level, "loss_first": first, "loss_last": last})
    opt.zero_grad(set_to_none=True)
    if config.gate:
        loss_after = full_size_losses(graph, frames, full, ssim_weight, lambda_sem, delta, weight)  # [F]
        back = [f for f, a, b in zip(frames, loss_after, loss_before) if not a < b]  # frames put back
        with torch.no_grad():
            for p, b in zip(params, before):
                p[back] = b[back]
        kept = [min(a, b) for a, b in zip(loss_after, loss_before)]
        report["gate"] = {"frames_kept": len(frames) - len(back), "frames": len(frames),
                          "loss_before": sum(loss_before) / max(len(frames), 1),
                          "loss_after": sum(kept) / max(len(frames), 1)}
    cam.omega.requires_grad_(True)  # trainable at the end, as at the start, whatever rotation_from did
    return report
