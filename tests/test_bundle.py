"""The scene bundle: round trip of every part, laziness (memory maps), validation errors, scale normalisation."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from agg.io.bundle import (PARTS, SceneBundle, SemanticFeatures, Tracklets, compute_scale_factor,
                           rebase_to_first_camera)
from agg.io.errors import (BundleError, BundleExistsError, BundleNotFoundError, BundleValidationError,
                           BundleVersionError)

T, H, W = 6, 12, 16
K = np.array([[20.0, 0, 7.5], [0, 21.0, 5.5], [0, 0, 1]])


def rot_y(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def make_poses(n: int = T, start: np.ndarray | None = None) -> np.ndarray:
    """[n, 4, 4] world_from_camera driving forward (+z) 2 units per frame while turning slowly."""
    p = np.tile(np.eye(4), (n, 1, 1))
    for i in range(n):
        p[i, :3, :3] = rot_y(0.05 * i)
        p[i, :3, 3] = (0.1 * i, 0.0, 2.0 * i)
    return p if start is None else start @ p


def make_frames(seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (T, H, W, 3), dtype=np.uint8)


def full_priors(rng: np.random.Generator) -> dict:
    sparse = [np.column_stack([rng.uniform(0, W - 1, i + 1), rng.uniform(0, H - 1, i + 1), rng.uniform(1, 9, i + 1),
                               rng.uniform(0, 1, i + 1)]).astype(np.float32) for i in range(T)]
    sparse[2] = np.zeros((0, 4), np.float32)  # a frame without points
    valid = np.ones((2, T), bool)
    valid[1, :2] = False
    boxes = rng.normal(size=(2, T, 7))
    boxes[1, :, 3:] = np.nan  # a centre-only track
    sem = SemanticFeatures(features=rng.normal(size=(T, 3, 4, 64)).astype(np.float16), C_bg=[0, 1, 2], C_ag=[5, 7],
                           pca_basis=rng.normal(size=(384, 64)).astype(np.float32),
                           pca_mean=rng.normal(size=384).astype(np.float32),
                           prototypes={"rigid": rng.normal(size=(3, 64)), "non-rigid": rng.normal(size=(1, 64)),
                                       "background": rng.normal(size=(5, 64))})
    return dict(poses=make_poses(), pose_conf=rng.uniform(0, 1, T).astype(np.float32), sparse=sparse,
                dense=rng.uniform(0, 50, (T, H, W)).astype(np.float32),
                dense_conf=rng.uniform(0, 1, (T, H, W)).astype(np.float16), masks=rng.uniform(size=(T, H, W)) > 0.5,
                ego=np.arange(H)[:, None].repeat(W, 1) >= H - 3,  # a bonnet: the bottom three rows
                tracklets=Tracklets(ids=np.array([7, 3]), classes=["rigid", "non-rigid"], boxes=boxes, valid=valid,
                                    confidence=rng.uniform(0, 1, (2, T)).astype(np.float32), labels=["car", "person"]),
                semantics=sem)


def write_all(b: SceneBundle, p: dict) -> None:
    b.write_poses(p["poses"], source=["gt"] * (T - 1) + ["interpolated"], confidence=p["pose_conf"])
    b.write_sparse_depth(p["sparse"])
    b.write_dense_depth(p["dense"], confidence=p["dense_conf"], dtype="float32")
    b.write_dynamic_masks(p["masks"])
    b.write_ego_mask(p["ego"], source="flow-residual")
    b.write_tracklets(p["tracklets"])
    b.write_semantics(p["semantics"])


def test_round_trip_required_parts_only(tmp_path):
    frames = make_frames()
    ts = np.arange(T) * 100_000 + 5_000_000
    b = SceneBundle.create(tmp_path / "s", frames, ts, K, frame_names=[f"{i}.png" for i in range(T)])
    b2 = SceneBundle.load(tmp_path / "s")
    assert b2.path == b.path and b2.manifest == b.manifest
    assert (len(b2), b2.width, b2.height, b2.kind) == (T, W, H, "scene")
    np.testing.assert_array_equal(b2.frames.raw, frames)
    np.testing.assert_allclose(b2.frame(3), frames[3] / 255.0, atol=1e-7)
    assert b2.frame(3).dtype == np.float32 and b2.frames[1:3].shape == (2, H, W, 3)
    np.testing.assert_array_equal(b2.timestamps_us, ts)
    assert b2.timestamps_us.dtype == np.int64
    np.testing.assert_array_equal(b2.intrinsics, np.broadcast_to(K, (T, 3, 3)))
    assert b2.frame_names[4] == "4.png" and b2.scale == 1.0 and b2.metric is False
    for part in PARTS:
        assert not b2.has(part)
    assert b2.world_from_camera is None and b2.dense_depth is None and b2.tracklets is None
    assert b2.semantics is None and b2.gt is None and b2.dynamic_masks is None
    with pytest.raises(BundleValidationError, match="no sparse depth"):
        b2.sparse_depth(0)


def test_float_frames_and_per_frame_intrinsics(tmp_path):
    f = np.random.default_rng(1).uniform(0, 1, (T, H, W, 3)).astype(np.float32)
    ks = np.stack([K * [[1 + 0.01 * i], [1], [1]] for i in range(T)])
    ks[:, 2] = (0, 0, 1)
    b = SceneBundle.create(tmp_path / "s", list(f), np.arange(T) * 10, ks)  # a list of frames works too
    b2 = SceneBundle.load(b.path)
    np.testing.assert_allclose(b2.frames[:], f, atol=0.5 / 255 + 1e-6)
    np.testing.assert_array_equal(b2.intrinsics, ks)
    assert b2.manifest["intrinsics"]["per_frame"] is True


def test_round_trip_every_optional_part(tmp_path):
    p = full_priors(np.random.default_rng(2))
    b = SceneBundle.create(tmp_path / "s", make_frames(), np.arange(T) * 100_000, K, scale=2.5, metric=True,
                           meta={"importer": "test"})
    write_all(b, p)
    b2 = SceneBundle.load(tmp_path / "s")
    for part in PARTS[:-1]:
        assert b2.has(part)
    np.testing.assert_array_equal(b2.world_from_camera, p["poses"])
    np.testing.assert_allclose(b2.camera_from_world @ b2.world_from_camera, np.tile(np.eye(4), (T, 1, 1)), atol=1e-12)
    np.testing.assert_array_equal(b2.pose_confidence, p["pose_conf"])
    assert b2.pose_source[-1] == "interpolated" and b2.pose_source[0] == "gt"
    for i in range(T):
        np.testing.assert_array_equal(b2.sparse_depth(i), p["sparse"][i])
    assert b2.sparse_depth(2).shape == (0, 4)
    np.testing.assert_array_equal(b2.dense_depth, p["dense"])
    np.testing.assert_array_equal(b2.dense_depth_confidence, p["dense_conf"])
    np.testing.assert_array_equal(b2.dynamic_masks, p["masks"].astype(np.uint8))
    assert b2.ego_mask.dtype == bool and b2.manifest["ego_mask"]["source"] == "flow-residual"
    np.testing.assert_array_equal(b2.ego_mask, p["ego"])
    tr, tr0 = b2.tracklets, p["tracklets"]
    assert tr.classes == ["rigid", "non-rigid"] and tr.labels == ["car", "person"] and tr.ids.tolist() == [7, 3]
    np.testing.assert_array_equal(tr.valid, tr0.valid)
    np.testing.assert_array_equal(tr.boxes[tr0.valid], tr0.boxes[tr0.valid])
    assert np.isnan(tr.boxes[~tr0.valid]).all() and np.isnan(tr.boxes[1, 3:, 3:]).all()
    np.testing.assert_array_equal(tr.confidence, tr0.confidence)
    assert tr.anchor == "world" and "anchor" not in b2.manifest["tracklets"]  # absent means world (older bundles)
    b2.write_tracklets(replace(tr0, anchor="camera"))  # boxes lifted through the bundle's cameras (agg priors)
    assert SceneBundle.load(b.path).tracklets.anchor == "camera"
    sem, sem0 = b2.semantics, p["semantics"]
    np.testing.assert_array_equal(sem.features, sem0.features)
    assert sem.features.dtype == np.float16 and sem.C_bg == [0, 1, 2] and sem.C_ag == [5, 7]
    np.testing.assert_array_equal(sem.pca_basis, sem0.pca_basis)
    np.testing.assert_array_equal(sem.pca_mean, sem0.pca_mean)
    assert sorted(sem.prototypes) == ["background", "non-rigid", "rigid"] and sem.prototypes["rigid"].shape == (3, 64)
    np.testing.assert_allclose(sem.prototypes["background"], sem0.prototypes["background"].astype(np.float32))
    assert sem.feature_min == float(sem0.features.min()) and sem.feature_max == float(sem0.features.max())
    assert b2.scale == 2.5 and b2.metric is True and b2.meta == {"importer": "test"}
    man = json.loads((tmp_path / "s" / "manifest.json").read_text())
    assert man["format"] == "agg-bundle" and man["version"] == 1 and man["depth_sparse"]["num_points"] == 18
    b2.remove("depth_dense")  # a part can be removed again
    b3 = SceneBundle.load(tmp_path / "s")
    assert not b3.has("depth_dense") and not (tmp_path / "s" / "depth" / "dense.npy").exists()
    assert b3.has("depth_sparse")


def test_loading_is_lazy_memory_mapped(tmp_path):
    p = full_priors(np.random.default_rng(3))
    b = SceneBundle.create(tmp_path / "s", make_frames(), np.arange(T), K)
    write_all(b, p)
    b2 = SceneBundle.load(tmp_path / "s")
    assert isinstance(b2.frames.raw, np.memmap) and b2.frames.shape == (T, H, W, 3)
    for arr in (b2.dense_depth, b2.dense_depth_confidence, b2.dynamic_masks, b2.semantics.features,
                b2.tracklets.boxes):
        assert isinstance(arr, np.memmap) and arr.mode == "r"
    assert not b2.frames.raw.flags.writeable  # read-only maps: the bundle cannot be changed by accident


def test_gt_sidecar(tmp_path):
    b = SceneBundle.create(tmp_path / "s", make_frames(), np.arange(T) * 100_000, K)
    noisy = make_poses()
    noisy[:, :3, 3] += np.random.default_rng(4).normal(scale=0.01, size=(T, 3))
    b.write_poses(noisy, source="synthetic-noisy", confidence=0.5, rebase=True)
    gt = b.create_gt()
    gt.write_poses(make_poses(), source="gt")
    gt.write_dynamic_masks(np.zeros((T, H, W), bool))
    gt.set_scale(1.0, metric=True)
    with pytest.raises(BundleExistsError):
        b.create_gt()
    b2 = SceneBundle.load(tmp_path / "s")
    g = b2.gt
    assert g.kind == "gt" and g.has("poses") and g.has("dynamic_masks") and not g.has("tracklets")
    np.testing.assert_array_equal(g.world_from_camera, make_poses())
    np.testing.assert_array_equal(g.intrinsics, b2.intrinsics)  # shared with the scene
    np.testing.assert_array_equal(g.timestamps_us, b2.timestamps_us)
    assert g.frames.shape == (T, H, W, 3) and g.metric and not b2.metric
    assert b2.pose_source[0] == "synthetic-noisy"
    np.testing.assert_allclose(b2.world_from_camera[0], np.eye(4))  # rebased
    np.testing.assert_allclose(b2.world_from_camera, rebase_to_first_camera(noisy), atol=1e-12)
    assert SceneBundle.load(tmp_path / "s" / "gt").kind == "gt"  # opening the sidecar folder opens it via its parent
    assert not (tmp_path / "s" / "gt" / "frames.npy").exists()
    k_exact = K + np.array([[0.5, 0, 0], [0, 0.5, 0], [0, 0, 0]])
    g.write_intrinsics(k_exact, source="gt")  # the sidecar may hold its own (exact) intrinsics
    b3 = SceneBundle.load(tmp_path / "s")
    np.testing.assert_array_equal(b3.gt.intrinsics[2], k_exact)
    np.testing.assert_array_equal(b3.intrinsics[2], K)


def test_validation_errors_on_load(tmp_path):
    with pytest.raises(BundleNotFoundError, match="manifest.json is missing"):
        SceneBundle.load(tmp_path / "nothing")
    b = SceneBundle.create(tmp_path / "s", make_frames(), np.arange(T), K)
    b.write_poses(make_poses())
    mpath = tmp_path / "s" / "manifest.json"
    good = mpath.read_text()

    def edit(fn):
        m = json.loads(good)
        fn(m)
        mpath.write_text(json.dumps(m))

    edit(lambda m: m.update(version=2))
    with pytest.raises(BundleVersionError, match="version 2 is not supported"):
        SceneBundle.load(b.path)
    edit(lambda m: m.update(format="something-else"))
    with pytest.raises(BundleVersionError, match="format"):
        SceneBundle.load(b.path)
    edit(lambda m: m.update(num_frames=T + 1))
    with pytest.raises(BundleValidationError, match="frames.npy is"):
        SceneBundle.load(b.path)
    edit(lambda m: m["poses"].update(source=["gt"] * (T - 1)))
    with pytest.raises(BundleValidationError, match="poses.source has"):
        SceneBundle.load(b.path)
    edit(lambda m: m.update(depth_dense={"file": "depth/dense.npy", "confidence_file": None}))
    with pytest.raises(BundleValidationError, match="missing"):
        SceneBundle.load(b.path)
    edit(lambda m: m["poses"].pop("source"))
    with pytest.raises(BundleValidationError, match="malformed manifest entry"):
        SceneBundle.load(b.path)
    edit(lambda m: m.update(ego_mask={"file": "poses/confidence.npy", "source": "given"}))
    with pytest.raises(BundleValidationError, match=r"ego mask\) is \(6,\), expected \(12, 16\)"):
        SceneBundle.load(b.path)
    mpath.write_text("{not json")
    with pytest.raises(BundleValidationError, match="not valid JSON"):
        SceneBundle.load(b.path)
    mpath.write_text(good)
    np.save(tmp_path / "s" / "poses" / "world_from_camera.npy", np.zeros((T, 3, 4)))
    with pytest.raises(BundleValidationError, match=r"expected \(6, 4, 4\)"):
        SceneBundle.load(b.path)
    np.save(tmp_path / "s" / "timestamps_us.npy", np.arange(T)[::-1].astype(np.int64))
    with pytest.raises(BundleValidationError, match="strictly increasing"):
        SceneBundle.load(b.path)
    assert issubclass(BundleValidationError, BundleError) and issubclass(BundleError, ValueError)


def test_validation_errors_on_write(tmp_path):
    with pytest.raises(BundleValidationError, match="strictly increasing"):
        SceneBundle.create(tmp_path / "a", make_frames(), np.zeros(T, int), K)
    with pytest.raises(BundleValidationError, match="positive fx"):
        SceneBundle.create(tmp_path / "b", make_frames(), np.arange(T), np.diag([0.0, 1, 1]))
    b = SceneBundle.create(tmp_path / "s", make_frames(), np.arange(T), K)
    with pytest.raises(BundleExistsError):
        SceneBundle.create(tmp_path / "s", make_frames(), np.arange(T), K)
    shifted = make_poses()
    shifted[:, 0, 3] += 1.0  # frame 0 is not the world origin
    with pytest.raises(BundleValidationError, match="must be the identity"):
        b.write_poses(shifted)
    bad = make_poses()
    bad[2, :3, :3] *= 1.1
    with pytest.raises(BundleValidationError, match="proper rotations"):
        b.write_poses(bad)
    with pytest.raises(BundleValidationError, match="confidence must be in"):
        b.write_poses(make_poses(), confidence=1.5)
    with pytest.raises(BundleValidationError, match=r"must be \[6, 12, 16\]"):
        b.write_dense_depth(np.ones((T, H, W + 1)))
    with pytest.raises(BundleValidationError, match="bool or 0/1"):
        b.write_dynamic_masks(np.full((T, H, W), 7, np.uint8))
    with pytest.raises(BundleValidationError, match=r"ego mask must be \[12, 16\]"):
        b.write_ego_mask(np.zeros((T, H, W), bool))
    with pytest.raises(BundleValidationError, match="bool or 0/1"):
        b.write_ego_mask(np.full((H, W), 2, np.uint8))
    with pytest.raises(BundleValidationError, match="whole image"):
        b.write_ego_mask(np.ones((H, W), bool))
    with pytest.raises(BundleValidationError, match="> 0"):
        b.write_sparse_depth([np.array([[1, 1, -2.0, 1]])] * T)
    tr = Tracklets(ids=np.array([1]), classes=["truck"], boxes=np.zeros((1, T, 7)), valid=np.ones((1, T), bool))
    with pytest.raises(BundleValidationError, match="classes"):
        b.write_tracklets(tr)
    with pytest.raises(BundleValidationError, match="anchor"):
        b.write_tracklets(replace(tr, classes=["rigid"], anchor="box"))
    sem = SemanticFeatures(features=np.zeros((T, 2, 2, 64)), C_bg=[0], C_ag=[64])
    with pytest.raises(BundleValidationError, match="C_ag has channel indices outside"):
        b.write_semantics(sem)
    assert not any(SceneBundle.load(b.path).has(part) for part in PARTS)  # failed writes left nothing behind


def test_scale_normalisation_path_length(tmp_path):
    p = full_priors(np.random.default_rng(5))
    b = SceneBundle.create(tmp_path / "s", make_frames(), np.arange(T), K, scale=1.0, metric=True)
    write_all(b, p)
    gt = b.create_gt()
    gt.write_poses(make_poses())
    length = float(np.linalg.norm(np.diff(make_poses()[:, :3, 3], axis=0), axis=1).sum())
    assert compute_scale_factor(make_poses()) == pytest.approx(length)
    f = b.normalise_scale(method="path_length")
    assert f == pytest.approx(length)
    b2 = SceneBundle.load(b.path)
    assert b2.scale == pytest.approx(length) and b2.metric
    c = b2.world_from_camera[:, :3, 3]
    assert np.linalg.norm(np.diff(c, axis=0), axis=1).sum() == pytest.approx(1.0)
    np.testing.assert_allclose(b2.world_from_camera[:, :3, :3], p["poses"][:, :3, :3])  # rotations untouched
    np.testing.assert_allclose(b2.sparse_depth(1)[:, 2], p["sparse"][1][:, 2] / f, rtol=1e-6)
    np.testing.assert_allclose(b2.sparse_depth(1)[:, [0, 1, 3]], p["sparse"][1][:, [0, 1, 3]])  # pixels kept
    np.testing.assert_allclose(b2.dense_depth, p["dense"] / f, rtol=1e-6)
    v = p["tracklets"].valid
    np.testing.assert_allclose(b2.tracklets.boxes[..., :6][v], p["tracklets"].boxes[..., :6][v] / f, rtol=1e-12)
    np.testing.assert_allclose(b2.tracklets.boxes[..., 6][v], p["tracklets"].boxes[..., 6][v])  # yaw kept
    # metric = scale * scene units still holds
    np.testing.assert_allclose(b2.scale * c, p["poses"][:, :3, 3], atol=1e-12)
    np.testing.assert_array_equal(b2.gt.world_from_camera, make_poses())  # gt untouched by default


def test_scale_normalisation_median_depth_and_include_gt(tmp_path):
    b = SceneBundle.create(tmp_path / "s", make_frames(), np.arange(T), K)
    depth = np.full((T, H, W), 4.0, np.float32)
    depth[:, 0] = 0.0  # "no depth" pixels are ignored
    b.write_dense_depth(depth)
    gt = b.create_gt()
    gt.write_poses(make_poses())
    f = b.normalise_scale(include_gt=True)  # no poses: auto falls back to the median depth
    assert f == pytest.approx(4.0)
    b2 = SceneBundle.load(b.path)
    assert float(np.median(b2.dense_depth[:, 1:])) == pytest.approx(1.0) and b2.scale == pytest.approx(4.0)
    np.testing.assert_allclose(b2.gt.world_from_camera[:, :3, 3], make_poses()[:, :3, 3] / 4.0)
    assert b2.gt.scale == pytest.approx(4.0)
    static = np.tile(np.eye(4), (T, 1, 1))
    with pytest.raises(ValueError, match="path length is zero"):
        compute_scale_factor(static, method="path_length")
    assert compute_scale_factor(static, depths=np.array([0.0, 2.0, 3.0, 9.0])) == pytest.approx(3.0)
    with pytest.raises(ValueError, match="cannot compute"):
        compute_scale_factor(static)
