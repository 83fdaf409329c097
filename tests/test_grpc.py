"""The agg.v1 gRPC services through a real server on a random loopback port and a real client (no mocks):
renders against the engine, every bad input's status code, tenants, checkpoint reloads, jobs over a real Redis,
health and reflection."""

from __future__ import annotations

import json
import threading
import time

import grpc
import numpy as np
import pytest
import torch
from grpc_health.v1 import health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection_pb2, reflection_pb2_grpc

from tests.redis_server import redis_proc  # noqa: F401  (module fixture: a real redis-server)
from tests.scene_dirs import make_bundle, make_graph, psnr, write_scene_dir
from worker.grpc_convert import decode_image, pose_to_proto
from worker.grpc_proto import common_pb2 as cpb
from worker.grpc_proto import job_pb2, job_pb2_grpc, render_pb2, render_pb2_grpc, scene_pb2, scene_pb2_grpc
from worker.grpc_server import build_server

KEYS = {"key-a": "a", "key-b": "b", "key-ro": "a"}  # key-ro: tenant a's read-only key (may not cancel)
OWNERS = {"sA": "a", "sB": "b", "sEmpty": "a", "sTrain": "a"}
A, B, RO = ((("authorization", f"Bearer {k}"),) for k in ("key-a", "key-b", "key-ro"))
MiB = 1 << 20


@pytest.fixture(scope="module")
def world(tmp_path_factory, redis_proc):  # noqa: F811
    from service.jobstore import JobStore

    root = tmp_path_factory.mktemp("grpc")
    bundle, gt = make_bundle(root)
    graph = make_graph(bundle)
    scenes = root / "scenes"
    for sid in ("sA", "sB"):
        write_scene_dir(scenes, sid, bundle, graph, iteration=11)
    write_scene_dir(scenes, "sEmpty", bundle, None, status="training",
                    metric_scale={"metres_per_unit": 2.5, "source": "camera_height"})
    write_scene_dir(scenes, "sTrain", bundle, graph, file="checkpoint.pt", iteration=1, status="training")
    store = JobStore(redis_proc.client(), data_dir=root)
    server = build_server(0, scenes, authenticate=KEYS.get, scene_tenant=OWNERS.get, jobs=store, host="127.0.0.1",
                          authorize=lambda tenant, key, action: not (key == "key-ro" and action == "cancel"),
                          list_scenes=lambda t: sorted(s for s, o in OWNERS.items() if o == t), watch_poll_ms=100)
    server.start()
    channel = grpc.insecure_channel(f"127.0.0.1:{server.bound_port}",
                                    options=[("grpc.max_receive_message_length", 64 * MiB)])
    yield dict(bundle=bundle, gt=gt, graph=graph, scenes=scenes, store=store, server=server, channel=channel,
               render=render_pb2_grpc.RenderServiceStub(channel), scene=scene_pb2_grpc.SceneServiceStub(channel),
               jobs=job_pb2_grpc.JobServiceStub(channel))
    channel.close()
    server.stop(0)


def _camera(world, frame: int, scale: float = 1.0, name: str = "front", rigid: bool = False) -> cpb.CameraSpec:
    g, b = world["graph"], world["bundle"]
    with torch.no_grad():
        wfc = g.camera.world_from_camera(torch.tensor([frame]))[0].double().numpy()
    K = np.asarray(b.intrinsics)[frame]  # noqa: N806
    pose = pose_to_proto(wfc)
    pose.ClearField("matrix" if rigid else "rigid")
    return cpb.CameraSpec(name=name, world_from_camera=pose, intrinsics=cpb.PinholeIntrinsics(
        fx=K[0, 0] * scale, fy=K[1, 1] * scale, cx=(K[0, 2] + 0.5) * scale - 0.5, cy=(K[1, 2] + 0.5) * scale - 0.5,
        width=round(b.width * scale), height=round(b.height * scale)))


