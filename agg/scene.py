"""A reconstructed scene loaded for serving: ``Scene.load(scene_dir)`` and stateless renders at any timestamp.

A scene directory holds ``scene.json`` (metadata: ``timestamps_us`` [T], ``width``, ``height``, ``K``,
``train_frames``, ``status``, ...) and the graph as ``model.pt`` (final) or, while training, ``checkpoint.pt``
(latest); both are ``torch.save({"graph": SceneGraph.state(), "iteration": int, ...})``. ``model.pt`` wins when
both exist; neither raises ``SceneNotReady``.

Time is addressed in integer microseconds on the clip's clock. ``frame_at(timestamp_us)`` maps it to a continuous
frame index f (exact frame timestamps give integers). Renders at a frame that was optimised use the node's own
refined agent poses; at a held-out or fractional frame the agent poses are interpolated between the neighbouring
optimised (train) frames, slerp of the rotation and lerp of the translation (``agg.eval.interpolate``), as the
novel-view evaluation does. The camera is always given by the caller (``world_from_camera``, OpenCV axes), so
no camera interpolation happens here.

Every request-validation failure is a ``SceneRequestError`` (a ``ValueError``) with a message fit for a client:
``InvalidCamera``, ``InvalidPose``, ``UnknownTrack`` and ``OutOfRange`` (timestamps outside the clip).
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from agg.eval.interpolate import interpolate_pose, neighbours
from agg.graph import SceneGraph
from agg.render import rasterize

MAX_IMAGE_SIDE = 8192  # width and height must be in [1, MAX_IMAGE_SIDE]
RIGID_TOLERANCE = 1e-3  # max |R^T R - I|, |det R - 1| and |last row - (0, 0, 0, 1)| of a pose matrix
MODEL_FILE, CHECKPOINT_FILE, META_FILE = "model.pt", "checkpoint.pt", "scene.json"


class SceneNotReady(RuntimeError):
    """The scene directory has no ``model.pt`` and no ``checkpoint.pt`` (or no ``scene.json``) yet."""


class SceneUnreadable(RuntimeError):
    """The checkpoint exists but could not be read (e.g. it is being rewritten); retrying may succeed."""


class SceneRequestError(ValueError):
    """A render request the scene cannot serve as asked; the message says why."""


class InvalidCamera(SceneRequestError):
    """Bad intrinsics or image size."""


class InvalidPose(SceneRequestError):
    """A pose with non-finite values, a zero quaternion or a non-rigid matrix."""


class UnknownTrack(SceneRequestError):
    """An agent override names a track id the scene does not have."""


class OutOfRange(SceneRequestError):
    """A timestamp outside the clip's [first, last] frame timestamps."""


# ----------------------------------------------------------------------------------------------- validation


def metres_per_unit(meta: dict) -> float | None:
    """Metres per scene unit of a scene's ``scene.json`` (``metric_scale``: exact for metric priors, else an estimate
    from the camera height, agg/priors/metric_scale.py); None for a scene trained before it was recorded."""
    value = (meta.get("metric_scale") or {}).get("metres_per_unit")
    return float(value) if value else None


def pose_matrix(values, what: str = "pose") -> np.ndarray:
    """A validated rigid [4, 4] float64 matrix from 16 row-major values or a [4, 4] array; the rotation block is
    re-orthonormalised (SVD) so tiny float errors do not shear the render."""
    m = np.asarray(values, dtype=np.float64)
    if m.size != 16:
        raise InvalidPose(f"{what}: a matrix needs 16 values (4x4 row-major), got {m.size}")
    m = m.reshape(4, 4)
    if not np.isfinite(m).all():
        raise InvalidPose(f"{what}: the matrix has NaN or infinite values")
    rot = m[:3, :3]
    err = max(np.abs(rot.T @ rot - np.eye(3)).max(), abs(np.linalg.det(rot) - 1.0),
              np.abs(m[3] - [0.0, 0.0, 0.0, 1.0]).max())
    if err > RIGID_TOLERANCE:
        raise InvalidPose(f"{what}: not a rigid transform (rotation block must be orthonormal with det +1 and the "
                          f"last row 0 0 0 1; error {err:.3g} > {RIGID_TOLERANCE})")
    u, _, vt = np.linalg.svd(rot)
    out = np.eye(4)
    out[:3, :3] = u @ vt
    out[:3, 3] = m[:3, 3]
    return out


