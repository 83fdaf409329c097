"""Ingest: read a video file (PyAV) or an image folder, sample frames, undistort and resize them.

Conventions (docs/CONVENTIONS.md): frames come out as RGB [T, H, W, 3], float32 in [0, 1] (or uint8 0..255 with
``IngestConfig(dtype="uint8")``), grayscale replicated to 3 channels; timestamps are int64 microseconds of
presentation time relative to the first frame of the source (image folders: ``round(1e6 * index / image_fps)``);
intrinsics are pinhole K [3, 3] in pixels with OpenCV pixel centres (top-left pixel centre at (0, 0)), at the output
resolution.

Sampling order: frames before ``start_s`` and from ``end_s`` on are dropped (both in seconds of that timeline),
then ``fps`` (keep the first frame of each 1/fps interval after ``start_s``; never duplicates frames) or ``stride``
(every stride-th frame from ``start_s``), then ``max_frames``. The whole stream is decoded from its start (no
seeking), so source frame indices are exact.
"""

from __future__ import annotations

import math
import re
import warnings
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Sequence

import numpy as np

from agg.io.errors import (CalibrationError, IngestError, NoDecodableFramesError, NotAVideoError, TooFewFramesError,
                           TooManyPixelsError, TruncatedVideoError, TruncatedVideoWarning)

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")
DEFAULT_MAX_SOURCE_PIXELS = 4096 * 2160  # DCI 4K (8.8 MP): covers UHD 3840x2160 and every dashcam we know


@dataclass
class IngestConfig:
    """How to sample and prepare frames. Times in seconds, sizes in pixels (width, height)."""

    fps: float | None = None  # target frame rate; None: use ``stride``
    stride: int = 1  # keep every stride-th frame (ignored when ``fps`` is set)
    start_s: float = 0.0  # first time kept (seconds from the source's first frame), inclusive
    end_s: float | None = None  # time where sampling stops (seconds), exclusive; None: to the end
    max_frames: int | None = None  # keep at most this many frames
    width: int | None = None  # output width; alone: keep aspect ratio
    height: int | None = None  # output height; alone: keep aspect ratio; with width: explicit W x H
    K: Sequence[Sequence[float]] | None = None  # [3, 3] intrinsics of the source (or of ``calib_size``)
    dist: Sequence[float] | None = None  # OpenCV (k1, k2, p1, p2, k3) or (k1, k2, p1, p2): undistorted at ingest
    calib_size: tuple[int, int] | None = None  # (W, H) at which K was calibrated, when not the source size
    undistort_alpha: float = 0.0  # cv2.getOptimalNewCameraMatrix alpha: 0 keeps only valid pixels
    max_source_pixels: int = DEFAULT_MAX_SOURCE_PIXELS  # W * H limit of a SOURCE frame
    min_frames: int = 2  # fewer usable frames raise TooFewFramesError
    strict: bool = False  # True: a truncated video raises TruncatedVideoError instead of warning
    dtype: str = "float32"  # "float32" in [0, 1] or "uint8" in 0..255
    image_fps: float = 10.0  # frame rate assumed for image folders (timestamps)

    def __post_init__(self) -> None:
        if self.fps is not None and not self.fps > 0:
            raise ValueError(f"IngestConfig.fps must be > 0, got {self.fps}")
        if self.stride < 1 or (self.max_frames is not None and self.max_frames < 1):
            raise ValueError("IngestConfig.stride and max_frames must be >= 1")
        if self.end_s is not None and self.end_s <= self.start_s:
            raise ValueError(f"IngestConfig.end_s ({self.end_s}) must be after start_s ({self.start_s})")
        if self.dtype not in ("float32", "uint8"):
            raise ValueError(f"IngestConfig.dtype must be 'float32' or 'uint8', got {self.dtype!r}")
        if any(v is not None and v < 1 for v in (self.width, self.height)) or self.image_fps <= 0:
            raise ValueError("IngestConfig width/height must be >= 1 and image_fps > 0")

    @classmethod
    def preset(cls, name: str, **overrides) -> "IngestConfig":
        """Named presets: "source" (as is), "train640" (640 px wide, 10 fps), "preview" (320 px, 5 fps, 100 frames)."""
        presets = {"source": {}, "train640": {"width": 640, "fps": 10.0},
                   "preview": {"width": 320, "fps": 5.0, "max_frames": 100}}
        if name not in presets:
            raise ValueError(f"unknown ingest preset {name!r}; presets are {sorted(presets)}")
        return cls(**{**presets[name], **overrides})


