"""Typed training configuration and the named presets (``fast``, ``balanced``, ``quality``, ``paper``).

Iteration milestones are written at the paper's scale (30,000 iterations, Sec. 4.2) and scaled by
``iterations / 30000`` (``TrainConfig.milestone``), so every preset keeps the same proportions: warm-up to 1/6,
Tick-Tock alternating every 1/30 until 2/3, then the joint phase; topology evolution every 1/6 from 1/6 to 2/3
(``agg.train.topology.TopologyConfig.scaled``).

Learning rates: Gaussian means use the 3DGS convention (``lr x scene extent``, decayed exponentially by 100x over
the run); the agent means and pose-translation rates are raised 10x over OmniRe's while Tick-Tock is on (the paper's
point: decoupling makes the larger steps safe), and fall back to OmniRe's when it is ablated. Agent pose rotations
keep 1e-5 either way: Sec. 4.2 raises translations only. Camera and agent pose rates are per step in scene units
(radians / metres): the paper's 1e-5 suits 30k steps on GPU-scale images; the shorter presets scale them by
``30000 / iterations`` so a preset can move a pose as far in total.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields, replace

from agg.io.bundle_priors import TRACK_ANCHORS
from agg.nodes.init import InitConfig
from agg.train.topology import TopologyConfig
from agg.train.camera_tracking import TrackingConfig

ABLATIONS = ("tick-tock", "semantic", "topology")
AGENT_ANCHORS = ("auto", *TRACK_ANCHORS)  # "auto": the bundle's Tracklets.anchor
CAMERA_TRACKING = ("on", "off", "auto")  # "auto": off where every camera prior is an SfM registration
PAPER_ITERATIONS = 30_000


@dataclass(frozen=True)
class LearningRates:
    means: float = 1.6e-4  # x scene extent (3DGS)
    means_final: float = 1.6e-6  # x scene extent, at the last iteration
    agent_means: float = 1.6e-4  # x scene extent; x agent_boost while Tick-Tock is on (paper: 1.6e-3)
    log_scales: float = 5e-3
    quats: float = 1e-3
    opacity_logits: float = 5e-2
    sh: float = 2.5e-3  # degree 0; higher bands / 20
    camera: float = 1e-5  # translation, per step at the paper's 30k iterations (scaled, see module doc)
    camera_rotation: float = 1e-5  # radians, per step at 30k iterations (the paper's camera rate)
    agent_pose: float = 1e-5  # translation; x agent_boost while Tick-Tock is on (paper: 1e-4)
    agent_rotation: float = 1e-5  # radians, never boosted: Sec. 4.2 raises pose translations only (OmniRe: 1e-5)
    agent_track_rate: float = 2e-6  # a spawned agent's track-speed correction (dimensionless), boosted like the
    # translations: x15 (balanced) x10 is 3e-4 a step, 0.06 (seed 2's speed error) in 200 Tock steps
    deform: float = 1e-3
    agent_boost: float = 10.0
    agent_boost_ablated: float = 1.0  # the boost with Tick-Tock ablated: OmniRe's rates (a probe can keep x10)
    boost_in_warmup: bool = True  # False: the warm-up (everything trains, nothing decoupled) keeps OmniRe's
    # agent rates and the boost starts with the first Tick
    warmup_pose_boost: bool = True  # False: the warm-up keeps OmniRe's pose-translation and track-rate rates
    # while the agent means stay boosted (with boost_in_warmup on)
    warmup_means_boost: bool = True  # False: the warm-up keeps OmniRe's agent-means rate while the pose
    # translations and track rates stay boosted (with boost_in_warmup on)
    joint_decay: float = 0.1  # camera and agent rates x this in the joint phase (the background's keep their own)


@dataclass(frozen=True)
class TrainConfig:
    name: str = "custom"
    max_width: int = 320  # training resolution: frames are downscaled to at most this width
    iterations: int = 3000
    sh_degree: int = 1
    max_gaussians: int = 80_000  # background budget (agents get agent_budget each)
    agent_budget: int = 4_000
    lr: LearningRates = field(default_factory=LearningRates)
    # milestones at the paper's scale (scaled by milestone())
    warmup: int = 5_000
    alternate: int = 1_000
    tick_share: float = 0.5  # share of each Tick + Tock cycle spent in the Tick (paper: 0.5, equal halves)
    tick_agent_mask: bool = False  # True: a Tick's L_photo leaves out the pixels the frozen agents cover (weight
    # 1 - their rendered alpha), so the camera and background learn from the static pixels only
    joint: int = 20_000
    # losses
    ssim_weight: float = 0.2
    lambda_sem: float = 0.8
    delta: float = 1e-6
    attention_norm: str = "global"  # "global" (paper: clip-wide min/max) | "percentile" (1st/99th percentiles)
    semantic_min_contrast: float | None = 1.5  # the semantic loss is off for a scene whose attention maps do not
    # separate the priors' dynamic masks by this ratio (agg.train.semantic.semantic_gate; None: always on)
    # densification (iteration numbers at the paper's scale too)
    densify: bool = True
    densify_from: int = 500
    densify_until: int = 15_000
    densify_every: int = 100
    opacity_reset_every: int = 3_000
    opacity_reset: bool = True  # False: no opacity reset (size pruning still starts at opacity_reset_every)
    events_at_tick_start: bool = False  # True: a camera-tracking round or the background's opacity reset that
    # falls inside the alternation waits for the next Tick's first iteration (TickTockSchedule.settles)
    grad_threshold: float = 2e-4
    densify_grad: str = "photo"  # what the densifier's screen gradient is of: "photo" (L_photo) | "total" (+ L_sem)
    restart_moments: bool = False  # True: a group's Adam state restarts when the loss it steps on changes (Eq. 3
    # on, off or to the other map; agg/train/moments.py)
    agent_anchor: str = "auto"  # "camera": the priors' agents move with the camera node's corrections, as
    # tracklets lifted into the world through the estimated cameras do (nodes/rigid.py); "world": they keep their
    # world poses; "auto": what the bundle's tracklets say they were measured against (Tracklets.anchor;
    # docs/TRAINING.md "Agents anchored to the camera")
    agent_box_margin: float | None = 0.25  # agents' canonical means stay in their box grown by this fraction of its
    # half extents (None: free, as before; docs/TRAINING.md "Agents stay in their boxes")
    ablate: frozenset = frozenset()
    seed: int = 0
    eval_every: int = 5  # hold out every 5th frame (frames i % 5 == 4)
    checkpoint_every: int = 500  # iterations between checkpoints (0: only at the end / on cancel)
    init: InitConfig = field(default_factory=InitConfig)
    tracking: TrackingConfig | None = field(default_factory=TrackingConfig)  # camera tracking (None: off)
    camera_tracking: str = "on"  # "on": the tracking rounds run (with ``tracking`` set); "off": they do not;
    # "auto" (the fast preset's): off where every camera's prior is a registration of the priors' SfM (pose source
    # "sfm"), on otherwise (docs/TRAINING.md "Tracking rounds only where the poses need them")
    evolution: TopologyConfig = field(default_factory=TopologyConfig)  # topology evolution's settings (paper scale)

    def __post_init__(self):
        if self.densify_grad not in ("photo", "total"):
            raise ValueError(f"densify_grad must be 'photo' or 'total', got {self.densify_grad!r}")
        if self.agent_anchor not in AGENT_ANCHORS:
            raise ValueError(f"agent_anchor must be one of {AGENT_ANCHORS}, got {self.agent_anchor!r}")
        if self.camera_tracking not in CAMERA_TRACKING:
            raise ValueError(f"camera_tracking must be one of {CAMERA_TRACKING}, got {self.camera_tracking!r}")
        if not 0.0 < self.tick_share < 1.0:
            raise ValueError(f"tick_share must lie strictly between 0 and 1, got {self.tick_share}")

    @property
    def scale(self) -> float:
        return self.iterations / PAPER_ITERATIONS

    def milestone(self, paper_iteration: int) -> int:
        return int(round(paper_iteration * self.scale))

    @property
    def tick_tock(self) -> bool:
        return "tick-tock" not in self.ablate

    @property
    def semantic(self) -> bool:
        return "semantic" not in self.ablate

    @property
    def topology(self) -> bool:
        return "topology" not in self.ablate

    def with_ablation(self, spec: str | None) -> "TrainConfig":
        """``"tick-tock,semantic"``; ``"all"`` is the fixed-topology GSG baseline; ``None`` / ``""`` nothing."""
        parts = {p.strip() for p in (spec or "").split(",") if p.strip()}
        if parts == {"all"}:
            parts = set(ABLATIONS)
        unknown = parts - set(ABLATIONS)
        if unknown:
            raise ValueError(f"unknown ablation(s) {sorted(unknown)}; choose from {', '.join(ABLATIONS)} or all")
        return replace(self, ablate=frozenset(parts))

    def override(self, values: dict | None) -> "TrainConfig":
        """A copy with top-level fields replaced (unknown names are an error)."""
        if not values:
            return self
        names = {f.name for f in fields(self)}
        bad = set(values) - names
        if bad:
            raise ValueError(f"unknown training option(s) {sorted(bad)}")
        return replace(self, **values)

    def as_dict(self) -> dict:
        d = asdict(self)
        d["ablate"] = sorted(self.ablate)
        return d


def _preset(name: str, max_width: int, iterations: int, sh_degree: int, max_gaussians: int, **kw) -> TrainConfig:
    init = InitConfig(background_budget=max_gaussians // 2, agent_budget=kw.pop("agent_budget", 3000),
                      sh_degree=sh_degree, opacity=kw.pop("init_opacity", 0.1))
    return TrainConfig(name=name, max_width=max_width, iterations=iterations, sh_degree=sh_degree,
                       max_gaussians=max_gaussians, init=init, **kw)


PRESETS: dict[str, TrainConfig] = {
    # CPU-sized presets; 'paper' is Sec. 4.2 (a GPU run: full resolution, 30k iterations, SH 3)
    "fast": _preset("fast", 320, 1_500, 0, 40_000, agent_budget=1500, checkpoint_every=250,
                    tracking=TrackingConfig(at=(2_500, 5_000), levels=(4, 2), steps=10), camera_tracking="auto"),
    "balanced": _preset("balanced", 480, 2_000, 1, 60_000, agent_budget=2000),
    "quality": _preset("quality", 960, 10_000, 2, 300_000, agent_budget=6000, checkpoint_every=1000),
    "paper": _preset("paper", 100_000, 30_000, 3, 1_000_000, agent_budget=20_000, checkpoint_every=2000),
}
# tests only: a few dozen iterations on tiny frames
PRESETS["tiny"] = _preset("tiny", 160, 80, 0, 20_000, agent_budget=500, checkpoint_every=20, init_opacity=0.5,
                          tracking=None)


def get_preset(name: str) -> TrainConfig:
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; choose from {', '.join(PRESETS)}")
    return PRESETS[name]
