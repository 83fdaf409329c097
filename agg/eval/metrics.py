"""Image quality metrics: PSNR, SSIM (full image or inside a mask) and LPIPS from local weights only.

Images are float RGB in [0, 1], HWC (``[H, W, C]`` tensors or arrays); masks are ``[H, W]`` bool. A masked metric
of an empty mask is ``None``.

- **PSNR** ``= 10 log10(1 / MSE)`` over every channel of the (masked) pixels, with the MSE floored at 1e-10, so
  identical images score 100 dB rather than infinity (the value must go into JSON).
- **SSIM** is kornia's SSIM map (11 x 11 Gaussian window, sigma 1.5, ``same`` padding) averaged over the pixels
  and channels (inside the mask for the masked variant).
- **LPIPS** (Zhang et al. 2018, v0.1) is computed only from weights on local disk: ``Lpips(path)`` or the
  ``AGG_LPIPS_WEIGHTS`` environment variable. Nothing is ever downloaded; without weights ``Lpips`` reports
  ``None`` and a reason string (``.note``). Accepted files:

  * a TorchScript module (``torch.jit.save``) or a ``torch.export`` program (``torch.export.save``, .pt2)
    called as ``module(x0, x1)`` on ``[B, 3, H, W]`` images in [-1, 1] and returning the distance (``[B]`` or
    ``[B, 1, 1, 1]``);
  * a state dict of the ``lpips`` package's model (``torch.save(lpips.LPIPS(net="alex").state_dict(), f)``,
    keys ``net.sliceN.*`` and ``linN.model.1.weight``), AlexNet or VGG16 trunk, detected from the tensors;
  * a torchvision AlexNet / VGG16 state dict (``features.*`` keys, e.g. ``alexnet-owt-7be5be79.pth``), with the
    linear calibration layers from ``lin_weights`` / ``AGG_LPIPS_LIN_WEIGHTS``, or else from the ``weights/v0.1``
    file that the ``lpips`` package ships when that package is installed (found without importing it, as it
    needs torchvision).

  The trunk is rebuilt here in plain torch (torchvision's layer layout), so torchvision is not needed.
"""

from __future__ import annotations

import importlib.util
import os
import warnings
import zipfile
from pathlib import Path

import numpy as np
import torch
from kornia.metrics import ssim as kornia_ssim
from torch import Tensor, nn

MIN_MSE = 1e-10  # PSNR ceiling of 100 dB
SSIM_WINDOW = 11


def as_image(x) -> Tensor:
    """Float tensor of an image array or tensor; uint8 is scaled to [0, 1]."""
    t = torch.as_tensor(np.array(x) if not isinstance(x, Tensor) else x)
    if t.dtype == torch.uint8:
        t = t.float() / 255.0
    return t.float()


def _pair(pred, gt) -> tuple[Tensor, Tensor]:
    p, g = as_image(pred), as_image(gt)
    if p.shape != g.shape or p.ndim != 3:
        raise ValueError(f"pred and gt must share an [H, W, C] shape, got {tuple(p.shape)} and {tuple(g.shape)}")
    return p, g.to(p.device)


def _mask(mask, shape, device) -> Tensor | None:
    if mask is None:
        return None
    m = torch.as_tensor(np.array(mask) if not isinstance(mask, Tensor) else mask).to(device=device,
                                                                                     dtype=torch.bool)
    if m.shape != shape[:2]:
        raise ValueError(f"mask must be [H, W] = {tuple(shape[:2])}, got {tuple(m.shape)}")
    return m


def squared_error(pred, gt, mask=None) -> tuple[float, int]:
    """(sum of squared errors, number of values) over the (masked) pixels and all channels, for pooling."""
    p, g = _pair(pred, gt)
    m = _mask(mask, p.shape, p.device)
    err = (p - g) ** 2  # [H, W, C]
    if m is not None:
        err = err[m]  # [M, C]
    return float(err.double().sum()), int(err.numel())


def psnr_from_mse(mse: float) -> float:
    """PSNR in dB of a mean squared error on [0, 1] images (MSE floored at ``MIN_MSE``)."""
    return float(10.0 * np.log10(1.0 / max(float(mse), MIN_MSE)))


def psnr(pred, gt, mask=None) -> float | None:
    """PSNR of ``pred`` vs ``gt`` [H, W, C]; inside ``mask`` [H, W] when given (None when it is empty)."""
    sse, n = squared_error(pred, gt, mask)
    return None if n == 0 else psnr_from_mse(sse / n)


def ssim_map(pred, gt) -> Tensor:
    """[H, W, C] SSIM map (kornia, 11 x 11 Gaussian window, ``same`` padding)."""
    p, g = _pair(pred, gt)
    m = kornia_ssim(p.permute(2, 0, 1)[None], g.permute(2, 0, 1)[None], SSIM_WINDOW, max_val=1.0)  # [1, C, H, W]
    return m[0].permute(1, 2, 0)


