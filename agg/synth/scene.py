"""Procedural driving scenes with exact geometry, deterministic by seed.

A scene is a straight road seen by an ego camera driving forward. Everything is built in a *road frame*
(OpenCV-like axes: x right, y down, z forward along the road; the road surface is the plane y = 0) and then
expressed in the *world frame* = the first camera's frame (``world_from_camera[0] = I``), as AGG's conventions ask.
The first camera has no pitch or roll relative to the road, so the world's vertical axis is its y axis (down).

Static content (road frame): the road plane with lane markings, two raised sidewalks (0.15 m boxes), building
blocks with textured facades on both sides, and an optional sky (a far-field colour gradient at infinite depth).

Agents (instance ids 1..K, in this order): moving cars, parked cars (rigid) and pedestrians (non-rigid, limbs swing
with time). Each agent has a per-frame ``world_from_agent`` pose and a fixed box size ``lwh`` (metres).

Agent frame = the tracklet box frame of docs/BUNDLE.md (KITTI's ``rotation_y`` convention): origin at the centre
of the 3D box, x along the length ``l`` (the heading), y along the height ``h`` (down), z along the width ``w``;
``world_from_agent = [R_y(yaw) | centre]`` with ``R_y(a) = [[cos a, 0, sin a], [0, 1, 0], [-sin a, 0, cos a]]``.
So yaw = 0 heads along world +x (right) and a car driving straight ahead along world +z has yaw = -pi/2.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

# Semantic classes (ids are stable: they index the class embeddings in features.py).
SEMANTIC_CLASSES: tuple[str, ...] = ("sky", "road", "marking", "sidewalk", "building", "car", "pedestrian")
SEM = {name: i for i, name in enumerate(SEMANTIC_CLASSES)}
BACKGROUND_CLASSES: tuple[str, ...] = ("sky", "road", "marking", "sidewalk", "building")
AGENT_KIND_OF_CLASS = {"car": "rigid", "pedestrian": "non_rigid"}

# Materials understood by raycast.shade (ints so that they can be stored in arrays).
MAT_ROAD, MAT_SIDEWALK, MAT_FACADE, MAT_PAINT, MAT_GLASS, MAT_RUBBER, MAT_SKIN, MAT_CLOTH = range(8)


class SceneConfigError(ValueError):
    """A scene configuration value is out of its valid range."""


@dataclass(frozen=True)
class SceneConfig:
    """What to generate. Lengths in metres, speeds in m/s, angles in degrees where named ``_deg``."""

    seed: int = 0
    frames: int = 24
    fps: float = 10.0
    width: int = 160  # pixels
    height: int = 96  # pixels
    hfov_deg: float = 80.0  # horizontal field of view; fx = fy = (width / 2) / tan(hfov / 2), cx, cy = image centre
    sky: bool = True  # False: the far field is black (still class "sky", depth invalid)
    moving_cars: int = 3
    parked_cars: int = 4
    pedestrians: int = 3
    ego_speed: float = 8.0
    camera_height: float = 1.6  # above the road surface
    lane_width: float = 3.5  # three lanes; the ego drives in the middle one
    parking_width: float = 2.5  # a parking strip outside each outer lane
    sidewalk_width: float = 3.0
    sway: float = 0.25  # lateral sway amplitude of the ego path (metres); its heading follows the path

    def validate(self) -> None:
        if self.frames < 2:
            raise SceneConfigError(f"frames must be >= 2, got {self.frames}")
        if self.width < 8 or self.height < 8:
            raise SceneConfigError(f"image must be at least 8x8 pixels, got {self.width}x{self.height}")
        if not 10.0 <= self.hfov_deg <= 150.0:
            raise SceneConfigError(f"hfov_deg must be in [10, 150], got {self.hfov_deg}")
        if self.fps <= 0:
            raise SceneConfigError(f"fps must be > 0, got {self.fps}")
        for name in ("moving_cars", "parked_cars", "pedestrians"):
            if not 0 <= getattr(self, name) <= 16:
                raise SceneConfigError(f"{name} must be in [0, 16], got {getattr(self, name)}")

    @property
    def road_half_width(self) -> float:
        return 1.5 * self.lane_width + self.parking_width

    def intrinsics(self) -> np.ndarray:
        """Pinhole K [3, 3] (pixels; OpenCV pixel-centre convention)."""
        f = 0.5 * self.width / np.tan(np.deg2rad(self.hfov_deg) / 2.0)
        return np.array([[f, 0.0, (self.width - 1) / 2.0], [0.0, f, (self.height - 1) / 2.0], [0.0, 0.0, 1.0]])


PRESETS: dict[str, SceneConfig] = {
    "default": SceneConfig(),
    "tiny": SceneConfig(frames=8, width=96, height=64, moving_cars=2, parked_cars=2, pedestrians=1),
    "wide": SceneConfig(width=192, height=64, hfov_deg=90.0),
}


@dataclass
class BoxSet:
    """Oriented boxes to ray-cast (struct of arrays, B boxes). Poses map box-local points to the world."""

    world_from_box: np.ndarray  # [B, 4, 4]
    half_size: np.ndarray  # [B, 3] half extents along the box's local x, y, z (metres)
    material: np.ndarray  # [B] int, MAT_*
    colour: np.ndarray  # [B, 3] base RGB in [0, 1]
    semantic: np.ndarray  # [B] int, SEM id
    instance: np.ndarray  # [B] int, 0 = background, k = agent k

    @staticmethod
    def empty() -> "BoxSet":
        return BoxSet(np.zeros((0, 4, 4)), np.zeros((0, 3)), np.zeros(0, int), np.zeros((0, 3)),
                      np.zeros(0, int), np.zeros(0, int))

    def __len__(self) -> int:
        return len(self.half_size)

    @staticmethod
    def concat(sets: list["BoxSet"]) -> "BoxSet":
        sets = [s for s in sets if len(s)] or [BoxSet.empty()]
        return BoxSet(*(np.concatenate([getattr(s, f) for s in sets]) for f in
                        ("world_from_box", "half_size", "material", "colour", "semantic", "instance")))

    def transformed(self, a_from_world: np.ndarray) -> "BoxSet":
        return replace(self, world_from_box=a_from_world[None] @ self.world_from_box)


@dataclass
class Part:
    """One box of an agent, posed in the agent frame; limbs swing about the lateral z axis through their joint."""

    half_size: np.ndarray  # [3] half extents along the agent's x (length), y (height), z (width)
    centre: np.ndarray  # [3] agent frame (for limbs: the joint position)
    material: int
    colour: np.ndarray  # [3]
    swing_amplitude: float = 0.0  # radians; 0 = rigid part
    swing_phase: float = 0.0  # radians

    def agent_from_part(self, gait_phase: float) -> np.ndarray:
        """[4, 4] at gait phase (radians). A limb hangs down (+y) from its joint and rotates about z."""
        out = np.eye(4)
        if self.swing_amplitude == 0.0:
            out[:3, 3] = self.centre
            return out
        angle = self.swing_amplitude * np.sin(gait_phase + self.swing_phase)
        rot = rot_z(angle)
        out[:3, :3] = rot
        out[:3, 3] = self.centre + rot @ np.array([0.0, self.half_size[1], 0.0])
        return out


@dataclass
class Agent:
    """An agent's exact motion. ``world_from_agent`` is the box frame (see module doc)."""

    name: str  # "moving_car", "parked_car", "pedestrian"
    semantic: int  # SEM["car"] or SEM["pedestrian"]
    kind: str  # "rigid" or "non_rigid"
    size_lwh: np.ndarray  # [3] metres
    world_from_agent: np.ndarray  # [N, 4, 4]
    parts: list[Part]
    gait_phase: np.ndarray  # [N] radians (pedestrians; zeros for cars)
    moving: bool

    def boxes(self, frame: int, instance: int) -> BoxSet:
        poses = np.stack([self.world_from_agent[frame] @ p.agent_from_part(self.gait_phase[frame])
                          for p in self.parts])
        return BoxSet(poses, np.stack([p.half_size for p in self.parts]), np.array([p.material for p in self.parts]),
                      np.stack([p.colour for p in self.parts]), np.full(len(self.parts), self.semantic),
                      np.full(len(self.parts), instance))