@dataclass
class TruncationInfo:
    """Where decoding stopped early: the first missing source frame index and its (estimated) time."""

    frame_index: int
    time_us: int | None
    reason: str


@dataclass
class IngestResult:
    frames: np.ndarray  # [T, H, W, 3] float32 in [0, 1] (or uint8), RGB
    timestamps_us: np.ndarray  # [T] int64, relative to the source's first frame
    source_indices: np.ndarray  # [T] int64 index of each kept frame in the source
    source_size: tuple[int, int]  # (W, H) of the source frames
    size: tuple[int, int]  # (W, H) of the output frames
    K: np.ndarray | None  # [3, 3] pinhole K at the output size (None when no intrinsics were given)
    source: str
    frame_names: list[str]
    source_fps: float | None = None
    truncated_at: TruncationInfo | None = None
    warnings: list[str] = field(default_factory=list)


def scale_intrinsics(K: np.ndarray, from_size: tuple[int, int], to_size: tuple[int, int]) -> np.ndarray:
    """K [3, 3] for an image resized from (W0, H0) to (W1, H1), OpenCV pixel centres: c' = (c + 0.5) s - 0.5."""
    sx, sy = to_size[0] / from_size[0], to_size[1] / from_size[1]
    out = np.array(K, dtype=np.float64)
    out[0, 0], out[0, 1], out[1, 1] = out[0, 0] * sx, out[0, 1] * sx, out[1, 1] * sy
    out[0, 2] = (out[0, 2] + 0.5) * sx - 0.5
    out[1, 2] = (out[1, 2] + 0.5) * sy - 0.5
    return out


def intrinsics_at(K, frame: int):  # noqa: N803
    """K [3, 3] of ``frame`` from intrinsics [T or 1, 3, 3] (numpy or torch): a shared K serves every frame."""
    return K[min(int(frame), len(K) - 1)]


def guess_intrinsics(width: int, height: int) -> np.ndarray:
    """Fallback K when nothing is known: fx = fy = 0.8 max(W, H) (~64 deg horizontal FOV), centred."""
    f = 0.8 * max(width, height)
    return np.array([[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]])


def load_opencv_calibration(path: str | Path) -> tuple[np.ndarray, np.ndarray, tuple[int, int] | None]:
    """Read an OpenCV FileStorage (YAML/XML) with ``K`` [3, 3], ``dist`` [5] and optional ``image_size`` (W, H)."""
    import cv2

    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    if not fs.isOpened():
        raise CalibrationError(f"cannot open calibration file {path}")
    try:
        K, dist = fs.getNode("K").mat(), fs.getNode("dist").mat()
        size = fs.getNode("image_size").mat()
    finally:
        fs.release()
    if K is None or np.asarray(K).shape != (3, 3) or dist is None:
        raise CalibrationError(f"{path} needs a 3x3 'K' and a 'dist' vector")
    wh = tuple(int(v) for v in np.asarray(size).ravel()[:2]) if size is not None else None
    return np.asarray(K, dtype=np.float64), np.asarray(dist, dtype=np.float64).ravel(), wh