def _request(world, frame: int = 2, **output) -> render_pb2.RenderRequest:
    ts = int(world["bundle"].timestamps_us[frame])
    return render_pb2.RenderRequest(scene_id="sA", timestamp_us=ts, cameras=[_camera(world, frame)],
                                    output=render_pb2.OutputSpec(**output))


def _code(call, *args, **kwargs) -> grpc.StatusCode:
    with pytest.raises(grpc.RpcError) as info:
        result = call(*args, **kwargs)
        if hasattr(result, "__iter__") and not hasattr(result, "ByteSize"):
            list(result)
    return info.value.code()


def test_render_at_a_training_timestamp_matches_the_engine(world):
    b, g = world["bundle"], world["graph"]
    target = b.frame(2)
    with torch.no_grad():
        direct = psnr(g.render(2).color.clamp(0, 1).numpy(), target)
    raw = world["render"].Render(_request(world, rgb_encoding=cpb.IMAGE_ENCODING_RAW, depth=True, alpha=True,
                                          aux_encoding=cpb.IMAGE_ENCODING_RAW), metadata=A)
    assert (raw.scene_id, raw.frame, raw.iteration, raw.source) == ("sA", 2.0, 11, "model")
    img = raw.images[0]
    rgb = decode_image(img.rgb)
    assert rgb.shape == (b.height, b.width, 3) and rgb.dtype == np.float32 and img.camera_name == "front"
    assert direct > 15.0 and abs(psnr(rgb, target) - direct) < 1e-3, (psnr(rgb, target), direct)
    png = world["render"].Render(_request(world, depth=True, alpha=True), metadata=A).images[0]
    rgb8 = decode_image(png.rgb)
    assert rgb8.dtype == np.uint8 and abs(psnr(rgb8 / 255.0, target) - direct) < 0.1
    depth16, depth = decode_image(png.depth), decode_image(img.depth)
    assert png.depth.scale == 256.0 and depth16.dtype == np.uint16
    near = (depth > 0) & (depth < 200)
    assert np.abs(depth16[near] / 256.0 - depth[near]).max() < 0.01
    assert np.abs(decode_image(png.alpha) / 255.0 - decode_image(img.alpha)).max() < 0.01
    jpeg = world["render"].Render(_request(world, rgb_encoding=cpb.IMAGE_ENCODING_JPEG, jpeg_quality=95),
                                  metadata=A).images[0]
    assert jpeg.rgb.data[:2] == b"\xff\xd8" and psnr(decode_image(jpeg.rgb) / 255.0, target) > direct - 1.0


def test_two_cameras_in_one_request(world):
    req = _request(world, rgb_encoding=cpb.IMAGE_ENCODING_RAW)
    req.cameras.append(_camera(world, 2, scale=0.5, name="half", rigid=True))  # pose as translation + wxyz
    res = world["render"].Render(req, metadata=A)
    full, half = (decode_image(i.rgb) for i in res.images)
    assert [i.camera_name for i in res.images] == ["front", "half"]
    assert full.shape == (64, 96, 3) and half.shape == (32, 48, 3)
    assert psnr(half, full.reshape(32, 2, 48, 2, 3).mean((1, 3))) > 20.0


