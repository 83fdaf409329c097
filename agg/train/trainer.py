"""The training loop: one optimiser per node group, Tick-Tock phases, densification, topology evolution,
checkpoints that resume bit-exactly, progress events and cooperative cancellation.

Node groups (``tick_tock.GROUPS``): ``camera`` (pose corrections), ``static`` (background and sky Gaussians),
``agents`` (every agent node's canonical Gaussians, per-frame poses and deformation network). Each has its own
Adam optimiser. A step renders one training frame (a seeded shuffled order, epoch by epoch), adds the semantic
attention loss in Tick / Tock phases (Eq. 3), back-propagates, steps the optimisers of the phase's trainable
groups, then densifies and, at the topology milestones, evolves the graph.
"""

from __future__ import annotations

import math
import time
from dataclasses import replace
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from agg.graph import SceneGraph
from agg.nodes.gaussians import keep_rows
from agg.io.bundle import SceneBundle
from agg.priors.metric_scale import MetricScale, estimate_metric_scale
from agg.train.camera_tracking import track_cameras
from agg.train.checkpoint import load_state, restore, save_state, trainer_state
from agg.train.config import TrainConfig
from agg.train.data import TrainData
from agg.train.densify import DensifyConfig, Densifier, highest
from agg.train.eta import RunClock
from agg.eval.ego import with_ego_from
from agg.eval.metrics import psnr
from agg.train.losses import photometric_loss, semantic_attention_loss
from agg.train.moments import loss_key, restart_on_change
from agg.train.tick_tock import GROUPS, TickTockSchedule, set_trainable

# what the topology log keeps of each evolution's report
BOOSTED = ("means", "tau", "rate")  # the agent parameter groups whose rates agent_boost raises
LOG_KEYS = ("iteration", "candidates", "clusters", "tracks", "track_runs", "floating", "fast", "static", "moving",
            "boxed", "silhouette", "reassigned", "spawned", "pruned", "demoted", "reanchored")


class Cancelled(Exception):
    """Training stopped because ``should_stop()`` returned True; the latest state is in the checkpoint."""


def scene_extent(graph: SceneGraph) -> float:
    """A scene size for the scale thresholds: the median distance of the background to the camera path's centre."""
    centres = graph.camera.prior[:, :3, 3]  # [T, 3]
    c = centres.mean(0)
    d = (graph.background.means.detach() - c).norm(dim=-1)
    radius = float((centres - c).norm(dim=-1).max())
    return max(float(d.median()) if len(d) else 1.0, radius, 1e-3)