def ssim_sum(pred, gt, mask=None) -> tuple[float, int]:
    """(sum of the SSIM map, number of values) over the (masked) pixels and all channels, for pooling."""
    s = ssim_map(pred, gt)
    m = _mask(mask, s.shape, s.device)
    if m is not None:
        s = s[m]
    return float(s.double().sum()), int(s.numel())


def ssim(pred, gt, mask=None) -> float | None:
    """Mean SSIM of ``pred`` vs ``gt`` [H, W, C]; the map averaged inside ``mask`` when given (None if empty)."""
    total, n = ssim_sum(pred, gt, mask)
    return None if n == 0 else total / n


# ---- LPIPS -------------------------------------------------------------------------------------------------------

# torchvision's feature layers: (kind, in, out, kernel, stride, padding) for convs, ("relu",), ("pool", k, s)
_ALEX = [("conv", 3, 64, 11, 4, 2), ("relu",), ("pool", 3, 2), ("conv", 64, 192, 5, 1, 2), ("relu",),
         ("pool", 3, 2), ("conv", 192, 384, 3, 1, 1), ("relu",), ("conv", 384, 256, 3, 1, 1), ("relu",),
         ("conv", 256, 256, 3, 1, 1), ("relu",)]
_VGG_CH = [(3, 64), (64, 64), "M", (64, 128), (128, 128), "M", (128, 256), (256, 256), (256, 256), "M",
           (256, 512), (512, 512), (512, 512), "M", (512, 512), (512, 512), (512, 512)]
_VGG = [layer for c in _VGG_CH for layer in
        ([("pool", 2, 2)] if c == "M" else [("conv", c[0], c[1], 3, 1, 1), ("relu",)])]
# LPIPS taps: the outputs of these feature layers (relu1 .. relu5), and their channels
_TRUNKS = {"alex": (_ALEX, [1, 4, 7, 9, 11], [64, 192, 384, 256, 256]),
           "vgg": (_VGG, [3, 8, 15, 22, 29], [64, 128, 256, 512, 512])}


