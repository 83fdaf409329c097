"""Camera tracking: pose-only refinement against a frozen map, and when the trainer runs it."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from agg.graph import SceneGraph
from agg.io.bundle import SceneBundle
from agg.synth.corrupt import NoiseConfig
from agg.synth.scene import SceneConfig
from agg.synth.suite import generate, write_bundle
from agg.io.video import scale_intrinsics
from agg.train.camera_tracking import TrackingConfig, level_size, track_cameras
from agg.train.config import get_preset
from agg.train.data import load_train_data
from agg.train.tick_tock import set_trainable
from agg.train.trainer import Cancelled, Trainer, scene_extent, seed_everything


@pytest.fixture(scope="module")
def bundle(tmp_path_factory):
    noise = NoiseConfig()  # exact priors: the map built from them is right, so a displaced camera has a target
    gt, priors = generate(SceneConfig(seed=2, frames=8, width=128, height=80), noise)
    path = tmp_path_factory.mktemp("trk") / "b"
    write_bundle(path, gt, priors, noise)
    return SceneBundle.load(path)


def test_level_intrinsics_keep_pixel_centres():
    K = np.array([[100.0, 0, 63.5], [0, 100.0, 39.5], [0, 0, 1]])  # noqa: N806
    assert level_size(128, 80, 2) == (64, 40) and level_size(128, 80, 32) == (8, 8)
    k2 = scale_intrinsics(K, (128, 80), level_size(128, 80, 2))
    assert np.allclose(k2, [[50.0, 0, 31.5], [0, 50.0, 19.5], [0, 0, 1]])
    assert np.array_equal(scale_intrinsics(K, (128, 80), level_size(128, 80, 1)), K)


def _displaced(bundle):
    """A graph whose training frames 2 and 5 are 0.4 m and 2 degrees off, and the targets of every frame: the
    map's own renders through the exact cameras, so tau = omega = 0 is the optimum."""
    cfg = get_preset("tiny")
    data = load_train_data(bundle, cfg.max_width)
    g = SceneGraph.from_bundle(bundle, cfg.init)
    g.K, g.width, g.height = data.K.clone(), data.width, data.height
    with torch.no_grad():
        images = torch.stack([g.render(i).color for i in range(len(g.camera))])  # [T, H, W, 3]
        g.camera.tau[2] = torch.tensor([0.3, 0.0, 0.25])
        g.camera.tau[5] = torch.tensor([-0.25, 0.1, -0.3])
        g.camera.omega[5] = torch.tensor([0.0, 0.035, 0.0])
    set_trainable({"all": list(g.parameters())}, frozenset())
    return g, images


def test_tracking_pulls_displaced_cameras_back_and_touches_nothing_else(bundle):
    g, images = _displaced(bundle)
    before = {k: v.detach().clone() for k, v in g.named_parameters() if not k.startswith("camera.")}
    frames = [2, 5]
    err0 = g.camera.tau[frames].detach().norm(dim=-1)  # [2] the displacement (the exact pose is tau = 0)
    rep = track_cameras(g, images, frames, TrackingConfig(), scene_extent(g))
    err1 = g.camera.tau[frames].detach().norm(dim=-1)
    assert (err1 < 0.4 * err0).all(), (err0, err1)
    assert float(g.camera.omega[5].detach().norm()) < 0.5 * 0.035
    assert all(lv["loss_last"] < lv["loss_first"] for lv in rep["levels"])
    # untracked frames (frame 0, the gauge, and every other) keep their corrections; Gaussians are untouched
    others = [i for i in range(len(g.camera)) if i not in frames]
    assert torch.equal(g.camera.tau[others], torch.zeros(len(others), 3))
    assert torch.equal(g.camera.omega[others], torch.zeros(len(others), 3))
    for k, v in g.named_parameters():
        if not k.startswith("camera."):
            assert torch.equal(v, before[k]), k
            assert v.grad is None, k


