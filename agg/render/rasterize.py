"""``rasterize``: the single functional entry point of the Gaussian renderer.

One camera per call. Projection and SH run in torch autograd; compositing runs on one of three backends:

- ``cpu``: native C++/OpenMP tile compositor (agg/render/csrc), built on first use and cached.
- ``cuda``: gsplat (``pip install gsplat``), for CUDA tensors.
- ``torch``: the plain-PyTorch reference (tests, tiny images, last resort).

``backend="auto"`` picks ``cuda`` for CUDA tensors when gsplat imports, else ``cpu``; if the native build fails it
falls back to ``torch`` with a warning. ``AGG_RENDER_BACKEND`` overrides ``auto``.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass

import torch
from torch import Tensor

from agg.render.projection import camera_center, invert_rigid, project_gaussians
from agg.render.sh import eval_sh, sh_degree_from_coeffs

log = logging.getLogger(__name__)
BACKENDS = ("auto", "cpu", "cuda", "torch")


@dataclass
class RenderMeta:
    """Per-Gaussian screen-space data of one render (N = number of input Gaussians)."""

    means2d: Tensor  # [N, 2] px; in the autograd graph: call .retain_grad() before backward to read dL/dmeans2d
    radii: Tensor  # [N, 2] int32 half extents (x, y) in px; 0 where culled
    visible: Tensor  # [N] bool
    depths: Tensor  # [N] camera z, metres
    conics: Tensor  # [N, 3] inverse 2D covariances (cpu/torch backends; gsplat's own on cuda)
    backend: str  # the backend that ran


@dataclass
class RenderOutput:
    color: Tensor  # [H, W, C]
    depth: Tensor  # [H, W] expected depth: sum_i w_i z_i / alpha (0 where alpha = 0), metres
    alpha: Tensor  # [H, W] accumulated opacity in [0, 1]
    meta: RenderMeta


def rasterize(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor | None = None,
    *,
    sh: Tensor | None = None,
    K: Tensor,
    width: int,
    height: int,
    viewmat: Tensor | None = None,
    world_from_camera: Tensor | None = None,
    near: float = 0.01,
    far: float = 1.0e10,
    background: Tensor | float | None = None,
    backend: str = "auto",
) -> RenderOutput:
    """Render 3D Gaussians into one pinhole camera.

    Args:
        means: [N, 3] centres in world coordinates (metres).
        quats: [N, 4] rotations, wxyz; any norm (normalised here; a zero quaternion acts as identity).
        scales: [N, 3] standard deviations along the local axes, linear (not log), metres.
        opacities: [N] in [0, 1] (not logits).
        colors: [N, C] per-Gaussian values for any C (RGB, features, one-hot instance ids, ...). Give exactly one
            of ``colors`` and ``sh``.
        sh: [N, K, 3] SH coefficients, K = (d+1)^2 with degree d in 0..3; colour = max(SH(dir) + 0.5, 0).
        K: [3, 3] pinhole intrinsics in pixels (OpenCV: the top-left pixel's centre is (0, 0)).
        width, height: image size in pixels (>= 1).
        viewmat: [4, 4] camera_from_world (world-to-camera, OpenCV axes). Give exactly one of ``viewmat`` and
            ``world_from_camera``.
        world_from_camera: [4, 4] camera-to-world pose; inverted here (differentiably).
        near, far: clipping planes on camera z, metres.
        background: [C] or scalar composited behind the Gaussians: color = accum + (1 - alpha) * background.
        backend: "auto" | "cpu" | "cuda" | "torch".

    Returns:
        RenderOutput with color [H, W, C], depth [H, W], alpha [H, W] and per-Gaussian meta.
        Differentiable w.r.t. means, quats, scales, opacities, colors / sh, and the camera pose.
    """
    means, quats, scales, opacities, colors, sh, K, viewmat = _check_inputs(
        means, quats, scales, opacities, colors, sh, K, width, height, viewmat, world_from_camera, near, far
    )
    chosen = _choose_backend(backend, means)
    if chosen == "cuda":
        from agg.render.raster_gsplat import rasterize_gsplat

        return rasterize_gsplat(means, quats, scales, opacities, colors, sh, K, width, height, viewmat, near, far,
                                background)

    if chosen == "cpu" and means.dtype == torch.float32:
        from agg.render.project_cpu import project_gaussians_cpu as project
    else:
        project = project_gaussians
    proj = project(means, quats, scales, opacities, viewmat, K, width, height, near, far)
    if sh is not None:
        colors = eval_sh(sh, means - camera_center(viewmat))  # [N, 3]
    C = colors.shape[-1]
    # Depth rides along as one more channel: accum[..., C] = sum_i w_i z_i.
    values = torch.cat([colors, proj.depths.unsqueeze(-1)], dim=-1)  # [N, C + 1]
    if chosen == "cpu":
        from agg.render.raster_cpu import composite_cpu as composite
    else:
        from agg.render.raster_torch import composite_torch as composite
    accum, alpha = composite(proj.means2d, proj.conics, values, opacities, proj.depths, proj.visible, width, height)
    color = accum[..., :C]
    depth = accum[..., C] / alpha.clamp_min(1e-10)
    if background is not None:
        bg = torch.as_tensor(background, dtype=color.dtype, device=color.device)
        color = color + (1.0 - alpha).unsqueeze(-1) * bg
    meta = RenderMeta(proj.means2d, proj.radii, proj.visible, proj.depths, proj.conics, chosen)
    return RenderOutput(color=color, depth=depth, alpha=alpha, meta=meta)


def _choose_backend(backend: str, means: Tensor) -> str:
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    explicit = backend != "auto"
    if not explicit:
        backend = os.environ.get("AGG_RENDER_BACKEND", "auto")
        if backend not in BACKENDS:
            raise ValueError(f"AGG_RENDER_BACKEND must be one of {BACKENDS}, got {backend!r}")
    if backend == "auto":
        if means.is_cuda:
            try:
                import gsplat  # noqa: F401

                return "cuda"
            except ImportError:
                log.warning("gsplat is not installed: rendering CUDA tensors with the slow torch backend")
                return "torch"
        from agg.render import native

        try:
            native.load()
            return "cpu"
        except native.NativeBuildError as exc:
            log.warning("%s; falling back to the slow torch backend", exc)
            return "torch"
    if backend == "cpu" and means.device.type != "cpu":
        raise ValueError(f"the cpu backend needs CPU tensors, got {means.device}")
    if backend == "cuda" and not means.is_cuda:
        raise ValueError(f"the cuda backend needs CUDA tensors, got {means.device}")
    return backend


def _check_inputs(means, quats, scales, opacities, colors, sh, K, width, height, viewmat, world_from_camera, near,
                  far):
    if int(width) < 1 or int(height) < 1:
        raise ValueError(f"image size must be at least 1x1, got {width}x{height}")
    if not 0 < near < far:
        raise ValueError(f"need 0 < near < far, got near={near}, far={far}")
    N = means.shape[0]
    if means.shape != (N, 3) or quats.shape != (N, 4) or scales.shape != (N, 3) or opacities.shape != (N,):
        raise ValueError(
            f"expected means [N,3], quats [N,4], scales [N,3], opacities [N]; got {tuple(means.shape)}, "
            f"{tuple(quats.shape)}, {tuple(scales.shape)}, {tuple(opacities.shape)}"
        )
    if (colors is None) == (sh is None):
        raise ValueError("give exactly one of colors [N, C] and sh [N, K, 3]")
    if colors is not None and (colors.dim() != 2 or colors.shape[0] != N):
        raise ValueError(f"colors must be [N, C] with N={N}, got {tuple(colors.shape)}")
    if sh is not None:
        if sh.dim() != 3 or sh.shape[0] != N or sh.shape[2] != 3:
            raise ValueError(f"sh must be [N, K, 3] with N={N}, got {tuple(sh.shape)}")
        sh_degree_from_coeffs(sh.shape[1])
    if (viewmat is None) == (world_from_camera is None):
        raise ValueError("give exactly one of viewmat (camera_from_world) and world_from_camera")
    if viewmat is None:
        if world_from_camera.shape != (4, 4):
            raise ValueError(f"world_from_camera must be [4, 4], got {tuple(world_from_camera.shape)}")
        viewmat = invert_rigid(world_from_camera)
    if viewmat.shape != (4, 4):
        raise ValueError(f"viewmat must be [4, 4], got {tuple(viewmat.shape)}")
    if K.shape != (3, 3):
        raise ValueError(f"K must be [3, 3], got {tuple(K.shape)}")
    if not (float(K[0, 0]) > 0 and float(K[1, 1]) > 0):
        raise ValueError("K must have fx > 0 and fy > 0")
    dtype, device = means.dtype, means.device
    cast = lambda t: None if t is None else t.to(device=device, dtype=dtype)  # noqa: E731
    return (means, cast(quats), cast(scales), cast(opacities), cast(colors), cast(sh), cast(K), cast(viewmat))
