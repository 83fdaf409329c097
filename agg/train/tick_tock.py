"""The Tick-Tock schedule (paper Sec. 3.2): warm-up, alternating Tick / Tock phases, then a joint phase.

- **warm-up** (until ``warmup``): every node group trains.
- **Tick**: the camera and the static nodes (background, sky) train; every agent parameter is frozen.
- **Tock**: the agents (canonical Gaussians, poses, deformation) train; camera and static nodes are frozen.
  Phases alternate every ``alternate`` iterations, Tick first (the paper's equal halves); ``tick_share`` other
  than 0.5 splits each Tick + Tock cycle of ``2 * alternate`` iterations unequally (0.75: a Tick three times as long
  as the Tock), so the background and camera train a larger share of a short run.
- **joint** (from ``joint``): everything trains; the rates Tick-Tock governs (camera poses and every agent rate,
  the raised ones included) are x ``joint_decay``, while the static nodes' Gaussians keep their default 3DGS
  schedules (Sec. 4.2: "general Gaussian attributes follow default schedules"). With Tick-Tock on, the background
  trains only in the warm-up and the Ticks; a decayed joint phase left it short of steps (docs/BENCHMARKS.md,
  eighteenth and nineteenth sessions).

Freezing sets ``requires_grad = False`` on the frozen groups' parameters for the step, so their gradients are not
small but exactly absent (``None``, i.e. zero) and their optimisers skip them; ``tests/test_train.py`` checks it.
With Tick-Tock ablated every group trains at every step ("joint" labels), and the semantic loss still follows the
same alternation of attention maps, so the ablation removes the freezing alone.
"""

from __future__ import annotations

from dataclasses import dataclass

GROUPS = ("camera", "static", "agents")
JOINT_DECAYED = frozenset({"camera", "agents"})  # the groups whose rates the joint phase decays


@dataclass(frozen=True)
class Phase:
    name: str  # "warmup" | "tick" | "tock" | "joint"
    trainable: frozenset  # subset of GROUPS
    lr_factor: float  # x the learning rates of the groups in ``decayed``
    attention: str | None  # "bg" | "ag" | None: which semantic attention map Eq. 3 uses
    decayed: frozenset = frozenset()  # subset of GROUPS whose rates are x lr_factor (the others x 1)

    def lr_factor_of(self, group: str) -> float:
        return self.lr_factor if group in self.decayed else 1.0


@dataclass(frozen=True)
class TickTockSchedule:
    warmup: int
    alternate: int
    joint: int
    enabled: bool = True
    joint_decay: float = 0.1
    tick_share: float = 0.5  # share of each Tick + Tock cycle (2 * alternate iterations) spent in the Tick

    @property
    def tick_length(self) -> int:
        """Iterations of each Tick (the rest of the ``2 * alternate`` cycle is the Tock); at least 1 of each."""
        cycle = 2 * max(self.alternate, 1)
        return min(max(int(round(cycle * self.tick_share)), 1), cycle - 1)

    def phase(self, iteration: int) -> Phase:
        everything = frozenset(GROUPS)
        if iteration >= self.joint:
            return Phase("joint", everything, self.joint_decay, None, JOINT_DECAYED)
        if iteration < self.warmup:
            return Phase("warmup", everything, 1.0, None)
        tick = (iteration - self.warmup) % (2 * max(self.alternate, 1)) < self.tick_length
        attention = "bg" if tick else "ag"
        if not self.enabled:
            return Phase("joint", everything, 1.0, attention)
        if tick:
            return Phase("tick", frozenset({"camera", "static"}), 1.0, attention)
        return Phase("tock", frozenset({"agents"}), 1.0, attention)

    def settles(self, iteration: int) -> bool:
        """Whether the camera and the background, changed just before this iteration, train from it on: outside
        the alternation (warm-up, joint phase, Tick-Tock off) or at the first iteration of a Tick. A change made
        late in a Tick would stand frozen through the Tock that follows."""
        if not self.enabled or iteration < self.warmup or iteration >= self.joint:
            return True
        return (iteration - self.warmup) % (2 * max(self.alternate, 1)) == 0

    def next_settled(self, iteration: int) -> int:
        """The first iteration >= ``iteration`` at which ``settles`` holds."""
        if self.settles(iteration):
            return iteration
        cycle = 2 * max(self.alternate, 1)
        return min(iteration + (-(iteration - self.warmup)) % cycle, self.joint)


def set_trainable(groups: dict[str, list], trainable: frozenset) -> None:
    """``requires_grad`` on every parameter of every group: True for the trainable groups, False otherwise."""
    for name, params in groups.items():
        on = name in trainable
        for p in params:
            p.requires_grad_(on)
