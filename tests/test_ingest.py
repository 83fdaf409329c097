"""Ingest of real video files (written here with PyAV / OpenCV) and image folders: sampling, resize, undistortion,
timestamps and the specific errors."""

from __future__ import annotations

import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

av = pytest.importorskip("av")
cv2 = pytest.importorskip("cv2")

from agg.io.bundle import SceneBundle  # noqa: E402
from agg.io.errors import (IngestError, NoDecodableFramesError, NotAVideoError, TooFewFramesError,  # noqa: E402
                           TooManyPixelsError, TruncatedVideoError, TruncatedVideoWarning)
from agg.io.video import (FrameProcessor, IngestConfig, ingest, ingest_to_bundle, intrinsics_at,  # noqa: E402
                          load_opencv_calibration, read_video, scale_intrinsics)

W, H, N = 64, 48, 10
UDACITY = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "udacity_highway"


def smooth_frames(n: int = N) -> list[np.ndarray]:
    """[H, W, 3] uint8 frames: a colour gradient with a bar moving 5 px per frame (easy for lossy codecs)."""
    yy, xx = np.mgrid[0:H, 0:W]
    out = []
    for i in range(n):
        f = np.stack([xx * 4, yy * 5, np.full_like(xx, 20 * i)], axis=-1).astype(np.uint8)
        f[:, 5 * i: 5 * i + 8] = 255
        out.append(f)
    return out


def noisy_frames(n: int = N, seed: int = 0) -> list[np.ndarray]:
    """Noise frames: every frame costs about the same bytes, so cutting a file in half keeps about half of them."""
    rng = np.random.default_rng(seed)
    return [rng.integers(0, 256, (H, W, 3), dtype=np.uint8) for _ in range(n)]


def write_av(path: Path, frames, codec: str = "libx264", pix_fmt: str = "yuv420p", rate: int = 10,
             options: dict | None = None, codec_options: dict | None = None) -> Path:
    with av.open(str(path), "w", options=options or {}) as c:
        s = c.add_stream(codec, rate=rate, options=codec_options or {})
        s.width, s.height, s.pix_fmt = frames[0].shape[1], frames[0].shape[0], pix_fmt
        for f in frames:
            fmt = "gray" if f.ndim == 2 else "rgb24"
            for p in s.encode(av.VideoFrame.from_ndarray(f, format=fmt)):
                c.mux(p)
        for p in s.encode():
            c.mux(p)
    return path


def write_cv(path: Path, frames, fourcc: str) -> Path:
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), 10, (W, H))
    assert vw.isOpened()
    for f in frames:
        vw.write(cv2.cvtColor(f, cv2.COLOR_RGB2BGR))
    vw.release()
    return path