def test_the_full_size_level_finishes_closer_than_half_size(bundle):
    """The default ends at the training size: splatted at half size (``render_full`` off), the optimum is not the
    full-size one, and a level at full size after (4, 2) brings the displaced cameras closer (docs/TRAINING.md,
    camera tracking)."""
    assert TrackingConfig().levels[-1] == 1
    errs = {}
    for levels in [(4, 2), (4, 2, 1)]:
        g, images = _displaced(bundle)
        track_cameras(g, images, [2, 5], TrackingConfig(levels=levels, render_full=False), scene_extent(g))
        tau, omega = g.camera.tau.detach(), g.camera.omega.detach()
        errs[levels] = (float(tau[[2, 5]].norm(dim=-1).sum()), float(omega[5].norm()))  # metres, radians
    assert errs[(4, 2, 1)][0] < 0.85 * errs[(4, 2)][0], errs  # measured: 0.171 m against 0.211 m
    assert errs[(4, 2, 1)][1] < 0.6 * errs[(4, 2)][1], errs  # 0.006 against 0.013 rad


def test_centre_only_levels_leave_the_rotations_alone(bundle):
    """``rotation_from``: the levels before it move the centres alone; the rotation is free from that level on."""
    g, images = _displaced(bundle)
    omega0 = g.camera.omega.detach().clone()
    track_cameras(g, images, [2, 5], TrackingConfig(levels=(4, 2), steps=5, rotation_from=2), scene_extent(g))
    assert torch.equal(g.camera.omega.detach(), omega0)  # no level turned a camera
    assert g.camera.omega.requires_grad  # trainable at the end, as the round makes it at the start
    assert float(g.camera.tau[2].detach().norm()) < 0.39  # the centres moved (from 0.39 m off)
    g, images = _displaced(bundle)
    track_cameras(g, images, [2, 5], TrackingConfig(levels=(4, 2), steps=5, rotation_from=1), scene_extent(g))
    assert not torch.equal(g.camera.omega.detach()[5], omega0[5])  # the second level turned frame 5


@pytest.fixture(scope="module")
def plain_round(bundle) -> torch.Tensor:
    """tau [T, 3] after a round splatted at each level's size (``render_full`` off, the default until 2026-12-07;
    ungated) over frames 2-5 of ``_displaced``: the reference the gate's and render_full's tests compare with."""
    g, images = _displaced(bundle)
    track_cameras(g, images, [2, 3, 4, 5], TrackingConfig(render_full=False), scene_extent(g))
    return g.camera.tau.detach().clone()


def test_the_gate_keeps_exact_cameras_exact_and_still_pulls_displaced_ones_back(bundle, plain_round):
    """``gate``: a frame keeps the round's pose only where its loss at the training size went down. Frames 3 and
    4 start exact: an ungated round moves them (Adam's first steps have the rate's size whatever the gradient's),
    the gated round puts them back to exactly zero. Displaced frames 2 and 5 keep their correction."""
    frames = [2, 3, 4, 5]
    assert (plain_round[[3, 4]].norm(dim=-1) > 0.03).all()  # measured 0.094, 0.068 m
    ungated = plain_round[[2, 5]]
    g, images = _displaced(bundle)
    err0 = g.camera.tau[[2, 5]].detach().norm(dim=-1)  # [2]
    rep = track_cameras(g, images, frames, TrackingConfig(gate=True, render_full=False), scene_extent(g))
    tau, omega = g.camera.tau.detach(), g.camera.omega.detach()
    assert torch.equal(tau[[3, 4]], torch.zeros(2, 3)) and torch.equal(omega[[3, 4]], torch.zeros(2, 3))
    assert torch.equal(tau[[2, 5]], ungated)  # the same round, kept where it paid
    assert (tau[[2, 5]].norm(dim=-1) < 0.4 * err0).all()
    gate = rep["gate"]
    assert (gate["frames_kept"], gate["frames"]) == (2, 4)
    assert gate["loss_after"] < gate["loss_before"]
    assert g.camera.omega.requires_grad and g.camera.tau.requires_grad