@dataclass
class Scene:
    """A generated scene: camera path, static boxes, the road plane and agents, all in the world frame."""

    config: SceneConfig
    K: np.ndarray  # [3, 3]
    world_from_camera: np.ndarray  # [N, 4, 4]
    world_from_road: np.ndarray  # [4, 4]; the road surface is y = 0 in the road frame
    static: BoxSet
    agents: list[Agent]
    texture_seed: int

    @property
    def frames(self) -> int:
        return len(self.world_from_camera)

    @property
    def timestamps_us(self) -> np.ndarray:
        return np.round(np.arange(self.frames) * 1e6 / self.config.fps).astype(np.int64)  # [N]

    def ground_plane(self) -> tuple[np.ndarray, float]:
        """World plane ``n . x = d`` of the road surface, normal pointing up (towards the sky): (n [3], d)."""
        n = self.world_from_road[:3, :3] @ np.array([0.0, -1.0, 0.0])
        return n, float(n @ self.world_from_road[:3, 3])

    def boxes_at(self, frame: int) -> BoxSet:
        """Every box (static and agent parts) at a frame, world frame."""
        return BoxSet.concat([self.static] + [a.boxes(frame, k + 1) for k, a in enumerate(self.agents)])


# ---------------------------------------------------------------------------------------------------------------
# small geometry helpers


