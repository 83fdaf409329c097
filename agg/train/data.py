"""Training data of a bundle at the training resolution: frames, intrinsics, attention maps, the NVS split, and the
weight that leaves the ego vehicle's pixels out."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F  # noqa: N812
from torch import Tensor

from agg.eval.ego import scene_pixels
from agg.eval.interpolate import split_frames
from agg.io.bundle import SceneBundle
from agg.io.video import scale_intrinsics
from agg.train.semantic import attention_maps, semantic_gate


@dataclass
class TrainData:
    images: Tensor  # [T, H, W, 3] float32 in [0, 1], training resolution
    K: Tensor  # [T, 3, 3] intrinsics at the training resolution
    width: int
    height: int
    m_bg: Tensor | None  # [T, H, W] semantic attention (background channels)
    m_ag: Tensor | None  # [T, H, W] semantic attention (agent channels)
    train_frames: list[int]
    test_frames: list[int]
    semantic: dict | None = None  # semantic_gate's report (None: no attention maps, or not checked)
    scene_weight: Tensor | None = None  # [H, W] 1 on the scene's pixels, 0 on the ego vehicle's (agg.eval.ego;
    # None: the bundle has no ego mask): every loss weighs the pixels by it

    @property
    def num_frames(self) -> int:
        return int(self.images.shape[0])

    def to(self, device: torch.device | str) -> "TrainData":
        """The same data with its tensors on ``device`` (frames, intrinsics and attention maps)."""
        def move(x):
            return None if x is None else x.to(device)

        return TrainData(self.images.to(device), self.K.to(device), self.width, self.height, move(self.m_bg),
                         move(self.m_ag), list(self.train_frames), list(self.test_frames), self.semantic,
                         move(self.scene_weight))


def training_size(width: int, height: int, max_width: int) -> tuple[int, int, float]:
    """(w, h, factor): the bundle size scaled down (never up) so that w <= max_width."""
    f = min(1.0, max_width / width)
    return max(8, int(round(width * f))), max(8, int(round(height * f))), f


def resize_images(frames: np.ndarray, width: int, height: int) -> Tensor:
    """[T, h, w, 3] uint8 (0..255) or float (0..1) -> [T, height, width, 3] float32 in [0, 1] (area resampling
    when shrinking)."""
    a = np.asarray(frames)
    x = torch.as_tensor(a).float()
    if a.dtype == np.uint8:
        x = x.div_(255.0)
    x = x.permute(0, 3, 1, 2)  # [T, 3, h, w]
    if x.shape[-2:] != (height, width):
        x = F.interpolate(x, size=(height, width), mode="area")
    return x.permute(0, 2, 3, 1).contiguous()


def load_train_data(bundle: SceneBundle, max_width: int, attention_norm: str = "global",
                    eval_every: int = 5, min_contrast: float | None = None) -> TrainData:
    """The training frames, intrinsics and attention maps at the training size. With ``min_contrast`` the attention
    maps are checked against the priors' dynamic masks over the training frames (``semantic_gate``) and dropped
    when they do not separate them: the semantic loss is then off (``TrainData.semantic`` says why)."""
    w, h, _ = training_size(bundle.width, bundle.height, max_width)
    images = resize_images(bundle.frames[:], w, h)
    K = torch.as_tensor(np.stack([scale_intrinsics(k, (bundle.width, bundle.height), (w, h))  # noqa: N806
                                  for k in bundle.intrinsics]), dtype=torch.float32)  # [T, 3, 3]
    m_bg = m_ag = gate = None
    sem = bundle.semantics
    train, test = split_frames(bundle.num_frames, eval_every)
    if sem is not None:
        m_bg, m_ag = attention_maps(sem.features, sem.C_bg, sem.C_ag, h, w, attention_norm)
        masks = bundle.dynamic_masks
        if masks is not None:
            masks = torch.as_tensor(resize_depth(np.asarray(masks)[train], w, h) > 0.5)  # [T_train, h, w]
        gate = semantic_gate(m_bg[train], m_ag[train], masks, min_contrast)
        if not gate["active"]:
            m_bg = m_ag = None
    scene = scene_pixels(bundle, w, h)
    weight = None if scene is None else scene.float()  # [h, w]
    if weight is not None and m_bg is not None:  # Eq. 3 leaves the ego vehicle out too
        m_bg, m_ag = m_bg * weight, m_ag * weight
    return TrainData(images, K, w, h, m_bg, m_ag, train, test, gate, weight)


def resize_depth(depth: np.ndarray, width: int, height: int) -> np.ndarray:
    """[T, h, w] depth (0 = none) -> [T, height, width] float32, nearest (depth must not blend across edges)."""
    d = torch.as_tensor(np.array(depth, np.float32))[:, None]  # [T, 1, h, w]
    if d.shape[-2:] != (height, width):
        d = F.interpolate(d, size=(height, width), mode="nearest")
    return d[:, 0].numpy()
