"""Adam moments restart when the loss a node group steps on changes (agg.train.moments)."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from agg.graph import SceneGraph
from agg.io.bundle import SceneBundle
from agg.synth.corrupt import NoiseConfig
from agg.synth.scene import SceneConfig
from agg.synth.suite import generate, write_bundle
from agg.train.config import get_preset
from agg.train.data import load_train_data
from agg.train.moments import loss_key, restart_on_change
from agg.train.trainer import Trainer, seed_everything


@pytest.fixture(scope="module")
def bundle(tmp_path_factory):
    noise = NoiseConfig(camera_translation_max=0.2)
    gt, priors = generate(SceneConfig(seed=1, frames=10, width=128, height=80), noise)
    path = tmp_path_factory.mktemp("m") / "b"
    write_bundle(path, gt, priors, noise)
    return SceneBundle.load(path)


def _trainer(bundle, iterations=44, **kw):
    # no densification and no topology evolution: every parameter keeps its identity (and its Adam state) for
    # the whole run, so a step count read off the state is the steps since the last restart
    cfg = replace(get_preset("tiny"), iterations=iterations, densify=False, **kw)
    seed_everything(cfg.seed)
    return Trainer(SceneGraph.from_bundle(bundle, cfg.init), load_train_data(bundle, cfg.max_width), cfg, bundle)


def _adam_steps(tr: Trainer) -> dict[str, int]:
    """The Adam step count of each group's first parameter that has state (0: none yet)."""
    out = {}
    for name, opt in tr.optimizers.items():
        states = [opt.state[p] for grp in opt.param_groups for p in grp["params"] if p in opt.state]
        out[name] = int(states[0]["step"]) if states else 0
    return out


def test_a_group_restarts_only_when_its_loss_key_changes():
    a, b = torch.nn.Parameter(torch.ones(3)), torch.nn.Parameter(torch.ones(2))
    opts = {"static": torch.optim.Adam([a]), "agents": torch.optim.Adam([b])}
    for p, opt in ((a, opts["static"]), (b, opts["agents"])):
        p.grad = torch.ones_like(p)
        opt.step()
    keys: dict[str, str] = {}
    assert restart_on_change(opts, keys, {"static", "agents"}, loss_key(None, False)) == []  # first key: kept
    assert restart_on_change(opts, keys, {"static"}, loss_key("bg", False)) == ["static"]
    assert a not in opts["static"].state and b in opts["agents"].state  # the frozen group keeps its moments
    assert keys == {"static": "bg", "agents": "photo"}
    assert restart_on_change(opts, keys, {"static"}, "bg") == []
    assert restart_on_change(opts, keys, {"static", "camera"}, loss_key("bg", True)) == ["static"]  # + mask
    assert loss_key(None, False) == "photo" and loss_key("ag", False) == "ag"


def test_tick_tock_restarts_each_group_where_eq3_joins_or_leaves_its_loss(bundle):
    tr = _trainer(bundle, restart_moments=True, ablate=frozenset({"topology"}))
    s = tr.schedule
    assert tr.data.m_bg is not None and 0 < s.warmup < s.joint < tr.cfg.iterations
    rows = []
    while tr.iteration < tr.cfg.iterations:
        phase = tr.step()["phase"]
        rows.append((phase, _adam_steps(tr)))
    phases = [p for p, _ in rows]
    first_tick, first_tock, joint = phases.index("tick"), phases.index("tock"), phases.index("joint")
    second_tick = phases.index("tick", first_tock)
    warm = rows[first_tick - 1][1]
    assert warm == {"camera": s.warmup, "static": s.warmup, "agents": s.warmup}  # the warm-up: one loss
    # first Tick: L_photo + Eq. 3 with M_bg, a new loss for the camera and the background; the agents are frozen
    assert rows[first_tick][1] == {"camera": 1, "static": 1, "agents": s.warmup}
    # first Tock: M_ag, a new loss for the agents; the frozen background keeps its count
    assert rows[first_tock][1] == {"camera": first_tock - first_tick, "static": first_tock - first_tick,
                                   "agents": 1}
    # the next Tick's loss is the last Tick's: the background carries on where it stopped
    ticks_before = phases[:second_tick].count("tick")
    assert rows[second_tick][1]["static"] == ticks_before + 1
    # joint: Eq. 3 leaves every group's loss
    assert rows[joint][1] == {"camera": 1, "static": 1, "agents": 1}
    assert rows[-1][1]["static"] == len(phases) - joint


def test_without_the_semantic_loss_the_switch_changes_nothing(bundle):
    runs = []
    for restart in (False, True):
        tr = _trainer(bundle, iterations=30, restart_moments=restart, ablate=frozenset({"topology", "semantic"}))
        tr.run()
        runs.append(tr)
    assert [r["loss"] for r in runs[0].history] == [r["loss"] for r in runs[1].history]
    assert torch.equal(runs[0].graph.background.means, runs[1].graph.background.means)


def test_a_checkpoint_keeps_the_keys_so_a_resumed_run_restarts_where_the_uninterrupted_one_does(bundle, tmp_path):
    tr = _trainer(bundle, restart_moments=True, ablate=frozenset({"topology"}))
    while tr.iteration < tr.schedule.warmup:  # stop on the last warm-up step: the next one is the first Tick's
        tr.step()
    tr.save(tmp_path / "ckpt.pt")
    resumed = Trainer.resume(tmp_path / "ckpt.pt", tr.data, tr.cfg, bundle)
    assert resumed.loss_keys == tr.loss_keys == {"camera": "photo", "static": "photo", "agents": "photo"}
    for t in (tr, resumed):
        assert t.step()["phase"] == "tick"
    assert _adam_steps(resumed) == _adam_steps(tr) == {"camera": 1, "static": 1, "agents": tr.schedule.warmup}