class Trainer:
    def __init__(self, graph: SceneGraph, data: TrainData, config: TrainConfig, bundle: SceneBundle | None = None,
                 progress: Callable[[dict], None] | None = None, should_stop: Callable[[], bool] | None = None,
                 checkpoint_ok: Callable[[], bool] | None = None, metric: MetricScale | None = None):
        """``checkpoint_ok()`` is asked before every checkpoint write; False skips it (a worker that lost its job's
        lease must not overwrite the checkpoint of the attempt that now owns the job). ``metric``: metres per scene
        unit (default: ``estimate_metric_scale(bundle)``; 1 without a bundle)."""
        self.graph, self.data, self.cfg, self.bundle = graph, data, config, bundle
        self.progress, self.should_stop, self.checkpoint_ok = progress, should_stop, checkpoint_ok
        graph.to(data.images.device)  # training runs where the data is (TrainData.to)
        graph.K = data.K.clone()
        graph.width, graph.height = data.width, data.height
        cfg = config
        self.schedule = TickTockSchedule(cfg.milestone(cfg.warmup), max(1, cfg.milestone(cfg.alternate)),
                                         cfg.milestone(cfg.joint), cfg.tick_tock, cfg.lr.joint_decay, cfg.tick_share)
        self.extent = scene_extent(graph)
        # metres per scene unit: the metric settings (topology, pose rates) read scene units through it
        if metric is None:
            metric = estimate_metric_scale(bundle) if bundle is not None else MetricScale(1.0, "none")
        self.metric = metric
        self.iteration = 0
        self.history: list[dict] = []  # one row per iteration: loss, psnr, phase
        self.spawned: list[int] = []
        self.pruned: list[int] = []
        self.topology_log: list[dict] = []  # one compact row per evolution (counts, ids, track runs)
        self.reanchored: dict[str, dict] = {}  # spawned track id -> re-anchoring when training ended (offset, fit)
        self.generator = torch.Generator().manual_seed(int(cfg.seed))
        self.order: list[int] = []
        dcfg = DensifyConfig(grad_threshold=cfg.grad_threshold, refine_start=cfg.densify_from,
                             refine_stop=cfg.densify_until, refine_every=cfg.densify_every,
                             reset_every=cfg.opacity_reset_every, max_gaussians=cfg.max_gaussians,
                             size_prune_start=cfg.opacity_reset_every, seed=cfg.seed).scaled(cfg.scale)
        # refine statistics need several views per refine, and opacity needs time to recover after a reset:
        # short presets keep the paper's proportions but not periods below these floors
        dcfg = replace(dcfg, refine_every=max(dcfg.refine_every, 20),
                       reset_every=max(dcfg.reset_every, 500) if cfg.opacity_reset else 0)
        self.densifier = Densifier(dcfg, self.extent) if cfg.densify else None
        # with events_at_tick_start, each opacity reset moves to the first iteration the background trains on from
        # (dropped if that falls after densification ends: nothing would prune what the reset leaves transparent)
        self.reset_at = None
        if cfg.events_at_tick_start:
            resets = range(dcfg.reset_every, dcfg.refine_stop, dcfg.reset_every) if dcfg.reset_every > 0 else ()
            self.reset_at = {m for m in map(self.schedule.next_settled, resets) if m < dcfg.refine_stop}
        self.topology = self._make_topology() if cfg.topology else None
        self.tracking = cfg.tracking.scaled(cfg.scale) if cfg.tracking is not None else None
        self.tracking_log: list[dict] = []  # one row per camera-tracking round
        self.optimizers: dict[str, torch.optim.Optimizer] = {}
        self.loss_keys: dict[str, str] = {}  # group -> the key of the loss it last stepped on (agg.train.moments)
        self.build_optimizers()
        self.clock = RunClock()  # what the iterations, tracking steps and evolutions cost (agg.train.eta)
        self._tracking_t = 0.0  # when the last tracking step ended

    # ------------------------------------------------------------------ set-up
    def _make_topology(self):
        """Topology evolution at the scaled milestones (paper: every 10k iterations up to 20k); needs the bundle's
        semantic features and prototype bank (without them there is nothing to call agent-like)."""
        b = self.bundle
        if b is None or b.semantics is None or b.semantics.prototypes is None:
            return None
        from agg.train.data import resize_depth
        from agg.train.topology import TopologyEvolution, frame_seconds
        from agg.train.topology_track import tracklet_half_extents

        depth = resize_depth(b.dense_depth, self.data.width, self.data.height) if b.has("depth_dense") else None
        ids = [int(i) for i in b.tracklets.ids] if b.tracklets is not None else []
        dynamic = (resize_depth(b.dynamic_masks, self.data.width, self.data.height) > 0.5
                   if b.has("dynamic_masks") else None)
        conf = b.dense_depth_confidence if depth is not None else None
        conf = resize_depth(conf, self.data.width, self.data.height) if conf is not None else None
        # the frames, for the motion test of a planned spawn (topology_motion); it reads only the training frames
        images = self.data.images.detach().cpu().numpy()  # [T, H, W, 3] float in [0, 1] (a view on the CPU)
        return TopologyEvolution(self.cfg.evolution.scaled(self.cfg.scale), b.semantics, self.data.K.cpu().numpy(),
                                 self.data.width, self.data.height, self.metric.metres_per_unit,
                                 depth=depth, reserved_ids=ids, dynamic=dynamic,
                                 box_half=tracklet_half_extents(b.tracklets), images=images, depth_confidence=conf,
                                 frame_seconds=frame_seconds(b.timestamps_us))

    def _lr_scale(self) -> float:
        """Pose-rate factor 30000 / iterations, at most 15 (the balanced preset's): below ~2,000 iterations a
        larger per-step rate only makes the poses jump (a 80-iteration run moved agents by centimetres a step)."""
        return min(30_000 / max(self.cfg.iterations, 1), 15.0)

    def _translation_scale(self) -> float:
        """The pose-translation rates are metres per step: scene units per metre turns them into scene units."""
        return self._lr_scale() * self.metric.units_per_metre

    def param_groups(self) -> dict[str, list[dict]]:
        g, lr, cfg = self.graph, self.cfg.lr, self.cfg
        boost = lr.agent_boost if cfg.tick_tock else lr.agent_boost_ablated
        pose_scale = self._lr_scale()

        def gaussian_lrs(means_lr: float) -> dict[str, float]:
            return {"means": means_lr * self.extent, "log_scales": lr.log_scales, "quats": lr.quats,
                    "opacity_logits": lr.opacity_logits, "sh": lr.sh}

        out: dict[str, list[dict]] = {name: [] for name in GROUPS}
        out["camera"] = g.camera.param_groups(lr.camera * self._translation_scale())
        out["camera"][0]["lr"] = lr.camera_rotation * pose_scale  # camera#omega
        out["static"] = g.background.param_groups("background", gaussian_lrs(lr.means))
        if g.sky is not None:
            out["static"] += g.sky.param_groups("sky", gaussian_lrs(lr.means))
        for name, node in (("rigid", g.rigid), ("nonrigid", g.nonrigid)):
            if node is None:
                continue
            lrs = gaussian_lrs(lr.agent_means * boost)
            pose_lr = lr.agent_pose * boost * self._translation_scale()  # translation: raised with Tick-Tock on
            rotation_lr = lr.agent_rotation * pose_scale  # never raised (the paper raises translations only)
            rate_lr = lr.agent_track_rate * boost * pose_scale  # dimensionless: no scene-unit factor
            if name == "nonrigid":
                groups = node.param_groups(name, lrs, pose_lr, lr.deform, rotation_lr, rate_lr)
            else:
                groups = node.param_groups(name, lrs, pose_lr, rotation_lr, rate_lr)
            for grp in groups:
                grp["boost"] = boost if grp["name"].split("#")[1] in BOOSTED else 1.0
            out["agents"] += groups
        for groups in out.values():
            for grp in groups:
                grp["base_lr"] = grp["lr"]
        return out

    def build_optimizers(self) -> None:
        """(Re)build the per-group Adam optimisers, keeping the moments of parameters that still exist."""
        old = {}
        for opt in self.optimizers.values():
            for grp in opt.param_groups:
                for p in grp["params"]:
                    if p in opt.state:
                        old[p] = opt.state[p]
        self.optimizers = {}
        for name, groups in self.param_groups().items():
            if groups:
                opt = torch.optim.Adam(groups, eps=1e-15)
                for grp in opt.param_groups:
                    for p in grp["params"]:
                        if p in old:
                            opt.state[p] = old[p]
                self.optimizers[name] = opt

    def group_params(self) -> dict[str, list[torch.nn.Parameter]]:
        return {name: [p for grp in opt.param_groups for p in grp["params"]]
                for name, opt in self.optimizers.items()}

    # ------------------------------------------------------------------ one step
    def next_frame(self) -> int:
        if not self.order:
            perm = torch.randperm(len(self.data.train_frames), generator=self.generator).tolist()
            self.order = [self.data.train_frames[i] for i in perm]
        return self.order.pop(0)

    def set_lrs(self, phase) -> None:
        lr = self.cfg.lr
        t = min(self.iteration / max(self.cfg.iterations, 1), 1.0)
        decay = (lr.means_final / lr.means) ** t  # exponential means decay (3DGS)
        warmup = phase.name == "warmup"
        unboost = warmup and not lr.boost_in_warmup  # every boosted group at OmniRe's rate
        unboost_poses = warmup and not lr.warmup_pose_boost  # the pose groups only
        unboost_means = warmup and not lr.warmup_means_boost  # the agent means only
        for name, opt in self.optimizers.items():
            factor = phase.lr_factor_of(name)
            for grp in opt.param_groups:
                means = grp["name"].endswith("#means")
                f = factor * (decay if means else 1.0)
                if unboost or (unboost_poses and not means) or (unboost_means and means):
                    f /= grp.get("boost", 1.0)
                grp["lr"] = grp["base_lr"] * f

    def trainable_groups(self, phase) -> set:
        trainable = set(phase.trainable)
        if self.graph.num_agents == 0 and phase.name == "tock":  # nothing to train in Tock without agents
            trainable = {"camera", "static"}
        return trainable

    def forward_backward(self, frame: int, phase) -> tuple[torch.Tensor, torch.Tensor | None, object]:
        """Freeze the groups the phase does not train, render ``frame``, back-propagate L_photo (+ L_sem).
        Returns (loss, semantic loss or None, RenderOutput)."""
        cfg, data = self.cfg, self.data
        set_trainable(self.group_params(), frozenset(self.trainable_groups(phase)))
        gt = data.images[frame]
        out = self.graph.render(frame)
        if self.densifier is not None and out.meta.means2d.requires_grad:
            out.meta.means2d.retain_grad()
        color = with_ego_from(gt, out.color, data.scene_weight)  # [H, W, 3] no gradient to the ego's pixels
        photo = photometric_loss(color, gt, cfg.ssim_weight, self._pixel_weight(frame, phase))
        loss, sem = photo, None
        if cfg.semantic and phase.attention is not None and data.m_bg is not None:
            m = (data.m_bg if phase.attention == "bg" else data.m_ag)[frame]
            sem = semantic_attention_loss(color, gt, m, cfg.lambda_sem, cfg.delta)
            loss = photo + sem
        if not loss.requires_grad:
            return loss, sem, out
        if sem is not None and self._densify_reads_photo(out):
            # the densifier's statistic is dL_photo/dmeans2d, the gradient its threshold is calibrated on; the
            # parameters get the gradient of the whole loss (two backward passes, summed into .grad)
            photo.backward(retain_graph=True)
            grad2d = out.meta.means2d.grad.clone()  # [N, 2]
            sem.backward()
            out.meta.means2d.grad = grad2d
        else:
            loss.backward()
        return loss, sem, out

    def _masks_agents(self, phase) -> bool:
        """Whether this phase's L_photo leaves out the frozen agents' pixels (a Tick with ``tick_agent_mask``)."""
        return self.cfg.tick_agent_mask and phase.name == "tick" and self.graph.num_agents > 0

    def _pixel_weight(self, frame: int, phase) -> torch.Tensor | None:
        """[H, W] L_photo's pixel weight: 0 on the ego vehicle (``TrainData.scene_weight``), times the static
        weight in a Tick with ``tick_agent_mask``; None where every pixel counts alike."""
        static, scene = self._static_weight(frame, phase), self.data.scene_weight
        if static is None or scene is None:
            return scene if static is None else static
        return static * scene

    def _static_weight(self, frame: int, phase) -> torch.Tensor | None:
        """[H, W] 1 - the frozen agents' rendered alpha in a Tick with ``tick_agent_mask`` on, else None."""
        if not self._masks_agents(phase):
            return None
        slices = self.graph.node_slices()  # rows in compose order: background, sky, then the agents
        agent = torch.zeros(slices["nonrigid"].stop, 1)  # [N, 1] 1 on agent rows
        agent[slices["rigid"].start:] = 1.0
        with torch.no_grad():
            out = self.graph.render(frame, colors=agent.to(self.graph.background.means.device))
        return (1.0 - out.color[..., 0]).clamp(0.0, 1.0)

    def _densify_reads_photo(self, out) -> bool:
        """Whether this step's screen-space gradients go to the densifier and must leave L_sem out."""
        d = self.densifier
        return (d is not None and self.cfg.densify_grad == "photo" and out.meta.means2d.requires_grad
                and self.iteration < d.config.refine_stop)

    def step(self) -> dict:
        g = self.graph
        phase = self.schedule.phase(self.iteration)
        trainable = self.trainable_groups(phase)
        self.set_lrs(phase)
        frame = self.next_frame()
        loss, sem, out = self.forward_backward(frame, phase)
        if self.topology is not None and g.background.means.grad is not None:
            self.topology.accumulate(frame, g.background.means.grad)
        if self.densifier is not None and out.meta.means2d.grad is not None:
            self._accumulate_2d(out, trainable)
        if self.cfg.restart_moments:
            restart_on_change(self.optimizers, self.loss_keys, trainable,
                              loss_key(phase.attention if sem is not None else None, self._masks_agents(phase)))
        for name in trainable:
            if name in self.optimizers:
                self.optimizers[name].step()
        if "agents" in trainable and self.cfg.agent_box_margin is not None:
            for node in g.agent_nodes():
                node.confine(self.cfg.agent_box_margin)
        for opt in self.optimizers.values():
            opt.zero_grad(set_to_none=True)
        self.iteration += 1
        self._densify(trainable)
        if self.topology is not None and self.topology.config.due(self.iteration):
            self._evolve()
        row = {"iteration": self.iteration, "frame": frame, "phase": phase.name, "loss": float(loss.detach()),
               "sem": None if sem is None else float(sem.detach()),
               "psnr": psnr(out.color.detach(), self.data.images[frame], self.data.scene_weight)}  # 0/1: a mask
        self.history.append(row)
        return row

    def _accumulate_2d(self, out, trainable: set) -> None:
        grad, radii, vis = out.meta.means2d.grad, out.meta.radii, out.meta.visible
        for key, sl in self.graph.node_slices().items():
            group = _group_of(key)
            if sl.stop > sl.start and group in trainable:
                self.densifier.accumulate(key, grad[sl], radii[sl], vis[sl], self.data.width, self.data.height)

    def _densify(self, trainable: set) -> None:
        """Densify / prune / reset the Gaussian sets of the groups this phase trains (frozen nodes stay as they
        are: a Tick never changes an agent)."""
        if self.densifier is None:
            return
        g = self.graph
        changed = False
        for key, params in g.gaussian_sets().items():
            group = _group_of(key)
            if group not in trainable or key == "sky":  # the far field is neither split nor size-pruned: its
                continue  # Gaussians are large by design (and would all go under max_screen_fraction)
            opt = self.optimizers.get(group)
            node = getattr(g, key) if key in ("rigid", "nonrigid") else None
            extent = None
            if node is not None and len(params):  # agents: sizes relative to the agents' own extent
                extent = max(2.0 * float(params.means.detach().abs().quantile(0.98)), 1e-3)
            src = self.densifier.step(key, params, opt, self.iteration, extent=extent,
                                      groups=node.instance if node is not None else None,
                                      reset_opacity=node is None and self.reset_at is None)
            if src is None:
                continue
            changed = True
            if node is not None:
                node.instance = node.instance[src]
            if key == "background" and self.topology is not None:
                self.topology.on_rows_changed(src)
        if changed:
            self._check_budget()
        if self.reset_at is not None and self.iteration in self.reset_at:  # after a Tock too: the Tick starts now
            self.densifier.reset_opacity(g.background, self.optimizers.get("static"))

    def _check_budget(self) -> None:
        n = len(self.graph.background)
        if n > self.cfg.max_gaussians:  # the densifier caps per set; keep the invariant visible
            raise RuntimeError(f"background has {n} Gaussians, over the budget {self.cfg.max_gaussians}")

    def _fit_budget(self) -> None:
        """A demoted agent's Gaussians may land in a full background: drop its least opaque rows to the budget."""
        bg = self.graph.background
        if len(bg) <= self.cfg.max_gaussians:
            return
        keep = highest(bg.opacity_logits.detach().reshape(len(bg), -1)[:, 0], self.cfg.max_gaussians)  # [N]
        keep_rows(bg, keep, self.optimizers.get("static"))
        src = torch.nonzero(keep).reshape(-1)
        if self.densifier is not None:
            self.densifier.remap("background", src)
        if self.topology is not None:
            self.topology.on_rows_changed(src)

    def _evolve(self) -> None:
        report = self.topology.evolve(self.graph, self.optimizers.get("static"), self.iteration)
        self.spawned += list(report.get("spawned", []))
        self.pruned += list(report.get("pruned", []))
        self.topology_log.append({k: report[k] for k in LOG_KEYS if k in report})
        if self.densifier is not None:
            src = report.get("bg_src")
            if src is not None:
                self.densifier.remap("background", src)
            for key in ("rigid", "nonrigid"):
                self.densifier.forget(key)
        self._fit_budget()
        self.build_optimizers()
        self.emit(event="topology", report={k: v for k, v in report.items() if k != "bg_src"})

    def _track_if_due(self) -> bool:
        """A camera-tracking round (``agg.train.camera_tracking``) once the next milestone is reached, before the
        first step whose phase trains the camera (a milestone that falls in a Tock waits for the next Tick).
        False when ``should_stop`` cancelled the round (the cameras are as they were before it)."""
        t = self.tracking
        if t is None or self.tracked >= len(t.at) or self.iteration < t.at[self.tracked]:
            return True
        if "camera" not in self.trainable_groups(self.schedule.phase(self.iteration)):
            return True
        if self.cfg.events_at_tick_start and not self.schedule.settles(self.iteration):
            return True  # late in a Tick: the cameras would move and the background stand frozen in the Tock
        set_trainable(self.group_params(), frozenset())  # every Gaussian frozen; tracking frees omega / tau
        t0 = self._tracking_t = time.perf_counter()
        attention = self.data.m_bg if self.cfg.semantic else None
        report = track_cameras(self.graph, self.data.images, self.data.train_frames, t, self.extent,
                               attention=attention, ssim_weight=self.cfg.ssim_weight, lambda_sem=self.cfg.lambda_sem,
                               delta=self.cfg.delta, should_stop=self.should_stop, on_step=self._tracking_step,
                               weight=self.data.scene_weight)
        if report is None:
            return False
        row = {"iteration": self.iteration, "seconds": round(time.perf_counter() - t0, 2), **report}
        self.tracking_log.append(row)
        self.emit(event="tracking", report=row)
        return True

    def _tracking_step(self, done: int, total: int) -> None:
        """After each step of a tracking round: time it, and report it (the iteration count stands still)."""
        now = time.perf_counter()
        self.clock.tracking_step(now - self._tracking_t, first=done == 1)
        self._tracking_t = now
        self._progress(None, done, tracking={"step": done, "steps": total})

    @property
    def tracked(self) -> int:
        """Tracking milestones served: those up to the last round's iteration (a round that waited for a Tick
        serves every milestone passed meanwhile)."""
        if self.tracking is None or not self.tracking_log:
            return 0
        return sum(1 for a in self.tracking.at if a <= self.tracking_log[-1]["iteration"])

    # ------------------------------------------------------------------ loop, events, checkpoints
    def emit(self, **event) -> None:
        if self.progress is not None:
            self.progress(event)

    def work_left(self, tracking_done: int = 0) -> tuple[int, int, int]:
        """(iterations, camera-tracking steps, topology evolutions) still to run, ``tracking_done`` steps into a
        round (the round under way counts as ahead until it ends)."""
        total, t = self.cfg.iterations, self.tracking
        steps = 0
        if t is not None:
            rounds = sum(1 for a in t.at if a <= total) - self.tracked
            steps = max(rounds * len(t.levels) * t.steps - tracking_done, 0)
        evolutions = self.topology.config.due_after(self.iteration, total) if self.topology is not None else 0
        return total - self.iteration, steps, evolutions

    def _progress(self, row: dict | None, tracking_done: int = 0, **extra) -> None:
        """A training progress event after iteration ``row`` (None: during a tracking round, ``tracking_done``
        steps into it)."""
        eta = self.clock.eta(*self.work_left(tracking_done), frames=len(self.data.train_frames))
        phase = row["phase"] if row is not None else self.schedule.phase(self.iteration).name
        self.emit(stage="train", iteration=self.iteration, total=self.cfg.iterations, phase=phase,
                  loss=None if row is None else row["loss"], psnr=None if row is None else row["psnr"],
                  n_gaussians=self.graph.num_gaussians(), agents_spawned=len(self.spawned),
                  agents_pruned=len(self.pruned), eta_s=eta, **extra)

    def run(self, checkpoint: Path | None = None, checkpoint_every: int | None = None) -> list[dict]:
        every = self.cfg.checkpoint_every if checkpoint_every is None else checkpoint_every
        total = self.cfg.iterations
        while self.iteration < total:
            if (self.should_stop is not None and self.should_stop()) or not self._track_if_due():
                self._checkpoint(checkpoint)
                raise Cancelled(f"cancelled at iteration {self.iteration}")
            t0, evolutions = time.perf_counter(), len(self.topology_log)
            row = self.step()
            seconds = time.perf_counter() - t0
            if len(self.topology_log) > evolutions:
                self.clock.evolution(seconds)
            else:
                self.clock.step(seconds)
            if not math.isfinite(row["loss"]):
                raise FloatingPointError(f"non-finite loss at iteration {self.iteration}: {row}")
            if self.iteration % 10 == 0 or self.iteration == total:
                self._progress(row)
            if every and self.iteration % every == 0:
                self._checkpoint(checkpoint)
        self._reanchor()
        return self.history

    def _reanchor(self) -> None:
        """When training ends: re-anchor the spawned agents' boxes on their rendered surfaces (renders do not
        change; ``agg.train.topology_anchor``); ``self.reanchored`` keeps the offsets, fits and whether applied."""
        if self.topology is None or not self.topology.config.reanchor or not self.topology.spawned_ids:
            return
        self.reanchored = self.topology.reanchor(self.graph)
        self.emit(event="reanchor", iteration=self.iteration, reanchored=self.reanchored)

    def _checkpoint(self, path: Path | None) -> None:
        if path is not None and (self.checkpoint_ok is None or self.checkpoint_ok()):
            self.save(path)

    def state_dict(self) -> dict:
        return trainer_state(self)

    def save(self, path: Path) -> None:
        save_state(self.state_dict(), path)

    @classmethod
    def resume(cls, path: Path, data: TrainData, config: TrainConfig, bundle: SceneBundle | None = None,
               **kwargs) -> "Trainer":
        """The trainer of the checkpoint at ``path``, on the device of ``data`` (agg.train.checkpoint)."""
        state = load_state(path)
        trainer = cls(SceneGraph.from_state(state["graph"]), data, config, bundle, **kwargs)
        restore(trainer, state)
        return trainer


def _group_of(key: str) -> str:
    """The optimiser group of a Gaussian set of ``SceneGraph.gaussian_sets`` / ``node_slices``."""
    return "static" if key in ("background", "sky") else "agents"


def seed_everything(seed: int) -> None:
    torch.manual_seed(seed)
    np.random.seed(seed % (2**32))