def rot_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rot_y(a: float) -> np.ndarray:
    """Rotation about +y (down); maps +z to (sin a, 0, cos a)."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def pose(rot: np.ndarray, t) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = rot
    out[:3, 3] = t
    return out


def yaw_of(a_from_b: np.ndarray) -> np.ndarray:
    """Yaw (radians) of rotation(s) ``R_y(yaw)`` given as [..., 4, 4] or [..., 3, 3]."""
    return np.arctan2(a_from_b[..., 0, 2], a_from_b[..., 0, 0])


# ---------------------------------------------------------------------------------------------------------------
# generation

_CAR_COLOURS = np.array([[0.75, 0.1, 0.1], [0.1, 0.25, 0.7], [0.9, 0.9, 0.88], [0.1, 0.1, 0.12], [0.85, 0.7, 0.1],
                         [0.2, 0.55, 0.25], [0.55, 0.55, 0.6], [0.9, 0.45, 0.1]])
_FACADE_COLOURS = np.array([[0.6, 0.28, 0.2], [0.78, 0.7, 0.55], [0.55, 0.55, 0.58], [0.7, 0.5, 0.35],
                            [0.45, 0.35, 0.3], [0.85, 0.82, 0.75]])
_CLOTH_COLOURS = np.array([[0.15, 0.2, 0.5], [0.6, 0.1, 0.15], [0.2, 0.45, 0.2], [0.3, 0.3, 0.3], [0.8, 0.6, 0.2]])
_SKIN_COLOURS = np.array([[0.92, 0.76, 0.62], [0.72, 0.53, 0.38], [0.45, 0.31, 0.22]])


def _box(centre, size, material, colour, semantic, yaw: float = 0.0) -> BoxSet:
    return BoxSet(pose(rot_y(yaw), centre)[None], 0.5 * np.asarray(size, float)[None], np.array([material]),
                  np.asarray(colour, float)[None], np.array([semantic]), np.array([0]))


def _ego_path(cfg: SceneConfig, phase: float) -> np.ndarray:
    """road_from_camera [N, 4, 4]: forward at ego_speed, lateral sway, heading along the path, a small pitch bob."""
    t = np.arange(cfg.frames) / cfg.fps  # [N] seconds
    omega = 2.0 * np.pi / 4.0  # 4 s sway period
    x = cfg.sway * np.sin(omega * t + phase)
    z = cfg.ego_speed * t
    yaw = np.arctan2(cfg.sway * omega * np.cos(omega * t + phase), cfg.ego_speed)
    pitch = np.deg2rad(0.4) * np.sin(2.0 * np.pi * 1.3 * t)  # 0 at t = 0, so camera 0 is level
    y = -cfg.camera_height + 0.02 * np.sin(2.0 * np.pi * 1.3 * t)
    return np.stack([pose(rot_y(yaw[i]) @ rot_x(pitch[i]), [x[i], y[i], z[i]]) for i in range(cfg.frames)])


def _static_boxes(cfg: SceneConfig, rng: np.random.Generator, z_end: float) -> BoxSet:
    """Sidewalks and building blocks (road frame)."""
    half = cfg.road_half_width
    z0, z1 = -30.0, z_end
    sets = []
    for side in (-1.0, 1.0):
        # sidewalk: 0.15 m high slab from the road edge to well behind the buildings
        x_in, x_out = half, half + 40.0
        sets.append(_box([side * 0.5 * (x_in + x_out), -0.075, 0.5 * (z0 + z1)], [x_out - x_in, 0.15, z1 - z0],
                         MAT_SIDEWALK, [0.62, 0.62, 0.6], SEM["sidewalk"]))
        z = z0 + rng.uniform(0.0, 4.0)
        while z < z1:
            length = rng.uniform(8.0, 20.0)
            depth = rng.uniform(8.0, 14.0)
            height = rng.uniform(6.0, 24.0)
            setback = half + cfg.sidewalk_width + rng.uniform(0.0, 1.5)
            colour = _FACADE_COLOURS[rng.integers(len(_FACADE_COLOURS))] * rng.uniform(0.85, 1.1)
            sets.append(_box([side * (setback + 0.5 * depth), -0.15 - 0.5 * height, z + 0.5 * length],
                             [depth, height, length], MAT_FACADE, np.clip(colour, 0, 1), SEM["building"]))
            z += length + (rng.uniform(1.0, 4.0) if rng.random() < 0.4 else 0.0)
    return BoxSet.concat(sets)


def _car_parts(rng: np.random.Generator) -> tuple[np.ndarray, list[Part]]:
    l, w = rng.uniform(3.8, 4.8), rng.uniform(1.7, 1.95)
    body_h, cabin_h, clear = rng.uniform(0.6, 0.8), rng.uniform(0.45, 0.6), 0.3
    h = clear + body_h + cabin_h
    colour = _CAR_COLOURS[rng.integers(len(_CAR_COLOURS))]
    bottom = 0.5 * h  # agent-frame y of the road surface (y down)
    parts = [Part(np.array([l, body_h, w]) / 2, np.array([0.0, bottom - clear - body_h / 2, 0.0]), MAT_PAINT, colour)]
    cabin_l = 0.5 * l
    parts.append(Part(np.array([cabin_l, cabin_h, w * 0.88]) / 2,
                      np.array([-0.08 * l, bottom - clear - body_h - cabin_h / 2, 0.0]), MAT_GLASS, colour * 0.5))
    wheel = np.array([0.64, 0.64, 0.24]) / 2
    for sx in (-1, 1):
        for sz in (-1, 1):
            parts.append(Part(wheel, np.array([sx * 0.32 * l, bottom - 0.32, sz * (w / 2 - wheel[2])]), MAT_RUBBER,
                              np.array([0.05, 0.05, 0.05])))
    return np.array([l, w, h]), parts


def _pedestrian_parts(rng: np.random.Generator) -> tuple[np.ndarray, list[Part]]:
    height = rng.uniform(1.6, 1.85)
    leg = 0.48 * height
    size = np.array([0.9, 0.7, height])  # l (stride room), w, h
    bottom = 0.5 * height
    hip = bottom - leg
    shirt = _CLOTH_COLOURS[rng.integers(len(_CLOTH_COLOURS))]
    trousers = _CLOTH_COLOURS[rng.integers(len(_CLOTH_COLOURS))] * 0.6
    skin = _SKIN_COLOURS[rng.integers(len(_SKIN_COLOURS))]
    torso_h, head = 0.36 * height, 0.14 * height
    amp = np.deg2rad(25.0)
    parts = [
        Part(np.array([0.24, torso_h, 0.42]) / 2, np.array([0.0, hip - torso_h / 2, 0.0]), MAT_CLOTH, shirt),
        Part(np.array([0.22, head, 0.2]) / 2, np.array([0.0, hip - torso_h - head / 2, 0.0]), MAT_SKIN, skin),
    ]
    for sz, ph in ((-1, 0.0), (1, np.pi)):
        parts.append(Part(np.array([0.16, leg, 0.15]) / 2, np.array([0.0, hip, sz * 0.11]), MAT_CLOTH, trousers,
                          amp, ph))
        parts.append(Part(np.array([0.1, 0.4 * height, 0.1]) / 2, np.array([0.0, hip - torso_h + 0.04, sz * 0.27]),
                          MAT_SKIN, skin, 0.8 * amp, ph + np.pi))
    return size, parts


def _in_view_fraction(cfg: SceneConfig, road_from_camera: np.ndarray, x: float, z: np.ndarray) -> float:
    """Fraction of frames in which road point (x, -1, z[i]) is at least 4 m ahead and inside 90% of the hfov."""
    cam_from_road = np.linalg.inv(road_from_camera)  # [N, 4, 4]
    p = np.stack([np.full_like(z, x), np.full_like(z, -1.0), z, np.ones_like(z)], -1)  # [N, 4]
    c = np.einsum("nij,nj->ni", cam_from_road, p)
    ok = (c[:, 2] > 4.0) & (np.abs(c[:, 0]) < 0.9 * np.tan(np.deg2rad(cfg.hfov_deg) / 2) * c[:, 2])
    return float(ok.mean())


def _agents(cfg: SceneConfig, rng: np.random.Generator, world_from_road: np.ndarray,
            road_from_camera: np.ndarray) -> list[Agent]:
    """Agents in the order: moving cars, parked cars, pedestrians."""
    n = cfg.frames
    t = np.arange(n) / cfg.fps  # [N] seconds
    lane = cfg.lane_width
    half = cfg.road_half_width
    travel = cfg.ego_speed * t[-1]
    out: list[Agent] = []
    placed: list[tuple[np.ndarray, np.ndarray, float, float]] = []  # (x [N], z [N], half x, half z), road frame

    def free(x, z, size, gap=0.5) -> bool:
        """No overlap (road-aligned footprints, 0.15 m slack for small yaws, plus ``gap``) with placed agents."""
        hx, hz = 0.5 * size[1] + 0.15, 0.5 * size[0] + 0.15
        return all(not np.any((np.abs(x - ox) < hx + ohx + gap) & (np.abs(z - oz) < hz + ohz + gap))
                   for ox, oz, ohx, ohz in placed)

    def add(name, sem, size, parts, x, z, heading, gait=None, moving=False, lift=0.0):
        yaw = np.zeros(n) + heading - 0.5 * np.pi  # heading: angle of travel from road +z towards +x
        pos = np.stack([x, np.full(n, -0.5 * size[2] - lift), z], -1)
        road_from_agent = np.stack([pose(rot_y(yaw[i]), pos[i]) for i in range(n)])
        out.append(Agent(name, SEM[sem], AGENT_KIND_OF_CLASS[sem], size, world_from_road[None] @ road_from_agent,
                         parts, np.zeros(n) if gait is None else gait, moving))
        placed.append((x, z, 0.5 * size[1] + 0.15, 0.5 * size[0] + 0.15))

    # moving cars: lane cycle (ahead in the ego lane, right lane same direction, left lane oncoming); the k-th car
    # of a lane starts 14 m further on and drives at the lane's speed, so cars of a lane never overlap
    lane_speed: dict[int, float] = {}
    for i in range(cfg.moving_cars):
        size, parts = _car_parts(rng)
        slot, k = i % 3, i // 3
        if slot == 0:  # ahead in the ego lane, slightly faster than the ego
            z0, v, x = 11.0 + rng.uniform(0.0, 4.0), cfg.ego_speed + rng.uniform(0.0, 1.5), 0.0
        elif slot == 1:  # right lane, same direction, overtaken or overtaking
            z0, v, x = 6.0 + rng.uniform(0.0, 4.0), cfg.ego_speed + rng.uniform(-3.0, 2.0), lane
        else:  # left lane, oncoming
            z0, v, x = travel + 18.0 + rng.uniform(0.0, 4.0), -rng.uniform(6.0, 10.0), -lane
        v = lane_speed.setdefault(slot, v)
        z0 += 14.0 * k
        heading = 0.0 if v >= 0 else np.pi
        add("moving_car", "car", size, parts, np.full(n, x), z0 + v * t, heading, moving=True)
    # parked cars: in the parking strips, ahead of the ego along the driven stretch
    z_max = travel + 35.0 + 6.0 * cfg.parked_cars
    for i in range(cfg.parked_cars):
        size, parts = _car_parts(rng)
        for _attempt in range(200):
            side = rng.choice([-1.0, 1.0])
            x = side * (half - 0.5 * size[1] - rng.uniform(0.15, 0.4))
            z = rng.uniform(6.0, z_max)
            if free(np.full(n, x), np.full(n, z), size):
                break
        else:
            raise SceneConfigError(f"could not place parked car {i + 1} of {cfg.parked_cars} without overlap")
        heading = (0.0 if side > 0 else np.pi) + rng.uniform(-0.05, 0.05)
        add("parked_car", "car", size, parts, np.full(n, x), np.full(n, z), heading)
    # pedestrians: walking along the sidewalks (alternate sides, left first: no same-direction traffic there),
    # preferring walks that stay in view (ahead of the camera and inside the field of view)
    for i in range(cfg.pedestrians):
        size, parts = _pedestrian_parts(rng)
        side = -1.0 if i % 2 == 0 else 1.0
        best = None
        for _attempt in range(200):
            x = side * (half + rng.uniform(0.5, cfg.sidewalk_width - 0.5))
            z0 = rng.uniform(10.0, travel + 25.0)
            speed = rng.uniform(1.0, 1.6)
            direction = rng.choice([-1.0, 1.0])
            z = z0 + direction * speed * t
            if not free(np.full(n, x), z, size, gap=0.2):
                continue
            score = _in_view_fraction(cfg, road_from_camera, x, z)
            if best is None or score > best[0]:
                best = (score, x, z, speed, direction)
            if score >= 0.8:
                break
        if best is None:
            raise SceneConfigError(f"could not place pedestrian {i + 1} of {cfg.pedestrians} without overlap")
        _, x, z, speed, direction = best
        gait = 2.0 * np.pi * (speed / 1.4) * t + rng.uniform(0, 2 * np.pi)  # one stride cycle per 1.4 m
        # the sidewalk top is 0.15 m above the road: lift the box
        add("pedestrian", "pedestrian", size, parts, np.full(n, x), z, 0.0 if direction > 0 else np.pi, gait,
            moving=True, lift=0.15)
    return out


def make_scene(cfg: SceneConfig) -> Scene:
    """Generate the scene for a config; identical configs give identical scenes."""
    cfg.validate()
    rng = np.random.default_rng([cfg.seed, 0x5C3E])
    road_from_camera = _ego_path(cfg, phase=rng.uniform(0.0, 2.0 * np.pi))  # [N, 4, 4]
    world_from_road = np.linalg.inv(road_from_camera[0])
    world_from_camera = world_from_road[None] @ road_from_camera
    world_from_camera[0] = np.eye(4)  # exact, not merely up to rounding
    z_end = float(road_from_camera[-1, 2, 3]) + 90.0
    static = _static_boxes(cfg, rng, z_end).transformed(world_from_road)
    agents = _agents(cfg, rng, world_from_road, road_from_camera)
    return Scene(cfg, cfg.intrinsics(), world_from_camera, world_from_road, static, agents,
                 texture_seed=int(rng.integers(2**31)))