def test_coarse_levels_that_blur_full_size_renders_leave_exact_cameras_and_pull_displaced_ones_home(bundle,
                                                                                                   plain_round):
    """``render_full``: a coarse level splats at the training size and area-averages the render, as the targets
    are averaged, so its optimum is the full-size one. Splatted at the level's size, the map's Gaussians render
    otherwise than blurred, and the round moves exact frames 3 and 4 (measured 0.094 and 0.068 m) and leaves
    displaced frames 2 and 5 0.06-0.11 m off; blurred, it keeps 3 and 4 within 2 mm and brings 2 and 5 within 5."""
    frames = [2, 3, 4, 5]
    splatted = plain_round[frames].norm(dim=-1)  # [4]
    g, images = _displaced(bundle)
    err0 = g.camera.tau[[2, 5]].detach().norm(dim=-1)  # [2], 0.39 and 0.40 m
    rep = track_cameras(g, images, frames, TrackingConfig(render_full=True), scene_extent(g))
    blurred = g.camera.tau.detach()[frames].norm(dim=-1)  # [4]
    assert rep["render_full"]  # the trainer's tracking log, and so a run's record, says how the round rendered
    assert (splatted[1:3] > 0.03).all() and (blurred[1:3] < 0.005).all()
    assert (blurred[[0, 3]] < 0.03 * err0).all() and (blurred < splatted).all()
    assert (g.camera.omega.detach()[[3, 4, 5]].norm(dim=-1) < 1e-3).all()


