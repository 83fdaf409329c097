"""Importers: KITTI odometry, nerfstudio transforms.json and COLMAP models written here (plus the real kitti06_51),
checked against the conventions: OpenCV camera axes, world = first camera, OpenCV pixel centres."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

cv2 = pytest.importorskip("cv2")

from agg.io.bundle import SceneBundle, rebase_to_first_camera  # noqa: E402
from agg.io.errors import ImporterError  # noqa: E402
from agg.io.importers import import_colmap, import_kitti, import_nerfstudio  # noqa: E402
from agg.io.video import IngestConfig  # noqa: E402

N, W, H = 5, 40, 30
KITTI = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "kitti06_51"


def random_rotation(rng: np.random.Generator, scale: float = 0.3) -> np.ndarray:
    return cv2.Rodrigues(rng.normal(scale=scale, size=3))[0]


def random_poses(rng: np.random.Generator, n: int = N) -> np.ndarray:
    """[n, 4, 4] world_from_camera (OpenCV axes) of a camera moving forward, in an arbitrary world frame."""
    start = np.eye(4)
    start[:3, :3], start[:3, 3] = random_rotation(rng, 1.0), rng.normal(scale=10, size=3)
    poses = np.tile(np.eye(4), (n, 1, 1))
    for i in range(n):
        poses[i, :3, :3] = random_rotation(rng, 0.05)
        poses[i, :3, 3] = (0.2 * rng.normal(), 0.1 * rng.normal(), 1.5 * i)
    return start @ poses


def write_images(folder: Path, names: list[str], gray: bool = False, seed: int = 0) -> list[np.ndarray]:
    folder.mkdir(parents=True, exist_ok=True)
    rng, out = np.random.default_rng(seed), []
    for name in names:
        img = rng.integers(0, 256, (H, W) if gray else (H, W, 3), dtype=np.uint8)
        cv2.imwrite(str(folder / name), img if gray else cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
        out.append(np.repeat(img[..., None], 3, axis=2) if gray else img)
    return out


# ------------------------------------------------------------------------------------------------ KITTI
def make_kitti(root: Path, rng: np.random.Generator, baseline: float = 0.54) -> dict:
    K = np.array([[35.0, 0, 19.3], [0, 35.0, 14.1], [0, 0, 1]])
    P0 = np.hstack([K, np.zeros((3, 1))])
    P1 = np.hstack([K, K @ np.array([[-baseline], [0], [0]])])  # right camera, x = +baseline in cam0
    root.mkdir(parents=True)
    (root / "calib.txt").write_text("".join(f"{n}: " + " ".join(f"{v:.12e}" for v in P.ravel()) + "\n"
                                            for n, P in (("P0", P0), ("P1", P1))))
    poses = random_poses(rng)
    np.savetxt(root / "poses.txt", poses[:, :3].reshape(N, 12), fmt="%.12e")
    times = np.arange(N) * 0.1037 + 0.013
    np.savetxt(root / "times.txt", times, fmt="%.6e")
    names = [f"{i:06d}.png" for i in range(N)]
    imgs = write_images(root / "image_0", names, gray=True)
    write_images(root / "image_1", names, gray=True, seed=1)
    return dict(K=K, poses=poses, times=times, images=imgs, baseline=baseline)


def test_kitti_round_trip(tmp_path):
    d = make_kitti(tmp_path / "seq", np.random.default_rng(0))
    b = SceneBundle.load(import_kitti(tmp_path / "seq", tmp_path / "out").path)
    assert len(b) == N and (b.width, b.height) == (W, H) and b.intrinsics_source == "calibration"
    np.testing.assert_allclose(b.intrinsics[0], d["K"], atol=1e-9)
    np.testing.assert_array_equal(b.frames.raw, np.stack(d["images"]))  # grayscale replicated to RGB
    np.testing.assert_array_equal(b.timestamps_us, np.round((d["times"] - d["times"][0]) * 1e6).astype(np.int64))
    expected = np.linalg.inv(d["poses"][0]) @ d["poses"]  # world = first camera
    np.testing.assert_allclose(b.world_from_camera, expected, atol=1e-6)
    np.testing.assert_allclose(b.world_from_camera[0], np.eye(4), atol=1e-12)
    assert b.pose_source == ["gt"] * N and (b.pose_confidence == 1).all() and b.metric and b.gt is None


def test_kitti_without_poses_gt_sidecar_other_camera_and_resize(tmp_path):
    d = make_kitti(tmp_path / "seq", np.random.default_rng(1))
    b = import_kitti(tmp_path / "seq", tmp_path / "a", with_poses=False, gt_poses=True)
    assert not b.has("poses") and not b.metric
    expected = np.linalg.inv(d["poses"][0]) @ d["poses"]
    np.testing.assert_allclose(b.gt.world_from_camera, expected, atol=1e-6)
    assert b.gt.metric and b.gt.pose_source[0] == "gt"
    # camera 1: world_from_cam1 = world_from_cam0 @ cam0_from_cam1, then rebased
    cam0_from_cam1 = np.eye(4)
    cam0_from_cam1[0, 3] = d["baseline"]
    b1 = import_kitti(tmp_path / "seq", tmp_path / "b", camera=1)
    np.testing.assert_allclose(b1.world_from_camera, rebase_to_first_camera(d["poses"] @ cam0_from_cam1), atol=1e-6)
    assert not np.allclose(b1.frames.raw, b.frames.raw)  # it read image_1
    # stride and resize: poses follow the kept frames, K is scaled with pixel centres
    b2 = import_kitti(tmp_path / "seq", tmp_path / "c", config=IngestConfig(stride=2, width=20))
    assert len(b2) == 3 and (b2.width, b2.height) == (20, 15)
    np.testing.assert_allclose(b2.world_from_camera, rebase_to_first_camera(d["poses"][[0, 2, 4]]), atol=1e-6)
    np.testing.assert_allclose(b2.intrinsics[0], [[17.5, 0, 9.4], [0, 17.5, 6.8], [0, 0, 1]], atol=1e-9)
    with pytest.raises(ImporterError, match="calib.txt is missing"):
        (tmp_path / "seq" / "calib.txt").unlink()
        import_kitti(tmp_path / "seq", tmp_path / "d")


def test_kitti_requested_poses_missing(tmp_path):
    make_kitti(tmp_path / "seq", np.random.default_rng(2))
    (tmp_path / "seq" / "poses.txt").unlink()
    assert not import_kitti(tmp_path / "seq", tmp_path / "a").has("poses")  # default: use poses when present
    with pytest.raises(ImporterError, match="poses.txt is missing"):
        import_kitti(tmp_path / "seq", tmp_path / "b", with_poses=True)


@pytest.mark.skipif(not (KITTI / "poses.txt").is_file(), reason="kitti06_51 not present")
def test_real_kitti06_51(tmp_path):
    b = import_kitti(KITTI, tmp_path / "kitti", gt_poses=True)
    b = SceneBundle.load(b.path)
    assert len(b) == 51 and (b.width, b.height) == (1226, 370)
    assert b.intrinsics[0, 0, 0] == pytest.approx(707.0912) and b.intrinsics[0, 1, 2] == pytest.approx(183.1104)
    raw = np.loadtxt(KITTI / "poses.txt").reshape(-1, 3, 4)
    poses = np.tile(np.eye(4), (51, 1, 1))
    poses[:, :3] = raw[:51]
    rel = np.linalg.inv(poses[0]) @ poses
    np.testing.assert_allclose(b.world_from_camera, rel, atol=1e-6)
    np.testing.assert_allclose(b.gt.world_from_camera, rel, atol=1e-6)
    # relative motion between consecutive frames agrees with poses.txt
    step = np.linalg.inv(b.world_from_camera[:-1]) @ b.world_from_camera[1:]
    np.testing.assert_allclose(step, np.linalg.inv(poses[:-1]) @ poses[1:], atol=1e-6)
    path = np.linalg.norm(np.diff(b.world_from_camera[:, :3, 3], axis=0), axis=1).sum()
    assert 55 < path < 65 and b.metric  # about 60 m of street
    assert np.all(np.diff(b.timestamps_us) > 90_000) and b.frames.raw.dtype == np.uint8


# ------------------------------------------------------------------------------------------------ nerfstudio
def make_nerfstudio(root: Path, rng: np.random.Generator, dist: dict | None = None) -> dict:
    K = np.array([[33.0, 0, 19.7], [0, 34.0, 14.2], [0, 0, 1]])  # OpenCV pixel centres
    poses = random_poses(rng)
    names = [f"frame_{i + 1}.png" for i in range(N)]  # natural order matters: frame_10 would follow frame_9
    imgs = write_images(root / "images", names)
    frames = [{"file_path": f"images/{n}", "transform_matrix": (poses[i] @ np.diag([1.0, -1, -1, 1])).tolist()}
              for i, n in enumerate(names)]
    meta = {"fl_x": 33.0, "fl_y": 34.0, "cx": 19.7 + 0.5, "cy": 14.2 + 0.5, "w": W, "h": H,
            "camera_model": "OPENCV", "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0, **(dist or {}),
            "frames": [frames[i] for i in rng.permutation(N)]}  # shuffled: the importer orders by file_path
    (root / "transforms.json").write_text(json.dumps(meta))
    return dict(K=K, poses=poses, images=imgs)


def test_nerfstudio_round_trip_opengl_to_opencv(tmp_path):
    d = make_nerfstudio(tmp_path / "ns", np.random.default_rng(3))
    b = SceneBundle.load(import_nerfstudio(tmp_path / "ns", tmp_path / "out", fps=20.0).path)
    np.testing.assert_allclose(b.intrinsics[0], d["K"], atol=1e-9)
    np.testing.assert_array_equal(b.frames.raw, np.stack(d["images"]))  # ordered by file name
    np.testing.assert_allclose(b.world_from_camera, rebase_to_first_camera(d["poses"]), atol=1e-6)
    np.testing.assert_array_equal(b.timestamps_us, np.arange(N) * 50_000)
    # a point 5 units along camera 3's optical axis (OpenCV +z) is at (0, 0, 5) in that camera
    p_world = rebase_to_first_camera(d["poses"])[3] @ np.array([0, 0, 5.0, 1])
    np.testing.assert_allclose(b.camera_from_world[3] @ p_world, [0, 0, 5, 1], atol=1e-9)
    assert b.pose_source[0] == "given" and not b.metric
    assert not import_nerfstudio(tmp_path / "ns" / "transforms.json", tmp_path / "np", with_poses=False).has("poses")


def test_nerfstudio_distortion_and_errors(tmp_path):
    dist = {"k1": -0.2, "k2": 0.05, "p1": 0.001, "p2": -0.002}
    d = make_nerfstudio(tmp_path / "ns", np.random.default_rng(4), dist=dist)
    b = import_nerfstudio(tmp_path / "ns", tmp_path / "out")
    cv_dist = np.array([-0.2, 0.05, 0.001, -0.002, 0.0])
    new_k, _ = cv2.getOptimalNewCameraMatrix(d["K"], cv_dist, (W, H), 0.0, (W, H))
    np.testing.assert_allclose(b.intrinsics[0], new_k, atol=1e-9)
    ref = cv2.undistort(d["images"][2], d["K"], cv_dist, None, new_k)
    assert np.abs(b.frames.raw[2].astype(int) - ref.astype(int)).mean() < 2.0
    make_nerfstudio(tmp_path / "fish", np.random.default_rng(5))
    meta = json.loads((tmp_path / "fish" / "transforms.json").read_text())
    meta["camera_model"] = "OPENCV_FISHEYE"
    (tmp_path / "fish" / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(ImporterError, match="OPENCV_FISHEYE"):
        import_nerfstudio(tmp_path / "fish", tmp_path / "x")
    (tmp_path / "ns" / "images" / "frame_3.png").unlink()
    with pytest.raises(ImporterError, match="missing"):
        import_nerfstudio(tmp_path / "ns", tmp_path / "y")


# ------------------------------------------------------------------------------------------------ COLMAP
def make_colmap(root: Path, rng: np.random.Generator, model: str = "PINHOLE", params=None):
    pycolmap = pytest.importorskip("pycolmap")
    params = params or [33.0, 34.0, 20.2, 14.7]  # COLMAP pixel centres: top-left pixel at (0.5, 0.5)
    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera(model=model, width=W, height=H, params=params, camera_id=1)
    rec.add_camera_with_trivial_rig(cam)
    world_from_cam = random_poses(rng)
    cam_from_world = np.linalg.inv(world_from_cam)
    pts_cam0 = np.column_stack([rng.uniform(-3, 3, 30), rng.uniform(-2, 2, 30), rng.uniform(8, 20, 30)])
    pts = pts_cam0 @ world_from_cam[0, :3, :3].T + world_from_cam[0, :3, 3]  # [30, 3] world
    names = [f"img_{i}.png" for i in range(N)] + ["img_unregistered.png"]  # the last one is not in the model
    keypoints = []
    for i in range(N):
        pc = pts @ cam_from_world[i, :3, :3].T + cam_from_world[i, :3, 3]
        kp = cam.img_from_cam(pc)  # [30, 2] COLMAP pixel coordinates
        keypoints.append(kp)
        img = pycolmap.Image(name=names[i], keypoints=kp, camera_id=1, image_id=i + 1)
        rec.add_image_with_trivial_frame(img, pycolmap.Rigid3d(cam_from_world[i, :3]))
    for j in range(len(pts)):
        track = pycolmap.Track()
        for i in range(N):
            track.add_element(i + 1, j)
        rec.add_point3D(pts[j], track)
    rec.update_point_3d_errors()
    (root / "sparse").mkdir(parents=True)
    rec.write(str(root / "sparse"))
    write_images(root / "images", names)
    return dict(world_from_cam=world_from_cam, cam_from_world=cam_from_world, pts=pts, keypoints=keypoints)


def test_colmap_round_trip_poses_intrinsics_sparse_depth(tmp_path):
    d = make_colmap(tmp_path / "c", np.random.default_rng(6))
    b = SceneBundle.load(import_colmap(tmp_path / "c" / "sparse", tmp_path / "c" / "images", tmp_path / "out").path)
    assert len(b) == N and b.meta["images_not_registered"] == ["img_unregistered.png"]
    np.testing.assert_allclose(b.intrinsics[0], [[33.0, 0, 19.7], [0, 34.0, 14.2], [0, 0, 1]], atol=1e-9)
    np.testing.assert_allclose(b.world_from_camera, rebase_to_first_camera(d["world_from_cam"]), atol=1e-6)
    assert b.pose_source == ["sfm"] * N and b.intrinsics_source == "sfm"
    for i in range(N):
        sd = b.sparse_depth(i)  # (u, v, z, confidence)
        pc = d["pts"] @ d["cam_from_world"][i, :3, :3].T + d["cam_from_world"][i, :3, 3]
        inside = ((d["keypoints"][i] >= 0) & (d["keypoints"][i] <= (W, H))).all(axis=1)
        assert len(sd) == inside.sum() > 0
        order = np.lexsort((sd[:, 1], sd[:, 0]))
        exp = np.column_stack([d["keypoints"][i][inside] - 0.5, pc[inside, 2]])  # COLMAP -> OpenCV pixel centres
        exp = exp[np.lexsort((exp[:, 1], exp[:, 0]))]
        np.testing.assert_allclose(sd[order, :3], exp, atol=1e-4)
        np.testing.assert_allclose(sd[:, 3], 1.0, atol=1e-3)  # exact points: reprojection error ~0
    # text models work too, and depth / poses can be left out
    import pycolmap

    (tmp_path / "txt").mkdir()
    pycolmap.Reconstruction(str(tmp_path / "c" / "sparse")).write_text(str(tmp_path / "txt"))
    b2 = import_colmap(tmp_path / "txt", tmp_path / "c" / "images", tmp_path / "out2", with_poses=False,
                       with_depth=False)
    assert not b2.has("poses") and not b2.has("depth_sparse") and len(b2) == N


def test_colmap_distorted_camera_is_undistorted_consistently(tmp_path):
    params = [33.0, 34.0, 20.2, 14.7, -0.15, 0.03, 0.001, 0.002]  # OPENCV: fx fy cx cy k1 k2 p1 p2
    d = make_colmap(tmp_path / "c", np.random.default_rng(7), "OPENCV", params)
    b = import_colmap(tmp_path / "c" / "sparse", tmp_path / "c" / "images", tmp_path / "out")
    K = np.array([[33.0, 0, 19.7], [0, 34.0, 14.2], [0, 0, 1]])
    dist = np.array(params[4:])
    new_k, _ = cv2.getOptimalNewCameraMatrix(K, dist, (W, H), 0.0, (W, H))
    np.testing.assert_allclose(b.intrinsics[0], new_k, atol=1e-9)
    # the sparse depth's pixels are where OpenCV maps the distorted observations in the undistorted image
    sd = b.sparse_depth(1)
    und = cv2.undistortPoints(d["keypoints"][1][None] - 0.5, K, dist, P=new_k).reshape(-1, 2)
    dmin = np.linalg.norm(sd[:, None, :2] - und[None], axis=2).min(axis=1)
    assert len(sd) > 0 and dmin.max() < 1e-2


def test_colmap_errors(tmp_path):
    with pytest.raises(ImporterError, match="no such folder"):
        import_colmap(tmp_path / "nope", tmp_path, tmp_path / "out")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ImporterError):
        import_colmap(tmp_path / "empty", tmp_path, tmp_path / "out")
    make_colmap(tmp_path / "c", np.random.default_rng(8), "SIMPLE_RADIAL_FISHEYE", [33.0, 20.2, 14.7, 0.1])
    with pytest.raises(ImporterError, match="SIMPLE_RADIAL_FISHEYE is not supported"):
        import_colmap(tmp_path / "c" / "sparse", tmp_path / "c" / "images", tmp_path / "out")