def pose_from_quaternion(translation, quaternion_wxyz, what: str = "pose") -> np.ndarray:
    """[4, 4] float64 pose from a translation [3] and a wxyz quaternion [4] of any non-zero norm."""
    t = np.asarray(translation, dtype=np.float64).reshape(-1)
    q = np.asarray(quaternion_wxyz, dtype=np.float64).reshape(-1)
    if t.shape != (3,) or q.shape != (4,):
        raise InvalidPose(f"{what}: need a translation [3] and a wxyz quaternion [4]")
    if not (np.isfinite(t).all() and np.isfinite(q).all()):
        raise InvalidPose(f"{what}: NaN or infinite translation or quaternion")
    norm = float(np.linalg.norm(q))
    if norm < 1e-12:
        raise InvalidPose(f"{what}: zero quaternion (w, x, y, z all 0) is not a rotation")
    out = np.eye(4)
    out[:3, :3] = Rotation.from_quat(q / norm, scalar_first=True).as_matrix()
    out[:3, 3] = t
    return out


def matrix_to_wxyz(rot: np.ndarray) -> np.ndarray:
    """[3, 3] rotation -> [4] unit wxyz quaternion with w >= 0."""
    return Rotation.from_matrix(np.asarray(rot, dtype=np.float64)).as_quat(scalar_first=True, canonical=True)


def intrinsics_matrix(fx: float, fy: float, cx: float, cy: float, width: int, height: int) -> np.ndarray:
    """Validated pinhole K [3, 3] float64 (fx, fy > 0, finite, image size in [1, MAX_IMAGE_SIDE])."""
    vals = np.array([fx, fy, cx, cy], dtype=np.float64)
    if not np.isfinite(vals).all():
        raise InvalidCamera("intrinsics: fx, fy, cx, cy must be finite")
    if fx <= 0 or fy <= 0:
        raise InvalidCamera(f"intrinsics: fx and fy must be > 0, got fx={fx:g}, fy={fy:g}")
    check_image_size(width, height)
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def check_image_size(width: int, height: int) -> None:
    for name, v in (("width", width), ("height", height)):
        try:
            ok = int(v) == v and 1 <= int(v) <= MAX_IMAGE_SIDE
        except (TypeError, ValueError, OverflowError):  # NaN, inf, None
            ok = False
        if not ok:
            raise InvalidCamera(f"{name} must be an integer in [1, {MAX_IMAGE_SIDE}], got {v}")


@dataclass(frozen=True)
class Camera:
    """A virtual pinhole camera: ``world_from_camera`` [4, 4] (OpenCV axes), ``K`` [3, 3], image size."""

    world_from_camera: np.ndarray
    K: np.ndarray  # noqa: N815
    width: int
    height: int

    @classmethod
    def checked(cls, world_from_camera, K, width: int, height: int) -> "Camera":  # noqa: N803
        """A camera whose pose, intrinsics and size passed validation."""
        k = np.asarray(K, dtype=np.float64)
        if k.shape != (3, 3):
            raise InvalidCamera(f"K must be [3, 3], got {k.shape}")
        k = intrinsics_matrix(k[0, 0], k[1, 1], k[0, 2], k[1, 2], width, height)
        return cls(pose_matrix(world_from_camera, "world_from_camera"), k, int(width), int(height))


@dataclass(frozen=True)
class NodeInfo:
    """One node of the scene graph as served: agents carry their track id and per-frame poses / validity."""

    id: str  # "camera", "background", "sky", "agent/<track_id>"
    kind: str  # "camera" | "background" | "sky" | "rigid" | "non-rigid"
    track_id: int  # 0 for non-agents
    num_gaussians: int
    poses: np.ndarray | None  # [T, 4, 4] world_from_camera / world_from_box, None for world-frame nodes
    valid: np.ndarray | None  # [T] bool