def test_agent_overrides_hide_and_move(world):
    gt = world["gt"]
    frame = 2
    base = world["render"].Render(_request(world, frame, instance=True, rgb_encoding=cpb.IMAGE_ENCODING_RAW),
                                  metadata=A).images[0]
    inst = decode_image(base.instance)
    ids = [int(t) for t in world["graph"].slot_track_ids()]
    tid = max(ids, key=lambda t: (gt.instance[frame] == t).sum())
    assert (inst == tid).sum() > 30
    req = _request(world, frame, instance=True, rgb_encoding=cpb.IMAGE_ENCODING_RAW)
    req.agent_overrides.append(render_pb2.AgentOverride(track_id=tid, hide=True))
    hidden = world["render"].Render(req, metadata=A).images[0]
    assert not (decode_image(hidden.instance) == tid).any()
    mask = gt.instance[frame] == tid
    change = np.abs(decode_image(hidden.rgb) - decode_image(base.rgb))
    assert change[mask].mean() > 0.02 and change[~mask].mean() < 0.01
    # move it 100 units further along the camera's z axis: it leaves the image too
    with torch.no_grad():
        node = world["graph"].rigid if tid in world["graph"].rigid.track_ids.tolist() else world["graph"].nonrigid
        j = node.track_ids.tolist().index(tid)
        pose = node.world_from_box(frame)[j].double().numpy().copy()
    pose[2, 3] += 100.0
    req = _request(world, frame, instance=True, aux_encoding=cpb.IMAGE_ENCODING_RAW)
    req.agent_overrides.append(render_pb2.AgentOverride(track_id=tid, world_from_box=pose_to_proto(pose)))
    moved = decode_image(world["render"].Render(req, metadata=A).images[0].instance)
    assert moved.dtype == np.int32 and (moved == tid).sum() < 0.2 * (inst == tid).sum()


def test_every_bad_input_gets_its_status_code(world):
    render, b = world["render"], world["bundle"]
    C = grpc.StatusCode  # noqa: N806

    def req(mutate=None, **output):
        r = _request(world, **output)
        if mutate:
            mutate(r)
        return r

    def set_nan(r):
        r.cameras[0].world_from_camera.matrix.values[3] = float("nan")

    def zero_quat(r):
        pose = r.cameras[0].world_from_camera
        pose.ClearField("matrix")
        pose.rigid.translation.x = 1.0
        pose.rigid.rotation.CopyFrom(cpb.Quaternion(w=0, x=0, y=0, z=0))

    def shear(r):
        r.cameras[0].world_from_camera.matrix.values[1] = 0.5

    def field(name, value):
        return lambda r: setattr(r.cameras[0].intrinsics, name, value)

    cases = {
        "nan pose": (req(set_nan), C.INVALID_ARGUMENT),
        "zero quaternion": (req(zero_quat), C.INVALID_ARGUMENT),
        "non-rigid matrix": (req(shear), C.INVALID_ARGUMENT),
        "no pose": (req(lambda r: r.cameras[0].ClearField("world_from_camera")), C.INVALID_ARGUMENT),
        "fx 0": (req(field("fx", 0.0)), C.INVALID_ARGUMENT),
        "fy < 0": (req(field("fy", -5.0)), C.INVALID_ARGUMENT),
        "width 0": (req(field("width", 0)), C.INVALID_ARGUMENT),
        "width 100000": (req(field("width", 100000)), C.INVALID_ARGUMENT),
        "no camera": (req(lambda r: r.ClearField("cameras")), C.INVALID_ARGUMENT),
        "unknown track": (req(lambda r: r.agent_overrides.add(track_id=999, hide=True)), C.INVALID_ARGUMENT),
        "empty override": (req(lambda r: r.agent_overrides.add(track_id=1)), C.INVALID_ARGUMENT),
        "jpeg depth": (req(depth=True, aux_encoding=cpb.IMAGE_ENCODING_JPEG), C.INVALID_ARGUMENT),
        "jpeg quality": (req(rgb_encoding=cpb.IMAGE_ENCODING_JPEG, jpeg_quality=101), C.INVALID_ARGUMENT),
        "before the clip": (req(lambda r: setattr(r, "timestamp_us", int(b.timestamps_us[0]) - 1)), C.OUT_OF_RANGE),
        "after the clip": (req(lambda r: setattr(r, "timestamp_us", int(b.timestamps_us[-1]) + 1)), C.OUT_OF_RANGE),
        "17 cameras": (req(lambda r: r.cameras.extend([r.cameras[0]] * 16)), C.RESOURCE_EXHAUSTED),
        "8192 x 8192": (req(lambda r: (field("width", 8192)(r), field("height", 8192)(r))), C.RESOURCE_EXHAUSTED),
        "raw over 64 MiB": (req(lambda r: (field("width", 2048)(r), field("height", 2048)(r),
                                           r.cameras.append(r.cameras[0])), rgb_encoding=cpb.IMAGE_ENCODING_RAW),
                            C.RESOURCE_EXHAUSTED),
        "another tenant's scene": (req(lambda r: setattr(r, "scene_id", "sB")), C.NOT_FOUND),
        "unknown scene": (req(lambda r: setattr(r, "scene_id", "nope")), C.NOT_FOUND),
        "traversal id": (req(lambda r: setattr(r, "scene_id", "../scenes/sA")), C.NOT_FOUND),
        "no checkpoint yet": (req(lambda r: setattr(r, "scene_id", "sEmpty")), C.FAILED_PRECONDITION),
    }
    got = {name: _code(render.Render, r, metadata=A) for name, (r, _) in cases.items()}
    assert got == {name: code for name, (_, code) in cases.items()}
    # keys: none, unknown, malformed -> UNAUTHENTICATED; tenant b sees its own scene, not a's
    assert _code(render.Render, _request(world)) == C.UNAUTHENTICATED
    assert _code(render.Render, _request(world), metadata=(("authorization", "Bearer wrong"),)) == C.UNAUTHENTICATED
    assert _code(render.Render, _request(world), metadata=(("authorization", "key-a"),)) == C.UNAUTHENTICATED
    assert _code(render.Render, _request(world), metadata=B) == C.NOT_FOUND
    mine = _request(world)
    mine.scene_id = "sB"
    assert len(render.Render(mine, metadata=B).images) == 1