class LpipsNet(nn.Module):
    """LPIPS v0.1: scaled input, trunk features at five taps, unit-normalised over channels, squared
    difference, a learned 1 x 1 linear layer per tap, spatial mean, summed over taps."""

    def __init__(self, trunk: str = "alex"):
        super().__init__()
        layers, self.taps, chans = _TRUNKS[trunk]
        mods: list[nn.Module] = []
        for spec in layers:
            if spec[0] == "conv":
                mods.append(nn.Conv2d(spec[1], spec[2], spec[3], stride=spec[4], padding=spec[5]))
            elif spec[0] == "relu":
                mods.append(nn.ReLU())
            else:
                mods.append(nn.MaxPool2d(spec[1], spec[2]))
        self.features = nn.Sequential(*mods)
        self.lins = nn.ModuleList([nn.Conv2d(c, 1, 1, bias=False) for c in chans])
        self.register_buffer("shift", torch.tensor([-0.030, -0.088, -0.188])[None, :, None, None])
        self.register_buffer("scale", torch.tensor([0.458, 0.448, 0.450])[None, :, None, None])

    def _taps(self, x: Tensor) -> list[Tensor]:
        out = []
        for i, layer in enumerate(self.features):
            x = layer(x)
            if i in self.taps:
                out.append(x)
            if i == self.taps[-1]:
                break
        return out

    def forward(self, x0: Tensor, x1: Tensor) -> Tensor:
        """[B] distances of [B, 3, H, W] images in [-1, 1]."""
        f0 = self._taps((x0 - self.shift) / self.scale)
        f1 = self._taps((x1 - self.shift) / self.scale)
        total = 0.0
        for a, b, lin in zip(f0, f1, self.lins):
            a = a / (a.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            b = b / (b.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            total = total + lin((a - b) ** 2).mean((2, 3))  # [B, 1]
        return total[:, 0]

    def load_weights(self, trunk_state: dict[str, Tensor], lin_state: dict[str, Tensor]) -> None:
        """Load a trunk in torchvision layout (``features.i.*``) and lpips lin layers (``linN.model.1.weight``)."""
        state = {k: v for k, v in trunk_state.items() if k.startswith("features.")}
        for n in range(len(self.lins)):
            key = next((k for k in (f"lin{n}.model.1.weight", f"lin{n}.model.0.weight") if k in lin_state), None)
            if key is None:
                raise ValueError(f"LPIPS linear weights lack lin{n}")
            state[f"lins.{n}.weight"] = lin_state[key]
        state["shift"], state["scale"] = self.shift, self.scale
        self.load_state_dict(state, strict=True)


def _lpips_layout_to_torchvision(state: dict[str, Tensor]) -> dict[str, Tensor]:
    """``net.sliceN.<i>.weight`` (the lpips package; i is the torchvision feature index) -> ``features.<i>.weight``."""
    out = {}
    for k, v in state.items():
        if k.startswith("net.slice"):
            _, _, idx, name = k.split(".", 3)
            out[f"features.{idx}.{name}"] = v
    return out


def _trunk_kind(features: dict[str, Tensor]) -> str:
    w = features.get("features.0.weight")
    if w is None:
        raise ValueError("no trunk weights (features.0.weight / net.slice1.0.weight) in the LPIPS file")
    return "alex" if tuple(w.shape[-2:]) == (11, 11) else "vgg"


def _shipped_lin(trunk: str) -> Path | None:
    spec = importlib.util.find_spec("lpips")
    if spec is None or not spec.submodule_search_locations:
        return None
    path = Path(list(spec.submodule_search_locations)[0]) / "weights" / "v0.1" / f"{trunk}.pth"
    return path if path.is_file() else None


def _archive_kind(path: Path) -> str:
    """"export" (a ``torch.export`` .pt2 archive), "torchscript" or "state_dict", from the zip's members."""
    try:
        with zipfile.ZipFile(path) as z:
            names = z.namelist()
    except zipfile.BadZipFile:
        return "state_dict"  # a legacy (non-zip) torch.save file
    if any(n.endswith("/archive_format") or n == "archive_format" for n in names):
        return "export"
    if any(n.endswith("/constants.pkl") for n in names):
        return "torchscript"
    return "state_dict"


def load_lpips(path: str | os.PathLike, lin_weights: str | os.PathLike | None = None) -> nn.Module:
    """An LPIPS module from a local file: a TorchScript module, a ``torch.export`` program (.pt2, traced at
    the resolution it will be called with), an lpips state dict, or a torchvision trunk + lin weights."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"LPIPS weights {path} not found")
    kind = _archive_kind(path)
    if kind == "export":
        return torch.export.load(str(path)).module()
    if kind == "torchscript":
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)  # torch.jit is deprecated but still loads
            return torch.jit.load(str(path), map_location="cpu").eval()
    state = torch.load(path, map_location="cpu", weights_only=True)
    if not isinstance(state, dict):
        raise ValueError(f"{path} is neither TorchScript nor a state dict")
    features = _lpips_layout_to_torchvision(state) or {k: v for k, v in state.items() if k.startswith("features.")}
    trunk = _trunk_kind(features)
    lin_state = state
    if not any(k.startswith("lin0.") for k in state):
        lin_path = lin_weights or os.environ.get("AGG_LPIPS_LIN_WEIGHTS") or _shipped_lin(trunk)
        if lin_path is None:
            raise ValueError(f"{path} holds only a {trunk} trunk: give the LPIPS linear layers "
                             "(lin_weights / AGG_LPIPS_LIN_WEIGHTS, or install the lpips package)")
        lin_state = torch.load(lin_path, map_location="cpu", weights_only=True)
    net = LpipsNet(trunk)
    net.load_weights(features, lin_state)
    return net.eval()


class Lpips:
    """LPIPS from local weights: ``Lpips(path)`` or ``AGG_LPIPS_WEIGHTS``; never downloads.

    ``.available`` says whether it computes; otherwise calls return None and ``.note`` says why. A configured file
    that cannot be loaded is reported in ``.note`` too (an evaluation should not fail on its last metric)."""

    def __init__(self, weights: str | os.PathLike | None = None, lin_weights: str | os.PathLike | None = None,
                 device: torch.device | str | None = None):
        self.net: nn.Module | None = None
        weights = weights or os.environ.get("AGG_LPIPS_WEIGHTS")
        if not weights:
            self.note = "LPIPS not computed: no local weights configured (set AGG_LPIPS_WEIGHTS)"
            return
        try:
            self.net = load_lpips(weights, lin_weights)
        except (OSError, ValueError, RuntimeError, KeyError) as e:
            self.note = f"LPIPS not computed: could not load {weights}: {e}"
            return
        if device is not None:
            self.net = self.net.to(device)
        self.note = f"LPIPS from {weights}"

    @property
    def available(self) -> bool:
        return self.net is not None

    @torch.no_grad()
    def __call__(self, pred, gt) -> float | None:
        """LPIPS distance of [H, W, 3] images in [0, 1] (None when unavailable)."""
        if self.net is None:
            return None
        p, g = _pair(pred, gt)
        dev = next(iter(self.net.parameters()), torch.empty(0)).device
        x0 = (p.permute(2, 0, 1)[None] * 2 - 1).to(dev)
        x1 = (g.permute(2, 0, 1)[None] * 2 - 1).to(dev)
        return float(self.net(x0, x1).reshape(-1)[0])