# ----------------------------------------------------------------------------------------------- the scene


class Scene:
    """A loaded scene graph with its metadata; thread-safe for concurrent renders (read-only, no autograd)."""

    def __init__(self, graph: SceneGraph, meta: dict, *, iteration: int = 0, source: str = "model",
                 path: Path | None = None, mtime_ns: int = 0):
        self.graph = graph.eval()
        self.meta = dict(meta)
        ts = np.asarray(self.meta.get("timestamps_us", []), dtype=np.int64).reshape(-1)
        if len(ts) != graph.num_frames:
            raise ValueError(f"scene.json has {len(ts)} timestamps for a graph of {graph.num_frames} frames")
        if len(ts) > 1 and not (np.diff(ts) > 0).all():
            raise ValueError("scene.json timestamps_us must be strictly increasing")
        self.timestamps_us = ts  # [T]
        train = self.meta.get("train_frames") or list(range(graph.num_frames))
        self.train_frames = sorted(int(i) for i in train)
        self._train_set = set(self.train_frames)
        self.iteration, self.source, self.path, self.mtime_ns = int(iteration), source, path, int(mtime_ns)
        self.device = graph.K.device
        self._slot_ids = [int(i) for i in graph.slot_track_ids().tolist()]  # [S] track id of node id s + 1

    # -------------------------------------------------------------------------------------------- loading

    @staticmethod
    def source_file(scene_dir: str | os.PathLike) -> Path:
        """The file ``load`` reads: ``model.pt``, else ``checkpoint.pt``; ``SceneNotReady`` when neither exists."""
        d = Path(scene_dir)
        for name in (MODEL_FILE, CHECKPOINT_FILE):
            if (d / name).is_file():
                return d / name
        raise SceneNotReady(f"scene {d.name!r} has no checkpoint yet")

    @classmethod
    def load(cls, scene_dir: str | os.PathLike, device: str | torch.device = "cpu") -> "Scene":
        """Load ``model.pt`` (or the latest ``checkpoint.pt``) and ``scene.json`` of a scene directory."""
        d = Path(scene_dir)
        path = cls.source_file(d)
        if not (d / META_FILE).is_file():
            raise SceneNotReady(f"scene {d.name!r} has no {META_FILE}")
        meta = json.loads((d / META_FILE).read_text())
        mtime = path.stat().st_mtime_ns
        try:
            state = torch.load(path, map_location="cpu", weights_only=True)  # built on the CPU, then moved
            graph = SceneGraph.from_state(state["graph"]).to(device)
        except (EOFError, RuntimeError, KeyError, OSError, ValueError) as exc:
            # RuntimeError also covers torch's UnpicklingError wrapper and truncated zip archives
            raise SceneUnreadable(f"could not read {path.name} of scene {d.name!r}: {exc}") from exc
        return cls(graph, meta, iteration=int(state.get("iteration", 0)),
                   source="model" if path.name == MODEL_FILE else "checkpoint", path=path, mtime_ns=mtime)

    # -------------------------------------------------------------------------------------------- metadata

    @property
    def num_frames(self) -> int:
        return int(self.graph.num_frames)

    @property
    def width(self) -> int:
        return int(self.graph.width)

    @property
    def height(self) -> int:
        return int(self.graph.height)

    @property
    def K(self) -> np.ndarray:  # noqa: N802
        """[T or 1, 3, 3] training intrinsics."""
        return self.graph.K.detach().cpu().numpy().astype(np.float64)

    @property
    def track_ids(self) -> list[int]:
        """Tracklet ids of the agents (the values of the instance image)."""
        return list(self._slot_ids)

    def world_from_camera(self) -> np.ndarray:
        """[T, 4, 4] refined camera poses of the clip's frames."""
        with torch.no_grad():
            return self.graph.camera.world_from_camera().cpu().numpy().astype(np.float64)

    @property
    def metres_per_unit(self) -> float | None:
        return metres_per_unit(self.meta)

    def frame_at(self, timestamp_us: int) -> float:
        """Continuous frame index of a timestamp (integer at frame timestamps); ``OutOfRange`` outside the clip."""
        ts, t = self.timestamps_us, int(timestamp_us)
        if t < ts[0] or t > ts[-1]:
            raise OutOfRange(f"timestamp_us {t} is outside the clip [{int(ts[0])}, {int(ts[-1])}]")
        j = int(np.searchsorted(ts, t, side="right")) - 1  # ts[j] <= t
        if j >= len(ts) - 1:
            return float(len(ts) - 1)
        return j + (t - int(ts[j])) / float(ts[j + 1] - ts[j])

    # -------------------------------------------------------------------------------------------- rendering

    def agent_state(self, frame: float) -> tuple[dict[int, np.ndarray], dict[int, bool]]:
        """Poses {track id: world_from_box [4, 4]} and validity {track id: bool} of every agent at a continuous
        frame: the refined poses of an optimised frame, else interpolated between the neighbouring train frames
        (valid at both: slerp/lerp; at one: that pose held; at neither: absent)."""
        if frame == int(frame) and int(frame) in self._train_set:
            lo = hi = int(frame)
            w = 0.0
        else:
            lo, hi, w = neighbours(self.train_frames, frame)
        poses, valid = {}, {}
        with torch.no_grad():
            for node in self.graph.agent_nodes():
                a, b = node.world_from_box(lo), node.world_from_box(hi)  # [K, 4, 4]
                va, vb = node.valid[lo].tolist(), node.valid[hi].tolist()
                for j, tid in enumerate(node.track_ids.tolist()):
                    if va[j] and vb[j]:
                        p = interpolate_pose(a[j], b[j], w)
                    else:
                        p = a[j] if va[j] else b[j]
                    poses[int(tid)] = p.cpu().numpy().astype(np.float64)
                    valid[int(tid)] = bool(va[j] or vb[j])
        return poses, valid

    def render(self, timestamp_us: int, world_from_camera, K, width: int, height: int,  # noqa: N803
               agent_poses: Mapping[int, np.ndarray] | None = None, hidden: Iterable[int] = (),
               outputs: Iterable[str] = ("rgb", "depth", "alpha", "instance")) -> dict[str, np.ndarray]:
        """One camera: dict(rgb [H, W, 3] float32 in [0, 1], depth [H, W] float32, alpha [H, W] float32,
        instance [H, W] int32 track id, 0 = none), restricted to ``outputs``."""
        cam = Camera.checked(world_from_camera, K, width, height)
        return self.render_cameras(timestamp_us, [cam], agent_poses, hidden, outputs)[0]

    def render_cameras(self, timestamp_us: int, cameras: list[Camera],
                       agent_poses: Mapping[int, np.ndarray] | None = None, hidden: Iterable[int] = (),
                       outputs: Iterable[str] = ("rgb", "depth", "alpha", "instance")) -> list[dict[str, np.ndarray]]:
        """Several cameras at one timestamp; the graph is composed once. ``agent_poses`` {track id:
        world_from_box [4, 4]} moves agents (and shows them even where absent), ``hidden`` removes them."""
        outputs = set(outputs)
        unknown = outputs - {"rgb", "depth", "alpha", "instance"}
        if unknown:
            raise SceneRequestError(f"unknown outputs {sorted(unknown)}")
        f = self.frame_at(timestamp_us)
        poses, valid = self.resolve_overrides(f, agent_poses or {}, hidden)
        frame = min(int(round(f)), self.num_frames - 1)
        t = f / max(self.num_frames - 1, 1)
        dev = self.device
        with torch.no_grad():
            g = self.graph.compose(frame, t=t, agent_poses=poses or None, agent_valid=valid or None)
            onehot = None
            if "instance" in outputs:
                onehot = torch.nn.functional.one_hot(g["node"], len(self._slot_ids) + 1).to(g["means"])  # [N, S+1]
                lut = torch.tensor([0, *self._slot_ids], dtype=torch.int32, device=dev)  # [S + 1]
            results = []
            for cam in cameras:
                view = dict(K=torch.as_tensor(cam.K, dtype=torch.float32, device=dev), width=cam.width,
                            height=cam.height,
                            world_from_camera=torch.as_tensor(cam.world_from_camera, dtype=torch.float32, device=dev))
                out = rasterize(g["means"], g["quats"], g["scales"], g["opacities"], sh=g["sh"], **view)
                res = {}
                if "rgb" in outputs:
                    res["rgb"] = out.color.clamp(0.0, 1.0).cpu().numpy().astype(np.float32)
                if "depth" in outputs:
                    res["depth"] = torch.where(out.alpha > 0, out.depth, 0.0).cpu().numpy().astype(np.float32)
                if "alpha" in outputs:
                    res["alpha"] = out.alpha.cpu().numpy().astype(np.float32)
                if onehot is not None:
                    share = rasterize(g["means"], g["quats"], g["scales"], g["opacities"], onehot, **view).color
                    inst = torch.where(out.alpha > 0.5, lut[share.argmax(-1)], 0)  # [H, W]
                    res["instance"] = inst.cpu().numpy().astype(np.int32)
                results.append(res)
        return results

    def resolve_overrides(self, frame: float, agent_poses: Mapping[int, np.ndarray],
                          hidden: Iterable[int]) -> tuple[dict[int, torch.Tensor], dict[int, bool]]:
        """The graph's ``agent_poses`` / ``agent_valid`` for a continuous frame plus the caller's overrides
        (validated: known track ids, rigid finite poses). Empty dicts mean "the node's own poses"."""
        known = set(self._slot_ids)
        hidden = {int(h) for h in hidden}
        for tid in [*agent_poses, *hidden]:
            if int(tid) not in known:
                raise UnknownTrack(f"unknown track id {int(tid)} (the scene's agents: {sorted(known)})")
        moved = {int(k): pose_matrix(v, f"world_from_box of track {int(k)}") for k, v in agent_poses.items()}
        own = frame == int(frame) and int(frame) in self._train_set
        if own and not moved and not hidden:
            return {}, {}
        poses, valid = ({}, {}) if own else self.agent_state(frame)
        for tid, p in moved.items():
            poses[tid], valid[tid] = p, True
        for tid in hidden:
            valid[tid] = False
        tensors = {k: torch.as_tensor(v, dtype=torch.float32, device=self.device) for k, v in poses.items()}
        return tensors, valid

    # -------------------------------------------------------------------------------------------- the graph

    def nodes(self) -> list[NodeInfo]:
        """Camera, background, sky (when present) and one entry per agent, with per-frame poses and validity."""
        t = self.num_frames
        everywhere = np.ones(t, dtype=bool)
        out = [NodeInfo("camera", "camera", 0, 0, self.world_from_camera(), everywhere),
               NodeInfo("background", "background", 0, len(self.graph.background), None, everywhere)]
        sky = getattr(self.graph, "sky", None)
        if sky is not None:  # a GaussianParams itself, or a node holding one
            out.append(NodeInfo("sky", "sky", 0, len(getattr(sky, "gaussians", sky)), None, everywhere))
        with torch.no_grad():
            for node, kind in ((self.graph.rigid, "rigid"), (getattr(self.graph, "nonrigid", None), "non-rigid")):
                if node is None:
                    continue
                poses = torch.stack([node.world_from_box(i) for i in range(t)], 1)  # [K, T, 4, 4]
                counts = torch.bincount(node.instance, minlength=node.num_instances)  # [K]
                valid = node.valid.T  # [K, T]
                for j, tid in enumerate(node.track_ids.tolist()):
                    out.append(NodeInfo(f"agent/{int(tid)}", kind, int(tid), int(counts[j]),
                                        poses[j].cpu().numpy().astype(np.float64), valid[j].cpu().numpy()))
        return out

    def graph_json(self) -> dict:
        """The scene graph document of ``agg.export.graph_json.scene_graph_json`` (nodes, classes, poses)."""
        from agg.export.graph_json import scene_graph_json

        return scene_graph_json(self.graph, self.timestamps_us, self.meta)