def cut_half(src: Path, dst: Path) -> Path:
    data = src.read_bytes()
    dst.write_bytes(data[: len(data) // 2])
    return dst


@pytest.mark.parametrize("name,writer", [
    ("h264.mkv", lambda p, f: write_av(p, f, "libx264")),
    ("vp9.webm", lambda p, f: write_av(p, f, "libvpx-vp9")),
    ("h264.mp4", lambda p, f: write_av(p, f, "libx264")),
    ("mjpeg.avi", lambda p, f: write_av(p, f, "mjpeg", "yuvj420p")),
    ("opencv_mp4v.mp4", lambda p, f: write_cv(p, f, "mp4v")),
    ("opencv_mjpg.avi", lambda p, f: write_cv(p, f, "MJPG")),
])
def test_reads_containers_and_codecs(tmp_path, name, writer):
    src = smooth_frames()
    r = read_video(writer(tmp_path / name, src))
    assert r.frames.shape == (N, H, W, 3) and r.frames.dtype == np.float32
    assert 0.0 <= r.frames.min() and r.frames.max() <= 1.0
    np.testing.assert_array_equal(r.timestamps_us, np.arange(N) * 100_000)
    np.testing.assert_array_equal(r.source_indices, np.arange(N))
    assert r.source_size == (W, H) and r.size == (W, H) and r.K is None and r.truncated_at is None
    err = np.abs(r.frames - np.stack(src).astype(np.float32) / 255).mean()
    assert err < 0.05, f"{name}: decoded frames differ from the written ones (mean abs {err:.3f})"


def test_grayscale_video_and_uint8_output(tmp_path):
    gray = [f[..., 0] for f in smooth_frames()]
    r = read_video(write_av(tmp_path / "gray.mkv", gray, "ffv1", "gray"), IngestConfig(dtype="uint8"))
    assert r.frames.dtype == np.uint8 and r.frames.shape == (N, H, W, 3)
    np.testing.assert_array_equal(r.frames[..., 0], r.frames[..., 2])  # replicated channels
    np.testing.assert_array_equal(r.frames[..., 1], np.stack(gray))  # ffv1 is lossless


def test_image_folder_natural_order_gray_and_timestamps(tmp_path):
    for i, f in enumerate(smooth_frames(12)):
        cv2.imwrite(str(tmp_path / f"frame_{i}.png"), f[..., 1])  # grayscale PNGs, unpadded names
    (tmp_path / "notes.txt").write_text("not an image")
    r = ingest(tmp_path, IngestConfig(image_fps=5.0))
    assert r.frame_names[:3] == ["frame_0.png", "frame_1.png", "frame_2.png"] and r.frame_names[10] == "frame_10.png"
    np.testing.assert_array_equal(r.timestamps_us, np.arange(12) * 200_000)
    assert r.frames.shape == (12, H, W, 3)
    np.testing.assert_allclose(r.frames[11, ..., 0], smooth_frames(12)[11][..., 1] / 255.0, atol=1e-6)
    np.testing.assert_array_equal(r.frames[..., 0], r.frames[..., 1])


def test_undecodable_image_is_skipped_or_strict_error(tmp_path):
    for i, f in enumerate(smooth_frames(4)):
        cv2.imwrite(str(tmp_path / f"{i:03d}.png"), cv2.cvtColor(f, cv2.COLOR_RGB2BGR))
    (tmp_path / "002.png").write_bytes(b"\x89PNG broken")
    with pytest.warns(UserWarning, match="002.png: image could not be decoded"):
        r = ingest(tmp_path)
    assert r.frame_names == ["000.png", "001.png", "003.png"]
    np.testing.assert_array_equal(r.source_indices, [0, 1, 3])
    with pytest.raises(NoDecodableFramesError, match="002.png"):
        ingest(tmp_path, IngestConfig(strict=True))


@pytest.mark.parametrize("cfg,indices", [
    (IngestConfig(stride=3), [0, 3, 6, 9]),
    (IngestConfig(fps=5.0), [0, 2, 4, 6, 8]),
    (IngestConfig(start_s=0.25, end_s=0.75), [3, 4, 5, 6, 7]),
    (IngestConfig(start_s=0.2, stride=2, max_frames=3), [2, 4, 6]),
])
def test_sampling(tmp_path, cfg, indices):
    r = read_video(write_av(tmp_path / "v.mkv", smooth_frames()), cfg)
    np.testing.assert_array_equal(r.source_indices, indices)
    np.testing.assert_array_equal(r.timestamps_us, np.array(indices) * 100_000)  # time of the source timeline


def test_resize_scales_intrinsics_with_pixel_centres(tmp_path):
    K = np.array([[50.0, 0, 31.5], [0, 52.0, 23.5], [0, 0, 1]])
    path = write_av(tmp_path / "v.mkv", smooth_frames())
    r = read_video(path, IngestConfig(width=32, K=K))
    assert r.size == (32, 24) and r.frames.shape == (N, 24, 32, 3)
    np.testing.assert_allclose(r.K, [[25.0, 0, 15.5], [0, 26.0, 11.5], [0, 0, 1]])  # centre stays the centre
    r2 = read_video(path, IngestConfig(width=40, height=20, K=K))
    assert r2.frames.shape == (N, 20, 40, 3)
    np.testing.assert_allclose(r2.K, scale_intrinsics(K, (W, H), (40, 20)))
    # K calibrated at another resolution is rescaled to the source first
    r3 = read_video(path, IngestConfig(K=scale_intrinsics(K, (W, H), (128, 96)), calib_size=(128, 96)))
    np.testing.assert_allclose(r3.K, K, atol=1e-12)


def test_intrinsics_at_shares_one_K_and_indexes_per_frame_K():
    shared = np.eye(3)[None] * 2.0  # [1, 3, 3]
    per_frame = np.stack([np.eye(3) * (i + 1) for i in range(4)])  # [4, 3, 3]
    assert np.array_equal(intrinsics_at(shared, 3), shared[0])
    assert np.array_equal(intrinsics_at(per_frame, np.int64(2)), per_frame[2])
    assert torch.equal(intrinsics_at(torch.as_tensor(per_frame), torch.tensor(1)), torch.as_tensor(per_frame[1]))


def test_undistortion_straightens_projected_points(tmp_path):
    """Dots drawn at distorted projections land at the pinhole projections of the returned K after ingest."""
    w, h = 320, 240
    K = np.array([[200.0, 0, 160.0], [0, 200.0, 120.0], [0, 0, 1]])
    dist = np.array([-0.3, 0.1, 0.001, -0.001, 0.0])
    gx, gy = np.meshgrid(np.linspace(-0.55, 0.55, 5), np.linspace(-0.4, 0.4, 4))
    pts = np.stack([gx.ravel(), gy.ravel(), np.ones(gx.size)], axis=1)  # [20, 3] camera frame, z = 1
    uv_d, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K, dist)
    for i in range(2):
        img = np.zeros((h, w), np.uint8)
        for u, v in uv_d.reshape(-1, 2):
            cv2.circle(img, (int(round(u * 16)), int(round(v * 16))), 3 * 16, 255, -1, cv2.LINE_AA, shift=4)
        cv2.imwrite(str(tmp_path / f"{i:02d}.png"), img)
    r = ingest(tmp_path, IngestConfig(K=K, dist=dist, dtype="float32"))
    Kn = r.K
    assert not np.allclose(Kn, K)  # the new pinhole camera differs from the distorted one
    uv_expected = pts[:, :2] @ Kn[:2, :2].T + Kn[:2, 2]  # [20, 2] pinhole projection with the returned K
    n_lab, labels, stats, cents = cv2.connectedComponentsWithStats((r.frames[0, ..., 0] > 0.3).astype(np.uint8))
    found = cents[1:]
    assert len(found) == len(pts)
    d = np.linalg.norm(found[:, None] - uv_expected[None], axis=2).min(axis=0)
    assert d.max() < 0.5, f"undistorted dots are {d.max():.2f} px from the pinhole projections"


def test_not_a_video_and_empty_file(tmp_path):
    txt = tmp_path / "notes.mp4"
    txt.write_text("this is not a video, just some text " * 20)
    with pytest.raises(NotAVideoError, match="not a video"):
        ingest(txt)
    empty = tmp_path / "empty.mkv"
    empty.write_bytes(b"")
    with pytest.raises(NotAVideoError, match="empty"):
        ingest(empty)
    with pytest.raises(NotAVideoError, match="no such file"):
        ingest(tmp_path / "missing.mp4")
    (tmp_path / "empty_dir").mkdir()
    with pytest.raises(NoDecodableFramesError, match="no image files"):
        ingest(tmp_path / "empty_dir")
    assert issubclass(NotAVideoError, ValueError) and issubclass(NotAVideoError, IngestError)


@pytest.mark.parametrize("name,kwargs", [
    ("noise.mkv", {"codec": "mjpeg", "pix_fmt": "yuvj420p"}),  # Matroska: duration in the header
    ("noise_fs.mp4", {"codec": "libx264", "options": {"movflags": "faststart"}}),  # MP4 index at the start
    ("noise.avi", {"codec": "mjpeg", "pix_fmt": "yuvj420p"}),
])
def test_truncated_keeps_decoded_frames_and_says_where(tmp_path, name, kwargs):
    full = write_av(tmp_path / name, noisy_frames(), **kwargs)
    cut = cut_half(full, tmp_path / ("cut_" + name))
    with pytest.warns(TruncatedVideoWarning, match=r"stopped at source frame \d+ \(t = [\d.]+ s\)"):
        r = read_video(cut)
    t = r.truncated_at
    assert t is not None and 2 <= len(r.frames) < N
    assert t.frame_index == len(r.frames) and t.time_us == len(r.frames) * 100_000
    assert r.warnings and "kept" in r.warnings[-1]
    ref = read_video(full).frames[: len(r.frames)]
    np.testing.assert_array_equal(r.frames, ref)  # the partial frames are the real ones
    with pytest.raises(TruncatedVideoError) as exc:
        read_video(cut, IngestConfig(strict=True))
    assert exc.value.frame_index == t.frame_index and exc.value.partial is not None
    assert len(exc.value.partial.frames) == len(r.frames)


def test_truncated_mp4_without_index_is_a_specific_error(tmp_path):
    cut = cut_half(write_cv(tmp_path / "v.mp4", smooth_frames(), "mp4v"), tmp_path / "cut.mp4")
    with pytest.raises(NoDecodableFramesError, match="moov atom.*truncated"):
        read_video(cut)


def test_too_many_pixels_and_too_few_frames(tmp_path):
    path = write_av(tmp_path / "v.mkv", smooth_frames())
    with pytest.raises(TooManyPixelsError, match=r"64x48 = 3072 pixels, over the limit of 3071"):
        read_video(path, IngestConfig(max_source_pixels=W * H - 1))
    assert len(read_video(path, IngestConfig(max_source_pixels=W * H)).frames) == N
    with pytest.raises(TooFewFramesError, match="1 usable frame"):
        read_video(write_av(tmp_path / "one.mkv", smooth_frames(1)))
    with pytest.raises(TooFewFramesError):
        read_video(path, IngestConfig(start_s=0.95))


def test_ingest_to_bundle_guesses_intrinsics_without_calibration(tmp_path):
    b = ingest_to_bundle(write_av(tmp_path / "v.mkv", smooth_frames()), tmp_path / "bundle", IngestConfig(width=32))
    b2 = SceneBundle.load(tmp_path / "bundle")
    assert b.path == b2.path and len(b) == len(b2)
    assert len(b2) == N and (b2.width, b2.height) == (32, 24) and b2.intrinsics_source == "guess"
    np.testing.assert_allclose(b2.intrinsics[0], [[25.6, 0, 15.5], [0, 25.6, 11.5], [0, 0, 1]])
    assert b2.meta["source_size"] == [W, H] and b2.meta["ingest_config"]["width"] == 32
    r = read_video(tmp_path / "v.mkv", IngestConfig(width=32, dtype="uint8"))
    np.testing.assert_array_equal(b2.frames.raw, r.frames)


@pytest.mark.skipif(not (UDACITY / "test_video.mp4").is_file(), reason="udacity_highway clip not present")
def test_real_dashcam_clip_with_undistortion():
    K, dist, size = load_opencv_calibration(UDACITY / "intrinsics_from_camera_cal.yml")
    assert size == (1280, 720) and dist.shape == (5,)
    cfg = IngestConfig(K=K, dist=dist, calib_size=size, width=640, dtype="uint8")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a complete clip must not warn
        r = read_video(UDACITY / "test_video.mp4", cfg)
    assert r.frames.shape == (38, 360, 640, 3) and r.source_size == (1280, 720) and r.truncated_at is None
    np.testing.assert_array_equal(r.timestamps_us, np.arange(38) * 40_000)  # 25 fps
    new_k, _ = cv2.getOptimalNewCameraMatrix(K, dist, size, 0.0, size)
    np.testing.assert_allclose(r.K, scale_intrinsics(new_k, size, (640, 360)))
    # alpha = 0 keeps only valid pixels: a white frame stays white after the remap (1-px border aside)
    proc = FrameProcessor((1280, 720), replace(cfg, width=None))
    white = proc(np.full((720, 1280, 3), 255, np.uint8))
    assert (white[1:-1, 1:-1] > 250).mean() > 0.999
    # and the ingested frame equals OpenCV's own undistortion of the decoded frame
    raw = read_video(UDACITY / "test_video.mp4", IngestConfig(dtype="uint8", max_frames=2)).frames[1]
    ref = cv2.resize(cv2.undistort(raw, K, dist, None, new_k), (640, 360), interpolation=cv2.INTER_AREA)
    assert np.abs(r.frames[1].astype(int) - ref.astype(int)).mean() < 1.0