def test_renders_follow_the_latest_checkpoint(world):
    render, graph = world["render"], world["graph"]
    folder = world["scenes"] / "sTrain"
    req = _request(world, rgb_encoding=cpb.IMAGE_ENCODING_RAW)
    req.scene_id = "sTrain"
    first = render.Render(req, metadata=A)
    assert (first.iteration, first.source) == (1, "checkpoint")
    state = graph.state()
    state["background"] = {k: v.clone() for k, v in state["background"].items()}
    state["background"]["sh"][:, 0] += 1.0  # a brighter background: training moved on
    torch.save({"graph": state, "iteration": 2}, folder / "checkpoint.pt.tmp")
    (folder / "checkpoint.pt.tmp").replace(folder / "checkpoint.pt")
    second = render.Render(req, metadata=A)
    assert second.iteration == 2
    assert decode_image(second.images[0].rgb).mean() > decode_image(first.images[0].rgb).mean() + 0.05
    torch.save({"graph": graph.state(), "iteration": 3}, folder / "model.pt")  # the job finished
    third = render.Render(req, metadata=A)
    assert (third.iteration, third.source) == (3, "model")


def test_render_trajectory_streams_every_step(world):
    ts = [int(t) for t in world["bundle"].timestamps_us]
    times = [ts[0], (ts[0] + ts[1]) // 2, ts[1], ts[4]]
    req = render_pb2.RenderTrajectoryRequest(scene_id="sA", output=render_pb2.OutputSpec(instance=True))
    for i, t in enumerate(times):
        req.steps.add(timestamp_us=t, cameras=[_camera(world, min(i, 4))])
    out = list(world["render"].RenderTrajectory(req, metadata=A))
    assert [r.step for r in out] == [0, 1, 2, 3] and [r.timestamp_us for r in out] == times
    assert [r.frame for r in out] == [0.0, 0.5, 1.0, 4.0]
    assert all(len(r.images) == 1 and r.images[0].instance.data for r in out)
    req.steps.add(timestamp_us=ts[-1] + 5, cameras=[_camera(world, 0)])  # a bad last step fails before any frame
    received = []
    with pytest.raises(grpc.RpcError) as info:
        for r in world["render"].RenderTrajectory(req, metadata=A):
            received.append(r)
    assert info.value.code() == grpc.StatusCode.OUT_OF_RANGE and received == []


def test_scene_service_lists_describes_and_graphs(world):
    stub, b, graph = world["scene"], world["bundle"], world["graph"]
    listed = stub.ListScenes(scene_pb2.ListScenesRequest(), metadata=A).scenes
    assert {s.scene_id for s in listed} == {"sA", "sEmpty", "sTrain"}
    info = stub.GetScene(scene_pb2.GetSceneRequest(scene_id="sA"), metadata=A)
    assert info.ready and info.status == "done" and list(info.timestamps_us) == b.timestamps_us.tolist()
    assert (info.time_range.start_us, info.time_range.end_us) == (int(b.timestamps_us[0]), int(b.timestamps_us[-1]))
    cam = info.cameras[0]
    assert (cam.intrinsics.width, cam.intrinsics.height) == (b.width, b.height) and len(cam.poses) == b.num_frames
    assert np.allclose(cam.poses[0].pose.matrix.values, np.eye(4).reshape(-1), atol=1e-5)  # world = camera 0
    empty = stub.GetScene(scene_pb2.GetSceneRequest(scene_id="sEmpty"), metadata=A)
    assert not empty.ready and not empty.cameras[0].poses
    assert info.scale == 1.0 and empty.scale == 2.5  # scene.json's metric_scale: metres per scene unit
    g = stub.GetSceneGraph(scene_pb2.GetSceneGraphRequest(scene_id="sA", include_json=True), metadata=A)
    ids = [int(t) for t in graph.slot_track_ids()]
    assert [n.id for n in g.nodes][:2] == ["camera", "background"]
    agents = [n for n in g.nodes if n.track_id]
    assert [n.track_id for n in agents] == ids
    assert {n.class_name for n in agents} == {"rigid", "non-rigid"}
    assert all(len(n.poses) == b.num_frames for n in agents)
    assert sum(n.num_gaussians for n in agents) == sum(len(a.gaussians) for a in graph.agent_nodes())
    assert sum(p.valid for p in agents[0].poses) == agents[0].num_valid_frames
    doc = json.loads(g.graph_json)
    assert [n["id"] for n in doc["nodes"]] == [n.id for n in g.nodes]
    C = grpc.StatusCode  # noqa: N806
    assert _code(stub.GetSceneGraph, scene_pb2.GetSceneGraphRequest(scene_id="sEmpty"), metadata=A) \
        == C.FAILED_PRECONDITION
    assert _code(stub.GetSceneGraph, scene_pb2.GetSceneGraphRequest(scene_id="sB"), metadata=A) == C.NOT_FOUND
    assert _code(stub.GetScene, scene_pb2.GetSceneRequest(scene_id="sA"), metadata=B) == C.NOT_FOUND


def test_health_and_reflection(world):
    health = health_pb2_grpc.HealthStub(world["channel"])
    for name in ("", "agg.v1.RenderService", "agg.v1.SceneService", "agg.v1.JobService"):
        assert health.Check(health_pb2.HealthCheckRequest(service=name)).status == \
            health_pb2.HealthCheckResponse.SERVING
    stub = reflection_pb2_grpc.ServerReflectionStub(world["channel"])
    reply = next(stub.ServerReflectionInfo(iter([reflection_pb2.ServerReflectionRequest(list_services="")])))
    names = {s.name for s in reply.list_services_response.service}
    assert {"agg.v1.RenderService", "agg.v1.SceneService", "agg.v1.JobService", "grpc.health.v1.Health"} <= names
    reply = next(stub.ServerReflectionInfo(iter([reflection_pb2.ServerReflectionRequest(
        file_containing_symbol="agg.v1.RenderService")])))
    assert reply.file_descriptor_response.file_descriptor_proto  # clients can build stubs from the server


def _new_job(store, tenant="a"):
    from service.jobstore import new_id

    return store.create(new_id("j"), tenant, "fast", input_path="/nowhere.mp4", timeout_s=60)["job_id"]


def test_job_service_get_watch_resume_cancel(world):
    store, jobs = world["store"], world["jobs"]
    C = grpc.StatusCode  # noqa: N806
    job_id = _new_job(store)
    got = jobs.GetJob(job_pb2.GetJobRequest(job_id=job_id), metadata=A)
    assert got.state == job_pb2.JOB_STATE_QUEUED and got.scene_id and got.preset == "fast" and got.created_at_us > 0
    assert "input_path" not in got.fields.fields  # server paths stay private
    assert job_id in [j.job_id for j in jobs.ListJobs(job_pb2.ListJobsRequest(), metadata=A).jobs]
    assert _code(jobs.GetJob, job_pb2.GetJobRequest(job_id=job_id), metadata=B) == C.NOT_FOUND
    assert _code(jobs.GetJob, job_pb2.GetJobRequest(job_id="j" + "0" * 24), metadata=A) == C.NOT_FOUND
    # a worker runs it while a client watches live
    watched: list = []
    live = jobs.WatchJob(job_pb2.WatchJobRequest(job_id=job_id, follow=True), metadata=A)
    reader = threading.Thread(target=lambda: watched.extend(live), daemon=True)
    reader.start()
    assert store.start(job_id, 1, "w1", 60) == "ok"
    for it in (10, 20):
        assert store.progress(job_id, 1, it / 40, {"type": "progress", "iteration": it, "total": 40}) == "ok"
        time.sleep(0.05)
    assert store.finish(job_id, 1, "succeeded", "w1") == "ok"
    reader.join(timeout=10)
    assert not reader.is_alive()  # the stream ended by itself after the final state
    kinds = [(e.event["type"], e.event["state"] if "state" in e.event else None) for e in watched]
    assert kinds[0] == ("state", "queued") and kinds[-1] == ("state", "succeeded")
    assert [e.event["iteration"] for e in watched if e.event["type"] == "progress"] == [10, 20]
    assert watched[-1].job.state == job_pb2.JOB_STATE_SUCCEEDED
    # resume after the second event: exactly the rest
    rest = list(jobs.WatchJob(job_pb2.WatchJobRequest(job_id=job_id, after_event_id=watched[1].event_id,
                                                      follow=True), metadata=A))
    assert [e.event_id for e in rest] == [e.event_id for e in watched[2:]]
    assert _code(jobs.WatchJob, job_pb2.WatchJobRequest(job_id=job_id, after_event_id="x"), metadata=A) \
        == C.INVALID_ARGUMENT
    assert _code(jobs.CancelJob, job_pb2.CancelJobRequest(job_id=job_id), metadata=A) == C.FAILED_PRECONDITION
    # cancelling: the read-only key may not; the owner may; another tenant cannot see the job
    queued = _new_job(store)
    assert _code(jobs.CancelJob, job_pb2.CancelJobRequest(job_id=queued), metadata=RO) == C.PERMISSION_DENIED
    assert _code(jobs.CancelJob, job_pb2.CancelJobRequest(job_id=queued), metadata=B) == C.NOT_FOUND
    assert jobs.CancelJob(job_pb2.CancelJobRequest(job_id=queued), metadata=A).job.state \
        == job_pb2.JOB_STATE_CANCELLED
    assert jobs.GetJob(job_pb2.GetJobRequest(job_id=queued), metadata=RO).state == job_pb2.JOB_STATE_CANCELLED


def test_unreachable_job_store_is_unavailable(world, tmp_path):
    import socket

    import redis

    from service.jobstore import JobStore

    with socket.socket() as s:  # a loopback port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    from redis.backoff import NoBackoff
    from redis.retry import Retry

    dead = JobStore(redis.Redis(host="127.0.0.1", port=port, socket_connect_timeout=0.5, socket_timeout=0.5,
                                retry=Retry(NoBackoff(), 0)))
    server = build_server(0, world["scenes"], authenticate=KEYS.get, jobs=dead)  # scene owners from the dead store
    server.start()
    try:
        with grpc.insecure_channel(f"127.0.0.1:{server.bound_port}") as ch:
            C = grpc.StatusCode  # noqa: N806
            jobs, scenes = job_pb2_grpc.JobServiceStub(ch), scene_pb2_grpc.SceneServiceStub(ch)
            assert _code(jobs.GetJob, job_pb2.GetJobRequest(job_id="j" + "0" * 24), metadata=A) == C.UNAVAILABLE
            assert _code(scenes.ListScenes, scene_pb2.ListScenesRequest(), metadata=A) == C.UNAVAILABLE
            req = _request(world)
            req.scene_id = "s" + "a" * 24  # a well-formed id: its owner must be asked of the store
            assert _code(render_pb2_grpc.RenderServiceStub(ch).Render, req, metadata=A) == C.UNAVAILABLE
    finally:
        server.stop(0)


def test_python_client_renders_the_clip_camera_into_a_png(world, tmp_path):
    import cv2

    from worker.grpc_client import AggClient

    target = world["bundle"].frame(2)
    with AggClient(f"127.0.0.1:{world['server'].bound_port}", "key-a") as client:
        info = client.scene("sA")
        images = client.render("sA", info.timestamps_us[2], [client.camera_of(info, 2)], depth=True, instance=True)
        assert len(client.scene_graph("sA", poses=False).nodes) >= 2
    rgb = images[0]["rgb"]
    assert rgb.dtype == np.uint8 and images[0]["depth"].dtype == np.float32
    assert set(np.unique(images[0]["instance"])) <= {0, *world["graph"].slot_track_ids().tolist()}
    path = tmp_path / "view.png"
    assert cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    back = cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB) / 255.0
    with torch.no_grad():
        direct = psnr(world["graph"].render(2).color.clamp(0, 1).numpy(), target)
    assert abs(psnr(back, target) - direct) < 0.1