class FrameProcessor:
    """Undistorts (OpenCV remap at the source size) then resizes uint8 RGB frames; tracks the output K."""

    def __init__(self, source_size: tuple[int, int], config: IngestConfig, K: np.ndarray | None = None,
                 dist: Sequence[float] | None = None):
        import cv2

        self._cv2 = cv2
        w0, h0 = source_size
        self.source_size = (int(w0), int(h0))
        K = config.K if K is None else K
        dist = config.dist if dist is None else dist
        self.maps = None
        k_src = None
        if K is not None:
            k_src = np.asarray(K, dtype=np.float64)
            if k_src.shape != (3, 3) or not np.isfinite(k_src).all() or k_src[0, 0] <= 0 or k_src[1, 1] <= 0:
                raise CalibrationError(f"K must be a finite 3x3 matrix with positive focal lengths, got {k_src}")
            if config.calib_size is not None and tuple(config.calib_size) != self.source_size:
                k_src = scale_intrinsics(k_src, tuple(config.calib_size), self.source_size)
        d = np.zeros(0) if dist is None else np.asarray(dist, dtype=np.float64).ravel()
        if d.size and k_src is None:
            raise CalibrationError("distortion coefficients need intrinsics K")
        if d.size not in (0, 4, 5, 8) or not np.isfinite(d).all():
            raise CalibrationError(f"distortion must be (k1, k2, p1, p2[, k3]), got {d}")
        if d.size and np.any(d != 0):
            new_k, _ = cv2.getOptimalNewCameraMatrix(k_src, d, self.source_size, config.undistort_alpha, self.source_size)
            self.maps = cv2.initUndistortRectifyMap(k_src, d, None, new_k, self.source_size, cv2.CV_32FC1)
            k_src = np.asarray(new_k, dtype=np.float64)
        self.size = output_size(self.source_size, config.width, config.height)
        self.K = None if k_src is None else scale_intrinsics(k_src, self.source_size, self.size)

    def __call__(self, rgb: np.ndarray) -> np.ndarray:
        """[H0, W0, 3] uint8 -> [H, W, 3] uint8."""
        cv2 = self._cv2
        if self.maps is not None:
            rgb = cv2.remap(rgb, self.maps[0], self.maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        if self.size != self.source_size:
            down = self.size[0] < self.source_size[0]
            rgb = cv2.resize(rgb, self.size, interpolation=cv2.INTER_AREA if down else cv2.INTER_LINEAR)
        return rgb


def output_size(source_size: tuple[int, int], width: int | None, height: int | None) -> tuple[int, int]:
    w0, h0 = source_size
    if width and height:
        return int(width), int(height)
    if width:
        return int(width), max(1, round(h0 * width / w0))
    if height:
        return max(1, round(w0 * height / h0)), int(height)
    return int(w0), int(h0)


def natural_key(name: str) -> list:
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def list_images(folder: str | Path) -> list[Path]:
    """Image files of ``folder`` in natural name order (frame_2 before frame_10)."""
    files = [p for p in Path(folder).iterdir() if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS]
    return sorted(files, key=lambda p: natural_key(p.name))


def read_image_rgb(path: str | Path) -> np.ndarray | None:
    """[H, W, 3] uint8 RGB (grayscale replicated, 16-bit scaled to 8-bit), or None when undecodable."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    return None if img is None else cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


class _Sampler:
    """Decides, frame by frame in time order, which source frames to keep (see the module docstring)."""

    def __init__(self, config: IngestConfig):
        self.c, self.seen, self.kept, self.last_bucket = config, 0, 0, -1

    def done(self, t_s: float) -> bool:
        c = self.c
        return (c.end_s is not None and t_s >= c.end_s - 1e-9) or (c.max_frames is not None and self.kept >= c.max_frames)

    def keep(self, t_s: float) -> bool:
        c = self.c
        if t_s < c.start_s - 1e-9:
            return False
        if c.fps is not None:
            bucket = math.floor((t_s - c.start_s) * c.fps + 1e-6)
            ok = bucket > self.last_bucket
            self.last_bucket = max(self.last_bucket, bucket)
        else:
            ok = self.seen % c.stride == 0
            self.seen += 1
        self.kept += int(ok)
        return ok


def _check_pixels(size: tuple[int, int], config: IngestConfig, source: str) -> None:
    if size[0] * size[1] > config.max_source_pixels:
        raise TooManyPixelsError(f"{source}: frames are {size[0]}x{size[1]} = {size[0] * size[1]} pixels, over the "
                                 f"limit of {config.max_source_pixels} (IngestConfig.max_source_pixels)")


def _finish(frames: list[np.ndarray], times_us: list[int], indices: list[int], names: list[str],
            proc: FrameProcessor | None, config: IngestConfig, source: str, source_fps: float | None,
            trunc: TruncationInfo | None, notes: list[str], any_decoded: bool) -> IngestResult:
    """Assemble the result; apply the truncation policy and the minimum frame count."""
    if not frames and any_decoded:
        raise TooFewFramesError(f"{source}: no frame left after sampling (start_s={config.start_s}, "
                                f"end_s={config.end_s}); need at least {config.min_frames}")
    if proc is None or not frames:
        raise NoDecodableFramesError(f"{source}: no frame could be decoded" + (f" ({trunc.reason})" if trunc else ""))
    arr = np.stack(frames)  # [T, H, W, 3] uint8
    if config.dtype == "float32":
        arr = arr.astype(np.float32) / np.float32(255.0)
    result = IngestResult(frames=arr, timestamps_us=np.asarray(times_us, dtype=np.int64),
                          source_indices=np.asarray(indices, dtype=np.int64), source_size=proc.source_size,
                          size=proc.size, K=proc.K, source=source, frame_names=names, source_fps=source_fps,
                          truncated_at=trunc, warnings=notes)
    enough = len(frames) >= config.min_frames
    if trunc is not None:
        msg = (f"{source}: decoding stopped at source frame {trunc.frame_index}"
               + (f" (t = {trunc.time_us / 1e6:.3f} s)" if trunc.time_us is not None else "")
               + f": {trunc.reason}; kept {len(frames)} frame(s) decoded before it")
        if config.strict:
            raise TruncatedVideoError(msg, frame_index=trunc.frame_index, time_us=trunc.time_us,
                                      partial=result if enough else None)
        notes.append(msg)
        warnings.warn(msg, TruncatedVideoWarning, stacklevel=3)
    if not enough:
        raise TooFewFramesError(f"{source}: {len(frames)} usable frame(s) after sampling, need at least "
                                f"{config.min_frames}" + (" (the file is truncated)" if trunc else ""))
    return result


def read_images(paths: Sequence[str | Path], config: IngestConfig | None = None,
                timestamps_s: Sequence[float] | None = None, K: np.ndarray | None = None,
                dist: Sequence[float] | None = None, source: str | None = None) -> IngestResult:
    """Ingest an ordered list of image files. ``timestamps_s`` [N] (seconds) defaults to index / image_fps.

    Images that cannot be decoded are skipped with a warning (strict mode: NoDecodableFramesError).
    """
    config = config or IngestConfig()
    paths = [Path(p) for p in paths]
    source = source or (str(paths[0].parent) if paths else "<no images>")
    if timestamps_s is not None and len(timestamps_s) != len(paths):
        raise IngestError(f"{source}: {len(timestamps_s)} timestamps for {len(paths)} images")
    times = [i / config.image_fps for i in range(len(paths))] if timestamps_s is None else list(timestamps_s)
    t0 = times[0] if times else 0.0
    sampler, proc, notes, n_tried, n_failed = _Sampler(config), None, [], 0, 0
    frames, times_us, indices, names = [], [], [], []
    for i, (p, t) in enumerate(zip(paths, times)):
        t_rel = t - t0
        if sampler.done(t_rel):
            break
        if not sampler.keep(t_rel):
            continue
        rgb = read_image_rgb(p)
        n_tried, n_failed = n_tried + 1, n_failed + int(rgb is None)
        if rgb is None:
            if config.strict:
                raise NoDecodableFramesError(f"{p}: image could not be decoded")
            notes.append(f"{p}: image could not be decoded, skipped")
            warnings.warn(notes[-1], stacklevel=2)
            continue
        size = (rgb.shape[1], rgb.shape[0])
        _check_pixels(size, config, str(p))
        if proc is None:
            proc = FrameProcessor(size, config, K, dist)
        elif size != proc.source_size:
            raise IngestError(f"{p}: image is {size[0]}x{size[1]}, earlier images are "
                              f"{proc.source_size[0]}x{proc.source_size[1]}")
        frames.append(proc(rgb))
        times_us.append(int(round(t_rel * 1e6)))
        indices.append(i)
        names.append(p.name)
    fps = None if timestamps_s is not None else config.image_fps
    return _finish(frames, times_us, indices, names, proc, config, source, fps, None, notes,
                   any_decoded=n_failed < n_tried or (n_tried == 0 and bool(paths)))


def _open_video(path: Path):
    import av

    try:
        container = av.open(str(path))
    except av.error.FFmpegError as exc:
        with open(path, "rb") as fh:
            head = fh.read(12)
        if len(head) == 0:
            raise NotAVideoError(f"{path}: file is empty") from exc
        if head[4:8] == b"ftyp":
            raise NoDecodableFramesError(f"{path}: MP4/MOV file without a readable index (moov atom); it is "
                                         f"probably truncated and no frame can be recovered ({exc})") from exc
        raise NotAVideoError(f"{path}: not a video file the decoder can open ({exc})") from exc
    if not container.streams.video:
        container.close()
        raise NotAVideoError(f"{path}: the file has no video stream")
    return container


def read_video(path: str | Path, config: IngestConfig | None = None) -> IngestResult:
    """Ingest a video file with PyAV (any container/codec FFmpeg has: mp4, mov, avi, mkv, webm, ...)."""
    import av

    config, path = config or IngestConfig(), Path(path)
    if not path.is_file():
        raise NotAVideoError(f"{path}: no such file")
    container = _open_video(path)
    with container:
        stream = container.streams.video[0]
        stream.thread_type = "AUTO"
        cc = stream.codec_context
        if cc.width and cc.height:
            _check_pixels((cc.width, cc.height), config, str(path))
        rate = float(stream.average_rate) if stream.average_rate else None
        tb = stream.time_base
        expected = int(stream.frames or 0)
        duration = float(stream.duration * tb) if stream.duration and tb else (
            container.duration / 1e6 if container.duration else None)
        sampler, proc, notes, trunc = _Sampler(config), None, [], None
        frames, times_us, indices, names = [], [], [], []
        decoded, t_first, last_t, stopped, cut = 0, None, None, False, []
        try:
            for frame in _decode(container, stream, cut):
                t_abs = float(frame.pts * tb) if frame.pts is not None and tb else decoded / (rate or config.image_fps)
                t_first = t_abs if t_first is None else t_first
                t_rel, k = t_abs - t_first, decoded
                decoded += 1
                if last_t is not None and t_rel <= last_t:
                    notes.append(f"{path}: frame {k} has a non-increasing timestamp, skipped")
                    continue
                last_t = t_rel
                if sampler.done(t_rel):
                    stopped = True
                    break
                if not sampler.keep(t_rel):
                    continue
                size = (frame.width, frame.height)
                _check_pixels(size, config, str(path))
                if proc is None:
                    proc = FrameProcessor(size, config)
                elif size != proc.source_size:
                    trunc = TruncationInfo(k, int(round(t_rel * 1e6)), f"the stream changes size to {size}")
                    break
                frames.append(proc(frame.to_ndarray(format="rgb24")))
                times_us.append(int(round(t_rel * 1e6)))
                indices.append(k)
                names.append(f"frame_{k:06d}")
        except (av.error.FFmpegError, EOFError) as exc:
            t_est = None if last_t is None or rate is None else int(round((last_t + 1.0 / rate) * 1e6))
            trunc = TruncationInfo(decoded, t_est, f"decoder error: {exc}")
    if trunc is None and cut and not stopped:
        t_est = None if last_t is None or rate is None else int(round((last_t + 1.0 / rate) * 1e6))
        trunc = TruncationInfo(decoded, t_est, cut[0])
    if trunc is None and not stopped and decoded > 0:
        trunc = _detect_early_end(decoded, last_t, expected, duration, rate)
    if decoded == 0:
        raise NoDecodableFramesError(f"{path}: the video stream has no decodable frame"
                                     + (f" ({trunc.reason})" if trunc else ""))
    return _finish(frames, times_us, indices, names, proc, config, str(path), rate, trunc, notes, True)


def _decode(container, stream, cut: list[str]):
    """Yield decoded frames; at an incomplete (cut) packet, flush the decoder's good frames, note why and stop."""
    for packet in container.demux(stream):
        if packet.is_corrupt:
            cut.append(f"incomplete packet (pts {packet.pts}): the file ends inside a frame")
            yield from stream.codec_context.decode(None)
            return
        yield from packet.decode()


def _detect_early_end(decoded: int, last_t: float | None, expected: int, duration: float | None,
                      rate: float | None) -> TruncationInfo | None:
    """Compare what decoded with the container's frame count / duration; None when the stream looks complete.

    Two frames of slack: MP4 edit lists and codec priming can legitimately drop a frame or two from the count.
    """
    t_next = None if last_t is None or rate is None else int(round((last_t + 1.0 / rate) * 1e6))
    if expected > 0 and decoded < expected - 2:
        return TruncationInfo(decoded, t_next, f"the stream ended after {decoded} of {expected} frames")
    if expected <= 0 and duration and rate and last_t is not None and last_t + 2.5 / rate < duration:
        return TruncationInfo(decoded, t_next, f"the stream ended at {last_t:.3f} s of {duration:.3f} s")
    return None


def ingest(source: str | Path, config: IngestConfig | None = None) -> IngestResult:
    """Ingest a video file or a folder of images (natural name order)."""
    source = Path(source)
    if source.is_dir():
        paths = list_images(source)
        if not paths:
            raise NoDecodableFramesError(f"{source}: folder has no image files ({', '.join(IMAGE_EXTENSIONS)})")
        return read_images(paths, config, source=str(source))
    return read_video(source, config)


def ingest_to_bundle(source: str | Path, out: str | Path, config: IngestConfig | None = None,
                     overwrite: bool = False):
    """Ingest ``source`` and write it as a scene bundle at ``out`` (no priors); returns the ``SceneBundle``.

    Without ``config.K`` the intrinsics are a guess (``guess_intrinsics``, source "guess").
    """
    from agg.io.bundle import SceneBundle

    config = config or IngestConfig()
    result = ingest(source, replace(config, dtype="uint8"))
    K = result.K if result.K is not None else guess_intrinsics(*result.size)
    meta = {"importer": "ingest", "source": str(source), "source_size": list(result.source_size),
            "source_indices": result.source_indices.tolist(), "source_fps": result.source_fps,
            "truncated_at": asdict(result.truncated_at) if result.truncated_at else None,
            "ingest_config": _jsonable(asdict(config))}
    return SceneBundle.create(out, result.frames, result.timestamps_us, K, frame_names=result.frame_names,
                              intrinsics_source="calibration" if result.K is not None else "guess", meta=meta,
                              overwrite=overwrite)


def _jsonable(obj):
    if isinstance(obj, dict):
        return {k: _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple, np.ndarray)):
        return [_jsonable(v) for v in (obj.tolist() if isinstance(obj, np.ndarray) else obj)]
    return obj.item() if isinstance(obj, np.generic) else obj

