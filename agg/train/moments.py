"""Adam moments that restart when the loss a node group steps on changes (``TrainConfig.restart_moments``).

Adam divides each step by its running estimate of the gradient's second moment, which decays by 0.999 a step: a
memory of about a thousand steps. Tick-Tock changes the loss a group trains on at fixed milestones. Eq. 3 joins
L_photo in the Ticks (with M_bg) and the Tocks (with M_ag), and leaves it out in the warm-up and the joint phase;
with Tick-Tock ablated it alternates between the two maps. The attention-weighted term is normalised by the map's
mass, so on the agents, a small share of the pixels, it weighs each pixel many times more than L_photo does. Carried
over, the moments of one loss set the step size for the next: at the first Tock the agents' steps jump, and in the
joint phase, where L_sem is gone, both the background and the agents step at a fraction of the size they take
without the semantic loss (docs/TRAINING.md, "Learning rates").

The key of a step's loss names what it is made of: ``"photo"``, or ``"bg"`` / ``"ag"`` when Eq. 3 adds that
attention map, and ``+mask`` when a Tick's L_photo leaves out the frozen agents' pixels (``tick_agent_mask``).
When a group steps on a loss whose key differs from the one it last stepped on, its Adam state is dropped, the step
count included, so Adam starts again with its bias correction (``torch.optim.Adam`` re-creates the state of a
parameter on its next step). A group the phase freezes keeps its moments and its last key, so a Tick-Tock run
restarts each group at most twice (warm-up to its first phase, its last phase to the joint one). Without the
semantic loss the key never changes and the run is the same bit for bit.
"""

from __future__ import annotations

import torch


def loss_key(attention: str | None, masked: bool) -> str:
    """The key of a step's loss: the Eq. 3 map in use (``"bg"`` / ``"ag"``, None: no L_sem) and whether L_photo
    is weighted by the frozen agents' alpha."""
    return (attention or "photo") + ("+mask" if masked else "")


def restart_moments(optimizer: torch.optim.Optimizer) -> None:
    """Drop the Adam state (moments and step count) of every parameter of ``optimizer``."""
    for group in optimizer.param_groups:
        for p in group["params"]:
            optimizer.state.pop(p, None)


def restart_on_change(optimizers: dict[str, torch.optim.Optimizer], keys: dict[str, str], trainable, key: str
                      ) -> list[str]:
    """Before the optimisers of the ``trainable`` groups step on a loss of ``key``: restart those whose last key
    (``keys``, updated in place) differs. Returns the names of the restarted groups."""
    restarted = []
    for name in sorted(trainable):
        if name not in optimizers:
            continue
        if keys.get(name, key) != key:
            restart_moments(optimizers[name])
            restarted.append(name)
        keys[name] = key
    return restarted