def test_generated_code_follows_the_protos(tmp_path):
    import shutil

    from worker import grpc_codegen

    protos = tmp_path / "proto"
    shutil.copytree(grpc_codegen.PROTO_ROOT, protos)
    out = tmp_path / "_gen"
    assert not grpc_codegen.is_current(out, protos)
    grpc_codegen.ensure_generated(out, protos)
    assert grpc_codegen.is_current(out, protos)
    text = (out / "render_pb2_grpc.py").read_text()
    assert "from . import render_pb2" in text and "from agg.v1" not in text  # never the engine package `agg`
    with open(protos / "agg" / "v1" / "render.proto", "a") as f:
        f.write("\n// an edit\n")
    assert not grpc_codegen.is_current(out, protos)  # stale after an edit: regenerated on the next import


def test_concurrent_renders_agree(world):
    from concurrent.futures import ThreadPoolExecutor

    req = _request(world, 3, rgb_encoding=cpb.IMAGE_ENCODING_RAW, instance=True)
    ref = world["render"].Render(req, metadata=A).images[0]

    def one(_):
        img = world["render"].Render(req, metadata=A).images[0]
        return img.rgb.data == ref.rgb.data and img.instance.data == ref.instance.data

    with ThreadPoolExecutor(6) as pool:
        assert all(pool.map(one, range(24)))


def test_scene_cache_is_lru_and_reloads_only_on_change(world):
    from worker.grpc_scenes import SceneCache

    cache = SceneCache(capacity=1)
    a, b = world["scenes"] / "sA", world["scenes"] / "sB"
    first = cache.get(a)
    assert cache.get(a) is first and cache.loads == 1  # unchanged file: no reload
    cache.get(b)
    assert len(cache) == 1 and cache.loads == 2  # sA evicted
    assert cache.get(a) is not first and cache.loads == 3
