"""A trainer's checkpoint: everything a run needs to go on as if it had never stopped.

The graph, every optimiser's state, the densifier's and topology's statistics, the frame-order generator and the
order left in the epoch, the loss history and the logs. Resuming reproduces the uninterrupted loss curve
(``tests/test_train.py``). The file is written beside its destination and renamed, so a reader never sees half of
it. The graph is rebuilt on the CPU and then moved to the device training goes on (that of the training data): a
checkpoint written on one device resumes on another, and the optimiser moments follow their parameters.
"""

from __future__ import annotations

from pathlib import Path

import torch


def trainer_state(trainer) -> dict:
    """The checkpoint of a ``Trainer`` (a dict ``torch.save`` writes)."""
    t = trainer
    return {"graph": t.graph.state(), "iteration": t.iteration, "history": list(t.history),
            "spawned": list(t.spawned), "pruned": list(t.pruned), "topology_log": list(t.topology_log),
            "tracking_log": list(t.tracking_log), "loss_keys": dict(t.loss_keys),
            "generator": t.generator.get_state(), "order": list(t.order),
            "optimizers": {k: o.state_dict() for k, o in t.optimizers.items()},
            "densifier": t.densifier.state_dict() if t.densifier is not None else None,
            "topology": t.topology.state_dict() if t.topology is not None else None,
            "extent": t.extent, "config": t.cfg.as_dict()}


def save_state(state: dict, path: Path) -> None:
    """Write ``state`` to ``path`` atomically: a reader never sees a half-written checkpoint."""
    path = Path(path)
    tmp = path.with_suffix(".tmp")
    torch.save(state, tmp)
    tmp.replace(path)


def load_state(path: Path) -> dict:
    return torch.load(path, map_location="cpu", weights_only=False)


def restore(trainer, state: dict) -> None:
    """Put a new ``Trainer`` (built on the checkpoint's graph, ``state["graph"]``) where the checkpoint left off."""
    t = trainer
    t.extent = state["extent"]
    t.build_optimizers()
    for k, o in t.optimizers.items():
        o.load_state_dict(state["optimizers"][k])
    t.iteration = state["iteration"]
    t.history = list(state["history"])
    t.spawned, t.pruned = list(state["spawned"]), list(state["pruned"])
    t.topology_log = list(state.get("topology_log", []))
    t.tracking_log = list(state.get("tracking_log", []))
    t.loss_keys = dict(state.get("loss_keys", {}))
    t.generator.set_state(state["generator"])
    t.order = list(state["order"])
    if t.densifier is not None and state["densifier"] is not None:
        t.densifier.load_state_dict(state["densifier"])
        t.densifier.scene_extent = t.extent
    if t.topology is not None and state["topology"] is not None:
        t.topology.load_state_dict(state["topology"], device=t.data.images.device)