def test_a_tracking_milestone_in_a_tock_waits_for_the_next_tick(bundle):
    # 30 iterations: warm-up 5, phases of 1 (tick at odd iterations from 5), joint from 20
    tracking = TrackingConfig(at=(6_000, 30_000 * 25 // 30), levels=(4,), steps=2)
    cfg = replace(get_preset("tiny"), iterations=30, tracking=tracking, ablate=frozenset({"topology"}))
    seed_everything(cfg.seed)
    tr = Trainer(SceneGraph.from_bundle(bundle, cfg.init), load_train_data(bundle, cfg.max_width), cfg, bundle)
    assert tr.schedule.phase(6).name == "tock" and tr.schedule.phase(7).name == "tick"
    tr.run()
    assert [row["iteration"] for row in tr.tracking_log] == [7, 25]
    assert tr.tracked == 2 and all("camera" in tr.schedule.phase(r["iteration"]).trainable
                                   for r in tr.tracking_log)


def test_a_tracking_round_reports_each_step_and_the_eta_counts_the_rounds_ahead(bundle):
    tracking = TrackingConfig(at=(6_000, 30_000 * 25 // 30), levels=(4, 2), steps=2)
    cfg = replace(get_preset("tiny"), iterations=30, tracking=tracking, ablate=frozenset({"topology"}))
    seed_everything(cfg.seed)
    events, left = [], []
    tr = Trainer(SceneGraph.from_bundle(bundle, cfg.init), load_train_data(bundle, cfg.max_width), cfg, bundle)

    def progress(event: dict) -> None:
        events.append(event)
        left.append(tr.work_left(event.get("tracking", {}).get("step", 0)))

    tr.progress = progress
    assert tr.work_left() == (30, 8, 0)  # two rounds of 2 levels x 2 steps ahead
    tr.run()
    # each round (iterations 7 and 25) reports its 4 steps while the iteration count stands still, and the work
    # left counts the round's own steps down
    rounds = [(e["iteration"], e["tracking"]["step"], e["tracking"]["steps"], w)
              for e, w in zip(events, left) if "tracking" in e]
    assert rounds == [(7, s, 4, (23, 8 - s, 0)) for s in (1, 2, 3, 4)] + [(25, s, 4, (5, 4 - s, 0))
                                                                          for s in (1, 2, 3, 4)]
    assert all(e["stage"] == "train" and e["phase"] in ("tick", "joint") and e["loss"] is None and e["eta_s"] >= 0
               for e in events if "tracking" in e)
    train = [(e["iteration"], w) for e, w in zip(events, left) if e.get("stage") == "train" and "tracking" not in e]
    assert train == [(10, (20, 4, 0)), (20, (10, 4, 0)), (30, (0, 0, 0))]
    assert events[-1]["eta_s"] == 0.0 and tr.clock.seconds_per_tracking_step(6) > 0


def test_a_cancel_inside_a_tracking_round_puts_the_cameras_back_and_the_resumed_run_is_exact(bundle, tmp_path):
    cfg = replace(get_preset("tiny"), iterations=30, tracking=TrackingConfig(at=(10_000,), levels=(4, 2), steps=3),
                  ablate=frozenset({"topology"}), densify_from=300, densify_every=300)

    def trainer(stop_after: int | None = None) -> Trainer:
        seed_everything(cfg.seed)
        tr = Trainer(SceneGraph.from_bundle(bundle, cfg.init), load_train_data(bundle, cfg.max_width), cfg, bundle)
        calls = {"n": 0}

        def stop() -> bool:  # asked before each iteration, and before each step inside a tracking round
            calls["n"] += 1
            return stop_after is not None and calls["n"] > stop_after
        tr.should_stop = stop
        return tr

    full = trainer()
    full.run()
    (r,) = [row["iteration"] for row in full.tracking_log]
    before_round = trainer(stop_after=r)  # stops at the loop check of iteration r, before the round
    with pytest.raises(Cancelled):
        before_round.run()
    inside = trainer(stop_after=r + 1 + 4)  # stops before the round's 5th step (the second level's 2nd)
    ckpt = tmp_path / "ckpt.pt"
    with pytest.raises(Cancelled):
        inside.run(ckpt, checkpoint_every=0)
    assert inside.iteration == before_round.iteration == r and inside.tracking_log == []
    assert torch.equal(inside.graph.camera.tau, before_round.graph.camera.tau)
    assert torch.equal(inside.graph.camera.omega, before_round.graph.camera.omega)
    assert inside.graph.camera.tau.grad is None
    resumed = Trainer.resume(ckpt, load_train_data(bundle, cfg.max_width), cfg, bundle)
    resumed.run()
    assert [row["iteration"] for row in resumed.tracking_log] == [r]
    torch.testing.assert_close(torch.tensor([h["loss"] for h in resumed.history]),
                               torch.tensor([h["loss"] for h in full.history]), rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(resumed.graph.camera.tau.detach(), full.graph.camera.tau.detach())


def test_with_events_at_tick_start_tracking_and_the_opacity_reset_wait_for_a_tick_start(bundle):
    # 150 iterations: warm-up 25, Ticks of 5 from 25 every 10, joint from 100; milestone 5,600 -> 28, mid-Tick
    tracking = TrackingConfig(at=(5_600,), levels=(4,), steps=2)
    cfg = replace(get_preset("tiny"), iterations=150, tracking=tracking, ablate=frozenset({"topology"}),
                  events_at_tick_start=True)
    seed_everything(cfg.seed)
    tr = Trainer(SceneGraph.from_bundle(bundle, cfg.init), load_train_data(bundle, cfg.max_width), cfg, bundle,
                 should_stop=lambda: tr.iteration >= 37)
    s = tr.schedule
    assert (s.warmup, s.alternate, s.joint) == (25, 5, 100) and s.phase(28).name == "tick"
    assert [s.next_settled(i) for i in (3, 25, 28, 31, 35, 96, 120)] == [3, 25, 35, 35, 35, 100, 120]
    with pytest.raises(Cancelled):
        tr.run()
    assert [row["iteration"] for row in tr.tracking_log] == [35]  # not 28: the Tock from 30 would freeze the map
    # the balanced preset's one opacity reset (iteration 500, 34 steps before a Tock) moves to the next Tick's start
    bal = replace(get_preset("balanced"), events_at_tick_start=True, tracking=None)
    tb = Trainer(SceneGraph.from_bundle(bundle, bal.init), load_train_data(bundle, 64), bal, bundle)
    assert tb.densifier.config.is_reset(500) and tb.reset_at == {601}
    assert tb.schedule.phase(600).name == "tock" and tb.schedule.phase(601).name == "tick"
    bg = tb.graph.background
    with torch.no_grad():
        bg.opacity_logits.fill_(3.0)
    for it in (500, 601):  # the step before 601 was a Tock: the background is reset all the same
        tb.iteration = it
        tb._densify({"agents"} if it == 601 else {"camera", "static"})
        top = float(torch.sigmoid(bg.opacity_logits).max())
        assert (top > 0.9) if it == 500 else (top <= 2 * tb.densifier.config.prune_opacity + 1e-6), (it, top)
