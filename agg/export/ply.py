"""3D Gaussian Splatting PLY files (the layout of the original 3DGS code, which standard viewers open).

One ``vertex`` element, binary little endian, every property ``float``, in this order::

    x y z  nx ny nz  f_dc_0 f_dc_1 f_dc_2  f_rest_0 .. f_rest_{3(K-1)-1}  opacity  scale_0..2  rot_0..3

- ``nx ny nz`` are zeros (3DGS writes them and ignores them).
- ``f_dc_*``: the degree-0 SH coefficient of R, G, B. ``f_rest_*``: the K - 1 higher coefficients,
  *channel-major* as 3DGS flattens ``features_rest.transpose(1, 2)``: all of R's coefficients, then G's, then
  B's (``f_rest_{c (K-1) + j}`` = coefficient j + 1 of channel c).
- ``opacity``: logit of the opacity; ``scale_*``: natural log of the linear scales; ``rot_*``: the unit
  quaternion w, x, y, z.

``read_ply`` reads such a file back (any 3DGS-layout PLY with float/double properties, binary little endian)
and returns activated values: opacity through a sigmoid, scales through exp.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

OPACITY_EPS = 1e-6  # opacities are clamped to [eps, 1 - eps] before the logit
MIN_SCALE = 1e-12  # scales are clamped before the log
_PLY_TYPES = {"float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8", "uchar": "u1", "uint8": "u1",
              "char": "i1", "int8": "i1", "ushort": "<u2", "uint16": "<u2", "short": "<i2", "int16": "<i2",
              "uint": "<u4", "uint32": "<u4", "int": "<i4", "int32": "<i4"}


def _np(x, name: str, shape_tail: tuple[int, ...]) -> np.ndarray:
    a = x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)
    a = a.astype(np.float64)
    if a.shape[1:] != shape_tail:
        raise ValueError(f"{name} must be [N, {', '.join(map(str, shape_tail))}], got {a.shape}")
    return a


def property_names(num_sh: int) -> list[str]:
    """The vertex properties, in file order, for ``num_sh`` = K SH coefficients per channel."""
    return (["x", "y", "z", "nx", "ny", "nz"] + [f"f_dc_{i}" for i in range(3)]
            + [f"f_rest_{i}" for i in range(3 * (num_sh - 1))] + ["opacity"]
            + [f"scale_{i}" for i in range(3)] + [f"rot_{i}" for i in range(4)])


def write_ply(path: str | os.PathLike, means, quats, scales, opacities, sh) -> Path:
    """Write N Gaussians: ``means`` [N, 3], ``quats`` [N, 4] wxyz, ``scales`` [N, 3] linear, ``opacities`` [N] in
    (0, 1), ``sh`` [N, K, 3]. Quaternions are normalised; non-finite values are rejected."""
    means = _np(means, "means", (3,))
    n = len(means)
    quats = _np(quats, "quats", (4,))
    scales = _np(scales, "scales", (3,))
    opac = _np(torch.as_tensor(opacities).reshape(-1, 1), "opacities", (1,))[:, 0]  # [N] ([N] or [N, 1] in)
    sh = np.asarray(sh.detach().cpu().numpy() if isinstance(sh, torch.Tensor) else sh, np.float64)
    if sh.ndim != 3 or sh.shape[0] != n or sh.shape[2] != 3 or sh.shape[1] < 1:
        raise ValueError(f"sh must be [N, K, 3], got {sh.shape}")
    if not (len(quats) == len(scales) == len(opac) == n):
        raise ValueError("means, quats, scales, opacities and sh must have the same N")
    for name, a in (("means", means), ("quats", quats), ("scales", scales), ("opacities", opac), ("sh", sh)):
        if not np.isfinite(a).all():
            raise ValueError(f"{name} has non-finite values")
    quats = quats / np.maximum(np.linalg.norm(quats, axis=1, keepdims=True), 1e-12)
    o = np.clip(opac, OPACITY_EPS, 1.0 - OPACITY_EPS)
    k = sh.shape[1]
    names = property_names(k)
    cols = np.concatenate([
        means, np.zeros((n, 3)), sh[:, 0, :],  # f_dc: [N, 3]
        sh[:, 1:, :].transpose(0, 2, 1).reshape(n, 3 * (k - 1)),  # f_rest channel-major: [N, 3 (K - 1)]
        np.log(o / (1.0 - o))[:, None], np.log(np.maximum(scales, MIN_SCALE)), quats], 1)
    rows = np.empty(n, dtype=[(name, "<f4") for name in names])
    for i, name in enumerate(names):
        rows[name] = cols[:, i]
    header = "ply\nformat binary_little_endian 1.0\n" + "comment written by agg (3DGS layout)\n" \
        + f"element vertex {n}\n" + "".join(f"property float {name}\n" for name in names) + "end_header\n"
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(rows.tobytes())
    return path


def read_header(f) -> tuple[int, list[tuple[str, str]]]:
    """(vertex count, [(property name, numpy dtype)]) of an open binary little-endian PLY; leaves ``f`` at
    the data."""
    if f.readline().strip() != b"ply":
        raise ValueError("not a PLY file")
    count, props, in_vertex, fmt = None, [], False, None
    while True:
        line = f.readline()
        if not line:
            raise ValueError("PLY header has no end_header")
        words = line.decode("ascii").split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "end_header":
            break
        if words[0] == "format":
            fmt = words[1]
        elif words[0] == "element":
            in_vertex = words[1] == "vertex"
            if in_vertex:
                count = int(words[2])
            elif count is None:
                raise ValueError("only PLY files whose first element is 'vertex' are supported")
        elif words[0] == "property" and in_vertex:
            if words[1] == "list" or words[1] not in _PLY_TYPES:
                raise ValueError(f"unsupported vertex property: {' '.join(words)}")
            props.append((words[2], _PLY_TYPES[words[1]]))
    if fmt != "binary_little_endian":
        raise ValueError(f"only binary_little_endian PLY is supported, got {fmt}")
    if count is None:
        raise ValueError("PLY file has no vertex element")
    return count, props


def read_ply(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """A 3DGS PLY as float32 arrays: means [N, 3], quats [N, 4] (as stored), scales [N, 3] (exp), opacities [N]
    (sigmoid), sh [N, K, 3], and ``properties`` (the header's names in file order)."""
    with open(path, "rb") as f:
        n, props = read_header(f)
        rows = np.frombuffer(f.read(), dtype=np.dtype(props), count=n)
    names = [p[0] for p in props]

    def cols(keys: list[str]) -> np.ndarray:
        missing = [k for k in keys if k not in names]
        if missing:
            raise ValueError(f"PLY lacks properties {missing}")
        return np.stack([rows[k].astype(np.float64) for k in keys], 1) if keys else np.zeros((n, 0))

    n_rest = sum(1 for p in names if p.startswith("f_rest_"))
    if n_rest % 3:
        raise ValueError(f"{n_rest} f_rest properties is not a multiple of 3")
    k = 1 + n_rest // 3
    dc = cols([f"f_dc_{i}" for i in range(3)])  # [N, 3]
    rest = cols([f"f_rest_{i}" for i in range(n_rest)]).reshape(n, 3, k - 1).transpose(0, 2, 1)  # [N, K-1, 3]
    logit = cols(["opacity"])[:, 0]
    return {"means": cols(["x", "y", "z"]).astype(np.float32),
            "quats": cols([f"rot_{i}" for i in range(4)]).astype(np.float32),
            "scales": np.exp(cols([f"scale_{i}" for i in range(3)])).astype(np.float32),
            "opacities": (1.0 / (1.0 + np.exp(-logit))).astype(np.float32),
            "sh": np.concatenate([dc[:, None, :], rest], 1).astype(np.float32),
            "properties": names}


def export_graph_ply(graph, path: str | os.PathLike, frame: int = 0) -> Path:
    """Write the composed world Gaussians of ``graph`` at ``frame`` (every node, agents at their refined poses).

    Gaussians with zero opacity (agents not present at that frame) are left out."""
    with torch.no_grad():
        g = graph.compose(int(frame))
    keep = g["opacities"].reshape(-1) > 0
    return write_ply(path, g["means"][keep], g["quats"][keep], g["scales"][keep], g["opacities"].reshape(-1)[keep],
                     g["sh"][keep])
